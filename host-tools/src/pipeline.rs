//! The identification pipeline: settings + data -> the identified model a user gets.
//!
//! Every front end (the `lpvid` command line, the device link's `pull`, `diagnose`'s refits,
//! the Python package) calls these functions, so a model identified one way is the model
//! identified any other way:
//!
//! - [`identify`]: LPV-PBSID_opt on a training file (kernel paper Algorithms 1-2 via
//!   [`crate::pbsid`], with `--refine` inside the fit), then the observer step (least-squares
//!   K, or the H-infinity gains of the sparse paper's LMI (30)-(31), and the frozen-scheduling
//!   stability region; [`crate::observer`]), the model file with its `fit` record
//!   ([`pbsid_fit_record`]), and free-run scores on the training and validation files.
//! - [`identify_from_stats`]: the same from second-moment statistics alone (a device's
//!   pull, or statistics merged from several sources): no data, so no observer redesign
//!   and no scores.
//! - [`identify_arx`]: LPV-ARX (LS, refined IV, BC-IV, BC-IV-LASSO of the BC-IV paper via
//!   [`crate::arx`]) with its model file and scores.
//!
//! Nothing here prints or parses arguments: front ends turn [`Identified`] into text.

use lpvid::PbsidDims;
use serde_json::{json, Value};

use crate::arx::{self, ArxDims, ArxFit, ArxOptions, Estimator, LambdaChoice, SigmaChoice};
use crate::data::Dataset;
use crate::error::Error;
use crate::model::{describe, ModelFile, ModelKind, SignalMap};
use crate::observer::{self, ObserverRequest, ObserverStep};
use crate::pbsid::{self, PbsidFit, PbsidOptions, Reg};
use crate::simulate::{simulate, Mode};

pub use crate::record::{
    fingerprint, order_rule, pbsid_fit_record, reg_name, solver_name, training_signals, DataFile,
};
pub use crate::simulate::{score, Score};

/// Everything `lpvid pbsid` asks for besides the data.
#[derive(Debug, Clone)]
pub struct PbsidSettings {
    /// The fit (regression, order, realization, refinement).
    pub fit: PbsidOptions,
    /// The observer step (least squares or H-infinity, the operating box).
    pub observer: ObserverRequest,
}

impl PbsidSettings {
    /// The command line's defaults with past window `past`.
    pub fn new(past: usize) -> PbsidSettings {
        PbsidSettings {
            fit: PbsidOptions::new(past),
            observer: ObserverRequest::default(),
        }
    }
}

/// The identified LPV state-space model and everything that was measured on the way.
#[derive(Debug, Clone)]
pub struct Identified {
    /// The model file (model, signals, `fit` record).
    pub model: ModelFile,
    /// The fit as the regression and realization left it (before the observer step).
    pub fit: PbsidFit,
    /// Free-run score on the training file.
    pub train_score: Score,
    /// Free-run score on the validation file, when given.
    pub val_score: Option<Score>,
    /// Training samples.
    pub samples: usize,
    /// Inputs, outputs, scheduling signals.
    pub dims: (usize, usize, usize),
    /// The observer step: gains used, certificates, stability region, lines to report.
    pub observer: ObserverStep,
    /// What looks wrong with the fit (degenerate, diverging, unstable predictor, fewer
    /// windows than regressors), each with what to try; front ends print them.
    pub warnings: Vec<String>,
}

/// Identify an LPV state-space model from a training file (and a validation file, which
/// BPDN-SV may use for its score and which is scored): fit, observer, model file, scores.
pub fn identify(
    train: &DataFile,
    val: Option<&Dataset>,
    settings: &PbsidSettings,
) -> Result<Identified, Error> {
    let opts = &settings.fit;
    let ds = &train.data;
    let (map, sig) = training_signals(ds, opts.past)?;
    let val_sig = match val {
        Some(v) if opts.reg == Reg::BpdnSv => Some(map.evaluate(v)?),
        _ => None,
    };
    let fit = pbsid::fit_with_validation(&sig, val_sig.as_ref(), opts).map_err(|e| Error::Fit {
        file: ds.source.clone(),
        source: e,
    })?;
    let names: Vec<String> = map.scheduling.iter().skip(1).map(|p| describe(p)).collect();
    let obs_step = observer::observer_step(
        &fit.model,
        fit.states.as_ref(),
        &sig,
        opts.past,
        &names,
        &settings.observer,
        // --refine replaced A, B, C, D (it runs inside the fit, before the observer step)
        matches!(fit.refinement, Some((before, after, _)) if after < before),
    )
    .map_err(Error::observer)?;
    let mut record = pbsid_fit_record(opts, &fit, train.record());
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
    let warnings = pbsid_warnings(opts, &fit, &obs_step, &train_score, val_score.as_ref());
    Ok(Identified {
        warnings,
        dims: (sig.u.ncols(), sig.y.ncols(), sig.p.ncols()),
        samples: ds.len(),
        model,
        fit,
        train_score,
        val_score,
        observer: obs_step,
    })
}

