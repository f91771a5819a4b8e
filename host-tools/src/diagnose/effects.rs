//! The catalogue of candidate missing effects (DESIGN.md section 6) and their scoring on
//! held-out data.
//!
//! Each effect proposes one or more variants: the model's structure with the effect added,
//! written with the model file's own machinery (an extra input channel, a scheduling basis
//! function, a factor with a delay, sin/cos of time, a larger order, an output equation with
//! C^(i), a noise model, the BC-IV path). Every variant is refit on the TRAINING data with
//! the model's own settings and scored on the VALIDATION data against the refit of the
//! unchanged structure (the null refit, so that the comparison is between two models made
//! the same way):
//!
//! explained = 1 - MSE(variant) / MSE(null), MSE = mean over outputs of
//! mean((y - yhat)^2) / var(y) on validation data (free-run simulation; one-step prediction
//! for `coloured-noise`, the only effect that cannot change the free run). The free run of
//! every model starts from its own initial state estimated on the first [`x0_samples`]
//! held-out samples, which are not scored: the held-out record starts in the middle of the
//! plant's motion, and from x0 = 0 the start transient can dominate the comparison (the
//! cascaded tanks' held-out record starts near 4 V: VAF 10.6 % from x0 = 0, 70.3 % with x0
//! estimated, for the same null refit). Effects whose variants are fitted by another estimator
//! are compared with the null structure fitted by that estimator ([`Candidate::null`]): the
//! BC-IV correction with the same LPV-ARX fit, an own-output (Lur'e) candidate, fitted with
//! the output-error refinement, with the model's structure refined the same way (without
//! that, on the smart rotor the refinement's own gain, 30-33 % of the held-out error, was
//! credited to y1^3 or sin y1 (0.3 % against the refined null), and on the clean plants of
//! `diagnose_planted` an own-output candidate was the best one in 28 of 30 seeds, 2 of them
//! false alarms; against the refined null in 2 of 30, none a finding).
//!
//! **Noise threshold.** A variant counts as a finding only when its improvement is
//! statistically significant: the held-out record is cut into 20 contiguous batches, the log
//! ratio of the null refit's to the variant's squared error is formed per batch, and the 20
//! ratios are tested by the exact one-sided Wilcoxon signed-rank test
//! ([`crate::significance::signed_rank_p`]; batches longer than the correlation time keep the test
//! valid for the strongly coloured free-run residual, where an i.i.d. test would not, and the
//! log ratio makes it scale-free; the ranks keep a few batches with a large ratio from
//! inflating the spread, which made the t test of their mean miss pendulums whose true model
//! improved 19 or 20 of 20 batches, docs/bench-diagnose.md, helper h24wil), one-sided at level
//! ALPHA / (number of variants tried) (Bonferroni: the family-wise false-alarm rate of a
//! diagnosis is at most ALPHA = 1 %), and when it explains at least [`MIN_EXPLAINED`] = 10 %
//! of the held-out error. The tests condition on the fitted models; estimation noise is not
//! in them, and an equally good structure can beat the null refit by recovering part of the
//! null refit's own estimation error (on the clean test plant, PBSID at N = 2000 and 5 %
//! noise, that excess over the true noise floor was 10-50 % of the held-out error). The floor
//! is calibrated on that plant: equally good structures that replicated recovered
//! 5-9 % in a few seeds in 60. Finally the variant must replicate on the two halves of the
//! training data, or on the folds of a short record ([`super::replicate`]).

use nalgebra::DMatrix;
use serde::Serialize;

use super::catalogue::{regressors, MAX_KERNEL_WINDOWS, MAX_REGRESSORS};
use super::memory::{judged, Basis};
use super::refit::{fit_spec, Fitted, Spec};
use super::residual::{ResidualReport, ALPHA};
use crate::data::{DataError, Dataset};
use crate::model::{ModelFile, ModelKind, SignalMap};
use crate::pbsid::Order;
use crate::significance::compare_in;
use crate::simulate::{simulate_signals, Mode};

/// Smallest fraction of the held-out error a finding must explain (see the module docs).
pub const MIN_EXPLAINED: f64 = 0.10;

/// The candidate effects, by their names in the report (DESIGN.md section 6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Effect {
    /// A constant on the output or input.
    OutputOffset,
    /// D != 0 was assumed away.
    Feedthrough,
    /// C or D depends on scheduling.
    ScheduledOutput,
    /// Dependence on p is not affine / degree too low.
    SchedulingNonlinearity,
    /// A static nonlinearity on an input.
    InputNonlinearity,
    /// Dead time on an input.
    InputDelay,
    /// The scheduling sensor is noisy.
    SchedulingNoise,
    /// A sinusoid not in the inputs.
    PeriodicDisturbance,
    /// Too few states / lags.
    OrderTooLow,
    /// Residual is not white.
    ColouredNoise,
    /// A logged column explains the residual.
    UnusedSignal,
    /// the model lacks a dependence on its own output level (diagnose/output.rs).
    OutputNonlinearity,
}

impl Effect {
    /// Every effect, in the order of the catalogue.
    pub const ALL: [Effect; 12] = [
        Effect::OutputOffset,
        Effect::Feedthrough,
        Effect::ScheduledOutput,
        Effect::SchedulingNonlinearity,
        Effect::InputNonlinearity,
        Effect::InputDelay,
        Effect::SchedulingNoise,
        Effect::PeriodicDisturbance,
        Effect::OrderTooLow,
        Effect::ColouredNoise,
        Effect::UnusedSignal,
        Effect::OutputNonlinearity,
    ];

    /// The name in the report.
    pub fn name(self) -> &'static str {
        match self {
            Effect::OutputOffset => "output-offset",
            Effect::Feedthrough => "feedthrough",
            Effect::ScheduledOutput => "scheduled-output",
            Effect::SchedulingNonlinearity => "scheduling-nonlinearity",
            Effect::InputNonlinearity => "input-nonlinearity",
            Effect::InputDelay => "input-delay",
            Effect::SchedulingNoise => "scheduling-noise",
            Effect::PeriodicDisturbance => "periodic-disturbance",
            Effect::OrderTooLow => "order-too-low",
            Effect::ColouredNoise => "coloured-noise",
            Effect::UnusedSignal => "unused-signal",
            Effect::OutputNonlinearity => "output-nonlinearity",
        }
    }

    /// What the model lacks, in words.
    pub fn lacks(self) -> &'static str {
        match self {
            Effect::OutputOffset => "a constant on the output or input",
            Effect::Feedthrough => "a direct feedthrough D (it was assumed zero)",
            Effect::ScheduledOutput => "an output equation that depends on scheduling",
            Effect::SchedulingNonlinearity => "a dependence on scheduling beyond its basis",
            Effect::InputNonlinearity => "a static nonlinearity on an input",
            Effect::InputDelay => "dead time on an input",
            Effect::SchedulingNoise => "a correction for noise on the scheduling sensor",
            Effect::PeriodicDisturbance => "a sinusoidal disturbance not in the inputs",
            Effect::OrderTooLow => "states (its order or past window is too small)",
            Effect::ColouredNoise => "a noise model (the one-step residual is not white)",
            Effect::UnusedSignal => "a logged signal that explains the residual",
            Effect::OutputNonlinearity => {
                "a dependence on its own output level (Lur'e feedback f(y) or scheduling on f(y))"
            }
        }
    }

    /// Which residual the effect is scored on.
    pub fn metric(self) -> Mode {
        match self {
            Effect::ColouredNoise => Mode::Predictor,
            _ => Mode::FreeRun,
        }
    }
}

