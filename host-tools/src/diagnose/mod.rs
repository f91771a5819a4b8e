//! Closing the loop with measured data (DESIGN.md section 6): `lpvid diagnose` computes the
//! residual of a model on validation data, tests it ([`residual`]), scores every candidate
//! missing effect of the catalogue ([`catalogue`]) by how much of the held-out residual a refit
//! with the effect added explains ([`refit`]), and with `--fix` adds the best one, refits
//! with the model's own settings and reports the error before and after ([`report`]), with
//! pictures ([`plots`]). Before an effect is named, its variant must also beat the model's
//! own structure refit with a larger past window ([`effects::larger_past`]): the bias of a
//! past window too short for the model's own structure is otherwise credited to whichever
//! effect absorbs it best; when that larger past window is what removes the error, it is
//! the `order-too-low` finding.
//!
//! Where each idea lives: [`stats`] (distributions, correlations, FFT, batch means, least
//! squares on the core's Gram), [`residual`] (the tests), [`catalogue`] (the variants of
//! each effect, one method per effect), [`output`] (the own-output variants), [`effects`]
//! (scoring on held-out data, the noise threshold, the evidence), [`replicate`] (replication
//! on training halves, cross-validation of short records), [`states`] (coloured-noise and
//! order-too-low against the refined structure), [`memory`] (scores that lean on the
//! estimated start), `judge` (the rules of a finding in order, the rule that blocked it),
//! `rank` (which finding comes first), [`encompass`] (the encompassing test of two
//! findings), [`refit`] (the model's own settings, constant channels, scheduled output
//! equation, noise model, BC-IV path), [`report`] (JSON and the engineer's note), [`plots`]
//! (SVG), [`plants`] (random plant families with one planted effect, for measuring the
//! diagnosis).

pub mod catalogue;
pub mod effects;
pub mod encompass;
mod judge;
pub mod latent;
pub mod memory;
pub mod output;
pub mod plants;
pub mod plots;
mod rank;
pub mod refit;
pub mod replicate;
pub mod report;
pub mod residual;
pub mod states;
pub mod stats;

use serde::Serialize;

use crate::data::{DataError, Dataset};
use crate::model::ModelFile;
use crate::simulate::{score_from, Mode, Score, X0};

use catalogue::{candidates, Context};
use effects::{Effect, Eval, Finding, Scored};
use refit::{fit_spec, Fitted, Spec};

pub use refit::RefitError;

/// Why a diagnosis could not be made at all (a candidate's failed refit is not an error:
/// it is recorded in the report).
#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    /// The validation or training data lack a column the model reads.
    #[error(transparent)]
    Data(#[from] DataError),
    /// The model's settings cannot be read back, or a step every candidate needs failed.
    #[error(transparent)]
    Refit(#[from] RefitError),
}
use residual::{analyse, ResidualReport, ALPHA};

/// What to do besides the diagnosis.
#[derive(Debug, Clone)]
pub struct Options {
    /// Add the best effect and refit.
    pub fix: bool,
    /// Repeat the fix at most this many times while the error drops meaningfully.
    pub max_steps: usize,
    /// Worker threads for the candidate refits (0: the machine's parallelism).
    pub threads: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            fix: false,
            max_steps: 1,
            threads: 0,
        }
    }
}

/// One applied fix.
#[derive(Debug, Clone, Serialize)]
pub struct Applied {
    /// 1-based step.
    pub step: usize,
    /// Effect name.
    pub effect: &'static str,
    /// What was added.
    pub detail: String,
    /// Fraction of the held-out error it explained.
    pub explained: f64,
    /// The residual it was scored on.
    pub residual: &'static str,
    /// Normalised validation MSE (mean over outputs of MSE / var y) before this step.
    pub mse_before: f64,
    /// ... and after.
    pub mse_after: f64,
    /// Mean free-run VAF before / after this step.
    pub vaf_before: f64,
    /// Mean free-run VAF after this step.
    pub vaf_after: f64,
}

/// The model's own structure refined by output error, written by `--fix` when nothing is
/// missing from the structure but its subspace estimate is biased (the last step's
/// [`states::refined_gain`]): the structure is kept, its estimate refined, as `lpvid pbsid
/// --refine` does.
#[derive(Debug, Clone, Serialize)]
pub struct RefinedFix {
    /// 1-based step whose structure was refined.
    pub step: usize,
    /// Fraction of the held-out free-run error of the structure's refit it explains.
    pub explained: f64,
    /// The p-value of that comparison (the level of a finding at that step).
    pub p_value: f64,
    /// Normalised held-out free-run MSE (mean over outputs of MSE / var y) before.
    pub mse_before: f64,
    /// ... and after.
    pub mse_after: f64,
    /// Mean free-run VAF before.
    pub vaf_before: f64,
    /// ... and after.
    pub vaf_after: f64,
}

/// The diagnosis of one step (the model as it stood then).
#[derive(Debug, Clone, Serialize)]
pub struct Step {
    /// 1-based.
    pub step: usize,
    /// Validation VAF (mean, free-run) of the null refit the candidates were compared with.
    pub null_refit_vaf: f64,
    /// Normalised validation MSE of the null refit (free-run, one-step).
    pub null_refit_mse: (f64, f64),
    /// Variants refit and scored.
    pub variants: usize,
    /// Ranked findings: above the threshold first, then by explained fraction.
    pub findings: Vec<Finding>,
    /// Effects that did not apply, with why.
    pub not_applicable: Vec<(String, String)>,
    /// Every variant refit and its score.
    pub variants_scored: Vec<VariantScore>,
}

