//! The `lpvid` command line (DESIGN.md section 5): thin wrappers that read files, call the
//! library and print a human summary or, with `--json`, a machine-readable one.

use std::ffi::OsString;
use std::io::Write;
use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};
use serde_json::{json, Value};

use crate::data::{DataError, Dataset};
use crate::metrics::{bfr_per_output, mean, vaf_per_output};
use crate::model::{ModelFile, ModelKind, SignalMap};
use crate::observer::{self, ObserverRequest};
use crate::pbsid::{self, BpdnScore, Order, PbsidFit, PbsidOptions, Reg, Solver};
use crate::simulate::{simulate, Mode};

/// lpvid: identify Linear Parameter-Varying systems from data.
#[derive(Debug, Parser)]
#[command(name = "lpvid", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the main job on the bundled fixture: identify, validate, print singular values and fit.
    Demo(DemoArgs),
    /// Identify an LPV state-space model with LPV-PBSID_opt.
    Pbsid(PbsidArgs),
    /// Identify an LPV-ARX model: LS, refined IV, bias-corrected IV, BC-IV-LASSO.
    Arx(crate::arx::ArxArgs),
    /// Score a model on a data file: VAF and BFR per output.
    Validate(ValidateArgs),
    /// Simulate a model on a data file and write its outputs as CSV.
    Simulate(SimulateArgs),
    /// Frozen-scheduling stability region of a model's one-step predictor A(mu) - K(mu) C.
    Stability(StabilityArgs),
    /// Talk to a device over a serial port: info, stream a file, pull statistics, solve, push a model.
    Device(crate::link::DeviceArgs),
    /// Test a model's residual on validation data, name the missing effect, add it and refit.
    Diagnose(crate::diagnose::DiagnoseArgs),
}

#[derive(Debug, Args)]
struct DemoArgs {
    /// Also write the identified model here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct PbsidArgs {
    /// Training data (CSV: u1.., y1.., p1.. columns).
    #[arg(long)]
    train: PathBuf,
    /// Validation data, scored by free-run simulation after the fit.
    #[arg(long)]
    val: Option<PathBuf>,
    /// Past window p.
    #[arg(long)]
    past: usize,
    /// Future window f <= p (row blocks of Gamma K Z used for the SVD); default p.
    #[arg(long)]
    future: Option<usize>,
    /// Model order, or `auto` to take it from the singular-value gap.
    #[arg(long, default_value = "auto")]
    order: Order,
    /// Solve the regression in its kernel (dual) form, never forming Z (kernel paper section 5).
    #[arg(long, conflicts_with = "primal")]
    kernel: bool,
    /// Solve the regression from the primal statistics even when the kernel form is cheaper.
    #[arg(long)]
    primal: bool,
    /// Kernel row selection (Algorithm 3): keep at most M rows of Z^T Z (implies --kernel).
    #[arg(long, value_name = "M", conflicts_with = "primal")]
    kernel_rows: Option<usize>,
    /// Admission tolerance of the row selection, relative to the mean kernel diagonal
    /// (0 keeps exactly the rows that span: the periodic-scheduling reduction).
    #[arg(long, default_value_t = 0.0)]
    kernel_tol: f64,
    /// Refine the subspace model by output-error Levenberg-Marquardt on the training data
    /// (removes the finite-window bias on open-loop data; off by default).
    #[arg(long)]
    refine: bool,
    /// Regularisation of the regression: none (minimum norm), tikhonov-gcv, or sparse
    /// bpdn-aic / bpdn-sv (how BPDN-SV scores its path: --bpdn-score).
    #[arg(long, default_value = "tikhonov-gcv")]
    reg: Reg,
    /// How --reg bpdn-sv scores the points of its lasso path: simulation (default; the
    /// free-run simulation of each point's realized model on --val, else on the whole
    /// training record with an AIC order penalty, which also picks the order) or paper (the
    /// sparse paper's Algorithm 1: one-step prediction error on --val, else on the last
    /// quarter of --train with the path on the first three quarters; the order then from
    /// the singular values). Only with --reg bpdn-sv.
    #[arg(long, value_name = "simulation|paper")]
    bpdn_score: Option<BpdnScore>,
    /// Observer gain: ls (least squares K from the innovation estimates) or hinf (the
    /// H-infinity LMI (30) of the sparse paper over the vertices of the scheduling box, gains
    /// (31); if it fails the least-squares gain is kept and the summary says why).
    #[arg(long, default_value = "ls", value_parser = ["ls", "hinf"])]
    observer: String,
    /// Operating range of a scheduling signal for the observer design and the stability
    /// report, NAME=LO:HI (e.g. p1=-0.8:1.2); repeat or comma-separate; default: the
    /// training data's range.
    #[arg(
        long = "scheduling-range",
        value_name = "NAME=LO:HI",
        allow_hyphen_values = true
    )]
    scheduling_range: Vec<String>,
    /// Strictness margin of the LMIs (normalised units; see `lpvid_host::observer`).
    #[arg(long, default_value_t = observer::DEFAULT_MARGIN)]
    lmi_margin: f64,
    /// Assume D = 0 (no direct feedthrough).
    #[arg(long)]
    no_feedthrough: bool,
    /// Scheduling weight kappa: mean |p|^2 after internal scaling (prior on deep Kronecker terms).
    #[arg(long, default_value_t = pbsid::DEFAULT_SCHED_WEIGHT)]
    sched_weight: f64,
    /// Largest order `--order auto` may choose.
    #[arg(long, default_value_t = 20)]
    max_order: usize,
    /// Where to write the model (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct ValidateArgs {
    /// Model file (JSON).
    #[arg(long)]
    model: PathBuf,
    /// Data file (CSV) with the model's columns.
    #[arg(long)]
    data: PathBuf,
    /// Score the one-step-ahead predictor instead of the free-run simulation.
    #[arg(long)]
    predictor: bool,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct SimulateArgs {
    /// Model file (JSON).
    #[arg(long)]
    model: PathBuf,
    /// Data file (CSV) with the model's columns.
    #[arg(long)]
    data: PathBuf,
    /// One-step-ahead predictor instead of free run.
    #[arg(long)]
    predictor: bool,
    /// Output CSV: the data columns plus yhat1.. per model output.
    #[arg(long)]
    out: PathBuf,
}