/// A variant of an effect: the structure with the effect added.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// Which effect.
    pub effect: Effect,
    /// What is added, in words.
    pub detail: String,
    /// The structure to refit.
    pub spec: Spec,
    /// The structure it is nested in and compared with, when that is not the model's own
    /// (the BC-IV correction is judged against the same LPV-ARX fit without it).
    pub null: Option<Spec>,
}

/// How many times the half-width of the measured outputs' range a simulated output may stray
/// from its middle before the model is taken to have run away ([`Eval::runs_away`]): an
/// order of magnitude, far beyond what any fit that tracks the data produces (a model that
/// explains nothing stays within about the range), fixed before measuring.
pub const RUNAWAY: f64 = 10.0;

/// Held-out samples used to estimate the initial state of a free run before it is scored:
/// a quarter of the record at most, [`crate::simulate::X0_SAMPLES`] at most (the rule of the
/// pipeline's order check, [`crate::pipeline::held_out_error`]). A held-out record starts in
/// the middle of the plant's motion; from x0 = 0 every model pays the same start transient,
/// which on a slow plant (the cascaded tanks start at 5 V, the model at 0) dominates the
/// held-out error and hides what a candidate explains.
pub fn x0_samples(n: usize) -> usize {
    (n / 4).min(crate::simulate::X0_SAMPLES)
}

/// A model evaluated on validation data: the free run from an initial state estimated on
/// the first [`x0_samples`] samples (least squares, [`crate::simulate::estimate_x0`]), the
/// one-step prediction from x0 = 0; both are scored after those samples.
#[derive(Debug, Clone)]
pub struct Eval {
    /// Measured outputs (model outputs' columns).
    pub y: DMatrix<f64>,
    /// Free-run simulation (every row; the first `skip` fitted by the initial state).
    pub yhat_free: DMatrix<f64>,
    /// One-step prediction.
    pub yhat_pred: DMatrix<f64>,
    /// Free run from the zero state (every row): how much the score leans on the estimated
    /// start ([`super::memory`]).
    pub yhat_zero: DMatrix<f64>,
    /// var(y_j) over the scored rows.
    pub var_y: Vec<f64>,
    /// Leading rows used for the initial state and not scored.
    pub skip: usize,
}

impl Eval {
    /// Evaluate `model` on `ds`.
    pub fn new(model: &ModelFile, ds: &Dataset) -> Result<Eval, DataError> {
        let sig = model.signals.evaluate(ds)?;
        // the free run goes through the model's own-output feedback, if any
        let fb = model.signals.feedback(ds)?;
        let skip = x0_samples(sig.len());
        let yhat_free = crate::simulate::free_run_estimated(&model.kind, &sig, &fb, skip);
        let yhat_pred = simulate_signals(&model.kind, &sig, Mode::Predictor);
        let yhat_zero = crate::simulate::simulate_feedback(&model.kind, &sig, &fb, Mode::FreeRun);
        let var_y = crate::metrics::output_variances(&sig.y, skip);
        Ok(Eval {
            y: sig.y,
            yhat_free,
            yhat_pred,
            yhat_zero,
            var_y,
            skip,
        })
    }

    /// The residual of a mode.
    pub fn residual(&self, mode: Mode) -> DMatrix<f64> {
        match mode {
            Mode::FreeRun => &self.y - &self.yhat_free,
            Mode::Predictor => &self.y - &self.yhat_pred,
        }
    }

    /// Per-sample normalised squared error sum_j e_jk^2 / var y_j / l over the scored rows
    /// (NaN rows when the simulation diverged).
    pub fn loss(&self, mode: Mode) -> Vec<f64> {
        let yhat = match mode {
            Mode::FreeRun => &self.yhat_free,
            Mode::Predictor => &self.yhat_pred,
        };
        crate::metrics::normalised_losses(&self.y, yhat, &self.var_y, self.skip)
    }

    /// Whether the simulated outputs of `mode` leave the measured outputs' range on the
    /// scored rows by more than [`RUNAWAY`] times its half-width about its middle, or are not
    /// finite: the refit model ran away from the data (a frozen pole outside the unit circle
    /// where the record dwells, say), which says the estimate failed, not how good its
    /// structure is ([`super::replicate::Halves`]).
    pub fn runs_away(&self, mode: Mode) -> bool {
        self.runaway_at(mode).is_some()
    }

    /// The first scored row at which [`Eval::runs_away`] holds, if any.
    pub fn runaway_at(&self, mode: Mode) -> Option<usize> {
        let yhat = match mode {
            Mode::FreeRun => &self.yhat_free,
            Mode::Predictor => &self.yhat_pred,
        };
        let rows = self.skip..self.y.nrows();
        let bounds: Vec<(f64, f64)> = (0..self.y.ncols())
            .map(|j| {
                let (lo, hi) = rows
                    .clone()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), k| {
                        (a.min(self.y[(k, j)]), b.max(self.y[(k, j)]))
                    });
                (0.5 * (lo + hi), 0.5 * (hi - lo))
            })
            .collect();
        rows.clone().find(|&k| {
            bounds.iter().enumerate().any(|(j, &(mid, half))| {
                let v = yhat[(k, j)];
                !v.is_finite() || (half > 0.0 && (v - mid).abs() > RUNAWAY * half)
            })
        })
    }

    /// Normalised mean square error of a mode (infinite when it diverged).
    pub fn mse(&self, mode: Mode) -> f64 {
        let v = self.loss(mode);
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        if m.is_finite() {
            m
        } else {
            f64::INFINITY
        }
    }
}

