//! The scheduling sequence behind a noisy sensor (issue 14, `scheduling-noise` on state-space
//! models). A white sensor noise on p biases every regression that multiplies p with the
//! states or inputs (errors in variables: the BC-IV paper's setting, there for LPV-ARX). Here
//! the outputs themselves say where the plant's p was: given a model fitted on the measured
//! p~, the maximum a posteriori sequence
//!
//! p^ = argmin_p  sum_k sum_l (y_l(k) - y^_l(k; p))^2 / sigma_l^2 + sum_k sum_c (p_c(k) - p~_c(k))^2 / s_c^2
//!
//! (Gaussian output error of the model's free-run variance sigma_l^2, Gaussian sensor noise of
//! variance s_c^2 per scheduling column; optionally a smoothness prior, + sum_k (p_c(k) -
//! 2 p_c(k-1) + p_c(k-2))^2 / v_c, [`SmoothnessPrior`]) by Gauss-Newton, and the model refitted on p^
//! ([`super::refit::fit_spec`] with [`super::refit::Spec::latent`]); both repeated a few rounds.
//! The Jacobian of the free run with respect to p is banded (p(k) moves y from k on, and a
//! stable model forgets it): it is formed by finite differences with every (W+1)-th sample
//! perturbed at once (W the model's measured memory), and the normal equations are solved in
//! band form, O(N W^2) per step.

use nalgebra::DMatrix;

use crate::data::Dataset;
use crate::model::ModelFile;
use crate::simulate::{simulate, Mode};

/// Longest memory (samples) the band keeps; a model that remembers p longer is cut here.
pub const MAX_MEMORY: usize = 120;

/// Largest band storage (samples x outputs x band width, 32 MB) a sequence estimate may use:
/// each Gauss-Newton step costs (W + 1) free runs per column, so about 3 * 10^4 samples at the
/// longest memory; longer records are not estimated (the variant fails with the reason).
pub const MAX_BAND_ENTRIES: usize = 4_000_000;

/// One scheduling column to estimate: its index in the dataset, the sensor noise variance and
/// what is known of the true signal's dynamics.
#[derive(Debug, Clone, Copy)]
pub struct NoisyColumn {
    /// Column index in the dataset.
    pub col: usize,
    /// Variance s_c^2 of the sensor noise (the prior's spread around the measurement).
    pub noise_var: f64,
    /// How smoothly the true signal moves ([`SmoothnessPrior::from_noisy`]); None: no prior
    /// on how p moves from sample to sample (each p(k) tied to its measurement alone).
    pub smooth: Option<SmoothnessPrior>,
}

/// A smoothness prior of a scheduling signal: its second difference p(k) - 2 p(k-1) + p(k-2)
/// white of variance `second_difference_var` (p an integrated random walk, the prior behind a
/// cubic smoothing spline). A slowly moving p (a rotor speed, a flow) is predictable from its
/// last two samples while a white sensor noise is not, so the prior lets the MAP estimate take
/// the measurement's unpredictable part for noise where the outputs do not say otherwise; its
/// term in the objective is sum_k (second difference)^2 / `second_difference_var`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SmoothnessPrior {
    /// Variance of the second difference.
    pub second_difference_var: f64,
}

