//! The `lpvid` command line (DESIGN.md section 5): one file per command, each a thin
//! wrapper that parses its arguments (clap), calls the library ([`crate::pipeline`] and the
//! algorithm modules) and prints a human summary or, with `--json`, a machine-readable one.
//! The library never imports this module; it is compiled only with the `cli` feature.

mod arx;
mod demo;
mod device;
mod diagnose;
mod files;
mod pbsid;
mod stability;
mod stats;
mod validate;

use std::ffi::OsString;
use std::io::{IsTerminal, Write};

use clap::{Parser, Subcommand};

use crate::data::DataError;

/// lpvid: identify Linear Parameter-Varying systems from data.
#[derive(Debug, Parser)]
#[command(name = "lpvid", version, about, long_about = None)]
pub struct Cli {
    /// No progress bars and no notes on stderr (warnings and errors are still printed).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

/// How a command talks to the user besides its output: progress bars and notes on stderr,
/// off with `--quiet`; bars only when stderr is a terminal.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Ui {
    /// `--quiet`.
    pub quiet: bool,
}

impl Ui {
    /// Whether progress bars are drawn.
    pub fn progress(&self) -> bool {
        !self.quiet && std::io::stderr().is_terminal()
    }

    /// A note on stderr (what is being waited for), unless `--quiet`.
    pub fn note(&self, msg: &str) {
        if !self.quiet {
            eprintln!("{msg}");
        }
    }

    /// A spinner with `msg` on stderr (hidden when progress is off).
    pub fn spinner(&self, msg: &str) -> indicatif::ProgressBar {
        if !self.progress() {
            return indicatif::ProgressBar::hidden();
        }
        let b = indicatif::ProgressBar::new_spinner();
        b.set_style(
            indicatif::ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
        );
        b.set_message(msg.to_string());
        b.enable_steady_tick(std::time::Duration::from_millis(120));
        b
    }

    /// A bar of `len` steps with `what` after the counts (hidden when progress is off).
    pub fn bar(&self, len: u64, what: &str) -> indicatif::ProgressBar {
        if !self.progress() {
            return indicatif::ProgressBar::hidden();
        }
        let b = indicatif::ProgressBar::new(len);
        b.set_style(
            indicatif::ProgressStyle::with_template(&format!(
                "{{bar:40}} {{pos}}/{{len}} {what} {{elapsed}} eta {{eta}}"
            ))
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    }
}

/// Warnings on stderr, one `warning: ...` line each.
fn print_warnings(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the main job on the bundled fixture: identify, validate, print singular values and fit.
    Demo(demo::DemoArgs),
    /// Identify an LPV state-space model with LPV-PBSID_opt.
    Pbsid(pbsid::PbsidArgs),
    /// Identify an LPV-ARX model: LS, refined IV, bias-corrected IV, BC-IV-LASSO.
    Arx(arx::ArxArgs),
    /// Score a model on a data file: VAF and BFR per output.
    Validate(validate::ValidateArgs),
    /// Simulate a model on a data file and write its outputs as CSV.
    Simulate(validate::SimulateArgs),
    /// Frozen-scheduling stability region of a model's one-step predictor A(mu) - K(mu) C.
    Stability(stability::StabilityArgs),
    /// Talk to a device over a serial port: info, stream a file, pull statistics, solve, push a model.
    Device(device::DeviceArgs),
    /// Test a model's residual on validation data, name the missing effect, add it and refit.
    Diagnose(diagnose::DiagnoseArgs),
}

/// Any failure of a command, with the message the user sees.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// The arguments do not parse (clap's message, which starts with "error: ").
    #[error("{0}")]
    Usage(String),
    /// A data or model file problem (names file, line, column).
    #[error(transparent)]
    Data(#[from] DataError),
    /// The library failed.
    #[error(transparent)]
    Lib(#[from] crate::Error),
    /// An argument combination the command rejects, in words.
    #[error("{0}")]
    Invalid(String),
    /// Standard output could not be written.
    #[error("cannot write output: {0}")]
    Output(#[from] std::io::Error),
}

impl CliError {
    /// The message as `main` prints it to stderr: `error: ...`, without doubling clap's own
    /// `error: ` prefix.
    pub fn message(&self) -> String {
        match self {
            CliError::Usage(m) => m.trim_end().to_string(),
            e => format!("error: {e}"),
        }
    }
}

/// Parse `args` (including the program name) and run the command, printing to `out`.
pub fn run<I, T>(args: I, out: &mut dyn Write) -> Result<(), CliError>
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) if e.use_stderr() => return Err(CliError::Usage(e.to_string())),
        Err(e) => {
            // --help / --version
            write!(out, "{e}")?;
            return Ok(());
        }
    };
    let ui = Ui { quiet: cli.quiet };
    keep_freed_memory();
    match cli.command {
        Command::Demo(a) => demo::run(&a, out),
        Command::Pbsid(a) => {
            one_heap();
            pbsid::run(&a, ui, out)
        }
        Command::Arx(a) => arx::run(&a, out),
        Command::Validate(a) => validate::run_validate(&a, out),
        Command::Simulate(a) => validate::run_simulate(&a, out),
        Command::Stability(a) => stability::run(&a, out),
        Command::Device(a) => device::run(&a, ui, out),
        Command::Diagnose(a) => diagnose::run(&a, ui, out),
    }
}