/// A candidate's score.
#[derive(Debug, Clone)]
pub struct Scored {
    /// The candidate.
    pub cand: Candidate,
    /// Its refit (None when the refit failed).
    pub fitted: Option<Fitted>,
    /// Its evaluation on validation data.
    pub eval: Option<Eval>,
    /// Fraction of the null refit's held-out error it removes.
    pub explained: f64,
    /// Batch-means t of the per-batch log ratios (shown beside the p-value; the test is the
    /// signed-rank one, [`crate::significance::Comparison`]).
    pub t: f64,
    /// One-sided p-value of the signed-rank test of the per-batch log ratios.
    pub p_value: f64,
    /// The per-batch log ratios of the null's to the variant's held-out squared error (the
    /// test's data; empty when it could not be scored).
    pub ratios: Vec<f64>,
    /// How it was compared with its null ([`super::memory::judged`]).
    pub basis: Basis,
    /// Why it could not be scored.
    pub error: Option<String>,
    /// Wall time of the refit and its evaluation, seconds.
    pub seconds: f64,
}

impl Scored {
    /// A candidate that could not be scored, and why.
    fn failed(cand: Candidate, fitted: Option<Fitted>, eval: Option<Eval>, why: String) -> Scored {
        Scored {
            cand,
            fitted,
            eval,
            explained: f64::NEG_INFINITY,
            t: 0.0,
            p_value: 1.0,
            ratios: vec![],
            basis: Basis::EstimatedStart,
            error: Some(why),
            seconds: 0.0,
        }
    }
}

/// Score a candidate against its null's evaluation `null` on `val` (the null refit of the
/// model's structure, or of the candidate's own null structure, [`Candidate::null`]; None:
/// the candidate's own null structure is refit here), with the comparison
/// [`super::memory::judged`] chooses.
pub fn score(
    cand: Candidate,
    train: &Dataset,
    val: &Dataset,
    base_fit: &serde_json::Value,
    null: Option<&Eval>,
) -> Scored {
    let t0 = std::time::Instant::now();
    let mut s = score_inner(cand, train, val, base_fit, null, false);
    s.seconds = t0.elapsed().as_secs_f64();
    s
}

/// [`score`] against the candidate's own null structure ([`Candidate::null`]) already fitted
/// (`null_fit`, on `train` with `base_fit`) and evaluated, `own_null`: compared as scored (the
/// symmetric memory rule is for refits of the model's own structure,
/// [`super::memory::judged`]). A candidate nested in that structure starts from its fit
/// ([`super::refit::fit_spec_on`]) rather than refitting it: the same fit, done once.
pub fn score_own(
    cand: Candidate,
    train: &Dataset,
    val: &Dataset,
    base_fit: &serde_json::Value,
    own_null: &Eval,
    null_fit: &Fitted,
) -> Scored {
    let t0 = std::time::Instant::now();
    let same = matches!((cand.spec.nested_in.as_deref(), &cand.null), (Some(a), Some(b)) if a.key() == b.key());
    let nested = same.then_some(null_fit);
    let parts = std::slice::from_ref(val);
    let null = Some(std::slice::from_ref(own_null));
    let mode = cand.effect.metric();
    let mut s = score_parts_inner(cand, train, parts, base_fit, null, true, nested, mode);
    s.seconds = t0.elapsed().as_secs_f64();
    s
}

fn score_inner(
    cand: Candidate,
    train: &Dataset,
    val: &Dataset,
    base_fit: &serde_json::Value,
    null: Option<&Eval>,
    own: bool,
) -> Scored {
    let parts = std::slice::from_ref(val);
    let mode = cand.effect.metric();
    score_parts_inner(
        cand,
        train,
        parts,
        base_fit,
        null.map(std::slice::from_ref),
        own,
        None,
        mode,
    )
}

/// [`score`] on a held-out record cut into `parts`, each scored from its own estimated
/// initial state, their per-sample losses joined before the test; `null` holds the null's
/// evaluation on each part. The replication scores a training half's refit only where the
/// held-out operating point lies in the range that half saw
/// ([`super::replicate::support_parts`]).
pub fn score_parts(
    cand: Candidate,
    train: &Dataset,
    parts: &[Dataset],
    base_fit: &serde_json::Value,
    null: Option<&[Eval]>,
) -> Scored {
    let mode = cand.effect.metric();
    score_parts_in(cand, train, parts, base_fit, null, mode)
}

/// [`score_parts`] on the residual of `mode` rather than the effect's own
/// ([`Effect::metric`]): a replication half whose null structure's free run cannot be had
/// compares the two refits' one-step predictions ([`super::replicate::Halves`]).
pub fn score_parts_in(
    cand: Candidate,
    train: &Dataset,
    parts: &[Dataset],
    base_fit: &serde_json::Value,
    null: Option<&[Eval]>,
    mode: Mode,
) -> Scored {
    let t0 = std::time::Instant::now();
    let mut s = score_parts_inner(cand, train, parts, base_fit, null, false, None, mode);
    s.seconds = t0.elapsed().as_secs_f64();
    s
}