impl SmoothnessPrior {
    /// The prior of the true signal behind `x` = p + white noise of variance `noise_var`, its
    /// variance fitted to the periodogram of `x` by the Whittle likelihood of the spectrum
    /// v / (2 - 2 cos omega)^2 + noise_var (the integrated random walk's plus the sensor's),
    /// sum over omega > 0 of ln S + I / S, minimised over ln v by golden section. Subtracting
    /// the noise from the measured covariances instead (noise-compensated Yule-Walker) is
    /// ill-posed for a slow p, whose smooth part moves the covariances less than the
    /// noise-floor estimate's error. None for fewer than 16 samples, a constant `x` or a
    /// non-positive `noise_var`.
    pub fn from_noisy(x: &[f64], noise_var: f64) -> Option<SmoothnessPrior> {
        let (_, sd) = crate::linalg::mean_std(x.iter().copied());
        let var = sd * sd;
        let positive = |v: f64| v > 0.0 && v.is_finite();
        if x.len() < 16 || x.iter().all(|v| *v == x[0]) || !positive(var) || !positive(noise_var) {
            return None;
        }
        let (w, per) = super::stats::periodogram(x, 1);
        let pts: Vec<(f64, f64)> = w
            .iter()
            .zip(&per)
            .skip(1)
            .map(|(w, i)| ((2.0 - 2.0 * w.cos()).powi(2), *i))
            .collect();
        let whittle = |t: f64| {
            let v = t.exp();
            pts.iter()
                .map(|(d, i)| {
                    let sp = v / d + noise_var;
                    sp.ln() + i / sp
                })
                .sum::<f64>()
        };
        let t = crate::linalg::golden_section(
            whittle,
            (1e-12 * var).ln(),
            (16.0 * var).ln(),
            200,
            1e-6,
        );
        let v = t.exp();
        v.is_finite().then_some(SmoothnessPrior {
            second_difference_var: v,
        })
    }
}

/// p(k) - 2 p(k-1) + p(k-2) (k >= 2): what [`SmoothnessPrior`] takes as white.
fn second_difference(p: &[f64], k: usize) -> f64 {
    p[k] - 2.0 * p[k - 1] + p[k - 2]
}

/// The joint negative log-likelihood (times 2) of a model's free run on a scheduling sequence
/// and of that sequence given the measurement: sum_l N ln(mse_l) (each output's error variance
/// concentrated out) + the sequence's terms of the module doc's objective (sensor noise and,
/// where a column has one, its smoothness prior). `y`, `yh` are the measured outputs and the
/// free run on `estimate` (the columns of `cols`, in order), `measured` holds p~. What
/// [`super::refit::fit_latent`] compares its rounds by: training data only, one scale for
/// every round (the MAP step's own weights 1 / sigma_l^2 change from round to round).
pub fn joint_objective(
    y: &DMatrix<f64>,
    yh: &DMatrix<f64>,
    cols: &[NoisyColumn],
    measured: &Dataset,
    estimate: &[Vec<f64>],
) -> f64 {
    let n = y.nrows() as f64;
    let mut f: f64 = crate::metrics::mse_per_output(y, yh, 0)
        .iter()
        .map(|m| n * m.max(1e-300).ln())
        .sum();
    for (c, p) in cols.iter().zip(estimate) {
        add_sequence_terms(&mut f, c, p, &measured.cols[c.col]);
    }
    f
}

/// Add a column's terms of the module doc's objective to `f`: sum_k (p(k) - p~(k))^2 / s^2
/// and, with a smoothness prior, sum_k (second difference)^2 / v.
fn add_sequence_terms(f: &mut f64, c: &NoisyColumn, p: &[f64], measured: &[f64]) {
    for (a, b) in p.iter().zip(measured) {
        *f += (a - b).powi(2) / c.noise_var;
    }
    if let Some(sm) = &c.smooth {
        *f += (2..p.len())
            .map(|k| second_difference(p, k).powi(2))
            .sum::<f64>()
            / sm.second_difference_var;
    }
}

/// What [`map_scheduling`] did.
#[derive(Debug, Clone)]
pub struct MapEstimate {
    /// The estimated columns, in the order asked.
    pub columns: Vec<Vec<f64>>,
    /// The model's memory W used for the band (samples).
    pub memory: usize,
    /// Gauss-Newton steps taken.
    pub steps: usize,
    /// RMS of p^ - p~ per column.
    pub moved_rms: Vec<f64>,
}

/// Free-run output of `model` on `ds` (N x outputs); None when it fails or is not finite.
fn free_run(model: &ModelFile, ds: &Dataset) -> Option<DMatrix<f64>> {
    measured_and_free_run(model, ds).map(|(_, yh)| yh)
}

