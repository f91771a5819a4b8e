//! Does a model forget its initial state within the held-out record?
//!
//! Diagnose scores every model by its free run from an initial state estimated on the first
//! held-out samples ([`super::effects::Eval`], issue 14 item 5). A refit that gained a slow
//! mode can then use that estimated state as a free offset or drift over the whole record:
//! it scores well from the estimated state and badly from any other start, which is a
//! property of the fit, not of the plant (a tank that starts empty, refit with a Lur'e
//! channel: 14x better with x0 estimated, 3x worse from the zero state it really started
//! in). The initial state's influence is the difference of two free runs of the same model
//! on the same signals, one from the estimated state and one from the zero state (for a
//! linear-in-the-state model the response to the estimated state alone; through an
//! own-output feedback the same difference of trajectories). This module measures it over
//! the second half of the scored rows, where a model that forgets its start no longer
//! depends on it.

use nalgebra::DMatrix;

use super::effects::Eval;
use crate::data::{DataError, Dataset};
use crate::model::ModelFile;
use crate::simulate::{simulate_feedback, Mode};

/// How much a model's free run still depends on its estimated initial state at the end of
/// the held-out record, next to its own error there (both normalised as [`Eval::loss`]:
/// squared, divided by var y_j, averaged over outputs and rows).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Memory {
    /// Mean square of (free run from the estimated state - free run from the zero state)
    /// over the second half of the scored rows (infinite when a run is not finite).
    pub influence: f64,
    /// Mean square of the free-run error from the estimated state over the same rows.
    pub error: f64,
}

impl Memory {
    /// The estimated initial state changes the output at the end of the record by more than
    /// the model's own error there: its score leans on a state fitted to the first samples.
    pub fn leans_on_start(&self) -> bool {
        !self.influence.is_finite() || self.influence > self.error
    }
}

/// The [`Memory`] of `model` evaluated as `eval` (its [`Eval`] on `ds`).
pub fn memory(model: &ModelFile, ds: &Dataset, eval: &Eval) -> Result<Memory, DataError> {
    let sig = model.signals.evaluate(ds)?;
    let fb = model.signals.feedback(ds)?;
    let from_zero = simulate_feedback(&model.kind, &sig, &fb, Mode::FreeRun);
    Ok(second_half(eval, &from_zero))
}

/// [`Memory`] from the estimated-state run inside `eval` and the zero-state run.
fn second_half(eval: &Eval, from_zero: &DMatrix<f64>) -> Memory {
    let rows = eval.y.nrows();
    let first = eval.skip + (rows - eval.skip.min(rows)) / 2;
    let l = eval.y.ncols().max(1) as f64;
    let (mut influence, mut error, mut count) = (0.0, 0.0, 0usize);
    for k in first..rows {
        for j in 0..eval.y.ncols() {
            let d = eval.yhat_free[(k, j)] - from_zero[(k, j)];
            let e = eval.y[(k, j)] - eval.yhat_free[(k, j)];
            influence += d * d / eval.var_y[j] / l;
            error += e * e / eval.var_y[j] / l;
        }
        count += 1;
    }
    let mean = |s: f64| {
        let m = s / count.max(1) as f64;
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

/// A candidate may be applied only if it forgets its initial state as its null does: it is
/// blocked when its score leans on the estimated start ([`Memory::leans_on_start`]) while
/// the null's does not. When both lean on it (a plant slower than the record, as the
/// cascaded tanks' held-out record is for every model) the comparison stands as scored.
pub fn forgets_as_null(candidate: &Memory, null: &Memory) -> bool {
    !candidate.leans_on_start() || null.leans_on_start()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn eval(y: Vec<f64>, yhat: Vec<f64>, skip: usize) -> Eval {
        let n = y.len();
        Eval {
            y: DMatrix::from_vec(n, 1, y),
            yhat_free: DMatrix::from_vec(n, 1, yhat.clone()),
            yhat_pred: DMatrix::from_vec(n, 1, yhat),
            var_y: vec![1.0],
            skip,
        }
    }

    #[test]
    fn a_start_that_persists_is_leaned_on() {
        // the estimated-state run matches y; from zero it keeps an offset of 0.5 to the end
        let y: Vec<f64> = (0..100).map(|k| (k as f64 * 0.3).sin()).collect();
        let e = eval(y.clone(), y.iter().map(|v| v + 0.01).collect(), 10);
        let zero = DMatrix::from_iterator(100, 1, y.iter().map(|v| v + 0.01 - 0.5));
        let m = second_half(&e, &zero);
        assert!((m.influence - 0.25).abs() < 1e-12, "{m:?}");
        assert!((m.error - 1e-4).abs() < 1e-12, "{m:?}");
        assert!(m.leans_on_start());
    }

    #[test]
    fn a_start_that_decays_is_forgotten() {
        // the difference of the two runs decays as 0.9^k: gone by the second half
        let y: Vec<f64> = (0..200).map(|k| (k as f64 * 0.1).cos()).collect();
        let yhat: Vec<f64> = y.iter().map(|v| v + 0.05).collect();
        let zero = DMatrix::from_iterator(
            200,
            1,
            yhat.iter()
                .enumerate()
                .map(|(k, v)| v - 2.0 * 0.9f64.powi(k as i32)),
        );
        let m = second_half(&eval(y, yhat, 20), &zero);
        assert!(
            m.influence < 1e-10 && (m.error - 0.0025).abs() < 1e-12,
            "{m:?}"
        );
        assert!(!m.leans_on_start());
        let lean = Memory {
            influence: 1.0,
            error: 0.1,
        };
        assert!(forgets_as_null(&m, &lean));
        assert!(!forgets_as_null(&lean, &m));
        assert!(forgets_as_null(&lean, &lean));
        // a diverged run leans on its start
        let nan = Memory {
            influence: f64::INFINITY,
            error: f64::INFINITY,
        };
        assert!(nan.leans_on_start());
    }
}
