//! Fit measures of the papers (DESIGN.md section 5): VAF = 100 max{0, 1 - var(y - yhat)/var(y)}
//! and BFR = 100 max{0, 1 - ||y - yhat|| / ||y - mean(y)||}, per output. A diverged or
//! non-finite prediction scores 0 (BENCHMARKS.md: count diverged runs, do not drop them).

use nalgebra::DMatrix;

fn variance(v: &[f64]) -> f64 {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n
}

/// VAF in percent of one output.
pub fn vaf(y: &[f64], yhat: &[f64]) -> f64 {
    if y.is_empty() || yhat.iter().any(|v| !v.is_finite()) {
        return 0.0;
    }
    let err: Vec<f64> = y.iter().zip(yhat).map(|(a, b)| a - b).collect();
    vaf_from_variances(variance(y), variance(&err))
}

/// VAF in percent from var(y) and var(y - yhat): the one formula, also used by scores that
/// accumulate the variances as they stream (0 when var(y) is not positive).
pub fn vaf_from_variances(var_y: f64, var_err: f64) -> f64 {
    if var_y.is_nan() || var_y <= 0.0 {
        return 0.0;
    }
    100.0 * (1.0 - var_err / var_y).max(0.0)
}

/// BFR in percent from ||y - yhat|| and ||y - mean(y)|| (0 when the latter is not positive).
pub fn bfr_from_norms(err_norm: f64, dev_norm: f64) -> f64 {
    if dev_norm.is_nan() || dev_norm <= 0.0 {
        return 0.0;
    }
    100.0 * (1.0 - err_norm / dev_norm).max(0.0)
}

/// BFR in percent of one output.
pub fn bfr(y: &[f64], yhat: &[f64]) -> f64 {
    if y.is_empty() || yhat.iter().any(|v| !v.is_finite()) {
        return 0.0;
    }
    let mean = y.iter().sum::<f64>() / y.len() as f64;
    let num: f64 = y
        .iter()
        .zip(yhat)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    let den: f64 = y
        .iter()
        .map(|a| (a - mean) * (a - mean))
        .sum::<f64>()
        .sqrt();
    bfr_from_norms(num, den)
}

/// Per-output VAF of the columns of `y` vs `yhat` (N x l), skipping the first `skip` rows.
pub fn vaf_per_output(y: &DMatrix<f64>, yhat: &DMatrix<f64>, skip: usize) -> Vec<f64> {
    per_output(y, yhat, skip, vaf)
}

/// Per-output BFR, as [`vaf_per_output`].
pub fn bfr_per_output(y: &DMatrix<f64>, yhat: &DMatrix<f64>, skip: usize) -> Vec<f64> {
    per_output(y, yhat, skip, bfr)
}

/// Mean square of `y - yhat` (0 for empty slices).
pub fn mse(y: &[f64], yhat: &[f64]) -> f64 {
    y.iter()
        .zip(yhat)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        / y.len().max(1) as f64
}

/// Per-output mean square error, as [`vaf_per_output`].
pub fn mse_per_output(y: &DMatrix<f64>, yhat: &DMatrix<f64>, skip: usize) -> Vec<f64> {
    per_output(y, yhat, skip, mse)
}

fn per_output(
    y: &DMatrix<f64>,
    yhat: &DMatrix<f64>,
    skip: usize,
    f: fn(&[f64], &[f64]) -> f64,
) -> Vec<f64> {
    (0..y.ncols())
        .map(|j| {
            let a: Vec<f64> = y.column(j).iter().skip(skip).copied().collect();
            let b: Vec<f64> = yhat.column(j).iter().skip(skip).copied().collect();
            f(&a, &b)
        })
        .collect()
}

/// Each output's variance over the rows of `y` from `skip` on, floored at 1e-300: the scale
/// of [`normalised_losses`] (a constant output would otherwise divide by zero).
pub fn output_variances(y: &DMatrix<f64>, skip: usize) -> Vec<f64> {
    (0..y.ncols())
        .map(|j| {
            let c: Vec<f64> = y.column(j).iter().skip(skip).copied().collect();
            if c.is_empty() {
                1e-300
            } else {
                variance(&c).max(1e-300)
            }
        })
        .collect()
}