/// The scoring of [`score`], [`score_own`] and [`score_parts`]: the candidate refit on
/// `train` (from `nested`, the structure it is nested in already fitted, when given),
/// evaluated on each part, compared with its null part by part on the residual of `mode`.
/// The [`Scored`] keeps the evaluation of the first part whose run ran away, else of the
/// first part.
#[allow(clippy::too_many_arguments)]
fn score_parts_inner(
    cand: Candidate,
    train: &Dataset,
    parts: &[Dataset],
    base_fit: &serde_json::Value,
    null: Option<&[Eval]>,
    own: bool,
    nested: Option<&Fitted>,
    mode: Mode,
) -> Scored {
    let fitted = match super::refit::fit_spec_on(&cand.spec, train, base_fit, nested) {
        Ok(f) => f,
        Err(e) => return Scored::failed(cand, None, None, e.to_string()),
    };
    let evals = match parts
        .iter()
        .map(|p| Eval::new(&fitted.model, p))
        .collect::<Result<Vec<_>, _>>()
    {
        Ok(e) => e,
        Err(e) => return Scored::failed(cand, Some(fitted), None, e.to_string()),
    };
    let own_null;
    let null = match (null, &cand.null) {
        (Some(n), _) if own => n,
        (Some(n), None) => n,
        (_, Some(ns)) => match fit_spec(ns, train, base_fit)
            .map_err(|e| e.to_string())
            .and_then(|f| {
                parts
                    .iter()
                    .map(|p| Eval::new(&f.model, p))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| e.to_string())
            }) {
            Ok(e) => {
                own_null = e;
                &own_null[..]
            }
            Err(e) => {
                let why = format!("the structure it is nested in cannot be refit: {e}");
                let first = evals.into_iter().next();
                return Scored::failed(cand, Some(fitted), first, why);
            }
        },
        (None, None) => {
            let why = "no null structure to compare it with".to_string();
            let first = evals.into_iter().next();
            return Scored::failed(cand, Some(fitted), first, why);
        }
    };
    // a run that leaves the measured range by an order of magnitude has failed as surely as
    // one that overflows: its error measures the estimate, not the structure, and against a
    // null that ran away too it would still "explain" nearly all of the error (a Lur'e
    // channel whose frequency the refinement drove to 1e-88 on a plant whose subspace model
    // diverged: after VAF 0, "explains 100 %")
    let away = evals
        .iter()
        .position(|e| e.loss(mode).iter().any(|v| !v.is_finite()) || e.runs_away(mode));
    if let Some(i) = away {
        let why = format!(
            "the refit model's {} on the validation data runs away (leaves the measured outputs' range by more than {RUNAWAY} times its half-width, or overflows)",
            match mode {
                Mode::FreeRun => "free run",
                Mode::Predictor => "one-step prediction",
            }
        );
        let e = evals.into_iter().nth(i);
        return Scored::failed(cand, Some(fitted), e, why);
    }
    // a null whose run is not finite leaves no error to explain: the comparison failed (it
    // is not a variant that "explains 0 %", which is what the test made of a NaN sum)
    if null
        .iter()
        .any(|n| n.loss(mode).iter().any(|v| !v.is_finite()))
    {
        let why = format!(
            "the null structure's {} on the validation data is not finite: nothing to compare the variant with",
            match mode {
                Mode::FreeRun => "free run",
                Mode::Predictor => "one-step prediction",
            }
        );
        return Scored::failed(cand, Some(fitted), evals.into_iter().next(), why);
    }
    // the symmetric memory rule corrects refits of the model's own structure; a variant
    // with its own null structure is compared with it as scored (super::memory::judged)
    let (mut basis, mut loss0, mut loss1) = (Basis::EstimatedStart, vec![], vec![]);
    for (i, (eval, null)) in evals.iter().zip(null).enumerate() {
        let (b, l0, l1) = if own || cand.null.is_some() {
            (Basis::EstimatedStart, null.loss(mode), eval.loss(mode))
        } else {
            judged(eval, null, mode)
        };
        if i == 0 {
            basis = b;
        }
        loss0.extend(l0);
        loss1.extend(l1);
    }
    let c = compare_in(&loss0, &loss1, basis.batches(loss0.len()));
    Scored {
        cand,
        fitted: Some(fitted),
        eval: evals.into_iter().next(),
        explained: c.explained,
        t: c.t,
        p_value: c.p_value,
        ratios: c.ratios,
        basis,
        error: None,
        seconds: 0.0,
    }
}

/// The structure `spec` fitted with the output-error refinement: the null of the scheduling
/// effects' refined variants ([`super::refit::fit_nested`]) and of the output-nonlinearity
/// candidates, and the larger past window refined for an own-output finding.
pub fn refined_null(spec: &Spec) -> Spec {
    Spec {
        refined: true,
        nested_in: None,
        latent: None,
        ..spec.clone()
    }
}

/// Whether a scored variant must also beat the model's own structure refined by output error
/// ([`refined_null`]): a scheduling variant (scheduled-output, scheduling-nonlinearity) judged
/// against the model's structure refit ([`Candidate::null`] None; a refined variant is judged
/// against the refined structure already). Its gain over the subspace refit can be the bias
/// of that estimate, which a richer scheduling basis absorbs and the structure's own
/// refinement removes: on the family's clean plants 9003 and 21000 (affine in p1) a p1^2 basis
/// was a replicated finding (70 % and 26 %), while the user's affine structure refined reached
/// a lower held-out error than the fix (6.1e-4 against 4.1e-3, 6.3e-4 against 6.8e-4).
/// The scheduling-noise variants judged against the refit, those that add low-pass
/// scheduling signals beside the measured ones, are a richer scheduling basis too (the latent
/// sequence and LPV-ARX have nulls of their own): on the fresh range 127000's clean plant
/// 127001 (affine in p1) lowpass0.8(p1) explained 14.1 % of the refit's held-out error,
/// replicated (5.3 %, 7.1 %).
/// A logged column added as a scheduling signal or an input channel (`unused-signal`) is
/// more coefficients of the same kind: on a plant of an independent generator whose logged
/// column `w` enters nowhere (docs/bench-diagnose.md, "A logged column must beat the
/// refined structure"), `w` as a scheduling signal explained 34.8 % of the refit's held-out
/// error, replicated, while the structure refined explained 42.1 %. An input channel
/// u^2, |u| u or sign(u) (`input-nonlinearity`) likewise: on that generator's seed 1 |u1| u1
/// explained 36.4 %, the structure refined 79.8 %; a nonlinearity the bias hides is found by
/// the nested variant, refined from that refined structure (`catalogue`). A noise model
/// fitted by PBSID (`coloured-noise`, more states through K), judged on the one-step error:
/// on seeds 1 and 6 of that generator (white output noise; the plant's output gain scheduled,
/// which the model lacks) one and two more states explained 43.7 % and 71.7 % of the refit's
/// one-step error while the refined structure's free-run residual, coloured by the missing
/// output gain, passed the states check ([`super::states::states_check`]).
pub fn needs_refined_null(s: &Scored) -> bool {
    matches!(
        s.cand.effect,
        Effect::ScheduledOutput
            | Effect::SchedulingNonlinearity
            | Effect::SchedulingNoise
            | Effect::UnusedSignal
            | Effect::InputNonlinearity
            | Effect::ColouredNoise
    ) && s.cand.null.is_none()
        && s.cand.spec.nested_in.is_none()
}

/// Coefficients of a fitted model that are free: the non-zero entries of A^(i), B^(i),
/// C^(i), D^(i) (and K^(i) for a one-step metric) of an LPV-SS model (a structural zero, e.g.
/// D of `--no-feedthrough`, is not counted), the a and b coefficients of an LPV-ARX model;
/// and one for each input channel or scheduling function that reads the model's own output
/// ([`own_output_signals`]): its function f(y) was chosen on the data among the
/// output-nonlinearity candidates, a degree of freedom the coefficients do not show. Without
/// it a Lur'e channel, which enters through B alone (the output equation cannot need the
/// output it computes), counted one coefficient fewer than a constant channel with its D
/// entry, and parsimony named a sqrt|y1| feedback in place of a planted output offset that
/// it did not beat (a chain of tanks with a heater input, docs/bench-diagnose.md).
pub fn parameter_count(model: &ModelFile, mode: Mode) -> usize {
    own_output_signals(&model.signals) + coefficient_count(model, mode)
}

/// Input channels and scheduling functions of `map` that read the model's own output.
pub fn own_output_signals(map: &SignalMap) -> usize {
    map.inputs
        .iter()
        .chain(&map.scheduling)
        .filter(|prod| prod.iter().any(|f| map.own_output(f).is_some()))
        .count()
}

