//! Simulation of any model file on a data file: free run (the model's own past outputs) or
//! one-step-ahead prediction (measured past outputs), for `lpv-ss` and `lpv-arx` models,
//! and its [`score`] (VAF and BFR per output, as the papers define them).
//!
//! A model whose input channels or scheduling functions read its own output (DESIGN.md
//! section 5: a factor on an output column) is run through that feedback in free run: at
//! each sample the output y_k = C(mu_k) x_k + D(mu_k) u_k is formed first (a model that
//! would need y_k for it is refused when read, [`crate::model::SignalMap::check_loops`]),
//! then the signals that read it are evaluated on the simulated outputs and the state
//! advances. In one-step prediction they read the measured outputs, as in identification.
//!
//! The initial state is zero, or estimated ([`X0::Estimate`]) from the first samples by
//! least squares on the free-run error (Gauss-Newton through the feedback; one exact step
//! for a model without feedback, whose free run is affine in x0), and only the samples after
//! them are scored, as the public benchmarks allow (Silverbox: 50 samples).

use nalgebra::{DMatrix, DVector};

use crate::data::{DataError, Dataset};
use crate::lpvss::{LpvSs, Signals};
use crate::metrics::{bfr_per_output, mean, vaf_per_output};
use crate::model::{ArxModel, Feedback, ModelFile, ModelKind};

/// How a run starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum X0 {
    /// From the zero state; every sample is scored.
    Zero,
    /// The initial state estimated from the first `samples` samples, which are then not
    /// scored (lpv-arx: the model runs on the measured outputs for those samples).
    Estimate {
        /// Samples used for the estimate (and left out of the score).
        samples: usize,
    },
}

/// The samples `validate --x0 estimate` uses by default (the Silverbox benchmark's rule).
pub const X0_SAMPLES: usize = 50;

/// A model run on a data set.
#[derive(Debug, Clone)]
pub struct Run {
    /// Measured outputs (N x l), as the model's `outputs` define them.
    pub y: DMatrix<f64>,
    /// The model's outputs (N x l).
    pub yhat: DMatrix<f64>,
    /// Leading samples not scored (used for the initial state).
    pub skip: usize,
    /// The initial state used (lpv-ss).
    pub x0: Option<DVector<f64>>,
}

/// Run `model` on `ds` in `mode` from the initial state `x0`, through its own-output
/// feedback (module docs).
pub fn run(model: &ModelFile, ds: &Dataset, mode: Mode, x0: X0) -> Result<Run, DataError> {
    let sig = model.signals.evaluate(ds)?;
    let fb = model.signals.feedback(ds)?;
    let n = sig.len();
    let skip = match x0 {
        X0::Zero => 0,
        X0::Estimate { samples } => samples.min(n),
    };
    let (yhat, x0v) = match &model.kind {
        ModelKind::Ss(m) => {
            let x = match x0 {
                X0::Zero => DVector::zeros(m.n()),
                X0::Estimate { .. } => estimate_x0(m, &sig, &fb, skip),
            };
            (run_ss(m, &sig, &fb, mode, &x), Some(x))
        }
        ModelKind::Arx(m) => (arx_run_from(m, &sig, &fb, mode, skip), None),
    };
    Ok(Run {
        y: sig.y,
        yhat,
        skip,
        x0: x0v,
    })
}

/// Free run or one-step-ahead predictor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Driven by inputs and scheduling only, from a zero initial state.
    FreeRun,
    /// One-step-ahead predictor using the measured outputs.
    Predictor,
}

/// The model's outputs on `ds` (N x l) together with the measured outputs, as the model
/// defines them (its `outputs` products).
pub fn simulate(
    model: &ModelFile,
    ds: &Dataset,
    mode: Mode,
) -> Result<(DMatrix<f64>, DMatrix<f64>), DataError> {
    let r = run(model, ds, mode, X0::Zero)?;
    Ok((r.y, r.yhat))
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
    /// Leading samples not scored (used to estimate the initial state); absent when 0.
    #[serde(skip_serializing_if = "is_zero")]
    pub skipped: usize,
    /// The first sample (0-based row of the data) where the model's output is not finite
    /// or larger than [`DIVERGED`] in magnitude: the simulation diverged there and VAF/BFR
    /// say nothing about the fit. Absent from the JSON when it did not diverge.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub diverged_at: Option<usize>,
}

/// A simulated output larger than this in magnitude counts as diverged.
pub const DIVERGED: f64 = 1e100;

/// The first row of `yhat` with a non-finite value or one larger than [`DIVERGED`].
pub fn diverged_at(yhat: &DMatrix<f64>) -> Option<usize> {
    (0..yhat.nrows()).find(|&k| {
        yhat.row(k)
            .iter()
            .any(|v| !v.is_finite() || v.abs() > DIVERGED)
    })
}