/// One refit variant and its score.
#[derive(Debug, Clone, Serialize)]
pub struct VariantScore {
    /// Effect name.
    pub effect: &'static str,
    /// What it adds.
    pub detail: String,
    /// Fraction of the null refit's held-out error it removes (raw, before any adjustment).
    pub explained: f64,
    /// How it was compared with its null ([`memory::judged`]).
    pub basis: memory::Basis,
    /// One-sided p-value.
    pub p_value: f64,
    /// Why it could not be scored.
    pub error: Option<String>,
    /// Wall time of the refit and its evaluation, seconds.
    pub seconds: f64,
}

/// The statistical threshold, as reported.
#[derive(Debug, Clone, Serialize)]
pub struct Threshold {
    /// Family-wise level.
    pub alpha: f64,
    /// Smallest explained fraction.
    pub min_explained: f64,
    /// The test, in words.
    pub test: &'static str,
}

/// Residual tests of the given model on validation data.
#[derive(Debug, Clone, Serialize)]
pub struct Residuals {
    /// Free-run residual.
    pub free_run: ResidualReport,
    /// One-step residual.
    pub one_step: ResidualReport,
}

/// The report (`--json`).
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// "diagnose".
    pub command: &'static str,
    /// Model source.
    pub model: String,
    /// Training data.
    pub train: String,
    /// Validation data.
    pub val: String,
    /// Model type and dimensions in words.
    pub model_summary: String,
    /// VAF and BFR per output on validation data, free run, of the given model.
    pub before: Score,
    /// ... one-step prediction.
    pub before_one_step: Score,
    /// After the fixes (None without --fix or when the model was not changed:
    /// [`Report::changed`]).
    pub after: Option<Score>,
    /// ... one-step prediction.
    pub after_one_step: Option<Score>,
    /// Ranked findings of the first step.
    pub findings: Vec<Finding>,
    /// Fixes applied, in order.
    pub applied: Vec<Applied>,
    /// With `--fix`, when no effect explains the residual of the last step's structure but
    /// that structure refined by output error predicts the held-out record significantly
    /// better: the refined structure is the model written ([`RefinedFix`]).
    pub refined: Option<RefinedFix>,
    /// Every step's diagnosis.
    pub steps: Vec<Step>,
    /// Why the loop stopped.
    pub stopped: String,
    /// The noise threshold.
    pub threshold: Threshold,
    /// Residual tests of the given model.
    pub residual: Residuals,
    /// Remarks (missing fit settings, refit differences).
    pub notes: Vec<String>,
    /// Where the fixed model was written.
    pub out: Option<String>,
    /// When the held-out data were carved from the training record: the chosen structure
    /// refit on all of it ([`refit_on_all`]; None otherwise).
    pub refit_all: Option<RefitAll>,
}

impl Report {
    /// Whether the diagnosis changed the model: a fix applied, or the structure's estimate
    /// refined ([`Report::refined`]).
    pub fn changed(&self) -> bool {
        !self.applied.is_empty() || self.refined.is_some()
    }
}

/// The final refit on the whole record ([`refit_on_all`]).
#[derive(Debug, Clone, Serialize)]
pub struct RefitAll {
    /// Rows it was fitted on (training + held-out).
    pub rows: usize,
    /// Its free-run score on the held-out rows: IN-SAMPLE (those rows are in its fit). The
    /// held-out estimate of the structure stays `after` (fitted without them).
    pub in_sample: Score,
}

/// Everything a diagnosis produces.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The report.
    pub report: Report,
    /// The final model (the given one when it was not changed: [`Report::changed`]).
    pub model: ModelFile,
    /// Evaluation of the given model on validation data.
    pub before_eval: Eval,
    /// Evaluation of the final model (when it was changed).
    pub after_eval: Option<Eval>,
    /// Singular values of the first null refit and of the final model's fit.
    pub singular_values: (Vec<f64>, Vec<f64>),
}

fn mean_vaf(e: &Eval) -> f64 {
    let v = crate::metrics::vaf_per_output(&e.y, &e.yhat_free, e.skip);
    crate::metrics::mean(&v)
}

fn mode_name(m: Mode) -> &'static str {
    match m {
        Mode::FreeRun => "free-run",
        Mode::Predictor => "one-step",
    }
}

/// A null structure some candidates of a step are compared with instead of the model's own
/// (the BC-IV fit without its correction, the refined fit of an own-output candidate's
/// structure), fitted once per step by [`score_all`].
pub(crate) struct NullFit {
    /// The structure's [`Spec::key`] (by which the candidates' nulls are found).
    pub key: String,
    /// Its fit on the training data.
    pub fitted: Fitted,
    /// Its held-out evaluation.
    pub eval: Eval,
}