/// The free coefficients of [`parameter_count`], without the own-output functions.
fn coefficient_count(model: &ModelFile, mode: Mode) -> usize {
    let nz = |ms: &[DMatrix<f64>]| {
        ms.iter()
            .map(|m| m.iter().filter(|v| **v != 0.0).count())
            .sum::<usize>()
    };
    match &model.kind {
        ModelKind::Ss(ss) => {
            nz(&ss.a)
                + nz(&ss.b)
                + nz(&ss.c)
                + nz(&ss.d)
                + if mode == Mode::Predictor {
                    nz(&ss.k)
                } else {
                    0
                }
        }
        ModelKind::Arx(m) => {
            m.a.iter().map(|v| v.len()).sum::<usize>()
                + m.b.iter().flatten().map(|v| v.len()).sum::<usize>()
        }
    }
}

/// Held-out error of a scored variant in its effect's residual (the mean of
/// [`Eval::loss`]; infinite without an evaluation): what variants and findings judged against
/// different nulls are compared on.
pub fn held_out_mse(s: &Scored) -> f64 {
    s.eval
        .as_ref()
        .map_or(f64::INFINITY, |e| e.mse(s.cand.effect.metric()))
}

/// The variant that represents each effect, as (effect, index into `scored`, variants tried
/// for it), in the order effects first appear (issue 14): among the effect's variants
/// significant against their own null ([`significant`] at the level of all `tried`) the one
/// with the lowest held-out error ([`held_out_mse`]), else the one explaining most. Variants
/// judged against different nulls (a PBSID refit against the model's structure refit, a
/// refined one against that structure refined, [`Candidate::null`]) are so compared on their
/// own held-out errors, not on fractions of different nulls; with one null both orders agree
/// (explained = 1 - error / the null's error).
pub fn best_variants(scored: &[Scored], tried: usize) -> Vec<(Effect, usize, usize)> {
    let mut best: Vec<(Effect, usize, usize)> = Vec::new();
    let sig = |s: &Scored| s.error.is_none() && significant(s.explained, s.p_value, tried);
    for (i, s) in scored.iter().enumerate() {
        match best.iter_mut().find(|b| b.0 == s.cand.effect) {
            Some(b) => {
                b.2 += 1;
                let cur = &scored[b.1];
                let better = match (sig(s), sig(cur)) {
                    (true, true) => held_out_mse(s) < held_out_mse(cur),
                    (true, false) => true,
                    (false, true) => false,
                    (false, false) => s.explained > cur.explained,
                };
                if better {
                    b.1 = i;
                }
            }
            None => best.push((s.cand.effect, i, 1)),
        }
    }
    for b in best.iter_mut() {
        while let Some(i) = nested_unbeaten(scored, b.1, &sig) {
            b.1 = i;
        }
    }
    best
}

/// The significant variant of the same effect that `scored[big]` only adds input channels to
/// ([`adds_inputs`]) and does not beat, lowest held-out error first: the added channels must
/// earn their place. `big` beats it when its held-out loss is lower at p < [`ALPHA`] on the
/// basis of the symmetric memory rule ([`judged`]: a variant that leans on its estimated
/// start against one that forgets its own is compared from the zero state). A Lur'e channel
/// with a constant beside it ([`super::output::candidates`]) so represents its effect only
/// when the constant helps: on the physical tank 231031 the twin with its constant tied the
/// plain sqrt|y1| (99.0 % held out), won by order, and its constant's equilibrium missed the
/// empty tank the family scores from x0 = 0 (error ratio 1.39 against 132.6 before the
/// twins; docs/bench-diagnose.md). A harmonic series must so beat its shorter series.
fn nested_unbeaten(scored: &[Scored], big: usize, sig: &impl Fn(&Scored) -> bool) -> Option<usize> {
    let b = &scored[big];
    let be = b.eval.as_ref()?;
    let mode = b.cand.effect.metric();
    scored
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            s.cand.effect == b.cand.effect
                && sig(s)
                && adds_inputs(&b.cand.spec, &s.cand.spec)
                && s.eval.as_ref().is_some_and(|se| {
                    let (b, l0, l1) = judged(be, se, mode);
                    let (explained, p) = versus_in(&l0, &l1, b.batches(l0.len()));
                    !(explained > 0.0 && p < ALPHA)
                })
        })
        .min_by(|x, y| held_out_mse(x.1).total_cmp(&held_out_mse(y.1)))
        .map(|(i, _)| i)
}

/// Whether `big` is `small` with input channels appended and nothing else changed (the same
/// scheduling, outputs, windows, order and estimator).
fn adds_inputs(big: &Spec, small: &Spec) -> bool {
    let (bs, ss) = (&big.signals, &small.signals);
    bs.inputs.len() > ss.inputs.len()
        && bs.inputs.starts_with(&ss.inputs)
        && bs.scheduling == ss.scheduling
        && bs.outputs == ss.outputs
        && big.opts.past == small.opts.past
        && big.opts.future == small.opts.future
        && big.opts.order == small.opts.order
        && big.reg_text == small.reg_text
        && big.scheduled_output == small.scheduled_output
        && big.output_ls == small.output_ls
        && big.noise == small.noise
        && big.refined == small.refined
        && big.latent == small.latent
        && big.arx.is_none()
        && small.arx.is_none()
        && big.nested_in.is_none()
        && small.nested_in.is_none()
}

/// One finding: an effect, its best variant, how much it explains and the evidence.
#[derive(Debug, Clone, Serialize)]
pub struct Finding {
    /// Effect name.
    pub effect: &'static str,
    /// What the best variant adds.
    pub detail: String,
    /// Fraction of the held-out error explained (after the coloured-noise adjustment).
    pub explained: f64,
    /// The residual it is scored on: "free-run" or "one-step".
    pub residual: &'static str,
    /// Batch-means t statistic of the per-batch log ratios (descriptive beside `p_value`; on
    /// a short record that of all folds' batches pooled).
    pub t: f64,
    /// One-sided p-value of the full-data test: the signed-rank test of the held-out batch log
    /// ratios ([`crate::significance::Comparison`]), or on a short record the same test of
    /// all folds' batches pooled ([`super::replicate::pooled_p`]).
    pub p_value: f64,
    /// Above the noise threshold.
    pub significant: bool,
    /// Explained fractions of the refits on each half of the training data (only for
    /// variants significant on the full data).
    pub replication: Option<Vec<f64>>,
    /// Validation VAF (mean over outputs, free-run) of the refit with the effect.
    pub vaf: Option<f64>,
    /// How it was compared with its null on the full data ([`super::memory::judged`]).
    pub basis: Basis,
    /// ... and on each training half (with the replication).
    pub replication_basis: Option<Vec<Basis>>,
    /// Variants tried for this effect.
    pub variants: usize,
    /// The evidence, in words.
    pub evidence: Vec<String>,
    /// Why it is not a finding (the rule of the noise threshold that blocked it; None when
    /// it is above the threshold).
    pub blocked_by: Option<String>,
    /// Replicated only with each training half scored on the held-out rows inside the
    /// range of the operating point (scheduling signals, or the output fed back) that half
    /// saw, not on the whole held-out record
    /// ([`super::replicate::Halves`]): its half-refits did not carry over the range.
    pub replicated_within_range: bool,
}

