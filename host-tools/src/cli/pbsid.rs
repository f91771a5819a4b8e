//! `lpvid pbsid`: LPV-PBSID_opt on a training file through [`crate::pipeline::identify`].

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;
use serde_json::{json, Value};

use super::files::{check_paths, Outputs};
use super::{fmt_list, print_json, print_warnings, CliError, Ui};
use crate::data::{DataError, Dataset};
use crate::observer::{self, ObserverRequest};
use crate::pbsid::{self, BpdnScore, Centre, Order, PbsidOptions, Reg, Solver};
use crate::pipeline::{self, reg_name, DataFile, Identified, PbsidSettings};

/// `lpvid pbsid` arguments.
#[derive(Debug, Args)]
pub struct PbsidArgs {
    /// Training data (CSV: u1.., y1.., p1.. columns).
    #[arg(long, required_unless_present = "stats")]
    pub train: Option<PathBuf>,
    /// Identify from statistics files instead of a data file (`lpvid device pull
    /// --stats-out`, or `lpvid.Statistics.to_bytes()` in Python); repeat to merge several
    /// experiments or devices into one fit (primal form; the least-squares observer gain).
    #[arg(long, value_name = "S.lpvs", conflicts_with_all = ["train", "val", "kernel", "kernel_rows", "refine", "bpdn_score"])]
    pub stats: Vec<PathBuf>,
    /// Validation data, scored by free-run simulation after the fit.
    #[arg(long)]
    pub val: Option<PathBuf>,
    /// Past window p (with --stats: taken from the statistics; if given, it must agree).
    #[arg(long, required_unless_present = "stats")]
    pub past: Option<usize>,
    /// Future window f <= p (row blocks of Gamma K Z used for the SVD); default p.
    #[arg(long)]
    pub future: Option<usize>,
    /// Model order, or `auto`: the singular-value gap, then one or two more states while their
    /// held-out free-run error is far lower (under half, or under 1/1.25 and 5 VAF points).
    #[arg(long, default_value = "auto")]
    pub order: Order,
    /// Solve the regression in its kernel (dual) form, never forming Z (kernel paper section 5).
    #[arg(long, conflicts_with = "primal")]
    pub kernel: bool,
    /// Solve the regression from the primal statistics even when the kernel form is cheaper.
    #[arg(long)]
    pub primal: bool,
    /// Kernel row selection (Algorithm 3): keep at most M rows of Z^T Z (implies --kernel).
    #[arg(long, value_name = "M", conflicts_with = "primal")]
    pub kernel_rows: Option<usize>,
    /// Admission tolerance of the row selection, relative to the mean kernel diagonal
    /// (0 keeps exactly the rows that span: the periodic-scheduling reduction).
    #[arg(long, default_value_t = 0.0)]
    pub kernel_tol: f64,
    /// Refine the subspace model by output-error Levenberg-Marquardt on the training data
    /// (removes the finite-window bias on open-loop data; off by default).
    #[arg(long)]
    pub refine: bool,
    /// Regularisation of the regression: none (minimum norm), tikhonov-gcv, or sparse
    /// bpdn-aic / bpdn-sv (how BPDN-SV scores its path: --bpdn-score).
    #[arg(long, default_value = "tikhonov-gcv")]
    pub reg: Reg,
    /// How --reg bpdn-sv scores the points of its lasso path: simulation (default; the
    /// free-run simulation of each point's realized model on --val, else on the whole
    /// training record with an AIC order penalty, which also picks the order) or paper (the
    /// sparse paper's Algorithm 1: one-step prediction error on --val, else on the last
    /// quarter of --train with the path on the first three quarters; the order then from
    /// the singular values). Only with --reg bpdn-sv.
    #[arg(long, value_name = "simulation|paper")]
    pub bpdn_score: Option<BpdnScore>,
    /// Observer gain: ls (least squares K from the innovation estimates) or hinf (the
    /// H-infinity LMI (30) of the sparse paper over the vertices of the scheduling box, gains
    /// (31); if it fails the least-squares gain is kept and the summary says why).
    #[arg(long, default_value = "ls", value_parser = ["ls", "hinf"])]
    pub observer: String,
    /// Operating range of a scheduling signal for the observer design and the stability
    /// report, NAME=LO:HI (e.g. p1=-0.8:1.2); repeat or comma-separate; default: the
    /// training data's range.
    #[arg(
        long = "scheduling-range",
        value_name = "NAME=LO:HI",
        allow_hyphen_values = true
    )]
    pub scheduling_range: Vec<String>,
    /// Strictness margin of the LMIs (normalised units; see `lpvid_host::observer`).
    #[arg(long, default_value_t = observer::DEFAULT_MARGIN)]
    pub lmi_margin: f64,
    /// Assume D = 0 (no direct feedthrough).
    #[arg(long)]
    pub no_feedthrough: bool,
    /// Scheduling weight kappa: mean |p|^2 after internal scaling (prior on deep Kronecker terms).
    #[arg(long, default_value_t = pbsid::DEFAULT_SCHED_WEIGHT)]
    pub sched_weight: f64,
    /// Where the scheduling signals are centred for the fit (the first local model of eq.
    /// (14)): auto (with 0 away from a signal's mean both 0 and the mean are fitted and the
    /// better free run on the training data kept), zero or mean.
    #[arg(long, default_value = "auto", value_name = "auto|zero|mean")]
    pub centre: Centre,
    /// Largest order `--order auto` may choose (at least 1).
    #[arg(long, default_value_t = 20, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub max_order: usize,
    /// Where to write the model (JSON).
    #[arg(long)]
    pub out: PathBuf,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