/// Per-sample normalised squared error over the rows of `y` from `skip` on,
/// sum_j (y_kj - yhat_kj)^2 / var_j / l (NaN rows where `yhat` is not finite): the losses
/// whose mean is a held-out score and whose per-batch ratios the paired tests compare
/// (`--order auto`'s check, diagnose's findings).
pub fn normalised_losses(
    y: &DMatrix<f64>,
    yhat: &DMatrix<f64>,
    var: &[f64],
    skip: usize,
) -> Vec<f64> {
    let l = y.ncols().max(1) as f64;
    (skip..y.nrows())
        .map(|k| {
            (0..y.ncols())
                .map(|j| (y[(k, j)] - yhat[(k, j)]).powi(2) / var[j])
                .sum::<f64>()
                / l
        })
        .collect()
}

/// Mean of a slice (0 for an empty one).
pub fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn vaf_bfr_values() {
        let y = [1.0, 2.0, 3.0, 4.0];
        assert_eq!(vaf(&y, &y), 100.0);
        assert_eq!(bfr(&y, &y), 100.0);
        let yh = [1.5, 2.5, 3.5, 4.5]; // constant offset: VAF ignores it, BFR does not
        assert!((vaf(&y, &yh) - 100.0).abs() < 1e-12);
        let expect = 100.0 * (1.0 - (4.0f64 * 0.25).sqrt() / 5.0f64.sqrt());
        assert!((bfr(&y, &yh) - expect).abs() < 1e-12);
        assert_eq!(vaf(&y, &[0.0, 0.0, f64::NAN, 0.0]), 0.0);
        assert_eq!(vaf(&y, &[-10.0, 10.0, -10.0, 10.0]), 0.0);
    }

    #[test]
    fn mse_values() {
        assert_eq!(mse(&[1.0, 2.0], &[0.0, 0.0]), 2.5);
        assert_eq!(mse(&[], &[]), 0.0);
        let y = DMatrix::from_row_slice(3, 2, &[9.0, 1.0, 1.0, 2.0, 2.0, 3.0]);
        let yh = DMatrix::from_row_slice(3, 2, &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(mse_per_output(&y, &yh, 1), vec![2.5, 6.5]);
        assert_eq!(mse_per_output(&y, &yh, 0), vec![86.0 / 3.0, 14.0 / 3.0]);
    }

    /// The normalised losses' mean is the mean over outputs of MSE / var y on the rows from
    /// `skip` on, each output scaled by its own variance there.
    #[test]
    fn normalised_losses_average_to_the_normalised_mse() {
        let y = DMatrix::from_fn(40, 2, |k, j| {
            ((k * (j + 2)) as f64 * 0.7).sin() * (j + 1) as f64
        });
        let yhat = DMatrix::from_fn(40, 2, |k, j| y[(k, j)] + 0.1 * ((k + j) as f64).cos());
        let skip = 5;
        let var = output_variances(&y, skip);
        let losses = normalised_losses(&y, &yhat, &var, skip);
        assert_eq!(losses.len(), 35);
        let direct: f64 = mse_per_output(&y, &yhat, skip)
            .iter()
            .zip(&var)
            .map(|(m, v)| m / v)
            .sum::<f64>()
            / 2.0;
        assert!(
            (mean(&losses) - direct).abs() < 1e-14 * direct,
            "{} {direct}",
            mean(&losses)
        );
        // a constant output is floored, not divided by zero
        let flat = DMatrix::from_element(10, 1, 3.0);
        assert_eq!(output_variances(&flat, 0), vec![1e-300]);
        let mut bad = yhat.clone();
        bad[(7, 1)] = f64::NAN;
        assert!(normalised_losses(&y, &bad, &var, skip)[2].is_nan());
    }
}