/// Evidence for an effect from the residual tests of the model on validation data.
pub fn evidence(
    effect: Effect,
    free: &ResidualReport,
    one: &ResidualReport,
    base: &Fitted,
    best: Option<&Scored>,
) -> Vec<String> {
    let mut ev = Vec::new();
    let nl = |pred: &dyn Fn(&str) -> bool, ev: &mut Vec<String>| {
        for t in free.nonlinear.iter().filter(|t| pred(&t.regressor)).take(3) {
            ev.push(format!(
                "residual of output {} vs {} at lag {}: r = {:+.3} ({:.1}x its 99 % Bartlett bound {:.3})",
                t.output, t.regressor, t.lag, t.r, t.ratio, t.bound
            ));
        }
    };
    match effect {
        Effect::OutputOffset => {
            for (j, m) in free.mean.iter().enumerate() {
                ev.push(format!(
                    "free-run residual of output {} has mean {:+.3e} = {:.0} % of its RMS (batch-means t = {:.1}, p = {:.2e})",
                    j + 1,
                    m,
                    100.0 * m.abs() / free.rms[j].max(1e-300),
                    free.mean_t[j],
                    free.mean_p[j]
                ));
            }
        }
        Effect::Feedthrough => {
            for c in free.cross.iter().filter(|c| c.kind == "input") {
                let mid = c.r.len() / 2;
                ev.push(format!(
                    "cross-correlation residual {} / {} at lag 0: {:+.3} (band +-{:.3}, Bartlett +-{:.3})",
                    c.output, c.signal, c.r[mid], c.band, c.bartlett_band
                ));
            }
        }
        Effect::ScheduledOutput | Effect::SchedulingNonlinearity => {
            for b in &free.bins {
                ev.push(format!(
                    "residual RMS of output {} across quintiles of {} from {:.3e} to {:.3e} (ratio {:.2}); bin means {}",
                    b.output,
                    b.signal,
                    b.bins.iter().map(|x| x.rms).fold(f64::INFINITY, f64::min),
                    b.bins.iter().map(|x| x.rms).fold(0.0, f64::max),
                    b.rms_ratio,
                    b.bins.iter().map(|x| format!("{:+.2e}", x.mean)).collect::<Vec<_>>().join(" ")
                ));
            }
            if effect == Effect::ScheduledOutput {
                nl(
                    &|r: &str| r.contains("*yhat") || (r.starts_with('p') && r.contains("*u")),
                    &mut ev,
                );
            } else {
                nl(
                    &|r: &str| {
                        r.starts_with('p')
                            && (r.contains('^')
                                || r.matches('p').count() > 1
                                    && !r.contains('u')
                                    && !r.contains("yhat"))
                    },
                    &mut ev,
                );
            }
        }
        Effect::InputNonlinearity => {
            nl(&|r: &str| r.contains('u') && !r.starts_with('p'), &mut ev);
        }
        Effect::InputDelay | Effect::OrderTooLow | Effect::UnusedSignal => {
            let kinds: &[&str] = match effect {
                Effect::UnusedSignal => &["logged"],
                _ => &["input"],
            };
            for c in free.cross.iter().filter(|c| kinds.contains(&c.kind)) {
                ev.push(format!(
                    "cross-correlation residual {} / {}: largest |r| = {:.3} at lag {} ({} the significance bound +-{:.3}: Bartlett's band at level {} with a Bonferroni correction over the lags; the 95 % band is +-{:.3})",
                    c.output,
                    c.signal,
                    c.max_abs,
                    c.at_lag,
                    if c.significant { "beyond" } else { "within" },
                    c.bound,
                    ALPHA,
                    c.bartlett_band
                ));
            }
            if effect == Effect::OrderTooLow {
                for w in &free.whiteness {
                    ev.push(format!(
                        "free-run residual {} autocorrelation: {} of {} lags outside +-{:.3}, Ljung-Box Q = {:.1} (p = {:.1e})",
                        w.output, w.excursions, w.acf.len() - 1, w.band, w.ljung_box, w.p_value
                    ));
                }
                let sv = &base.singular_values;
                let n = base.order;
                if n < sv.len() && sv[n] > 0.0 {
                    ev.push(format!(
                        "singular values around the order {n}: sigma_{n} / sigma_{} = {:.2}",
                        n + 1,
                        sv[n - 1] / sv[n]
                    ));
                }
            }
        }
        Effect::SchedulingNoise => {
            if let Some(sp) = best.and_then(|b| b.fitted.as_ref()).and_then(|f| f.sigma_p) {
                ev.push(format!(
                    "the BC-IV fit uses a scheduling noise sigma_eta = {sp:.4}"
                ));
            }
            if let Some(b) = best.filter(|b| b.cand.spec.arx.is_none()) {
                // the smoothed-scheduling variant (catalogue::Catalogue::smoothed_scheduling)
                ev.push(format!(
                    "the model predicts better when the slow part of the scheduling signal is weighted apart from its fast part, as with a white sensor noise on it: {}",
                    b.cand.detail
                ));
            }
            nl(
                &|r: &str| r.starts_with('p') && (r.contains("*u") || r.contains("*y")),
                &mut ev,
            );
        }
        Effect::PeriodicDisturbance => {
            if let Some(b) = best {
                // the candidate's line comes from the training residual (choosing it on the
                // validation data would score it on the data it was chosen with)
                ev.push(format!(
                    "the candidate adds the lines of the refit's training residual, grouped as a harmonic series of one fundamental: {}",
                    b.cand.detail
                ));
            }
            for s in &free.spectrum {
                match s.peaks.first() {
                    Some(p) => ev.push(format!(
                        "validation periodogram of residual {}: line at {:.4} rad/sample (period {:.2} samples), {:.0}x the local level (threshold {:.1})",
                        s.output, p.omega, p.period, p.ratio, p.threshold
                    )),
                    None => ev.push(format!(
                        "validation periodogram of residual {}: no significant line (largest {:.1}x the local level at {:.4} rad/sample, threshold {:.1})",
                        s.output, s.top.ratio, s.top.omega, s.top.threshold
                    )),
                }
            }
        }
        Effect::ColouredNoise => {
            for w in &one.whiteness {
                ev.push(format!(
                    "one-step residual {} autocorrelation: {} of {} lags outside +-{:.3}, Ljung-Box Q = {:.1} on {} lags (p = {:.1e})",
                    w.output, w.excursions, w.acf.len() - 1, w.band, w.ljung_box, w.dof, w.p_value
                ));
            }
            if let Some(f) = best.and_then(|b| b.fitted.as_ref()) {
                if !f.noise_orders.is_empty() {
                    ev.push(format!(
                        "BIC chooses autoregressive noise orders {:?} for the outputs",
                        f.noise_orders
                    ));
                }
            }
        }
        // the output-nonlinearity candidates (diagnose/output.rs)
        Effect::OutputNonlinearity => ev.extend(super::output::evidence(best)),
    }
    ev
}