/// Refit and score every candidate, on `threads` worker threads; with the null structures
/// fitted on the way.
fn score_all(
    cands: Vec<effects::Candidate>,
    train: &Dataset,
    val: &Dataset,
    fit: &serde_json::Value,
    base: &Eval,
    threads: usize,
    progress: Option<Progress<'_>>,
) -> (Vec<Scored>, Vec<NullFit>) {
    let threads = if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    };
    // the null structures some candidates are compared with instead of the model's own
    // (the BC-IV fit without its correction, the refined fit of an own-output candidate's
    // structure): refit once per distinct structure, not once per candidate, on the worker
    // threads too (a refined null is a refinement by output error); a candidate nested in its
    // null starts from the null's fit (effects::score_own)
    let mut keys: Vec<(String, &Spec)> = Vec::new();
    for c in &cands {
        let Some(ns) = &c.null else { continue };
        let key = ns.key();
        if !keys.iter().any(|(k, _)| *k == key) {
            keys.push((key, ns));
        }
    }
    // a null that cannot be refit is left to `effects::score`, which reports why
    let nulls: Vec<NullFit> = parallel_map(
        &keys,
        threads,
        |(key, ns)| {
            let f = fit_spec(ns, train, fit).ok()?;
            let e = Eval::new(&f.model, val).ok()?;
            Some(NullFit {
                key: key.clone(),
                fitted: f,
                eval: e,
            })
        },
        |_| {},
    )
    .into_iter()
    .flatten()
    .collect();
    let results = parallel_map(
        &cands,
        threads,
        |c| {
            let own = c.null.as_ref().and_then(|ns| {
                let key = ns.key();
                nulls.iter().find(|n| n.key == key)
            });
            // the own null's evaluation is given: score against it without refitting it
            match own {
                Some(n) => effects::score_own(c.clone(), train, val, fit, &n.eval, &n.fitted),
                None => effects::score(c.clone(), train, val, fit, Some(base)),
            }
        },
        |done| {
            if let Some(p) = progress {
                p(done, cands.len());
            }
        },
    );
    (results, nulls)
}

/// `f` of each item on `threads` worker threads, the results in the items' order; `done`
/// is told how many are finished after each one. Each item's result is what `f` computes
/// alone, whichever thread runs it.
pub(crate) fn parallel_map<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    f: impl Fn(&T) -> R + Sync,
    done: impl Fn(usize) + Sync,
) -> Vec<R> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let slots: std::sync::Mutex<Vec<Option<R>>> =
        std::sync::Mutex::new(items.iter().map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..threads.clamp(1, items.len().max(1)) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                let r = f(item);
                let finished = {
                    let mut slots = slots.lock().expect("no panics while holding the lock");
                    slots[i] = Some(r);
                    slots.iter().filter(|r| r.is_some()).count()
                };
                done(finished);
            });
        }
    });
    slots
        .into_inner()
        .expect("no panics while holding the lock")
        .into_iter()
        .flatten()
        .collect()
}

/// `spec` refit on `train` ([`fit_spec`]) and evaluated on `val` ([`Eval::new`]); None when
/// either fails.
fn fit_eval(
    spec: &Spec,
    train: &Dataset,
    val: &Dataset,
    base_fit: &serde_json::Value,
) -> Option<Eval> {
    fit_eval_order(spec, train, val, base_fit).map(|(_, e)| e)
}

/// [`fit_eval`] with the order the refit took (its states).
fn fit_eval_order(
    spec: &Spec,
    train: &Dataset,
    val: &Dataset,
    base_fit: &serde_json::Value,
) -> Option<(usize, Eval)> {
    let f = fit_spec(spec, train, base_fit).ok()?;
    Some((f.order, Eval::new(&f.model, val).ok()?))
}

fn threshold() -> Threshold {
    Threshold {
        alpha: ALPHA,
        min_explained: effects::MIN_EXPLAINED,
        test: "explained >= min_explained and an exact one-sided Wilcoxon signed-rank test of the per-batch log ratios of held-out squared errors (free run from an initial state estimated on the first held-out samples, which are not scored; up to 20 batches of >= 25 samples) at level alpha / (variants tried), replicated on each half of the training data (explained > 0, p < 0.05 each; a half where the variant's or the null's refit runs away from the held-out data, its free run beyond ten times the outputs' half-range, is refit with both one past sample longer; for the two scheduling effects and output-nonlinearity, when no variant replicates so and a half saw only part of the range of the operating point (the scheduling signals; the output fed back) the held-out record covers, that half is scored on the held-out stretches inside its range); a short held-out record (fewer than 20 batches) is cross-validated in 5 contiguous blocks (the held-out record and 4 blocks of the training data; each training block is scored by a refit on the other blocks and the held-out record, against the null structure refit on the same rows): the batches of all 5 folds are pooled in one signed-rank test at that level, and the replication is that all folds but one explain part of the null's error there; every effect but order-too-low must also beat the model's own structure with a past window 2 longer by the same evidence, a scheduling effect judged against the subspace refit also that structure refined by output error, an own-output effect also that structure refined from the variant's own fit with its own-output signals linearised, a periodic disturbance also the same fit without its sinusoids (their columns of B and D zero), and a free-run effect must forget its start as the null refit does (its free runs from the estimated and from the zero state agree at the end of the held-out record to within its own error there, unless the null's do not either); when a free-run variant forgets its start and the model it is compared with (the null refit, on the full data or a training half, or the larger past window) leans on its own, both are compared from the zero state over the second half of the scored rows",
    }
}

/// The residual tests of a model evaluated as `eval` on the held-out data `val` (free run,
/// one-step prediction).
fn residual_reports(eval: &Eval, val: &Dataset) -> (ResidualReport, ResidualReport) {
    (
        analyse(
            "free-run",
            &eval.residual(Mode::FreeRun),
            &eval.yhat_free,
            val,
        ),
        analyse(
            "one-step",
            &eval.residual(Mode::Predictor),
            &eval.yhat_free,
            val,
        ),
    )
}