/// Any failure of a command, with the message the user sees.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A data or model file problem (names file, line, column).
    #[error("{0}")]
    Data(#[from] DataError),
    /// Anything else, in words.
    #[error("{0}")]
    Other(String),
}

/// Parse `args` (including the program name) and run the command, printing to `out`.
pub fn run<I, T>(args: I, out: &mut dyn Write) -> Result<(), CliError>
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) if e.use_stderr() => return Err(CliError::Other(e.to_string())),
        Err(e) => {
            // --help / --version
            write!(out, "{e}").map_err(io_err)?;
            return Ok(());
        }
    };
    match cli.command {
        Command::Demo(a) => demo(&a, out),
        Command::Pbsid(a) => pbsid_cmd(&a, out),
        Command::Arx(a) => crate::arx::arx_cmd(&a, out),
        Command::Validate(a) => validate_cmd(&a, out),
        Command::Simulate(a) => simulate_cmd(&a, out),
        Command::Stability(a) => stability_cmd(&a, out),
        Command::Device(a) => crate::link::device_cmd(&a, out),
        Command::Diagnose(a) => crate::diagnose::run_cli(&a, out),
    }
}

fn io_err(e: std::io::Error) -> CliError {
    CliError::Other(format!("cannot write output: {e}"))
}

/// FNV-1a 64-bit fingerprint of a file's bytes (recorded in the model's `fit`).
pub fn fingerprint(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf29ce484222325;
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    format!("{h:016x}")
}

/// The training data as the fit sees it, checked: every used column present and not
/// constant, enough rows for the window.
fn training_signals(
    ds: &Dataset,
    past: usize,
) -> Result<(SignalMap, crate::lpvss::Signals), CliError> {
    let map = SignalMap::default_for(ds)?;
    for name in ds.channels('u').iter().chain(ds.channels('p').iter()) {
        ds.check_not_constant(name)?;
    }
    let needed = past + 3;
    if ds.len() < needed {
        return Err(DataError::new(
            &ds.source,
            Some(ds.len() + 1),
            None,
            format!(
                "{} data rows, but a past window of {past} needs at least {needed} (and many more for a useful fit)",
                ds.len()
            ),
        )
        .into());
    }
    let sig = map.evaluate(ds)?;
    Ok((map, sig))
}