/// A variant's held-out loss `loss1` against a null's `loss0` (same mode): the explained
/// fraction and the p-value of [`compare`]; (-inf, 1) when the variant's loss is not finite
/// or the records differ.
pub fn versus(loss0: &[f64], loss1: &[f64]) -> (f64, f64) {
    versus_in(loss0, loss1, crate::significance::batch_count(loss0.len()))
}

/// [`versus`] in `batches` batches ([`crate::significance::compare_in`]; the batches of a
/// comparison [`super::memory::judged`] chose, [`Basis::batches`]).
pub fn versus_in(loss0: &[f64], loss1: &[f64], batches: usize) -> (f64, f64) {
    if loss1.len() != loss0.len() || loss1.iter().any(|v| !v.is_finite()) {
        return (f64::NEG_INFINITY, 1.0);
    }
    let c = crate::significance::compare_in(loss0, loss1, batches);
    (c.explained, c.p_value)
}

/// Whether a variant judged against its own null ([`Candidate::null`]: the BC-IV path's
/// LPV-ARX fit, the refined structure of an own-output candidate) also improves on the null
/// refit of the model's own structure, which its fix would replace: on a long held-out record
/// with the evidence a finding needs ([`significant`], at the same Bonferroni level), on a
/// short one (whose held-out test alone cannot pass that level, [`super::replicate::SHORT_BATCHES`]) at least
/// a lower held-out error. `vs_user` is [`versus`] of the model's null refit and the variant.
/// Without it a BC-IV correction that explained 100 % of its own LPV-ARX null's error was
/// applied to a seed-3000 output-offset plant of the family and made the user's LPV-SS
/// model's held-out error 6.7 times worse (docs/bench-diagnose.md). The same rule judges a
/// finding against the model's structure with a larger past window ([`larger_past`],
/// `vs_user` then [`versus_larger`]; not asked of `order-too-low`, whose variants are the
/// larger structures themselves).
pub fn beats_user(vs_user: (f64, f64), tried: usize, short: bool) -> bool {
    if short {
        vs_user.0 > 0.0
    } else {
        significant(vs_user.0, vs_user.1, tried)
    }
}

/// Whether a scored variant is above the noise threshold with `tried` variants in all.
pub fn significant(explained: f64, p_value: f64, tried: usize) -> bool {
    explained >= MIN_EXPLAINED && p_value < ALPHA / tried.max(1) as f64
}

/// The model of a scored variant, if it has one.
pub fn model_of(s: &Scored) -> Option<&ModelFile> {
    s.fitted.as_ref().map(|f| &f.model)
}

/// Is this an LPV-ARX model?
pub fn is_arx(m: &ModelFile) -> bool {
    matches!(m.kind, ModelKind::Arx(_))
}

/// The model's own structure refit with a larger past window (same order setting, same
/// signals, same regularisation): the `order-too-low` variant "past window p + 2" of
/// [`super::catalogue::candidates`], which a careful user would try first when the held-out error looks biased.
/// A finding must also beat it ([`beats_user`] on [`versus_larger`]). A past window p truncates the
/// predictor's memory of the plant at lag p; when the plant's (frozen) dynamics are slower,
/// the user's refit is biased, and that bias gets credited to whichever effect absorbs it
/// best: on the family's clean scheduled plants an offset channel (20 %), p1^2 (70 %) or two
/// noise states through K (47 % of the one-step error) passed every test of a finding
/// (docs/bench-diagnose.md). Why the past window alone, not order + 1 as well: a larger
/// past window leaves the model class unchanged (the same order and structure; only the
/// estimator's bias shrinks), so it cannot absorb a real effect, while one or two more
/// states reproduce an input delay of one or two samples exactly, or noise states.
///
/// When the regressor of p + 2 exceeds [`MAX_REGRESSORS`] (and twice the model's own:
/// LPV-PBSID's Kronecker regressor grows as m^p with m - 1 scheduling signals, so a
/// scheduled model at past 7 has 508 regressors and at past 9 2044), it is fitted in the
/// kernel form (`Solver::Dual`, the cost of which does not grow with the regressor length)
/// when the record has at most [`MAX_KERNEL_WINDOWS`] windows, as the scheduling effects
/// are; otherwise p + 1 is tried, then nothing (None; also for LPV-ARX models).
pub fn larger_past(spec: &Spec, rows: usize) -> Option<Candidate> {
    let past = spec.opts.past;
    for p in [past + 2, past + 1] {
        let Some(sp) = with_past(spec, p, rows) else {
            continue;
        };
        let detail = format!(
            "past window {p} (was {past}), order {}",
            match sp.opts.order {
                Order::Auto => "from the singular values".to_string(),
                Order::Fixed(o) => o.to_string(),
            }
        );
        return Some(Candidate {
            effect: Effect::OrderTooLow,
            detail,
            spec: sp,
            null: None,
        });
    }
    None
}

/// `spec` with past window `p` (a future window capped at `p`), the structure it is nested in
/// alike: in the kernel form (`Solver::Dual`) when its regression grows beyond
/// [`MAX_REGRESSORS`] (or twice its own) and the record of `rows` samples has at most
/// [`MAX_KERNEL_WINDOWS`] windows ([`larger_past`]). None for an LPV-ARX model (no past
/// window) or when neither form can fit it.
pub fn with_past(spec: &Spec, p: usize, rows: usize) -> Option<Spec> {
    if spec.arx.is_some() {
        return None;
    }
    let mut sp = spec.clone();
    sp.opts.past = p;
    if let Some(f) = sp.opts.future {
        sp.opts.future = Some(f.min(p));
    }
    if regressors(&sp) > MAX_REGRESSORS.max(2 * regressors(spec)) {
        if rows.saturating_sub(p) > MAX_KERNEL_WINDOWS {
            return None;
        }
        sp.opts.solver = crate::pbsid::Solver::Dual;
    }
    if let Some(n) = &spec.nested_in {
        sp.nested_in = Some(Box::new(with_past(n, p, rows)?));
    }
    Some(sp)
}