/// Score `model` on `ds`: VAF and BFR (DESIGN.md section 5) of the free run or the
/// one-step predictor.
pub fn score(model: &ModelFile, ds: &Dataset, mode: Mode) -> Result<Score, DataError> {
    score_from(model, ds, mode, X0::Zero)
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

/// [`score`] from the initial state `x0` (with [`X0::Estimate`] the samples used for it
/// are not scored).
pub fn score_from(model: &ModelFile, ds: &Dataset, mode: Mode, x0: X0) -> Result<Score, DataError> {
    let Run { y, yhat, skip, .. } = run(model, ds, mode, x0)?;
    let vaf = vaf_per_output(&y, &yhat, skip);
    let bfr = bfr_per_output(&y, &yhat, skip);
    Ok(Score {
        skipped: skip,
        file: ds.source.clone(),
        mode: match mode {
            Mode::FreeRun => "free-run",
            Mode::Predictor => "predictor",
        },
        vaf_mean: mean(&vaf),
        bfr_mean: mean(&bfr),
        vaf,
        bfr,
        diverged_at: diverged_at(&yhat),
    })
}

/// As [`simulate`], on signals already evaluated.
pub fn simulate_signals(kind: &ModelKind, sig: &Signals, mode: Mode) -> DMatrix<f64> {
    match (kind, mode) {
        (ModelKind::Ss(m), Mode::FreeRun) => m.simulate(sig, None),
        (ModelKind::Ss(m), Mode::Predictor) => m.predict(sig),
        (ModelKind::Arx(m), mode) => arx_run(m, sig, mode),
    }
}

/// As [`simulate_signals`], through the own-output feedback `fb` (from
/// [`crate::model::SignalMap::feedback`] on the same data) and from the zero state.
pub fn simulate_feedback(
    kind: &ModelKind,
    sig: &Signals,
    fb: &Feedback,
    mode: Mode,
) -> DMatrix<f64> {
    match kind {
        ModelKind::Ss(m) => run_ss(m, sig, fb, mode, &DVector::zeros(m.n())),
        ModelKind::Arx(m) => arx_run_from(m, sig, fb, mode, 0),
    }
}

/// The free run through `fb` over the whole record from an initial state estimated on its
/// first `samples` samples ([`estimate_x0`]; lpv-arx: the measured outputs stand for the
/// model's own over them). Every row is returned (the first ones fitted, not predicted), so
/// a comparison of models on the same rows stays aligned.
pub fn free_run_estimated(
    kind: &ModelKind,
    sig: &Signals,
    fb: &Feedback,
    samples: usize,
) -> DMatrix<f64> {
    match kind {
        ModelKind::Ss(m) => {
            let x0 = estimate_x0(m, sig, fb, samples);
            run_ss(m, sig, fb, Mode::FreeRun, &x0)
        }
        ModelKind::Arx(m) => arx_run_from(m, sig, fb, Mode::FreeRun, samples.min(sig.len())),
    }
}

/// How much a model's free run still depends on its initial state over the last rows of a
/// record, next to its own error there (both squared, divided by var y_j, averaged over
/// outputs and rows): diagnose's memory rule on the held-out record
/// ([`crate::diagnose::memory`]) and the pipeline's choice of a refinement start on the
/// training record ([`crate::refine::leans_on_start`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Memory {
    /// Mean square of (free run from the initial state - free run from the zero state)
    /// (infinite when a run is not finite).
    pub influence: f64,
    /// Mean square of the free-run error from the initial state over the same rows.
    pub error: f64,
}

impl Memory {
    /// The initial state changes the output at the end of the record by more than the
    /// model's own error there: its score leans on a state fitted to the first samples.
    pub fn leans_on_start(&self) -> bool {
        !self.influence.is_finite() || self.influence > self.error
    }
}

/// The [`Memory`] of a model over rows `first..` from its free runs `from_start` (from its
/// initial state) and `from_zero` (from the zero state), against the measured `y`.
pub fn start_influence(
    y: &DMatrix<f64>,
    from_start: &DMatrix<f64>,
    from_zero: &DMatrix<f64>,
    var_y: &[f64],
    first: usize,
) -> Memory {
    let (rows, l) = (y.nrows(), y.ncols());
    let per_output = l.max(1) as f64;
    let (mut influence, mut error) = (0.0, 0.0);
    for k in first..rows {
        for j in 0..l {
            let d = from_start[(k, j)] - from_zero[(k, j)];
            let e = y[(k, j)] - from_start[(k, j)];
            influence += d * d / var_y[j] / per_output;
            error += e * e / var_y[j] / per_output;
        }
    }
    let mean = |s: f64| {
        let m = s / rows.saturating_sub(first).max(1) as f64;
        if m.is_finite() {
            m
        } else {
            f64::INFINITY
        }
    };
    Memory {
        influence: mean(influence),
        error: mean(error),
    }
}