/// The measured outputs and the free run of `model` on `ds`.
fn measured_and_free_run(model: &ModelFile, ds: &Dataset) -> Option<(DMatrix<f64>, DMatrix<f64>)> {
    let (y, yh) = simulate(model, ds, Mode::FreeRun).ok()?;
    yh.iter().all(|v| v.is_finite()).then_some((y, yh))
}

/// The model's memory of p: the samples after which the free-run response to a change of
/// one scheduling sample has fallen below 1e-3 of its peak (at least 2, at most
/// [`MAX_MEMORY`] and N / 4); None when p does not move the output at all.
fn memory(
    model: &ModelFile,
    ds: &Dataset,
    y0: &DMatrix<f64>,
    cols: &[NoisyColumn],
) -> Option<usize> {
    let n = ds.len();
    let k0 = n / 4;
    let mut w = 0usize;
    let mut any = false;
    for c in cols {
        let mut d = ds.clone();
        let h = step_size(&ds.cols[c.col]);
        d.cols[c.col][k0] += h;
        let y1 = free_run(model, &d)?;
        let diff: Vec<f64> = (k0..n)
            .map(|i| {
                (0..y0.ncols())
                    .map(|l| (y1[(i, l)] - y0[(i, l)]).abs())
                    .fold(0.0, f64::max)
            })
            .collect();
        let peak = diff.iter().copied().fold(0.0, f64::max);
        if peak <= 0.0 {
            continue;
        }
        any = true;
        let last = diff.iter().rposition(|v| *v > 1e-3 * peak).unwrap_or(0);
        w = w.max(last);
    }
    any.then(|| w.clamp(2, MAX_MEMORY.min(n / 4).max(2)))
}

/// Finite-difference step for a column: 1e-4 of its spread (1e-4 when constant).
fn step_size(x: &[f64]) -> f64 {
    let (_, s) = crate::linalg::mean_std(x.iter().copied());
    1e-4 * if s > 0.0 { s } else { 1.0 }
}

/// Band Cholesky factorisation in place: `a[q][d]` holds A(q, q - d), d = 0..=b; on return
/// L(q, q - d). False when A is not positive definite.
fn band_cholesky(a: &mut [Vec<f64>], b: usize) -> bool {
    let n = a.len();
    for q in 0..n {
        for d in (0..=b.min(q)).rev() {
            let r = q - d;
            // A(q, r) - sum_t L(q, t) L(r, t), t from max(q, r) - b .. r
            let lo = q.saturating_sub(b);
            let mut s = a[q][d];
            for t in lo..r {
                s -= a[q][q - t] * a[r][r - t];
            }
            if d == 0 {
                if s <= 0.0 || !s.is_finite() {
                    return false;
                }
                a[q][0] = s.sqrt();
            } else {
                a[q][d] = s / a[r][0];
            }
        }
    }
    true
}

/// Solve L L^T x = g with the band factor of [`band_cholesky`].
fn band_solve(l: &[Vec<f64>], b: usize, g: &mut [f64]) {
    let n = l.len();
    for q in 0..n {
        let mut s = g[q];
        for t in q.saturating_sub(b)..q {
            s -= l[q][q - t] * g[t];
        }
        g[q] = s / l[q][0];
    }
    for q in (0..n).rev() {
        let mut s = g[q];
        for t in q + 1..n.min(q + b + 1) {
            s -= l[t][t - q] * g[t];
        }
        g[q] = s / l[q][0];
    }
}