/// A progress callback: (candidates scored, candidates of the step), called from the worker
/// threads after each candidate refit.
pub type Progress<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// Diagnose `model` with training data `train` and validation data `val`.
pub fn diagnose(
    model: &ModelFile,
    train: &Dataset,
    val: &Dataset,
    opts: &Options,
) -> Result<Outcome, DiagnoseError> {
    diagnose_with_progress(model, train, val, opts, None)
}

/// [`diagnose`], reporting the candidate refits of each step to `progress`.
pub fn diagnose_with_progress(
    model: &ModelFile,
    train: &Dataset,
    val: &Dataset,
    opts: &Options,
    progress: Option<Progress<'_>>,
) -> Result<Outcome, DiagnoseError> {
    // the structure is refit many times on the same record with only the order, the
    // refinement or the noise model changed: their regression is made once
    let _memo = crate::pbsid::memo::Scope::open();
    let mut notes = Vec::new();
    let spec = Spec::from_model(model, &mut notes)?;
    // scored as the candidates are: from an initial state estimated on the first held-out
    // samples (effects::x0_samples), which are then not scored
    let x0 = X0::Estimate {
        samples: effects::x0_samples(val.len()),
    };
    let score_model = |m: &ModelFile, mode: Mode| score_from(m, val, mode, x0);
    let before = score_model(model, Mode::FreeRun)?;
    let before_one_step = score_model(model, Mode::Predictor)?;
    notes.extend(unstable_predictor(model, val, &before_one_step));
    let before_eval = Eval::new(model, val)?;
    notes.extend(runaway_free_run(model, train, val, &before_eval));
    let (free0, one0) = residual_reports(&before_eval, val);
    let mut trail = Trail {
        model: model.clone(),
        steps: Vec::new(),
        applied: Vec::new(),
        refined: None,
        stopped: String::new(),
        notes,
    };
    let singular_values = match fit_spec(&spec, train, &model.fit) {
        Err(e) => {
            // the residual tests still stand; no candidate can be compared with a refit
            trail.stopped = format!(
                "cannot refit the model with its own settings ({e}): no candidate effect was scored"
            );
            (vec![], vec![])
        }
        Ok(base) => {
            let first = base.singular_values.clone();
            let last = fix_steps(
                spec,
                base,
                (&before, &before_eval, (&free0, &one0)),
                (train, val),
                opts,
                progress,
                &mut trail,
            )?;
            (first, last)
        }
    };
    let Trail {
        model: current,
        steps,
        applied,
        refined,
        stopped,
        notes,
    } = trail;
    let (after, after_one_step, after_eval) = if applied.is_empty() && refined.is_none() {
        (None, None, None)
    } else {
        (
            Some(score_model(&current, Mode::FreeRun)?),
            Some(score_model(&current, Mode::Predictor)?),
            Some(Eval::new(&current, val)?),
        )
    };
    let report = Report {
        command: "diagnose",
        model: String::new(),
        train: train.source.clone(),
        val: val.source.clone(),
        model_summary: report::model_summary(model),
        before,
        before_one_step,
        after,
        after_one_step,
        findings: steps
            .first()
            .map(|s| s.findings.clone())
            .unwrap_or_default(),
        applied,
        refined,
        steps,
        stopped,
        threshold: threshold(),
        residual: Residuals {
            free_run: free0,
            one_step: one0,
        },
        notes,
        out: None,
        refit_all: None,
    };
    Ok(Outcome {
        report,
        singular_values,
        model: current,
        before_eval,
        after_eval,
    })
}

/// What the diagnosis has done so far: the model as fixed, each step's record, the fixes
/// applied, why it stopped and its remarks.
struct Trail {
    model: ModelFile,
    steps: Vec<Step>,
    applied: Vec<Applied>,
    refined: Option<RefinedFix>,
    stopped: String,
    notes: Vec<String>,
}

