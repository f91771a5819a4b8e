//! Simulation of any model file on a data file: free run (the model's own past outputs) or
//! one-step-ahead prediction (measured past outputs), for `lpv-ss` and `lpv-arx` models,
//! and its [`score`] (VAF and BFR per output, as the papers define them).

use nalgebra::DMatrix;

use crate::data::{DataError, Dataset};
use crate::lpvss::Signals;
use crate::metrics::{bfr_per_output, mean, vaf_per_output};
use crate::model::{ArxModel, ModelFile, ModelKind};

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
    let sig = model.signals.evaluate(ds)?;
    let yhat = simulate_signals(&model.kind, &sig, mode);
    Ok((sig.y, yhat))
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

/// LPV-ARX recursion y(k) = -sum_i a_i(mu_k) y(k-i) + sum_j b_j(mu_k) u(k-j) with
/// a_i(mu) = sum_q `a[i][q]` mu^(q); samples before the record are zero.
pub fn arx_run(m: &ArxModel, sig: &Signals, mode: Mode) -> DMatrix<f64> {
    let n = sig.len();
    let mut yhat = DMatrix::<f64>::zeros(n, 1);
    for k in 0..n {
        let mu = sig.mu(k);
        let coef = |c: &[f64]| c.iter().zip(mu.iter()).map(|(a, b)| a * b).sum::<f64>();
        let mut v = 0.0;
        for (i, a) in m.a.iter().enumerate() {
            let lag = i + 1;
            if k >= lag {
                let past = match mode {
                    Mode::FreeRun => yhat[(k - lag, 0)],
                    Mode::Predictor => sig.y[(k - lag, 0)],
                };
                v -= coef(a) * past;
            }
        }
        for (input, lags) in m.b.iter().enumerate() {
            for (j, b) in lags.iter().enumerate() {
                if k >= j {
                    v += coef(b) * sig.u[(k - j, input)];
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
    }
    yhat
}