/// The free run (through `fb`) or the one-step predictor of an lpv-ss model from `x0`.
pub fn run_ss(
    m: &LpvSs,
    sig: &Signals,
    fb: &Feedback,
    mode: Mode,
    x0: &DVector<f64>,
) -> DMatrix<f64> {
    if mode == Mode::Predictor || fb.is_empty() {
        return m.run_from(sig, x0, mode == Mode::Predictor);
    }
    free_run_ss(m, sig, fb, x0, sig.len())
}

/// Free run through the feedback over the first `upto` samples (the rest of the output is
/// zero; NaN from a divergence on: a state not finite or beyond 1e150). Allocation-free in
/// the sample loop: the output-error refinement runs it once per parameter per iteration.
pub fn free_run_ss(
    m: &LpvSs,
    sig: &Signals,
    fb: &Feedback,
    x0: &DVector<f64>,
    upto: usize,
) -> DMatrix<f64> {
    let mut out = DMatrix::<f64>::zeros(sig.len(), m.l());
    let mut x: Vec<f64> = x0.iter().copied().collect();
    free_run_ss_into(m, sig, fb, &mut x, 0, upto, &mut out);
    out
}

/// [`free_run_ss`] over samples `start..upto` into `out` (N x l), whose rows before `start`
/// hold the outputs already run (what the feedback reads of them), from the state `x`, left
/// in `x` at the end: the streamed free run ([`crate::stream`]) continues a record chunk by
/// chunk with it. False when the run diverged (the rest of `out` is NaN).
pub fn free_run_ss_into(
    m: &LpvSs,
    sig: &Signals,
    fb: &Feedback,
    x: &mut Vec<f64>,
    start: usize,
    upto: usize,
    out: &mut DMatrix<f64>,
) -> bool {
    let big_n = sig.len();
    let (n, r, l, mm) = (m.n(), m.r(), m.l(), m.m());
    let s = sig.p.ncols().min(mm - 1);
    // the sample loop allocates nothing: the feedback writes the signals it computes into
    // the sample's own inputs and weights, over the record's
    let step = m.stepper();
    let mut xn = vec![0.0; n];
    let mut uk = vec![0.0; r];
    let mut yk = vec![0.0; l];
    let mut mu = vec![1.0; mm];
    for k in start..upto.min(big_n) {
        for q in 0..s {
            mu[q + 1] = sig.p[(k, q)];
        }
        for (j, v) in uk.iter_mut().enumerate() {
            *v = sig.u[(k, j)];
        }
        // the signals that read outputs up to k-1 (a delay-0 own value counts as 0 here: the
        // output equation does not use it, SignalMap::check_loops)
        if !fb.is_empty() {
            fb.fill_sample(k, out, k, &mut uk, &mut mu[1..=s]);
        }
        step.output_into(&mu, x, &uk, &mut yk);
        let finite = yk.iter().all(|v| v.is_finite());
        for (j, v) in yk.iter().enumerate() {
            out[(k, j)] = *v;
        }
        // ... then with y_k known
        if !fb.is_empty() {
            fb.fill_sample(k, out, k + 1, &mut uk, &mut mu[1..=s]);
        }
        step.state_into(&mu, x, &uk, None, &mut xn);
        std::mem::swap(x, &mut xn);
        if !finite || x.iter().any(|v| !v.is_finite() || v.abs() > 1e150) {
            for kk in k + 1..big_n {
                for j in 0..l {
                    out[(kk, j)] = f64::NAN;
                }
            }
            return false;
        }
    }
    true
}

fn mu_of(p: &DMatrix<f64>, k: usize) -> DVector<f64> {
    DVector::from_fn(
        p.ncols() + 1,
        |i, _| if i == 0 { 1.0 } else { p[(k, i - 1)] },
    )
}