/// The diagnosis's steps from the model's structure `spec` refit as `base`: each step
/// diagnosed ([`diagnose_step`]) and, with `--fix`, its first finding applied, until nothing
/// is found, the fix is not an lpv-ss model or `--max-steps` is reached. `before` is the given
/// model's score, evaluation and residual tests on the held-out data. Returns the singular
/// values of the last structure's fit.
fn fix_steps(
    mut spec: Spec,
    mut base: Fitted,
    (before, before_eval, (free0, one0)): (&Score, &Eval, (&ResidualReport, &ResidualReport)),
    (train, val): (&Dataset, &Dataset),
    opts: &Options,
    progress: Option<Progress<'_>>,
    trail: &mut Trail,
) -> Result<Vec<f64>, DiagnoseError> {
    let max_steps = if opts.fix { opts.max_steps.max(1) } else { 1 };
    // the provenance the given model already carries
    let given = match trail.model.fit.get("diagnose") {
        Some(serde_json::Value::Array(h)) => h.clone(),
        _ => vec![],
    };
    for step_no in 1..=max_steps {
        let base_eval = Eval::new(&base.model, val)?;
        let (free, one) = if step_no == 1 {
            let v_refit = mean_vaf(&base_eval);
            if (v_refit - before.vaf_mean).abs() > 1.0 {
                trail.notes.push(format!(
                    "the refit of the model with its own settings on the training data scores VAF {v_refit:.2} % on the validation data, the given model {:.2} %: candidates are compared with the refit",
                    before.vaf_mean
                ));
            }
            (free0.clone(), one0.clone())
        } else {
            residual_reports(&base_eval, val)
        };
        let Diagnosed { step, top, refined } = diagnose_step(
            step_no,
            &spec,
            &base,
            &base_eval,
            (&free, &one),
            (train, val, &trail.model.fit),
            (opts.threads, progress),
            &mut trail.notes,
        )?;
        // what the first finding explained (a noise model's discounted, as ranked)
        let explained = step.findings.first().map(|f| f.explained);
        trail.steps.push(step);
        // the held-out error and mean VAF a fix of this step starts from: the given model's
        // at step 1, the structure's as fixed so far after
        let before_step = |mode: Mode| {
            if step_no == 1 {
                (before_eval.mse(mode), before.vaf_mean)
            } else {
                (base_eval.mse(mode), mean_vaf(&base_eval))
            }
        };
        let s = match top {
            Ok(s) => s,
            Err(why) => {
                trail.stopped = why;
                // nothing is missing from the structure, but its estimate is biased: the
                // structure refined by output error is the fix
                if let Some(r) = refined.filter(|_| opts.fix) {
                    let (mse_before, vaf_before) = before_step(Mode::FreeRun);
                    let fix = RefinedFix {
                        step: step_no,
                        explained: r.explained,
                        p_value: r.p_value,
                        mse_before,
                        mse_after: r.eval.mse(Mode::FreeRun),
                        vaf_before,
                        vaf_after: mean_vaf(&r.eval),
                    };
                    let mut model = with_provenance(r.model, &given, &trail.applied);
                    if let serde_json::Value::Object(m) = &mut model.fit {
                        m.insert(
                            "refined_by_diagnose".into(),
                            serde_json::json!({"step": fix.step, "explained": fix.explained, "p_value": fix.p_value}),
                        );
                    }
                    trail.model = model;
                    trail.refined = Some(fix);
                }
                break;
            }
        };
        if !opts.fix {
            trail.stopped = "diagnosis only (no --fix)".into();
            break;
        }
        let (Some(fitted), Some(eval)) = (s.fitted, s.eval) else {
            trail.stopped = "the best variant has no model".into();
            break;
        };
        let mode = s.cand.effect.metric();
        let (mse_before, vaf_before) = before_step(mode);
        trail.applied.push(Applied {
            step: step_no,
            effect: s.cand.effect.name(),
            detail: s.cand.detail.clone(),
            explained: explained.unwrap_or(s.explained),
            residual: mode_name(mode),
            mse_before,
            mse_after: eval.mse(mode),
            vaf_before,
            vaf_after: mean_vaf(&eval),
        });
        trail.model = with_provenance(fitted.model.clone(), &given, &trail.applied);
        spec = s.cand.spec.as_written();
        base = Fitted {
            model: trail.model.clone(),
            ..fitted
        };
        if effects::is_arx(&trail.model) {
            trail.stopped = "the model is now an lpv-arx model (BC-IV path); further candidate refits are implemented for lpv-ss models".into();
            break;
        }
        if step_no == max_steps {
            trail.stopped = format!("reached --max-steps {max_steps}");
        }
    }
    Ok(base.singular_values)
}

/// `fixed` with the provenance of the fixes in its fit record (`"diagnose"`: what diagnose
/// added, in order): `given`, the record of the model diagnosed, then `applied`.
fn with_provenance(
    mut fixed: ModelFile,
    given: &[serde_json::Value],
    applied: &[Applied],
) -> ModelFile {
    let mut history = given.to_vec();
    history.extend(applied.iter().map(|a| {
        serde_json::json!({"effect": a.effect, "detail": a.detail, "explained": a.explained, "residual": a.residual})
    }));
    if let serde_json::Value::Object(m) = &mut fixed.fit {
        m.insert("diagnose".into(), serde_json::Value::Array(history));
    }
    fixed
}

/// A note when the model's one-step predictor A(mu) - K(mu) C is unstable over the held-out
/// data's scheduling range (largest frozen spectral radius >= 1,
/// [`crate::observer::max_predictor_radius`]): its one-step prediction then runs away from
/// the outputs, its one-step VAF says nothing of the model's dynamics, and a noise model's
/// error ratio against it is unbounded (the family's coloured-noise plant 197000: order 2,
/// past window 8, radius 1.17, ratio 6.5e199). `lpvid pbsid` warns of it; the report says it
/// again beside the one-step scores it explains.
fn unstable_predictor(model: &ModelFile, val: &Dataset, one_step: &Score) -> Option<String> {
    let crate::model::ModelKind::Ss(ss) = &model.kind else {
        return None;
    };
    let sig = model.signals.evaluate(val).ok()?;
    let names = model.signals.scheduling_names();
    let sbox = crate::observer::SchedBox::from_signals(&names, &sig);
    let rho = crate::observer::max_predictor_radius(ss, &sbox, crate::observer::REPORT_GRID);
    (rho >= 1.0).then(|| {
        format!(
            "the model's one-step predictor A(mu) - K(mu) C is unstable: its spectral radius reaches {rho:.4} over the validation data's scheduling range, so its one-step prediction runs away from the outputs (one-step VAF {} %) and any error ratio against it is unbounded; `lpvid pbsid --observer hinf` designs a stable gain (see `lpvid stability`)",
            one_step
                .vaf
                .iter()
                .map(|v| format!("{v:.2}"))
                .collect::<Vec<_>>()
                .join(" / ")
        )
    })
}