/// The MAP scheduling sequence of the module doc: `cols` of `train` re-estimated from the
/// outputs of `model`, `output_var` the output-error variance per output (sigma_l^2), at most
/// `max_steps` Gauss-Newton steps (each with a halving line search on the objective), started
/// from `start` (the columns of `cols`, in order; None: from the measurement p~). None when
/// the model's free run fails, p does not move its output, `start` has the wrong shape, or the
/// band would exceed [`MAX_BAND_ENTRIES`].
pub fn map_scheduling(
    model: &ModelFile,
    train: &Dataset,
    cols: &[NoisyColumn],
    output_var: &[f64],
    max_steps: usize,
    start: Option<&[Vec<f64>]>,
) -> Option<MapEstimate> {
    let n = train.len();
    let s = cols.len();
    if n < 8
        || s == 0
        || cols
            .iter()
            .any(|c| c.noise_var.is_nan() || c.noise_var <= 0.0)
    {
        return None;
    }
    let mut ds = train.clone();
    if let Some(start) = start {
        if start.len() != s || start.iter().any(|c| c.len() != n) {
            return None;
        }
        for (c, p) in cols.iter().zip(start) {
            ds.cols[c.col] = p.clone();
        }
    }
    let (y, mut y0) = measured_and_free_run(model, &ds)?;
    let l = y.ncols();
    if output_var.len() != l || output_var.iter().any(|v| v.is_nan() || *v <= 0.0) {
        return None;
    }
    let w = memory(model, &ds, &y0, cols)?;
    let width = (w + 1) * s;
    if n.saturating_mul(l).saturating_mul(width) > MAX_BAND_ENTRIES {
        return None;
    }
    let objective = |d: &Dataset, yh: &DMatrix<f64>| -> f64 {
        let mut f = 0.0;
        for j in 0..l {
            for i in 0..n {
                f += (y[(i, j)] - yh[(i, j)]).powi(2) / output_var[j];
            }
        }
        for c in cols {
            add_sequence_terms(&mut f, c, &d.cols[c.col], &train.cols[c.col]);
        }
        f
    };
    let mut f0 = objective(&ds, &y0);
    let mut steps = 0;
    // jac[(i * l + j) * width + (i - k) * s + ci] = d y_j(i) / d p_ci(k), k in i - w ..= i
    let mut jac = vec![0.0; n * l * width];
    for _ in 0..max_steps {
        jac.iter_mut().for_each(|v| *v = 0.0);
        for (ci, c) in cols.iter().enumerate() {
            let h = step_size(&train.cols[c.col]);
            for o in 0..=w {
                let mut d = ds.clone();
                for k in (o..n).step_by(w + 1) {
                    d.cols[c.col][k] += h;
                }
                let y1 = free_run(model, &d)?;
                for k in (o..n).step_by(w + 1) {
                    for i in k..n.min(k + w + 1) {
                        for j in 0..l {
                            jac[(i * l + j) * width + (i - k) * s + ci] =
                                (y1[(i, j)] - y0[(i, j)]) / h;
                        }
                    }
                }
            }
        }
        // normal equations in band form over q = k * s + ci, band b = width - 1
        let b = width - 1;
        let nq = n * s;
        let mut a = vec![vec![0.0; b + 1]; nq];
        let mut g = vec![0.0; nq];
        for i in 0..n {
            for j in 0..l {
                let row = &jac[(i * l + j) * width..(i * l + j + 1) * width];
                let r = (y[(i, j)] - y0[(i, j)]) / output_var[j];
                for (ea, va) in row.iter().enumerate() {
                    if *va == 0.0 || ea / s > i {
                        continue;
                    }
                    let qa = (i - ea / s) * s + ea % s;
                    g[qa] += va * r;
                    for (eb, vb) in row.iter().enumerate() {
                        if eb / s > i {
                            continue;
                        }
                        let qb = (i - eb / s) * s + eb % s;
                        if qb <= qa && qa - qb <= b {
                            a[qa][qa - qb] += va * vb / output_var[j];
                        }
                    }
                }
            }
        }
        for (ci, c) in cols.iter().enumerate() {
            for k in 0..n {
                let q = k * s + ci;
                a[q][0] += 1.0 / c.noise_var;
                g[q] -= (ds.cols[c.col][k] - train.cols[c.col][k]) / c.noise_var;
            }
            // the prior's term sum_k w(k)^2 / v, w(k) = c . (p(k), p(k-1), p(k-2)) with
            // c = (1, -2, 1): its Hessian c c^T / v on samples k, k-1, k-2 (within the band:
            // b >= 2 s since the memory w >= 2), its gradient c w(k) / v
            if let Some(sm) = &c.smooth {
                let coef = [1.0, -2.0, 1.0];
                let v = sm.second_difference_var;
                let p = &ds.cols[c.col];
                for k in 2..n {
                    let wk = second_difference(p, k) / v;
                    for (i, ci_) in coef.iter().enumerate() {
                        let qi = (k - i) * s + ci;
                        g[qi] -= ci_ * wk;
                        for (j, cj) in coef.iter().enumerate().skip(i) {
                            let qj = (k - j) * s + ci;
                            a[qi][qi - qj] += ci_ * cj / v;
                        }
                    }
                }
            }
        }
        if !band_cholesky(&mut a, b) {
            break;
        }
        band_solve(&a, b, &mut g);
        let mut t = 1.0;
        let mut taken = None;
        for _ in 0..8 {
            let mut d = ds.clone();
            for (ci, c) in cols.iter().enumerate() {
                for k in 0..n {
                    d.cols[c.col][k] += t * g[k * s + ci];
                }
            }
            if let Some(y1) = free_run(model, &d) {
                let f1 = objective(&d, &y1);
                if f1 < f0 {
                    taken = Some((d, y1, f1));
                    break;
                }
            }
            t *= 0.5;
        }
        let Some((d, y1, f1)) = taken else { break };
        let done = f0 - f1 <= 1e-6 * f0;
        ds = d;
        y0 = y1;
        f0 = f1;
        steps += 1;
        if done {
            break;
        }
    }
    let moved_rms = cols
        .iter()
        .map(|c| {
            let d: f64 = (0..n)
                .map(|k| (ds.cols[c.col][k] - train.cols[c.col][k]).powi(2))
                .sum();
            (d / n as f64).sqrt()
        })
        .collect();
    Some(MapEstimate {
        columns: cols.iter().map(|c| ds.cols[c.col].clone()).collect(),
        memory: w,
        steps,
        moved_rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform deviates in [-1, 1) from a fixed LCG (the test's own, reproducible).
    fn uniform(seed: u64, n: usize) -> Vec<f64> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
            })
            .collect()
    }

    /// x(k+1) = (0.5 + 0.4 p) x + (1 + 0.8 p) u, y = x: a first-order plant whose gain and pole
    /// move with p, driven by a white p (no smoothing can separate its noise).
    const PLANT: &str = r#"{
  "type": "lpv-ss",
  "A": [[[0.5]], [[0.4]]],
  "B": [[[1.0]], [[0.8]]],
  "K": [[[0.0]], [[0.0]]],
  "C": [[1.0]],
  "D": [[0.0]]
}"#;

    /// The plant's record: u, the output with 1 % noise, the true p and p with a white sensor
    /// noise of std `sensor`.
    fn record(n: usize, sensor: f64) -> (Dataset, Vec<f64>) {
        record_of(uniform(2, n), sensor)
    }

    /// [`record`] with the true scheduling sequence `p` given.
    fn record_of(p: Vec<f64>, sensor: f64) -> (Dataset, Vec<f64>) {
        let n = p.len();
        let u = uniform(1, n);
        let e = uniform(3, n);
        let eta = uniform(4, n);
        let mut x = 0.0;
        let y: Vec<f64> = (0..n)
            .map(|k| {
                let yk = x + 0.01 * 3f64.sqrt() * e[k];
                x = (0.5 + 0.4 * p[k]) * x + (1.0 + 0.8 * p[k]) * u[k];
                yk
            })
            .collect();
        let noisy: Vec<f64> = (0..n)
            .map(|k| p[k] + sensor * 3f64.sqrt() * eta[k])
            .collect();
        let ds = Dataset {
            source: "plant.csv".into(),
            names: vec!["u1".into(), "y1".into(), "p1".into()],
            cols: vec![u, y, noisy],
        };
        (ds, p)
    }

    fn rms(a: &[f64], b: &[f64]) -> f64 {
        (a.iter().zip(b).map(|(x, z)| (x - z) * (x - z)).sum::<f64>() / a.len() as f64).sqrt()
    }

    #[test]
    fn the_outputs_pull_a_noisy_scheduling_sequence_towards_the_true_one() {
        let model = ModelFile::from_json_str("plant.json", PLANT).unwrap();
        let (ds, p) = record(600, 0.2);
        let before = rms(&ds.cols[2], &p);
        let col = [NoisyColumn {
            col: 2,
            noise_var: 0.04,
            smooth: None,
        }];
        let est = map_scheduling(&model, &ds, &col, &[1e-4], 6, None).unwrap();
        let after = rms(&est.columns[0], &p);
        // the sensor noise is 0.2 RMS; the outputs (1 % noise) locate p(k) wherever x or u is
        // not small (measured: 0.20 -> 0.068)
        assert!((before - 0.2).abs() < 0.02, "{before}");
        assert!(after < 0.5 * before, "{before} -> {after}");
        assert!(est.steps >= 1 && est.memory >= 2, "{est:?}");
        // a prior far tighter than the sensor (a sensor trusted to 1e-4) keeps the measurement
        let tight = [NoisyColumn {
            col: 2,
            noise_var: 1e-8,
            smooth: None,
        }];
        let kept = map_scheduling(&model, &ds, &tight, &[1e-4], 6, None).unwrap();
        assert!(rms(&kept.columns[0], &ds.cols[2]) < 1e-3);
    }

    /// A slowly wandering p (period 150 samples) behind a white sensor noise of std
    /// `sensor`, the plant's record as [`record`] gives it otherwise.
    fn slow_record(n: usize, sensor: f64) -> (Dataset, Vec<f64>) {
        let p = (0..n)
            .map(|k| 0.8 * (2.0 * std::f64::consts::PI * k as f64 / 150.0).sin())
            .collect();
        record_of(p, sensor)
    }

    #[test]
    fn the_smoothness_prior_is_fitted_to_the_measured_spectrum() {
        let (ds, p) = slow_record(1500, 0.2);
        // a slow p: its second difference is tiny beside the sensor's (6 x 0.04)
        let slow = SmoothnessPrior::from_noisy(&ds.cols[2], 0.04).unwrap();
        let exact: f64 = (2..p.len())
            .map(|k| second_difference(&p, k).powi(2))
            .sum::<f64>()
            / (p.len() - 2) as f64;
        assert!(
            slow.second_difference_var < 1e-3 * 0.24 && slow.second_difference_var > 1e-3 * exact,
            "{slow:?}, the true p's {exact:e}"
        );
        // a white p measured without noise moves as fast as it can: a second difference of
        // variance about 6 var(p)
        let white = uniform(7, 1500);
        let fast = SmoothnessPrior::from_noisy(&white, 1e-6).unwrap();
        assert!(fast.second_difference_var > 1.0, "{fast:?}");
        assert!(SmoothnessPrior::from_noisy(&white[..10], 0.04).is_none());
        assert!(SmoothnessPrior::from_noisy(&white, 0.0).is_none());
        assert!(SmoothnessPrior::from_noisy(&vec![0.3; 100], 0.04).is_none());
    }

    #[test]
    fn a_smoothness_prior_recovers_a_slow_scheduling_sequence_better() {
        let model = ModelFile::from_json_str("plant.json", PLANT).unwrap();
        let (ds, p) = slow_record(800, 0.2);
        let before = rms(&ds.cols[2], &p);
        let white = NoisyColumn {
            col: 2,
            noise_var: 0.04,
            smooth: None,
        };
        let smooth = NoisyColumn {
            smooth: SmoothnessPrior::from_noisy(&ds.cols[2], 0.04),
            ..white
        };
        assert!(smooth.smooth.is_some());
        let alone = map_scheduling(&model, &ds, &[white], &[1e-4], 6, None).unwrap();
        let with = map_scheduling(&model, &ds, &[smooth], &[1e-4], 6, None).unwrap();
        let (a, w) = (rms(&alone.columns[0], &p), rms(&with.columns[0], &p));
        // measured: 0.203 -> 0.065 (white), 0.0064 (smooth)
        assert!(
            w < 0.2 * a && a < 0.5 * before,
            "{before} -> {a} (white), {w} (smooth)"
        );
    }

    #[test]
    fn the_joint_objective_ranks_the_true_sequence_first_and_a_warm_start_keeps_the_map() {
        let model = ModelFile::from_json_str("plant.json", PLANT).unwrap();
        let (ds, p) = record(600, 0.2);
        let col = [NoisyColumn {
            col: 2,
            noise_var: 0.04,
            smooth: None,
        }];
        let score = |seq: &[f64]| {
            let mut d = ds.clone();
            d.cols[2] = seq.to_vec();
            let (y, yh) = measured_and_free_run(&model, &d).unwrap();
            joint_objective(&y, &yh, &col, &ds, &[seq.to_vec()])
        };
        // the measurement itself: no sensor term, the output error of a p off by 0.2 RMS; the
        // true p: a sensor term of about N (600) and the output error of the 1 % noise alone
        let (at_truth, at_measured) = (score(&p), score(&ds.cols[2]));
        assert!(
            at_truth < at_measured - 1000.0,
            "{at_truth} vs {at_measured}"
        );
        // the MAP estimate lies between them in p and below both in the objective's output part
        let est = map_scheduling(&model, &ds, &col, &[1e-4], 6, None).unwrap();
        assert!(
            score(&est.columns[0]) < at_measured,
            "{}",
            score(&est.columns[0])
        );
        // warm-started at its own result, the Gauss-Newton steps barely move it
        let again = map_scheduling(&model, &ds, &col, &[1e-4], 6, Some(&est.columns[..])).unwrap();
        assert!(
            rms(&again.columns[0], &est.columns[0]) < 0.05 * rms(&est.columns[0], &ds.cols[2]),
            "moved {}",
            rms(&again.columns[0], &est.columns[0])
        );
        // a start of the wrong shape is refused
        assert!(map_scheduling(&model, &ds, &col, &[1e-4], 6, Some(&[vec![0.0; 5]])).is_none());
    }

    #[test]
    fn a_model_that_ignores_p_gives_no_estimate() {
        let model = ModelFile::from_json_str(
            "plant.json",
            &PLANT
                .replace("[[0.4]]]", "[[0.0]]]")
                .replace("[[0.8]]]", "[[0.0]]]"),
        )
        .unwrap();
        let (ds, _) = record(200, 0.2);
        let col = [NoisyColumn {
            col: 2,
            noise_var: 0.04,
            smooth: None,
        }];
        assert!(map_scheduling(&model, &ds, &col, &[1e-4], 6, None).is_none());
    }

    #[test]
    fn band_cholesky_solves_a_banded_system() {
        // tridiagonal 2, -1 plus a second band 0.3: positive definite
        let n = 9;
        let b = 2;
        let full = DMatrix::from_fn(n, n, |i, j| match i.abs_diff(j) {
            0 => 3.0,
            1 => -1.0,
            2 => 0.3,
            _ => 0.0,
        });
        let mut a: Vec<Vec<f64>> = (0..n)
            .map(|q| {
                (0..=b)
                    .map(|d| if d <= q { full[(q, q - d)] } else { 0.0 })
                    .collect()
            })
            .collect();
        assert!(band_cholesky(&mut a, b));
        let rhs: Vec<f64> = (0..n).map(|i| (i as f64).sin() + 1.0).collect();
        let mut x = rhs.clone();
        band_solve(&a, b, &mut x);
        let back = &full * nalgebra::DVector::from_vec(x);
        for i in 0..n {
            assert!(
                (back[i] - rhs[i]).abs() < 1e-12,
                "{i}: {} vs {}",
                back[i],
                rhs[i]
            );
        }
    }

    #[test]
    fn an_indefinite_band_is_refused() {
        let mut a = vec![vec![1.0, 0.0], vec![-1.0, 2.0], vec![0.5, -3.0]];
        a[1] = vec![1.0, 2.0];
        assert!(!band_cholesky(&mut a, 1));
    }
}