/// Fit settings and the result, as recorded in the model file's `fit`.
fn fit_record(
    opts: &PbsidOptions,
    fit: &PbsidFit,
    train: &Path,
    ds: &Dataset,
    bytes: &[u8],
) -> Value {
    json!({
        "method": "lpv-pbsid-opt",
        "past": opts.past,
        "future": opts.future.unwrap_or(opts.past),
        "order": fit.order,
        "order_rule": match opts.order { Order::Auto => "auto".to_string(), Order::Fixed(n) => n.to_string() },
        "order_reason": fit.order_reason,
        "max_order": opts.max_order,
        "reg": reg_name(opts.reg),
        "bpdn_score": (opts.reg == Reg::BpdnSv).then(|| opts.bpdn_score.name()),
        "lambda": fit.lambda,
        "effective_parameters": fit.dof,
        "solver": fit.solver.name(),
        "solver_reason": fit.solver_reason,
        "feedthrough": opts.feedthrough,
        "observer": "ls",
        "sched_weight": opts.sched_weight,
        "kernel_rows": opts.kernel_rows,
        "kernel_tol": opts.kernel_tol,
        "refine": fit.refinement.map(|(before, after, it)| json!({
            "method": "output-error Levenberg-Marquardt",
            "mse_before": before, "mse_after": after, "iterations": it,
        })),
        "regressors": fit.q,
        "windows": fit.windows,
        "singular_values": fit.singular_values,
        "scaling": {
            "u": fit.scaling.u, "y": fit.scaling.y,
            "p_center": fit.scaling.p_center, "p_scale": fit.scaling.p_scale,
        },
        "train": {
            "file": train.display().to_string(),
            "rows": ds.len(),
            "fnv1a64": fingerprint(bytes),
        },
        "lpvid_version": env!("CARGO_PKG_VERSION"),
    })
}

fn reg_name(r: Reg) -> String {
    match r {
        Reg::None => "none".into(),
        Reg::TikhonovGcv => "tikhonov-gcv".into(),
        Reg::Tikhonov(v) => format!("tikhonov={v}"),
        Reg::BpdnAic => "bpdn-aic".into(),
        Reg::BpdnSv => "bpdn-sv".into(),
    }
}

/// VAF/BFR per output of a model on a data set.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Score {
    /// The data file.
    pub file: String,
    /// "free-run" or "predictor".
    pub mode: &'static str,
    /// VAF per output, percent.
    pub vaf: Vec<f64>,
    /// BFR per output, percent.
    pub bfr: Vec<f64>,
    /// Mean VAF over outputs.
    pub vaf_mean: f64,
    /// Mean BFR over outputs.
    pub bfr_mean: f64,
}

/// Score `model` on `ds`.
pub fn score(model: &ModelFile, ds: &Dataset, mode: Mode) -> Result<Score, CliError> {
    let (y, yhat) = simulate(model, ds, mode)?;
    let vaf = vaf_per_output(&y, &yhat, 0);
    let bfr = bfr_per_output(&y, &yhat, 0);
    Ok(Score {
        file: ds.source.clone(),
        mode: match mode {
            Mode::FreeRun => "free-run",
            Mode::Predictor => "predictor",
        },
        vaf_mean: mean(&vaf),
        bfr_mean: mean(&bfr),
        vaf,
        bfr,
    })
}