/// A note when the given model's free run runs away on the held-out data
/// ([`Eval::runaway_at`]): every fraction explained is then of a failed run's error, so the
/// user should first get a model that can be simulated; where the held-out scheduling
/// signals leave the training data's range, the model extrapolates there, which is said too.
fn runaway_free_run(
    model: &ModelFile,
    train: &Dataset,
    val: &Dataset,
    eval: &Eval,
) -> Option<String> {
    let k = eval.runaway_at(Mode::FreeRun)?;
    let names = model.signals.scheduling_names();
    let sched_box = |d: &Dataset| {
        let sig = model.signals.evaluate(d).ok()?;
        Some(crate::observer::SchedBox::from_signals(&names, &sig))
    };
    let beyond = match (sched_box(train), sched_box(val)) {
        (Some(t), Some(v)) => (0..v.dim().min(t.dim()))
            .filter(|&j| v.lo[j] < t.lo[j] || v.hi[j] > t.hi[j])
            .map(|j| {
                format!(
                    "{} in [{:.3}, {:.3}] against [{:.3}, {:.3}] in training",
                    v.names[j], v.lo[j], v.hi[j], t.lo[j], t.hi[j]
                )
            })
            .collect::<Vec<_>>(),
        _ => vec![],
    };
    Some(format!(
        "the model's free run runs away on the validation data: from sample {k} its output leaves the measured range by more than {} times the range's half-width, so each fraction explained below is of a failed run's error and a fix is first of all a model that can be simulated{}; a model that can be simulated may come from `lpvid pbsid --refine`, a smaller `--past` or another `--order`",
        effects::RUNAWAY,
        if beyond.is_empty() {
            String::new()
        } else {
            format!(
                " (the validation data leave the training data's scheduling range, where the model extrapolates: {})",
                beyond.join("; ")
            )
        }
    ))
}

/// The residual of the null refit on the TRAINING data that the catalogue designs frequencies
/// from ([`Context::train_residual`]): the free run; where it carries no information (it
/// diverges, or its error exceeds an output's own variance: a model worse than the output's
/// mean), the one-step prediction; where that carries none either, the one-step residual of a
/// linear ARX model fitted by least squares ([`arx_residual`]), which cannot diverge. On the
/// family's periodic-disturbance plant 53002 the user's order-3 refit diverges in free run
/// (error ratio 5.5e156 on the validation record) and its one-step predictor is unstable too
/// (spectral radius 1.17), so no line was seen and no periodic-disturbance variant was tried.
fn design_residual(
    base: &Fitted,
    sig: &crate::lpvss::Signals,
    fb: &crate::model::Feedback,
) -> nalgebra::DMatrix<f64> {
    let run = |mode| &sig.y - crate::simulate::simulate_feedback(&base.model.kind, sig, fb, mode);
    // each output's own variance, once
    let var_y = crate::metrics::output_variances(&sig.y, 0);
    let informative = |res: &nalgebra::DMatrix<f64>| {
        var_y.iter().enumerate().all(|(j, v)| {
            let mse = res.column(j).iter().map(|e| e * e).sum::<f64>() / res.nrows().max(1) as f64;
            mse.is_finite() && mse <= *v
        })
    };
    let free = run(Mode::FreeRun);
    if informative(&free) {
        return free;
    }
    let one_step = run(Mode::Predictor);
    if informative(&one_step) {
        return one_step;
    }
    arx_residual(sig, base.order + 2).unwrap_or(free)
}

/// One-step residual of the linear ARX model y(k) = sum_{i=1..lags} A_i y(k-i) +
/// sum_{j=0..lags} B_j u(k-j) + c fitted by least squares to `sig` (the first `lags` rows
/// zero): a residual that keeps a disturbance's spectral lines whatever the state-space
/// refit does. None when the record is too short or the fit fails.
fn arx_residual(sig: &crate::lpvss::Signals, lags: usize) -> Option<nalgebra::DMatrix<f64>> {
    let (n, l, r) = (sig.y.nrows(), sig.y.ncols(), sig.u.ncols());
    let nreg = lags * l + (lags + 1) * r + 1;
    if n < lags + 4 * nreg {
        return None;
    }
    let fill = |k: usize, row: &mut [f64]| {
        let mut c = 0;
        for i in 1..=lags {
            for j in 0..l {
                row[c] = sig.y[(k - i, j)];
                c += 1;
            }
        }
        for i in 0..=lags {
            for j in 0..r {
                row[c] = sig.u[(k - i, j)];
                c += 1;
            }
        }
        row[c] = 1.0;
    };
    let (theta, _) = stats::lstsq(n - lags, nreg, l, |k, row| {
        let k = k + lags;
        fill(k, &mut row[..nreg]);
        for j in 0..l {
            row[nreg + j] = sig.y[(k, j)];
        }
    })
    .ok()?;
    let mut res = nalgebra::DMatrix::zeros(n, l);
    let mut row = vec![0.0; nreg];
    for k in lags..n {
        fill(k, &mut row);
        for j in 0..l {
            let fit: f64 = (0..nreg).map(|c| theta[(j, c)] * row[c]).sum();
            res[(k, j)] = sig.y[(k, j)] - fit;
        }
    }
    res.iter().all(|v| v.is_finite()).then_some(res)
}

/// One step of the diagnosis: the candidates of the catalogue for the model's structure
/// What [`diagnose_step`] returns.
struct Diagnosed {
    /// The step's record.
    step: Step,
    /// Its first finding's variant, or why there is none (the stop line).
    top: Result<Scored, String>,
    /// The structure refined by output error, when it predicts significantly better.
    refined: Option<judge::RefinedEstimate>,
}

