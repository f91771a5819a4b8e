//! `lpvid arx`: LPV-ARX identification (BC-IV paper) through
//! [`crate::pipeline::identify_arx`].

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use serde_json::json;

use super::{print_json, CliError};
use crate::arx::{
    basis_names, coef_name, parse_sigma_grid, ArxError, ArxFit, ArxOptions, Estimator,
    LambdaChoice, Precision, SigmaChoice, SigmaData,
};
use crate::data::Dataset;
use crate::model::Factor;
use crate::pipeline::{self, DataFile, Score};

/// `lpvid arx`: identify an LPV-ARX model (LS, refined IV, BC-IV, BC-IV-LASSO).
#[derive(Debug, Clone, Args)]
pub struct ArxArgs {
    /// Training data (CSV: u1.., y1, p1.. columns).
    #[arg(long)]
    pub train: PathBuf,
    /// Calibration data (same columns) for the cross-validation of lambda and sigma_eta;
    /// without it the last fifth of the training data is held out.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// Validation data, scored by free-run simulation after the fit.
    #[arg(long)]
    pub val: Option<PathBuf>,
    /// Output lags n_a.
    #[arg(long)]
    pub na: usize,
    /// Input lags 0..=n_b.
    #[arg(long)]
    pub nb: usize,
    /// Polynomial degree n_g of the scheduling basis (all monomials of total degree <= n_g).
    #[arg(long)]
    pub ng: usize,
    /// Cost: ls (least squares), iv (refined instrumental variables, eq. (8)) or bciv
    /// (bias-corrected IV, eq. (10)).
    #[arg(long, default_value = "bciv")]
    pub estimator: Estimator,
    /// Scheduling-noise standard deviation sigma_eta, or `auto` (section 5.3); bciv only
    /// (default auto for bciv).
    #[arg(long = "sigma-p")]
    pub sigma_p: Option<SigmaChoice>,
    /// l1 weight lambda of cost (10) in the paper's convention, `cv` (cross-validation on the
    /// calibration cost), or 0 for the full unpenalised model.
    #[arg(long, default_value = "cv")]
    pub lambda: LambdaChoice,
    /// sigma grid of `--sigma-p auto`: LO:STEP:HI or a comma-separated list (default 31
    /// points from 0 to 0.6 x the smallest standard deviation of the scheduling signals).
    #[arg(long = "sigma-grid")]
    pub sigma_grid: Option<String>,
    /// Statistics the sigma cost is minimised on once the structure is fixed: all
    /// (training + calibration, sharper) or calib (calibration only, the paper).
    #[arg(long = "sigma-data", default_value = "all")]
    pub sigma_data: SigmaData,
    /// Plain l1 penalty (unit weights) instead of adaptive weights 1/|theta_full|.
    #[arg(long)]
    pub plain_l1: bool,
    /// Keep the penalised (shrunk) Lasso estimate instead of the de-biased refit.
    #[arg(long)]
    pub no_debias: bool,
    /// Cross-validation takes the lowest calibration cost instead of the sparsest structure
    /// within one standard error of it.
    #[arg(long)]
    pub min_cost: bool,
    /// Do not refine sigma by golden-section search between grid points.
    #[arg(long)]
    pub no_refine: bool,
    /// Refit the selected structure on the training data only (default: training +
    /// calibration once lambda and sigma are chosen).
    #[arg(long)]
    pub refit_train_only: bool,
    /// Largest number of instrument refinements (iv, bciv).
    #[arg(long, default_value_t = 10)]
    pub max_iter: usize,
    /// Accumulate the statistics in f32, as a device does (solves stay in f64).
    #[arg(long)]
    pub f32: bool,
    /// Noise-variance ratios rho_s per scheduling signal (sigma_s^2 = rho_s sigma^2),
    /// comma-separated; default all 1 (0: a noise-free signal).
    #[arg(long = "noise-ratios")]
    pub noise_ratios: Option<String>,
    /// Where to write the model (JSON).
    #[arg(long)]
    pub out: PathBuf,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

fn options_from_args(a: &ArxArgs) -> Result<ArxOptions, ArxError> {
    let mut o = ArxOptions::new(a.na, a.nb, a.ng);
    o.estimator = a.estimator;
    o.sigma = match (a.sigma_p, a.estimator) {
        (Some(s), _) => s,
        (None, Estimator::Bciv) => SigmaChoice::Auto,
        (None, _) => SigmaChoice::Fixed(0.0),
    };
    o.lambda = a.lambda;
    o.sigma_grid = a.sigma_grid.as_deref().map(parse_sigma_grid).transpose()?;
    o.sigma_data = a.sigma_data;
    o.adaptive = !a.plain_l1;
    o.debias = !a.no_debias;
    o.one_se = !a.min_cost;
    o.refine_sigma = !a.no_refine;
    o.refit_all = !a.refit_train_only;
    o.max_iter = a.max_iter;
    o.precision = if a.f32 {
        Precision::F32
    } else {
        Precision::F64
    };
    o.noise_ratios = match &a.noise_ratios {
        None => None,
        Some(t) => Some(
            t.split(',')
                .map(|v| match v.trim().parse::<f64>() {
                    Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
                    _ => Err(ArxError::Options(format!(
                        "--noise-ratios '{t}': '{v}' is not a finite number >= 0"
                    ))),
                })
                .collect::<Result<_, _>>()?,
        ),
    };
    Ok(o)
}

/// Run `lpvid arx`: read the files, identify through [`crate::pipeline::identify_arx`],
/// write the model, print the summary.
pub(super) fn run(a: &ArxArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let opts = options_from_args(a).map_err(crate::Error::from)?;
    let mut inputs = vec![("--train", a.train.as_path())];
    if let Some(p) = &a.calib {
        inputs.push(("--calib", p.as_path()));
    }
    if let Some(p) = &a.val {
        inputs.push(("--val", p.as_path()));
    }
    super::files::check_paths(&inputs, &[("--out", a.out.as_path())])?;
    let train = DataFile::read(&a.train)?;
    let calib = match &a.calib {
        Some(p) => Some(DataFile::read(p)?),
        None => None,
    };
    let val = match &a.val {
        Some(p) => Some(Dataset::read_csv(p)?),
        None => None,
    };
    let id = pipeline::identify_arx(&train, calib.as_ref(), val.as_ref(), &opts)?;
    let (fitted, model) = (&id.fit, &id.model);
    let (train_score, train_diverged, val_score) =
        (&id.train_score, id.train_diverged, &id.val_score);
    let mut outputs = super::files::Outputs::default();
    outputs.model(model, &a.out)?;
    outputs.commit()?;
    if a.json {
        let summary = json!({
            "command": "arx",
            "estimator": fitted.report.estimator,
            "sigma_p": fitted.report.sigma_p,
            "lambda": fitted.report.lambda,
            "support": fitted.report.support_names,
            "iterations": fitted.report.iterations,
            "converged": fitted.report.converged,
            "costs": {"train": fitted.report.train_cost, "calib": fitted.report.calib_cost},
            "train": train_score,
            "train_free_run_diverged": train_diverged,
            "val": val_score,
            "out": a.out.display().to_string(),
            "fit": model.fit,
        });
        print_json(out, &summary)?;
    } else {
        print_summary(
            fitted,
            &opts,
            &train.data,
            (train_score, train_diverged),
            val_score.as_ref(),
            out,
        )?;
        writeln!(out, "  model written to {}", a.out.display())?;
    }
    Ok(())
}

fn print_summary(
    f: &ArxFit,
    opts: &ArxOptions,
    train: &Dataset,
    (train_score, train_diverged): (&Score, bool),
    val: Option<&Score>,
    out: &mut dyn Write,
) -> std::io::Result<()> {
    let r = &f.report;
    let d = &f.dims;
    let title = match (opts.estimator, opts.lambda) {
        (Estimator::Ls, LambdaChoice::Fixed(0.0)) => "LS",
        (Estimator::Ls, _) => "LS-LASSO",
        (Estimator::Iv, LambdaChoice::Fixed(0.0)) => "IV",
        (Estimator::Iv, _) => "IV-LASSO",
        (Estimator::Bciv, LambdaChoice::Fixed(0.0)) => "BC-IV",
        (Estimator::Bciv, _) => "BC-IV-LASSO",
    };
    writeln!(
        out,
        "LPV-ARX {title} on {}: {} samples, {} inputs, {} scheduling signals",
        train.source,
        train.len(),
        d.r,
        d.s
    )?;
    writeln!(
        out,
        "  na = {}, nb = {}, ng = {}: {} parameters; calibration: {} ({} regressors)",
        d.na, d.nb, d.ng, r.n_theta, r.calibration, r.samples.1
    )?;
    if opts.estimator != Estimator::Ls {
        writeln!(
            out,
            "  instruments: free-run simulation of the current model, {} refinement{} ({})",
            r.iterations,
            if r.iterations == 1 { "" } else { "s" },
            if r.converged {
                "settled"
            } else if r.cycle {
                "stopped on a cycle between structures"
            } else {
                "not settled within --max-iter"
            }
        )?;
        // a pass whose model could not be simulated took its instruments from a fallback
        for (k, from) in r.instruments_from.iter().enumerate() {
            if from.fallback.is_some() {
                writeln!(out, "    pass {}: instruments from {from}", k + 1)?;
            }
        }
    }
    if opts.estimator == Estimator::Bciv {
        writeln!(out, "  sigma_eta = {:.4} ({})", r.sigma_p, r.sigma_rule)?;
    }
    match r.lambda {
        Some(l) => writeln!(
            out,
            "  lambda = {l:.4e} (paper convention; {}; weights {}; {})",
            r.lambda_rule,
            r.weights,
            if opts.debias {
                format!("de-biased refit on {}", r.final_refit)
            } else {
                "penalised estimate".into()
            }
        )?,
        None => writeln!(out, "  no penalty: the full model")?,
    }
    writeln!(
        out,
        "  structure: {} of {} coefficients non-zero",
        r.support.len(),
        r.n_theta
    )?;
    let sched: Vec<Vec<Factor>> = (1..=d.s)
        .map(|i| vec![Factor::col(&format!("p{i}"))])
        .collect();
    let basis = basis_names(&sched, d.ng).unwrap_or_default();
    for &j in r.support.iter().take(40) {
        writeln!(
            out,
            "    {:<16} {:>+12.6}",
            coef_name(d, j, &basis),
            r.theta[j]
        )?;
    }
    if r.support.len() > 40 {
        writeln!(out, "    ... ({} more)", r.support.len() - 40)?;
    }
    match r.calib_cost {
        Some(c) => writeln!(
            out,
            "  J_CIV(theta, 0, N): training {:.4e}, calibration {c:.4e}",
            r.train_cost
        )?,
        None => writeln!(out, "  J_CIV(theta, 0, N): training {:.4e}", r.train_cost)?,
    }
    if train_diverged {
        writeln!(
            out,
            "  {} (free-run): the simulation diverges on the measured scheduling, no score",
            train_score.file
        )?;
    } else {
        // the free run uses the measured scheduling: with sigma_eta > 0 that is noisy, and
        // the score reflects the noise as much as the model
        let note = if r.sigma_p > 0.0 {
            format!(
                "  (simulated with the noisy scheduling, sigma_eta ~ {:.3}: the validation score \
                 on clean data is the measure of the model)",
                r.sigma_p
            )
        } else {
            String::new()
        };
        writeln!(
            out,
            "  {} ({}): VAF {:.3} %, BFR {:.2} %{note}",
            train_score.file, train_score.mode, train_score.vaf_mean, train_score.bfr_mean
        )?;
    }
    if let Some(sc) = val {
        writeln!(
            out,
            "  {} ({}): VAF {:.3} %, BFR {:.2} %",
            sc.file, sc.mode, sc.vaf_mean, sc.bfr_mean
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use crate::model::ModelFile;

    /// The human summary names each IV pass whose instruments came from a fallback model, in
    /// the fit record's words (the arx unit test's plant whose first IV estimate cannot be
    /// simulated: `arx::tests::an_iv_pass_whose_model_cannot_be_simulated_...`).
    #[test]
    fn the_summary_names_the_passes_whose_instruments_came_from_a_fallback() {
        let (sig, _) = crate::arx::tests::noisy_first_order((0.8, 0.15), (0.5, 0.5), 300, 17);
        let dir = tempfile::tempdir().unwrap();
        let (t, m) = (dir.path().join("train.csv"), dir.path().join("m.json"));
        crate::data::Dataset::from_signals(&sig, "train.csv")
            .write_csv(&t)
            .unwrap();
        let mut out = Vec::new();
        let args = [
            "lpvid", "arx", "--na", "4", "--nb", "4", "--ng", "2", "--train",
        ];
        let args = args.iter().map(std::ffi::OsString::from);
        let files = [t.as_os_str(), "--out".as_ref(), m.as_os_str()].map(|a| a.to_owned());
        crate::cli::run(args.chain(files), &mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        let printed: Vec<&str> = text
            .lines()
            .filter_map(|l| l.trim_start().split_once(": instruments from "))
            .map(|(_, what)| what)
            .collect();
        let record = ModelFile::read(&m).unwrap().fit["instruments_from"].clone();
        let fallbacks: Vec<&str> = record
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|w| w.as_str())
            .filter(|w| w.contains("cannot be simulated"))
            .collect();
        assert_eq!(printed, fallbacks, "{text}");
        assert!(
            printed.iter().any(|w| w.starts_with(
                "the estimate of IV pass 1 with its frozen poles scaled by 0.8 (the model before it cannot be simulated"
            )),
            "{text}"
        );
    }
}