fn fmt_list(v: &[f64], prec: usize) -> String {
    v.iter()
        .map(|x| format!("{x:.prec$}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn pbsid_options(a: &PbsidArgs) -> PbsidOptions {
    let mut o = PbsidOptions::new(a.past);
    o.order = a.order;
    o.reg = a.reg;
    o.feedthrough = !a.no_feedthrough;
    o.solver = if a.kernel {
        Solver::Dual
    } else if a.primal {
        Solver::Primal
    } else {
        Solver::Auto
    };
    o.future = a.future;
    o.sched_weight = a.sched_weight;
    o.kernel_rows = a.kernel_rows;
    o.kernel_tol = a.kernel_tol;
    o.refine = a.refine;
    o.max_order = a.max_order;
    o.bpdn_score = a.bpdn_score.unwrap_or_default();
    o
}

/// Everything a pbsid run produces, for printing.
struct PbsidRun {
    model: ModelFile,
    fit: PbsidFit,
    train_score: Score,
    val_score: Option<Score>,
    samples: usize,
    dims: (usize, usize, usize),
    observer: observer::ObserverStep,
}

fn run_pbsid(
    train: (&Path, &Dataset, &[u8]),
    val: Option<&Dataset>,
    opts: &PbsidOptions,
    obs: &ObserverRequest,
) -> Result<PbsidRun, CliError> {
    let (path, ds, bytes) = train;
    let (map, sig) = training_signals(ds, opts.past)?;
    let val_sig = match val {
        Some(v) if opts.reg == Reg::BpdnSv => Some(map.evaluate(v)?),
        _ => None,
    };
    let fit = pbsid::fit_with_validation(&sig, val_sig.as_ref(), opts)
        .map_err(|e| CliError::Other(format!("{}: {e}", ds.source)))?;
    let names: Vec<String> = map
        .scheduling
        .iter()
        .skip(1)
        .map(|p| crate::model::describe(p))
        .collect();
    let obs_step = observer::observer_step(
        &fit.model,
        fit.states.as_ref(),
        &sig,
        opts.past,
        &names,
        obs,
        // --refine replaced A, B, C, D (it runs inside the fit, before the observer step)
        matches!(fit.refinement, Some((before, after, _)) if after < before),
    )
    .map_err(CliError::Other)?;
    let mut record = fit_record(opts, &fit, path, ds, bytes);
    obs_step.annotate(&mut record);
    let model = ModelFile {
        kind: ModelKind::Ss(obs_step.model.clone()),
        signals: map,
        fit: record,
    };
    let train_score = score(&model, ds, Mode::FreeRun)?;
    let val_score = match val {
        Some(v) => Some(score(&model, v, Mode::FreeRun)?),
        None => None,
    };
    Ok(PbsidRun {
        dims: (sig.u.ncols(), sig.y.ncols(), sig.p.ncols()),
        samples: ds.len(),
        model,
        fit,
        train_score,
        val_score,
        observer: obs_step,
    })
}

fn print_pbsid(run: &PbsidRun, opts: &PbsidOptions, out: &mut dyn Write) -> std::io::Result<()> {
    let f = &run.fit;
    let (r, l, s) = run.dims;
    writeln!(
        out,
        "LPV-PBSID_opt on {}: {} samples, {r} inputs, {l} outputs, {s} scheduling signals",
        run.train_score.file, run.samples
    )?;
    writeln!(
        out,
        "  past window p = {}, future f = {}: {} regressors, {} windows",
        opts.past,
        opts.future.unwrap_or(opts.past),
        f.q,
        f.windows
    )?;
    writeln!(out, "  solver: {}", f.solver_reason)?;
    match f.lambda {
        Some(lam) => writeln!(
            out,
            "  regularisation: {}{}, lambda = {lam:.3e} x {} ({:.1} effective parameters per output)",
            reg_name(opts.reg),
            if opts.reg == Reg::BpdnSv {
                format!(" (score: {})", opts.bpdn_score.name())
            } else {
                String::new()
            },
            if matches!(opts.reg, Reg::BpdnSv | Reg::BpdnAic) {
                "lambda_max"
            } else {
                "largest eigenvalue"
            },
            f.dof
        )?,
        None => writeln!(
            out,
            "  regularisation: none (minimum norm, {:.0} parameters per output)",
            f.dof
        )?,
    }
    writeln!(out, "  singular values of Gamma K Z:")?;
    let top = f
        .singular_values
        .first()
        .copied()
        .unwrap_or(1.0)
        .max(1e-300);
    for (i, sv) in f.singular_values.iter().enumerate() {
        let bar = ((sv / top).log10() * 6.0 + 60.0).max(0.0) as usize;
        let mark = if i + 1 == f.order { "  <- order" } else { "" };
        writeln!(
            out,
            "    {:>3} {:>12.5e} {}{mark}",
            i + 1,
            sv,
            "#".repeat(bar.min(60))
        )?;
    }
    writeln!(out, "  order n = {}: {}", f.order, f.order_reason)?;
    for line in &run.observer.lines {
        writeln!(out, "  {line}")?;
    }
    for sc in std::iter::once(&run.train_score).chain(run.val_score.iter()) {
        writeln!(
            out,
            "  {} ({}): VAF {} %  (mean {:.3}), BFR {} %  (mean {:.3})",
            sc.file,
            sc.mode,
            fmt_list(&sc.vaf, 3),
            sc.vaf_mean,
            fmt_list(&sc.bfr, 2),
            sc.bfr_mean
        )?;
    }
    Ok(())
}

fn pbsid_json(run: &PbsidRun, out_path: Option<&Path>) -> Value {
    json!({
        "command": "pbsid",
        "order": run.fit.order,
        "order_reason": run.fit.order_reason,
        "singular_values": run.fit.singular_values,
        "solver": run.fit.solver.name(),
        "lambda": run.fit.lambda,
        "train": run.train_score,
        "val": run.val_score,
        "out": out_path.map(|p| p.display().to_string()),
        "fit": run.model.fit,
        "observer": run.observer.used,
        "stability_region": run.observer.stability_json(),
    })
}

fn read_with_bytes(path: &Path) -> Result<(Dataset, Vec<u8>), CliError> {
    let bytes = std::fs::read(path).map_err(|e| {
        DataError::new(
            path.display().to_string(),
            None,
            None,
            format!("cannot read: {e}"),
        )
    })?;
    let ds = Dataset::parse(&path.display().to_string(), &bytes[..])?;
    Ok((ds, bytes))
}

fn pbsid_cmd(a: &PbsidArgs, out: &mut dyn Write) -> Result<(), CliError> {
    if a.bpdn_score.is_some() && a.reg != Reg::BpdnSv {
        return Err(CliError::Other(format!(
            "--bpdn-score applies to --reg bpdn-sv only (got --reg {})",
            reg_name(a.reg)
        )));
    }
    let opts = pbsid_options(a);
    let (ds, bytes) = read_with_bytes(&a.train)?;
    let val = match &a.val {
        Some(p) => Some(Dataset::read_csv(p)?),
        None => None,
    };
    let obs = ObserverRequest {
        hinf: a.observer == "hinf",
        ranges: a.scheduling_range.clone(),
        opts: observer::HinfOptions {
            margin: a.lmi_margin,
            ..Default::default()
        },
    };
    let run = run_pbsid((&a.train, &ds, &bytes), val.as_ref(), &opts, &obs)?;
    run.model.write(&a.out)?;
    if a.json {
        writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(&pbsid_json(&run, Some(&a.out))).unwrap()
        )
        .map_err(io_err)?;
    } else {
        print_pbsid(&run, &opts, out).map_err(io_err)?;
        writeln!(out, "  model written to {}", a.out.display()).map_err(io_err)?;
    }
    Ok(())
}

/// The bundled default fixture: B1 (Verdult-Verhaegen benchmark), N = 1000, 40 dB.
const DEMO_TRAIN: &[u8] = include_bytes!("../../fixtures/b1-train.csv");
const DEMO_VAL: &[u8] = include_bytes!("../../fixtures/b1-val.csv");

fn demo(a: &DemoArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let train = Dataset::parse("fixtures/b1-train.csv", DEMO_TRAIN)?;
    let val = Dataset::parse("fixtures/b1-val.csv", DEMO_VAL)?;
    let mut opts = PbsidOptions::new(3);
    opts.reg = Reg::TikhonovGcv;
    let run = run_pbsid(
        (Path::new("fixtures/b1-train.csv"), &train, DEMO_TRAIN),
        Some(&val),
        &opts,
        &ObserverRequest::default(),
    )?;
    if let Some(p) = &a.out {
        run.model.write(p)?;
    }
    if a.json {
        writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(&pbsid_json(&run, a.out.as_deref())).unwrap()
        )
        .map_err(io_err)?;
        return Ok(());
    }
    writeln!(
        out,
        "lpvid demo: the Verdult-Verhaegen LPV benchmark (4 states, 2 inputs, 3 outputs, 4 local models),\n\
         1000 samples at 40 dB, identified with LPV-PBSID_opt (p = 3, Tikhonov + GCV, order from the data),\n\
         validated by free-run simulation on a fresh noise-free data set.\n"
    )
    .map_err(io_err)?;
    print_pbsid(&run, &opts, out).map_err(io_err)?;
    if let Some(p) = &a.out {
        writeln!(out, "  model written to {}", p.display()).map_err(io_err)?;
    }
    Ok(())
}