/// `spec` (fitted as `base`, evaluated on the held-out data as `base_eval`) refit and scored,
/// judged by the rules of a finding ([`judge`]) and ranked. Returns the step's record,
/// its first finding's variant (or why there is none) and the refined structure ([`Diagnosed`]).
#[allow(clippy::too_many_arguments)]
fn diagnose_step(
    step_no: usize,
    spec: &Spec,
    base: &Fitted,
    base_eval: &Eval,
    (free, one): (&ResidualReport, &ResidualReport),
    (train, val, fit): (&Dataset, &Dataset, &serde_json::Value),
    (threads, progress): (usize, Option<Progress<'_>>),
    notes: &mut Vec<String>,
) -> Result<Diagnosed, DiagnoseError> {
    let train_sig = base.model.signals.evaluate(train)?;
    // through the model's own-output feedback, if any
    let train_fb = base.model.signals.feedback(train)?;
    let train_res = design_residual(base, &train_sig, &train_fb);
    let ctx = Context {
        spec,
        base,
        train,
        val,
        train_residual: &train_res,
        train_signals: &train_sig,
    };
    let (mut cands, na, mut skipped) = candidates(&ctx);
    // the model's own structure with a larger past window, which every finding must also
    // beat (effects::larger_past): scored as an order-too-low variant (the verdict when it
    // is what removes the error), added when the catalogue did not try it (a scheduled
    // model's regressor at past + 2 exceeds the catalogue's limit; it is fitted in the
    // kernel form here)
    let larger = effects::larger_past(spec, train.len());
    if let Some(l) = &larger {
        if !cands.iter().any(|c| effects::is_larger_past(c, l)) {
            skipped.retain(|s| !effects::is_larger_past(&s.cand, l));
            cands.push(l.clone());
        }
    }
    let mut tried = cands.len();
    let (mut scored, nulls) = score_all(cands, train, val, fit, base_eval, threads, progress);
    // a dead time the model's fixed order may hold in states, at the delay its delayed
    // variants scored best (catalogue::fewer_states_delays): one more variant per input
    for c in catalogue::fewer_states_delays(spec, &scored) {
        tried += 1;
        scored.push(effects::score(c, train, val, fit, Some(base_eval)));
    }
    // the evaluation of the model's structure with a larger past window, which every
    // finding must also beat (used by the replication's alternatives and the check below)
    let larger_eval = larger.as_ref().and_then(|l| {
        scored
            .iter()
            .find(|s| effects::is_larger_past(&s.cand, l))
            .and_then(|s| s.eval.as_ref())
    });
    let bench = judge::Bench {
        spec,
        order: base.order,
        train,
        val,
        fit,
        scored: &scored,
        tried,
        base_eval,
        larger: larger.as_ref(),
        larger_eval,
        nulls: &nulls,
    };
    let (judgements, short, refined) = judge::judge(&bench, notes);
    // a noise model cannot explain the part of the residual an input-driven effect does;
    // that part as a fraction of coloured-noise's null, the model's structure refit (a
    // variant judged against its own null, e.g. refined, by what it explains of that
    // refit: fractions of different nulls are not compared)
    let det_best = judgements
        .iter()
        .filter(|j| j.effect.metric() == Mode::FreeRun && j.passed)
        .map(|j| {
            j.vs_user
                .map_or(scored[j.index].explained, |v| v.0)
                .clamp(0.0, 1.0)
        })
        .fold(0.0, f64::max);
    let mut findings: Vec<(Finding, usize)> = judgements
        .iter()
        .map(|j| {
            let mut explained = scored[j.index].explained;
            if j.effect == Effect::ColouredNoise {
                explained *= 1.0 - det_best;
            }
            (j.finding(&bench, explained, (free, one), base), j.index)
        })
        .collect();
    let fold_loss: Vec<(usize, &[Vec<f64>])> = judgements
        .iter()
        .map(|j| (j.index, j.fold_loss.as_slice()))
        .collect();
    rank::rank(
        &mut findings,
        &scored,
        tried,
        (train, val, fit),
        rank::FoldLosses(&fold_loss),
    );
    // the rule that blocked each finding, for the stop line and the summary (human text
    // and JSON say the same)
    for (f, i) in findings.iter_mut().filter(|f| !f.0.significant) {
        let j = judgements
            .iter()
            .find(|j| j.index == *i)
            .expect("a finding per judgement");
        f.blocked_by = Some(j.blocked_by(f, &bench, short));
    }
    let top = findings.first().filter(|f| f.0.significant).map(|f| f.1);
    let top_finding = findings.first().map(|f| f.0.clone());
    let blocked_by = findings.first().and_then(|(f, _)| f.blocked_by.clone());
    let variants_scored = scored
        .iter()
        .map(|s| VariantScore {
            effect: s.cand.effect.name(),
            detail: s.cand.detail.clone(),
            explained: s.explained,
            basis: s.basis,
            p_value: s.p_value,
            error: s.error.clone(),
            seconds: s.seconds,
        })
        .collect();
    let step = Step {
        step: step_no,
        variants_scored,
        null_refit_vaf: mean_vaf(base_eval),
        null_refit_mse: (base_eval.mse(Mode::FreeRun), base_eval.mse(Mode::Predictor)),
        variants: tried,
        findings: findings.into_iter().map(|f| f.0).collect(),
        not_applicable: na
            .into_iter()
            .map(|(e, why)| (e.name().to_string(), why))
            .chain(
                skipped
                    .iter()
                    .map(|s| (s.cand.effect.name().to_string(), report::not_tried(s))),
            )
            .collect(),
    };
    let Some(i) = top else {
        let stopped = match top_finding {
            Some(f) => format!(
                "nothing explains the residual above the noise threshold (best: {} explains {:.1} % of the held-out {} error, p = {:.2e}; not a finding because {}; a finding needs >= {:.0} %, p < {:.1e} and {})",
                f.effect,
                100.0 * f.explained,
                f.residual,
                f.p_value,
                blocked_by.as_deref().unwrap_or("it is below the noise threshold"),
                100.0 * effects::MIN_EXPLAINED,
                ALPHA / tried.max(1) as f64,
                if short {
                    "the agreement of all cross-validation folds but one"
                } else {
                    "replication on each half of the training data"
                }
            ),
            None => "no candidate effect applies to this model".into(),
        };
        return Ok(Diagnosed {
            step,
            top: Err(stopped),
            refined,
        });
    };
    let top = scored
        .into_iter()
        .nth(i)
        .expect("index of a scored variant");
    Ok(Diagnosed {
        step,
        top: Ok(top),
        refined,
    })
}

/// Select on held-out data, then refit on everything: when the held-out record was carved
/// from the tail of the training record (not a separate validation file), the structure the
/// diagnosis chose is refit with its own settings on the training rows followed by the
/// held-out rows (a short record loses a fifth of its data to the hold-out: on the cascaded
/// tanks' 1024 estimation rows the selected structure fitted on the first 819 gives 0.55 V
/// on the validation file from an estimated initial state, fitted on all of them 0.490 V).
/// `val` must continue `train`.
///
/// The outcome's model becomes the refit; `report.after` (and `after_eval`) stay the held-out
/// score of the structure fitted on the training rows alone (the honest estimate), and
/// `report.refit_all` gives the refit's score on the held-out rows, which is in-sample. Does
/// nothing when no fix was applied (the given model is kept as it is).
pub fn refit_on_all(
    outcome: &mut Outcome,
    train: &Dataset,
    val: &Dataset,
) -> Result<(), DiagnoseError> {
    if !outcome.report.changed() {
        return Ok(());
    }
    let all = replicate::concat(&[train, val], format!("{} + {}", train.source, val.source))
        .ok_or_else(|| {
            DataError::new(
                val.source.clone(),
                None,
                None,
                "the held-out rows lack a column of the training rows: they cannot be joined for the final refit",
            )
        })?;
    let mut notes = Vec::new();
    // a structure refined by output error (the refined fix, a nested refinement) says so in
    // its record and is refined again on all rows
    let spec = Spec::from_model(&outcome.model, &mut notes)?;
    let mut fitted = fit_spec(&spec, &all, &outcome.model.fit)?.model;
    // provenance: the diagnose history of the selected model
    if let serde_json::Value::Object(m) = &mut fitted.fit {
        for key in ["diagnose", "refined_by_diagnose"] {
            if let Some(h) = outcome.model.fit.get(key) {
                m.insert(key.into(), h.clone());
            }
        }
    }
    let x0 = X0::Estimate {
        samples: effects::x0_samples(val.len()),
    };
    let in_sample = score_from(&fitted, val, Mode::FreeRun, x0)?;
    outcome.report.notes.extend(notes);
    outcome.report.notes.push(format!(
        "the held-out rows were carved from the training record: after the selection, the chosen structure was refit on all {} rows (training + held-out); its held-out VAF {} % is in-sample, the held-out estimate is the \"after\" score of the structure fitted on the training rows alone",
        all.len(),
        in_sample.vaf.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>().join(" / ")
    ));
    outcome.report.refit_all = Some(RefitAll {
        rows: all.len(),
        in_sample,
    });
    // `after_eval` stays the held-out evaluation of the structure fitted without those rows,
    // like `report.after`
    outcome.model = fitted;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn applied(step: usize, effect: &'static str) -> Applied {
        Applied {
            step,
            effect,
            detail: format!("detail {step}"),
            explained: 0.5,
            residual: "free-run",
            mse_before: 1.0,
            mse_after: 0.5,
            vaf_before: 50.0,
            vaf_after: 75.0,
        }
    }

    #[test]
    fn provenance_is_the_given_record_then_each_fix_once() {
        let text = r#"{"type": "lpv-ss", "fit": {"method": "lpv-pbsid-opt"},
            "A": [[[0.5]]], "B": [[[1.0]]], "C": [[[1.0]]], "D": [[[0.0]]], "K": [[[0.0]]]}"#;
        let model = ModelFile::from_json_str("m.json", text).unwrap();
        let given = vec![serde_json::json!({"effect": "output-offset"})];
        let steps = [applied(1, "input-delay"), applied(2, "feedthrough")];
        // applied one step after the other, as the diagnosis does: no fix recorded twice
        let once = with_provenance(model.clone(), &given, &steps[..1]);
        let twice = with_provenance(once, &given, &steps);
        let h = twice.fit["diagnose"].as_array().unwrap();
        let effects: Vec<&str> = h.iter().map(|v| v["effect"].as_str().unwrap()).collect();
        assert_eq!(effects, ["output-offset", "input-delay", "feedthrough"]);
        assert_eq!(h[2]["detail"], "detail 2");
        assert_eq!(twice.fit["method"], "lpv-pbsid-opt");
    }
}