/// Whether `c` is the structure `larger` of [`larger_past`] (the same past window and order
/// setting of an `order-too-low` variant without its own null): then it is not refit twice.
pub fn is_larger_past(c: &Candidate, larger: &Candidate) -> bool {
    c.effect == Effect::OrderTooLow
        && c.null.is_none()
        && c.spec.opts.past == larger.spec.opts.past
        && c.spec.opts.order == larger.spec.opts.order
        && c.spec.opts.future == larger.spec.opts.future
}

/// A variant's held-out loss `loss1` against the model's own structure with a larger past
/// window, `loss_larger` ([`larger_past`]; same mode): [`versus`], or None when that
/// structure's free run diverged (a variant needs no evidence against a diverged model).
pub fn versus_larger(loss_larger: &[f64], loss1: &[f64]) -> Option<(f64, f64)> {
    versus_larger_in(
        loss_larger,
        loss1,
        crate::significance::batch_count(loss_larger.len()),
    )
}

/// [`versus_larger`] in `batches` batches ([`versus_in`]).
pub fn versus_larger_in(loss_larger: &[f64], loss1: &[f64], batches: usize) -> Option<(f64, f64)> {
    loss_larger
        .iter()
        .all(|v| v.is_finite())
        .then(|| versus_in(loss_larger, loss1, batches))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Factor;

    /// A Lur'e channel sqrt|y1| and a quasi-LPV function |y1| count one each for the choice
    /// of f(y); a constant channel, a plain input and u1^2 count none.
    #[test]
    fn own_output_signals_count_the_chosen_functions() {
        let mut map = SignalMap::standard(1, 1, 1);
        assert_eq!(own_output_signals(&map), 0);
        let mut sq = Factor::col("u1");
        sq.pow = 2.0;
        map.inputs.push(vec![sq]);
        map.inputs.push(vec![]);
        assert_eq!(own_output_signals(&map), 0);
        let mut root = Factor::col("y1");
        root.pow = 0.5;
        map.inputs.push(vec![root]);
        assert_eq!(own_output_signals(&map), 1);
        let mut abs = Factor::col("y1");
        abs.func = Some(crate::model::FactorFn::Abs);
        map.scheduling.push(vec![abs]);
        assert_eq!(own_output_signals(&map), 2);
    }

    /// A null whose held-out free run is not finite leaves nothing to compare with: the
    /// variant's score is a failed comparison that says so, not "explains 0 %" at p = 1 (what
    /// the test made of a NaN sum).
    #[test]
    fn a_null_that_is_not_finite_fails_the_comparison() {
        let case = crate::diagnose::plants::family_case("clean", 5, 600).unwrap();
        let train = crate::pipeline::DataFile {
            path: "train.csv".into(),
            data: case.train.clone(),
            bytes: vec![],
        };
        let mut settings = crate::pipeline::PbsidSettings::new(5);
        settings.fit.order = Order::Fixed(case.planted.order);
        let model = crate::pipeline::identify(&train, None, &settings)
            .unwrap()
            .model;
        let spec = Spec::from_model(&model, &mut vec![]).unwrap();
        let mut larger = spec.clone();
        larger.opts.order = Order::Fixed(case.planted.order + 1);
        let cand = Candidate {
            effect: Effect::OrderTooLow,
            detail: "one more state".into(),
            spec: larger,
            null: None,
        };
        let null = Eval::new(&model, &case.val).unwrap();
        let fine = score(
            cand.clone(),
            &case.train,
            &case.val,
            &model.fit,
            Some(&null),
        );
        assert!(
            fine.error.is_none() && fine.explained.is_finite(),
            "{:?}",
            fine.error
        );
        let mut broken = null.clone();
        let k = broken.skip + 10;
        broken.yhat_free[(k, 0)] = f64::NAN;
        let s = score(cand, &case.train, &case.val, &model.fit, Some(&broken));
        let why = s.error.expect("a failed comparison");
        assert!(
            why.contains("null structure") && why.contains("not finite"),
            "{why}"
        );
        assert_eq!((s.explained, s.p_value), (f64::NEG_INFINITY, 1.0));
    }

    /// A variant that only adds a channel to another significant variant of its effect
    /// represents the effect only when it beats that variant (p < ALPHA): a tie goes to the
    /// smaller structure, a clear gain to the larger, and a variant that changes something
    /// else than its inputs is not nested.
    #[test]
    fn an_added_channel_must_earn_its_place() {
        let spec = super::super::refit::tests::plain();
        let mut cube = Factor::col("y1");
        cube.pow = 3.0;
        let mut plain = spec.clone();
        plain.signals.inputs.push(vec![cube]);
        let mut twin = plain.clone();
        twin.signals.inputs.push(vec![]);
        assert!(adds_inputs(&twin, &plain) && !adds_inputs(&plain, &twin));
        let mut longer = twin.clone();
        longer.opts.past = 10;
        assert!(!adds_inputs(&longer, &plain));
        // held-out errors: white noise of a given scale about a sine, drawn from `seed`
        let n = 4000;
        let y = DMatrix::from_fn(n, 1, |k, _| (0.05 * k as f64).sin());
        let noise =
            |seed: f64, k: usize| ((k as f64 * 12.9898 + seed).sin() * 43758.5453).fract() - 0.5;
        let scored = |sp: &Spec, scale: f64, seed: f64| {
            let yhat = DMatrix::from_fn(n, 1, |k, _| y[(k, 0)] + scale * noise(seed, k));
            Scored {
                cand: Candidate {
                    effect: Effect::OutputNonlinearity,
                    detail: String::new(),
                    spec: sp.clone(),
                    null: None,
                },
                fitted: None,
                eval: Some(Eval {
                    y: y.clone(),
                    yhat_free: yhat.clone(),
                    yhat_pred: yhat.clone(),
                    yhat_zero: yhat,
                    var_y: vec![0.5],
                    skip: 0,
                }),
                explained: 0.99,
                t: 10.0,
                p_value: 1e-12,
                ratios: vec![],
                basis: Basis::EstimatedStart,
                error: None,
                seconds: 0.0,
            }
        };
        // the twin 0.5 % better, other draws: a tie, the plain channel represents the effect
        let tie = [scored(&twin, 0.0995, 1.0), scored(&plain, 0.1, 2.0)];
        assert!(held_out_mse(&tie[0]) < held_out_mse(&tie[1]));
        assert_eq!(
            best_variants(&tie, 2),
            vec![(Effect::OutputNonlinearity, 1, 2)]
        );
        // the twin's error a third lower on every sample: it earns its place
        let gain = [scored(&twin, 0.08, 1.0), scored(&plain, 0.1, 2.0)];
        assert_eq!(
            best_variants(&gain, 2),
            vec![(Effect::OutputNonlinearity, 0, 2)]
        );
    }
}