/// The warnings of an LPV-PBSID_opt fit: degenerate (no variance explained on its own
/// training data, fewer windows than regressors), diverging free run, unstable one-step
/// predictor somewhere in the scheduling box; each says what to try.
pub fn pbsid_warnings(
    opts: &PbsidOptions,
    fit: &PbsidFit,
    obs: &ObserverStep,
    train: &Score,
    val: Option<&Score>,
) -> Vec<String> {
    let mut w = Vec::new();
    let p = opts.past;
    let smaller = if p > 1 {
        format!("a smaller --past (now {p}, e.g. {})", (p / 2).max(1))
    } else {
        "more data".to_string()
    };
    // the kernel form routinely has more regressors than windows: that alone is no warning,
    // only as the likely cause of a degenerate fit
    let q_all = fit.q + if opts.feedthrough { fit.model.r() } else { 0 };
    let few_windows = if fit.windows <= q_all {
        format!(" with only {} windows for {q_all} regressors", fit.windows)
    } else {
        String::new()
    };
    for sc in std::iter::once(train).chain(val) {
        if let Some(k) = sc.diverged_at {
            w.push(format!(
                "the free-run simulation on {} diverged at sample {k}: its VAF/BFR mean \
                 nothing; try {smaller}, a smaller --order, or --refine",
                sc.file
            ));
        }
    }
    if train.diverged_at.is_none() && train.vaf_mean < 1.0 {
        w.push(format!(
            "degenerate fit: VAF {:.3} % on its own training data ({}){few_windows}; try \
             {smaller}, a fixed --order, or check that the columns are the signals you mean",
            train.vaf_mean, train.file
        ));
    }
    if opts.order == crate::pbsid::Order::Auto {
        let f = opts.future.unwrap_or(p);
        if fit.singular_values.len() <= 1 {
            w.push(format!(
                "order 1 forced: only {} singular value(s) of Gamma K Z (future window f = {f} \
                 times the outputs); try a larger --future or --past",
                fit.singular_values.len()
            ));
        } else if fit.order >= opts.max_order && opts.max_order < fit.singular_values.len() {
            w.push(format!(
                "the order {} is the largest --max-order allows: the singular-value gap may lie \
                 beyond it; try a larger --max-order or a fixed --order",
                fit.order
            ));
        }
    }
    if obs.max_rho >= 1.0 {
        w.push(format!(
            "UNSTABLE predictor: the one-step predictor A(mu) - K(mu) C has spectral radius \
             {:.4} >= 1 in the scheduling box (see the stability region); try --observer hinf, \
             {smaller}, or a smaller --order",
            obs.max_rho
        ));
    }
    w
}

/// Identify an LPV state-space model from extended second-moment statistics alone (a
/// device's pull, or statistics merged from several experiments): the same regression and
/// realization as [`identify`] ([`pbsid::fit_from_stats`]) and the same `fit` record;
/// `source` says where the statistics came from. The gain K is the least-squares one.
pub fn identify_from_stats<S: AsRef<[f64]> + AsMut<[f64]>>(
    gram: &lpvid::Gram<f64, S>,
    dims: &PbsidDims,
    opts: &PbsidOptions,
    source: Value,
) -> Result<(ModelFile, PbsidFit), Error> {
    let fit = pbsid::fit_from_stats(gram, dims, opts).map_err(|e| Error::Fit {
        file: "statistics".into(),
        source: e,
    })?;
    let mut record = pbsid_fit_record(opts, &fit, Value::Null);
    if let Value::Object(m) = &mut record {
        m.remove("train");
        m.insert("source".into(), source);
    }
    let model = ModelFile {
        kind: ModelKind::Ss(fit.model.clone()),
        signals: SignalMap::standard(dims.r, dims.l, dims.s),
        fit: record,
    };
    Ok((model, fit))
}