/// Least-squares initial state from the first `samples` samples of the free run through the
/// feedback (Gauss-Newton with a Levenberg damping on finite-difference Jacobians; for a model
/// without feedback the free run is affine in x0 and the first step is exact).
pub fn estimate_x0(m: &LpvSs, sig: &Signals, fb: &Feedback, samples: usize) -> DVector<f64> {
    let n = m.n();
    let l = m.l();
    let ns = samples.min(sig.len());
    if ns == 0 || n == 0 {
        return DVector::zeros(n);
    }
    let head = sig.slice(0, ns);
    let fb_head = fb.rows(0, ns);
    let resid = |x: &DVector<f64>| -> Option<DVector<f64>> {
        let yh = free_run_ss(m, &head, &fb_head, x, ns);
        let r = DVector::from_fn(ns * l, |i, _| head.y[(i / l, i % l)] - yh[(i / l, i % l)]);
        r.iter().all(|v| v.is_finite()).then_some(r)
    };
    let mut x = DVector::zeros(n);
    let Some(mut r) = resid(&x) else { return x };
    let mut cost = r.norm_squared();
    let mut lambda = 0.0;
    for _ in 0..30 {
        let mut jac = DMatrix::<f64>::zeros(ns * l, n);
        for i in 0..n {
            let h = 1e-6 * (1.0 + x[i].abs());
            let mut xp = x.clone();
            xp[i] += h;
            let Some(rp) = resid(&xp) else { return x };
            jac.set_column(i, &((&rp - &r) / h));
        }
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * &r;
        let mut improved = false;
        for _ in 0..8 {
            let mut lhs = jtj.clone();
            for d in 0..n {
                lhs[(d, d)] += lambda * jtj[(d, d)] + 1e-12 * (1.0 + jtj[(d, d)]);
            }
            // r = y - yhat, J = dr/dx: the step is -(J'J)^-1 J' r
            let Some(step) = lhs.cholesky().map(|c| c.solve(&(-&g))) else {
                lambda = (lambda * 10.0).max(1e-6);
                continue;
            };
            let cand = &x + step;
            if let Some(rc) = resid(&cand) {
                let c2 = rc.norm_squared();
                if c2 < cost {
                    let rel = (cost - c2) / cost.max(1e-300);
                    x = cand;
                    r = rc;
                    cost = c2;
                    lambda /= 10.0;
                    improved = rel > 1e-10;
                    break;
                }
            }
            lambda = (lambda * 10.0).max(1e-6);
        }
        if !improved {
            break;
        }
    }
    x
}

/// LPV-ARX recursion y(k) = -sum_i a_i(mu_k) y(k-i) + sum_j b_j(mu_k) u(k-j) with
/// a_i(mu) = sum_q `a[i][q]` mu^(q); samples before the record are zero.
pub fn arx_run(m: &ArxModel, sig: &Signals, mode: Mode) -> DMatrix<f64> {
    arx_run_from(m, sig, &Feedback::default(), mode, 0)
}

/// [`arx_run`] through the own-output feedback `fb` (free run), with the measured outputs
/// standing for the model's own for the first `warm` samples (the ARX model's initial state).
pub fn arx_run_from(
    m: &ArxModel,
    sig: &Signals,
    fb: &Feedback,
    mode: Mode,
    warm: usize,
) -> DMatrix<f64> {
    let n = sig.len();
    let mut yhat = DMatrix::<f64>::zeros(n, 1);
    let free = mode == Mode::FreeRun && !fb.is_empty();
    let mut u_fb = sig.u.clone();
    let mut p_fb = sig.p.clone();
    // the outputs the feedback reads: measured for the warm-up samples, then the model's
    let mut y_run = sig.y.clone();
    for k in 0..n {
        let (u, mu) = if free {
            fb.fill(k, &y_run, k, &mut u_fb, &mut p_fb);
            (&u_fb, mu_of(&p_fb, k))
        } else {
            (&sig.u, sig.mu(k))
        };
        let coef = |c: &[f64]| c.iter().zip(mu.iter()).map(|(a, b)| a * b).sum::<f64>();
        let mut v = 0.0;
        for (i, a) in m.a.iter().enumerate() {
            let lag = i + 1;
            if k >= lag {
                let past = match mode {
                    Mode::FreeRun if k - lag >= warm => yhat[(k - lag, 0)],
                    _ => sig.y[(k - lag, 0)],
                };
                v -= coef(a) * past;
            }
        }
        for (input, lags) in m.b.iter().enumerate() {
            for (j, b) in lags.iter().enumerate() {
                if k >= j {
                    v += coef(b) * u[(k - j, input)];
                }
            }
        }
        if !v.is_finite() || v.abs() > 1e150 {
            for kk in k..n {
                yhat[(kk, 0)] = f64::NAN;
            }
            break;
        }
        yhat[(k, 0)] = v;
        if k >= warm {
            y_run[(k, 0)] = v;
        }
        if free {
            // the delay-0 values with y_k known (b_0 does not use them, check_loops)
            fb.fill(k, &y_run, k + 1, &mut u_fb, &mut p_fb);
        }
    }
    yhat
}