/// glibc's allocator returns every block of 128 KiB or more to the kernel when it is freed
/// (its own mmap), so each dense matrix of a fit (a 422 x 422 Gram is 1.4 MB; the copies of
/// the regression and its reductions come and go) costs fresh zeroed pages again: about
/// 1000 of the 3850 page faults of the B1 p = 3 Tikhonov-GCV process (`perf stat`), which
/// this removes by keeping freed blocks up to 32 MB in the heap (`mallopt` M_MMAP_THRESHOLD)
/// and not trimming the heap below 128 MB. The peak memory is unchanged (a block freed is
/// reused, not added); larger blocks are mapped as before. Once per process; nothing on
/// other C libraries.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        static ONCE: std::sync::Once = std::sync::Once::new();
        ONCE.call_once(|| {
            use std::os::raw::c_int;
            extern "C" {
                fn mallopt(param: c_int, value: c_int) -> c_int;
            }
            const M_TRIM_THRESHOLD: c_int = -1;
            const M_MMAP_THRESHOLD: c_int = -3;
            // SAFETY: glibc's `int mallopt(int, int)` (it takes the allocator's own lock);
            // it only changes the allocator's thresholds (a value it rejects leaves the
            // default).
            unsafe {
                mallopt(M_MMAP_THRESHOLD, 32 << 20);
                mallopt(M_TRIM_THRESHOLD, 128 << 20);
            }
        });
    }
}

/// One malloc arena for every thread of the process (glibc `mallopt` M_ARENA_MAX = 1; call
/// before any thread starts): glibc gives each new thread an arena of its own, so the
/// blocks a worker frees (a Gram half's batch scratch, 3 MB at B1 p = 3) are never reused by
/// the main thread, whose next matrices cost fresh zeroed pages again. The threads of a fit
/// allocate per batch or per matrix, not per element (small blocks come from each thread's
/// cache without the arena's lock). Nothing on other C libraries.
fn one_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::os::raw::c_int;
        extern "C" {
            fn mallopt(param: c_int, value: c_int) -> c_int;
        }
        const M_ARENA_MAX: c_int = -8;
        // SAFETY: glibc's `int mallopt(int, int)`; it only changes how many arenas the
        // allocator may create (a value it rejects leaves the default).
        unsafe {
            mallopt(M_ARENA_MAX, 1);
        }
    }
}

/// Numbers with `prec` decimals, space separated.
fn fmt_list(v: &[f64], prec: usize) -> String {
    v.iter()
        .map(|x| format!("{x:.prec$}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Pretty JSON on its own line.
fn print_json(out: &mut dyn Write, v: &serde_json::Value) -> Result<(), CliError> {
    let text = serde_json::to_string_pretty(v)
        .map_err(|e| CliError::Invalid(format!("cannot encode the summary: {e}")))?;
    writeln!(out, "{text}")?;
    Ok(())
}