fn validate_cmd(a: &ValidateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let ds = Dataset::read_csv(&a.data)?;
    let mode = if a.predictor {
        Mode::Predictor
    } else {
        Mode::FreeRun
    };
    let sc = score(&model, &ds, mode)?;
    if a.json {
        writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(
                &json!({"command": "validate", "model": a.model.display().to_string(), "score": sc})
            )
            .unwrap()
        )
        .map_err(io_err)?;
    } else {
        writeln!(out, "{} on {} ({}):", a.model.display(), sc.file, sc.mode).map_err(io_err)?;
        for (i, (v, b)) in sc.vaf.iter().zip(&sc.bfr).enumerate() {
            writeln!(out, "  output {}: VAF {v:.3} %  BFR {b:.2} %", i + 1).map_err(io_err)?;
        }
        writeln!(
            out,
            "  mean:     VAF {:.3} %  BFR {:.2} %",
            sc.vaf_mean, sc.bfr_mean
        )
        .map_err(io_err)?;
    }
    Ok(())
}

fn simulate_cmd(a: &SimulateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let mut ds = Dataset::read_csv(&a.data)?;
    let mode = if a.predictor {
        Mode::Predictor
    } else {
        Mode::FreeRun
    };
    let (_, yhat) = simulate(&model, &ds, mode)?;
    for j in 0..yhat.ncols() {
        let mut name = format!("yhat{}", j + 1);
        while ds.names.contains(&name) {
            name.push('_');
        }
        ds.names.push(name);
        ds.cols.push(yhat.column(j).iter().copied().collect());
    }
    ds.write_csv(&a.out)?;
    writeln!(
        out,
        "wrote {} rows with {} simulated outputs to {}",
        ds.len(),
        yhat.ncols(),
        a.out.display()
    )
    .map_err(io_err)?;
    Ok(())
}