/// An identified LPV-ARX model and its scores.
#[derive(Debug, Clone)]
pub struct ArxIdentified {
    /// The fit: coefficients, the structure chosen, the report of the selection.
    pub fit: ArxFit,
    /// The model file.
    pub model: ModelFile,
    /// The sigma grid searched (for the record and the summary).
    pub grid: Vec<f64>,
    /// Free-run score on the training file.
    pub train_score: Score,
    /// Whether the training free run diverged (noisy scheduling on an unstable plant).
    pub train_diverged: bool,
    /// Free-run score on the validation file, when given.
    pub val_score: Option<Score>,
}

/// Identify an LPV-ARX model (BC-IV paper): check the files, fit with the options, build
/// the model file and score it.
pub fn identify_arx(
    train: &DataFile,
    calib: Option<&DataFile>,
    val: Option<&Dataset>,
    opts: &ArxOptions,
) -> Result<ArxIdentified, Error> {
    let ds = &train.data;
    let map = SignalMap::default_for(ds)?;
    for prefix in ['u', 'y', 'p'] {
        for name in ds.channels(prefix) {
            ds.check_scale(&name)?;
        }
    }
    let s = ds.channels('p').len();
    arx::check_options(opts, s)?;
    let dims = ArxDims::new(ds.channels('u').len(), s, opts.na, opts.nb, opts.ng).map_err(|e| {
        Error::Arx(arx::ArxError::Options(format!(
            "na = {}, nb = {}, ng = {}: {e}",
            opts.na, opts.nb, opts.ng
        )))
    })?;
    let needs_cv = matches!(opts.lambda, LambdaChoice::Cv)
        || (opts.estimator == Estimator::Bciv && opts.sigma == SigmaChoice::Auto);
    arx::check_dataset(ds, &dims, "training file", calib.is_none() && needs_cv)?;
    if let Some(c) = calib {
        arx::check_same_channels(ds, &c.data)?;
        arx::check_dataset(&c.data, &dims, "calibration file", false)?;
    }
    if let Some(v) = val {
        arx::check_same_channels(ds, v)?;
    }
    let tsig = map.evaluate(ds)?;
    let csig = match calib {
        Some(c) => Some(map.evaluate(&c.data)?),
        None => None,
    };
    let grid = match &opts.sigma_grid {
        Some(g) => g.clone(),
        None => arx::default_sigma_grid(&tsig.p),
    };
    let fitted = arx::fit(&tsig, csig.as_ref(), opts).map_err(|e| Error::ArxFit {
        file: ds.source.clone(),
        source: e,
    })?;
    let files = json!({
        "train": train.record(),
        "calib": calib.map_or(Value::Null, DataFile::record),
    });
    let record = arx::fit_record(opts, &fitted, &grid, files);
    let model = arx::model_file(&fitted, &map, record)?;
    let train_score = score(&model, ds, Mode::FreeRun)?;
    // with noisy scheduling a locally unstable plant's free run may blow up on the training
    // data even for the right model: the front end says so rather than print a bare 0 %
    let (_, yhat) = simulate(&model, ds, Mode::FreeRun)?;
    let train_diverged = yhat.iter().any(|v| !v.is_finite());
    let val_score = match val {
        Some(v) => Some(score(&model, v, Mode::FreeRun)?),
        None => None,
    };
    Ok(ArxIdentified {
        fit: fitted,
        model,
        grid,
        train_score,
        train_diverged,
        val_score,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_is_fnv1a64() {
        // FNV-1a 64 of the empty input is the offset basis; of "a" the published value
        assert_eq!(fingerprint(b""), "cbf29ce484222325");
        assert_eq!(fingerprint(b"a"), "af63dc4c8601ec8c");
    }

    #[test]
    fn identify_records_what_it_did() {
        let train = DataFile::from_bytes(
            "fixtures/b1-train.csv",
            include_bytes!("../../fixtures/b1-train.csv"),
        )
        .unwrap();
        let id = identify(&train, None, &PbsidSettings::new(3)).unwrap();
        assert_eq!(id.model.fit["past"], 3);
        assert_eq!(id.model.fit["train"]["fnv1a64"], fingerprint(&train.bytes));
        assert_eq!(id.fit.order, 4);
        assert!(
            id.train_score.vaf_mean > 99.0,
            "{}",
            id.train_score.vaf_mean
        );
    }
}