pub(super) fn pbsid_options(a: &PbsidArgs, past: usize) -> PbsidOptions {
    let mut o = PbsidOptions::new(past);
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
    o.centre = a.centre;
    o
}

pub(super) fn print_pbsid(
    run: &Identified,
    opts: &PbsidOptions,
    out: &mut dyn Write,
) -> std::io::Result<()> {
    let f = &run.fit;
    let (r, l, s) = run.dims;
    writeln!(
        out,
        "LPV-PBSID_opt on {}: {} samples, {r} inputs, {l} outputs, {s} scheduling signals",
        run.train_score.file, run.samples
    )?;
    let r_ft = if opts.feedthrough { r } else { 0 };
    writeln!(
        out,
        "  past window p = {}, future f = {}: q = {} regressors{}, {} windows",
        opts.past,
        opts.future.unwrap_or(opts.past),
        f.q,
        if r_ft > 0 {
            format!(" (+ {r_ft} feedthrough)")
        } else {
            String::new()
        },
        f.windows
    )?;
    writeln!(out, "  solver: {}", f.solver_reason)?;
    let centred: Vec<String> = (f.scaling.p_center.iter().enumerate())
        .filter(|(_, c)| **c != 0.0)
        .map(|(j, c)| format!("signal {} at {c:.6e}", j + 1))
        .collect();
    // the centre the fit used and why (`--centre auto`: the free run chose between 0 and the
    // mean when 0 lies away from the mean; else 0 inside the range, the mean outside)
    let checked = run.model.fit.get("centre_check").is_some();
    let why = match opts.centre {
        _ if checked => "its free run on the training data better than at 0",
        Centre::Mean => "--centre mean",
        Centre::Zero => "--centre zero",
        Centre::Auto => "0 lying outside its range",
    };
    if !centred.is_empty() {
        writeln!(
            out,
            "  scheduling centred at its mean, {why} (the first local model of eq. (14)): {}",
            centred.join(", ")
        )?;
    } else if checked {
        writeln!(
            out,
            "  scheduling centred at 0, its free run on the training data better than at the mean (the first local model of eq. (14))"
        )?;
    }
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
    if opts.refine {
        match f.refinement {
            Some((before, after, it)) => writeln!(
                out,
                "  --refine: output-error Levenberg-Marquardt, training mse {before:.4e} -> \
                 {after:.4e} in {it} iterations{}",
                if after < before {
                    ""
                } else {
                    " (no improvement: the subspace model is kept)"
                }
            )?,
            None => writeln!(out, "  --refine: not run")?,
        }
    }
    for line in &run.observer.lines {
        writeln!(out, "  {line}")?;
    }
    if run.observer.max_rho >= 1.0 {
        writeln!(
            out,
            "  UNSTABLE predictor: spectral radius of A(mu) - K(mu) C up to {:.4} >= 1 in the \
             scheduling box",
            run.observer.max_rho
        )?;
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

pub(super) fn pbsid_json(run: &Identified, out_path: Option<&Path>) -> Value {
    json!({
        "command": "pbsid",
        "order": run.fit.order,
        "order_reason": run.fit.order_reason,
        "singular_values": run.fit.singular_values,
        "solver": run.model.fit["solver"],
        "lambda": run.fit.lambda,
        "train": run.train_score,
        "val": run.val_score,
        "out": out_path.map(|p| p.display().to_string()),
        "fit": run.model.fit,
        "observer": run.observer.used,
        "stability_region": run.observer.stability_json(),
        "warnings": run.warnings,
    })
}

/// Whether a fit of the CSV file `bytes` with `opts` reaches faer's large matrix product:
/// the primal form's Gram update always does (a batch's syrk), the kernel form's reductions
/// only above [`crate::linalg::TRIDIAG_UNBLOCKED_MAX`] windows. The row count is a bound
/// (blank lines counted), the form is [`crate::pbsid::primal_is_cheaper`] on the header's
/// u/y/p columns as `Solver::Auto` decides it; anything unclear answers yes.
fn needs_large_product(bytes: &[u8], opts: &PbsidOptions) -> bool {
    let rows = bytes.iter().filter(|&&b| b == b'\n').count();
    let windows = rows.saturating_sub(opts.past);
    if windows > crate::linalg::TRIDIAG_UNBLOCKED_MAX {
        return true;
    }
    let header = bytes.split(|&b| b == b'\n').next().unwrap_or_default();
    let header = String::from_utf8_lossy(header);
    let names: Vec<&str> = header
        .trim_start_matches('\u{feff}')
        .split(',')
        .map(str::trim)
        .collect();
    let count = |prefix: char| {
        (1..)
            .take_while(|i| names.contains(&format!("{prefix}{i}").as_str()))
            .count()
    };
    let (r, l, s) = (count('u'), count('y'), count('p'));
    let Ok(q) = lpvid::PbsidDims::new(r, l, s, opts.past).and_then(|d| d.q()) else {
        return true;
    };
    let r_ft = if opts.feedthrough { r } else { 0 };
    match opts.solver {
        _ if opts.kernel_rows.is_some() => false,
        Solver::Primal => true,
        Solver::Dual => false,
        Solver::Auto => crate::pbsid::primal_is_cheaper(q + r_ft, windows, opts.past),
    }
}

/// Run `lpvid pbsid`.
pub(super) fn run(a: &PbsidArgs, ui: Ui, out: &mut dyn Write) -> Result<(), CliError> {
    if a.bpdn_score.is_some() && a.reg != Reg::BpdnSv {
        return Err(CliError::Invalid(format!(
            "--bpdn-score applies to --reg bpdn-sv only (got --reg {})",
            reg_name(a.reg)
        )));
    }
    let (Some(train_path), Some(past)) = (&a.train, a.past) else {
        return super::stats::run_pbsid(a, ui, out);
    };
    let mut inputs = vec![("--train", train_path.as_path())];
    if let Some(v) = &a.val {
        inputs.push(("--val", v.as_path()));
    }
    check_paths(&inputs, &[("--out", a.out.as_path())])?;
    let settings = PbsidSettings {
        fit: pbsid_options(a, past),
        observer: ObserverRequest {
            hinf: a.observer == "hinf",
            ranges: a.scheduling_range.clone(),
            opts: observer::HinfOptions {
                margin: a.lmi_margin,
                ..Default::default()
            },
        },
    };
    // faer's large product, whose first use reads the cache sizes from sysfs, is set up on
    // a thread of its own while the files are read ([`crate::linalg::prefetch_matmul_setup`])
    // when the fit will reach it: never for BPDN-SV (B2 p = 5 and 8 stay below it; the
    // thread was 1.1-1.7 ms of their 9-10 ms CPU), nor for the kernel form of at most
    // TRIDIAG_UNBLOCKED_MAX windows; the primal form's Gram update always does
    let prefetch = |bytes: Option<&[u8]>| {
        if a.reg == Reg::BpdnSv {
            return;
        }
        let needed = match bytes {
            None => true,
            Some(b) => needs_large_product(b, &settings.fit),
        };
        if needed {
            crate::linalg::prefetch_matmul_setup();
        }
    };
    let spin = ui.spinner(&format!("reading {}", train_path.display()));
    let run = std::thread::scope(|sc| {
        // a large training file with options that need only the statistics is streamed in
        // chunks (constant memory); anything else, and any trouble, reads it whole
        if crate::stream::should_stream(train_path, &settings) {
            prefetch(None);
            let val = a.val.as_ref().map(|p| Dataset::read_csv(p)).transpose()?;
            spin.set_message(format!(
                "fitting LPV-PBSID_opt (p = {past}) streaming {}",
                train_path.display()
            ));
            if let Some(run) =
                crate::stream::identify_streaming(train_path, val.as_ref(), &settings)
            {
                return Ok(run);
            }
            let train = DataFile::read(train_path)?;
            return Ok(pipeline::identify(&train, val.as_ref(), &settings)?);
        }
        let bytes = crate::data::read_input(train_path);
        if let Ok(b) = &bytes {
            prefetch(Some(b));
        }
        // the validation file is parsed on a second thread while the training file is
        // parsed when a core is to spare (a thread waiting for a busy core would stall the
        // join), else first; its errors come first either way
        type ValJob<'s> = std::thread::ScopedJoinHandle<'s, Result<Dataset, DataError>>;
        let (val_job, val_first): (Option<ValJob<'_>>, _) = match &a.val {
            Some(p) if crate::linalg::spare_core() => {
                (Some(sc.spawn(move || Dataset::read_csv(p))), None)
            }
            Some(p) => (None, Some(Dataset::read_csv(p))),
            None => (None, None),
        };
        let train = bytes.and_then(|b| DataFile::from_read_input(train_path, b));
        let val = match (val_job, val_first) {
            (Some(j), _) => Some(j.join().unwrap_or_else(|e| std::panic::resume_unwind(e))?),
            (None, Some(v)) => Some(v?),
            (None, None) => None,
        };
        let train = train?;
        spin.set_message(format!(
            "fitting LPV-PBSID_opt (p = {}, {} samples)",
            past,
            train.data.len()
        ));
        Ok::<_, CliError>(pipeline::identify(&train, val.as_ref(), &settings)?)
    });
    spin.finish_and_clear();
    let run = run?;
    let mut outputs = Outputs::default();
    outputs.model(&run.model, &a.out)?;
    outputs.commit()?;
    print_warnings(&run.warnings);
    if a.json {
        print_json(out, &pbsid_json(&run, Some(&a.out)))?;
    } else {
        print_pbsid(&run, &settings.fit, out)?;
        writeln!(out, "  model written to {}", a.out.display())?;
    }
    Ok(())
}