#[derive(Debug, Args)]
struct StabilityArgs {
    /// Model file (JSON, type lpv-ss).
    #[arg(long)]
    model: PathBuf,
    /// Data file whose scheduling range is the operating box and whose means hold the other
    /// signals (default: the training range and means recorded in the model's `fit`).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Operating range NAME=LO:HI overriding the data's (repeat or comma-separate).
    #[arg(long, value_name = "NAME=LO:HI", allow_hyphen_values = true)]
    range: Vec<String>,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    json: bool,
}

/// `lpvid stability`: for each scheduling signal (the others at their mean) the interval
/// around its mean where the frozen predictor A(mu) - K(mu) C(mu) has spectral radius < 1,
/// and the largest spectral radius over the operating box.
fn stability_cmd(a: &StabilityArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let ss = match &model.kind {
        ModelKind::Ss(m) => m,
        _ => {
            return Err(CliError::Other(format!(
                "{}: the stability region is defined for lpv-ss models (A, K, C); this is an lpv-arx model",
                a.model.display()
            )))
        }
    };
    let names: Vec<String> = model
        .signals
        .scheduling
        .iter()
        .skip(1)
        .map(|p| crate::model::describe(p))
        .collect();
    let sig = match &a.data {
        Some(p) => Some(model.signals.evaluate(&Dataset::read_csv(p)?)?),
        None => None,
    };
    let rep = observer::stability_report(ss, &names, &model.fit, sig.as_ref(), &a.range)
        .map_err(|e| CliError::Other(format!("{}: {e}", a.model.display())))?;
    if a.json {
        let mut v = rep.to_json();
        if let Value::Object(o) = &mut v {
            o.insert("command".into(), "stability".into());
            o.insert("model".into(), a.model.display().to_string().into());
            o.insert(
                "observer".into(),
                model.fit.get("observer").cloned().unwrap_or(Value::Null),
            );
        }
        writeln!(out, "{}", serde_json::to_string_pretty(&v).unwrap()).map_err(io_err)?;
        return Ok(());
    }
    let gamma = model
        .fit
        .get("observer")
        .and_then(|o| o.get("gamma"))
        .and_then(Value::as_f64);
    writeln!(
        out,
        "{}: predictor A(mu) - K(mu) C, frozen scheduling (others at the {}){}",
        a.model.display(),
        rep.reference_source,
        gamma
            .map(|g| format!(", H-infinity gain with gamma = {g:.4e}"))
            .unwrap_or_default()
    )
    .map_err(io_err)?;
    for r in &rep.regions {
        writeln!(out, "  {}", r.describe()).map_err(io_err)?;
    }
    writeln!(
        out,
        "  max spectral radius over the box: {:.4} ({})",
        rep.max_rho,
        if rep.max_rho < 1.0 {
            "stable at every frozen point of the box"
        } else {
            "UNSTABLE somewhere in the box"
        }
    )
    .map_err(io_err)?;
    Ok(())
}
