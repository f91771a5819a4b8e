//! The sample-space engine for the group-lasso path of BPDN problem (33) (sparse paper,
//! `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md`, section 4.2, in its Lagrangian form):
//! the same problem, lambda grid and stopping rule as the core's covariance-update engine
//! (`lpvid::lasso::CoordinateDescent`), for when the regressors outnumber the windows
//! (q >> N: on B2 at p = 14, q = 65 534 regressors for 61 windows).
//!
//! The covariance engine keeps the gradient C - Theta G (l x q) up to date, so every
//! coordinate move costs a Gram column (q) and every new active column a Gram column
//! evaluation (q N). This engine keeps the *residual* E = Y - Theta Phi (l x N) instead
//! (glmnet's "naive" update): a move costs l N, and the gradient of every column is formed
//! only in a KKT pass, one product Phi E^T (q N l), after the active columns have settled.
//! The sequential strong rule (Tibshirani et al. 2012) picks the columns swept at each new
//! lambda (non-zero columns and those with ||Phi_j E^T|| >= 2 lambda_k - lambda_{k-1} at the
//! previous solution); the KKT pass adds any violator and the sweeps resume, so the solution
//! is that of the full problem, to the same tolerance.

use std::ops::ControlFlow;

use lpvid::lasso::{Fit, Settings};

use super::bpdn::{BpdnError, LazyGram};
use crate::kernel_sweep::dot4;

/// Scale information of one problem (as the core's engine computes it).
struct Scale {
    /// Stopping threshold on max_j G_jj ||Delta Theta[:, j]||^2 (tol x s0).
    thresh: f64,
    /// max_j ||C[:, j]|| (KKT normalisation).
    cmax: f64,
    /// Columns with G_jj at or below this are flat and fixed at zero.
    flat: f64,
}

/// Group-lasso path of min 1/2 ||Y - Theta Phi||_F^2 + lambda sum_j ||Theta[:, j]|| over
/// the regressors of `g` (rows of Phi) and targets `y` (l x N row-major), `cross` = Y Phi^T
/// (l x q). Lambda grid, warm starts, stopping rule (max-change relative to
/// s0 = max_j ||C[:, j]||^2 / G_jj) and flat-column rule as `CoordinateDescent::path` with
/// unit weights, so the two engines solve the same problems; `f` sees every point and may
/// stop the path. Returns the number of points visited.
pub fn path<F>(
    g: &LazyGram,
    y: &[f64],
    cross: &[f64],
    l: usize,
    settings: &Settings<f64>,
    theta: &mut [f64],
    mut f: F,
) -> Result<usize, BpdnError>
where
    F: FnMut(&Fit<f64>, &[f64]) -> ControlFlow<()>,
{
    let (q, n) = (g.regressors(), g.windows());
    if l == 0 || y.len() != l * n || cross.len() != l * q || theta.len() != l * q {
        return Err(BpdnError::Path(lpvid::Error::Mismatch));
    }
    if settings.n_lambda == 0 {
        return Err(BpdnError::Path(lpvid::Error::InvalidConfig(
            "n_lambda must be >= 1",
        )));
    }
    let ratio = settings.lambda_min_ratio;
    if !(ratio > 0.0 && ratio <= 1.0) {
        return Err(BpdnError::Path(lpvid::Error::InvalidConfig(
            "lambda_min_ratio must be in (0, 1]",
        )));
    }
    let diag = g.diagonal();
    let sc = scale(diag, cross, l, settings.tol)?;
    let fixed: Vec<bool> = diag.iter().map(|&d| d <= sc.flat).collect();
    theta.fill(0.0);
    let mut e = y.to_vec();
    // gradient norms ||Phi_j E^T|| at the last KKT pass; at Theta = 0 they are ||C_j||
    let mut gnorm: Vec<f64> = (0..q)
        .map(|j| {
            if fixed[j] {
                0.0
            } else {
                (0..l).map(|o| cross[o * q + j].powi(2)).sum::<f64>().sqrt()
            }
        })
        .collect();
    let lmax = gnorm.iter().copied().fold(0.0, f64::max);
    if !lmax.is_finite() {
        return Err(BpdnError::Path(lpvid::Error::Overflow));
    }
    let points = if lmax > 0.0 { settings.n_lambda } else { 1 };
    let lr = ratio.ln();
    let mut engine = Engine {
        g,
        l,
        q,
        n,
        e: &mut e,
        fixed: &fixed,
        in_set: vec![false; q],
        set: Vec::new(),
        grad: vec![0.0; l],
        e_ref: y.to_vec(),
        g_ref: gnorm.clone(),
        norm: diag.iter().map(|d| d.max(0.0).sqrt()).collect(),
        open: Vec::new(),
    };
    let yy: f64 = y.iter().map(|v| v * v).sum();
    let mut prev = lmax;
    for k in 0..points {
        let lambda = if k == 0 {
            lmax
        } else {
            lmax * (lr * k as f64 / (points - 1) as f64).exp()
        };
        let (iterations, converged) =
            engine.solve(lambda, prev, theta, &mut gnorm, &sc, settings.max_iter)?;
        let (kkt, active) = engine.certificate(lambda, theta, &gnorm, &sc);
        let rss: f64 = engine.e.iter().map(|v| v * v).sum();
        // the non-zero columns are all in the swept set
        let pen: f64 = engine
            .set
            .iter()
            .map(|&j| (0..l).map(|o| theta[o * q + j].powi(2)).sum::<f64>().sqrt())
            .sum();
        let fit = Fit {
            index: k,
            lambda,
            iterations,
            converged,
            active,
            kkt,
            objective: 0.5 * (rss - yy) + lambda * pen,
        };
        prev = lambda;
        if f(&fit, theta).is_break() {
            return Ok(k + 1);
        }
    }
    Ok(points)
}

/// Threshold, KKT normalisation and flat level, as the core's engine derives them.
fn scale(diag: &[f64], cross: &[f64], l: usize, tol: f64) -> Result<Scale, BpdnError> {
    if !(tol >= 0.0 && tol.is_finite()) {
        return Err(BpdnError::Path(lpvid::Error::InvalidConfig(
            "tol must be finite and >= 0",
        )));
    }
    let q = diag.len();
    if diag.iter().any(|d| !d.is_finite()) {
        return Err(BpdnError::NonFiniteResidual);
    }
    let dmax = diag.iter().fold(0.0f64, |a, d| a.max(d.abs()));
    let flat = dmax * f64::EPSILON * q as f64;
    let mut s0 = 0.0f64;
    let mut cmax = 0.0f64;
    for (j, &gjj) in diag.iter().enumerate() {
        let n2: f64 = (0..l).map(|o| cross[o * q + j].powi(2)).sum();
        cmax = cmax.max(n2.sqrt());
        if gjj > flat {
            s0 = s0.max(n2 / gjj);
        }
    }
    if !s0.is_finite() {
        return Err(BpdnError::Path(lpvid::Error::Overflow));
    }
    Ok(Scale {
        thresh: tol * s0,
        cmax,
        flat,
    })
}

/// The engine's state between path points.
struct Engine<'a> {
    g: &'a LazyGram,
    l: usize,
    q: usize,
    n: usize,
    /// Residual E = Y - Theta Phi (l x N, row-major).
    e: &'a mut [f64],
    fixed: &'a [bool],
    /// Membership of the swept set.
    in_set: Vec<bool>,
    /// The swept set (strong set, non-zero columns, KKT violators).
    set: Vec<usize>,
    /// Scratch: the gradient of one column (l).
    grad: Vec<f64>,
    /// The residual at the last full KKT pass.
    e_ref: Vec<f64>,
    /// ||Phi_j E_ref^T|| for every column.
    g_ref: Vec<f64>,
    /// ||Phi_j|| for every column.
    norm: Vec<f64>,
    /// Scratch: the columns a KKT pass has to evaluate.
    open: Vec<usize>,
}

impl Engine<'_> {
    /// Phi_j E^T into `self.grad`.
    fn gradient(&mut self, j: usize) {
        let row = self.g.row(j);
        for o in 0..self.l {
            self.grad[o] = dot4(row, &self.e[o * self.n..(o + 1) * self.n]);
        }
    }

    /// Exact group step on column j at `lambda`; returns G_jj ||delta||^2.
    fn step(&mut self, j: usize, lambda: f64, theta: &mut [f64]) -> f64 {
        let (l, q, n) = (self.l, self.q, self.n);
        let gjj = self.g.diagonal()[j];
        self.gradient(j);
        let mut n2 = 0.0;
        for o in 0..l {
            let rho = self.grad[o] + gjj * theta[o * q + j];
            self.grad[o] = rho;
            n2 += rho * rho;
        }
        let norm = n2.sqrt();
        let factor = if norm > lambda {
            (1.0 - lambda / norm) / gjj
        } else {
            0.0
        };
        let row = self.g.row(j);
        let mut change = 0.0;
        for o in 0..l {
            let new = factor * self.grad[o];
            let delta = new - theta[o * q + j];
            if delta != 0.0 {
                theta[o * q + j] = new;
                for (ev, rv) in self.e[o * n..(o + 1) * n].iter_mut().zip(row) {
                    *ev -= delta * rv;
                }
                change += gjj * delta * delta;
            }
        }
        change
    }

    fn add(&mut self, j: usize) {
        if !self.in_set[j] {
            self.in_set[j] = true;
            self.set.push(j);
        }
    }

    /// Coordinate descent at `lambda`, warm-started from `theta`; `gnorm` holds the gradient
    /// norms at the previous solution (previous lambda `prev`) and receives those of this
    /// one when the solve converges. Returns (sweeps, converged).
    fn solve(
        &mut self,
        lambda: f64,
        prev: f64,
        theta: &mut [f64],
        gnorm: &mut [f64],
        sc: &Scale,
        max_iter: usize,
    ) -> Result<(usize, bool), BpdnError> {
        let (l, q) = (self.l, self.q);
        for &j in &self.set {
            self.in_set[j] = false;
        }
        self.set.clear();
        let strong = 2.0 * lambda - prev;
        for j in 0..q {
            if self.fixed[j] {
                continue;
            }
            if gnorm[j] >= strong || (0..l).any(|o| theta[o * q + j] != 0.0) {
                self.add(j);
            }
        }
        let mut sweeps = 0;
        loop {
            loop {
                if sweeps >= max_iter {
                    return Ok((sweeps, false));
                }
                sweeps += 1;
                let mut dmax = 0.0f64;
                for k in 0..self.set.len() {
                    let j = self.set[k];
                    dmax = dmax.max(self.step(j, lambda, theta));
                }
                if !dmax.is_finite() || self.e.iter().any(|v| !v.is_finite()) {
                    theta.fill(0.0);
                    return Err(BpdnError::Path(lpvid::Error::NoConvergence));
                }
                if dmax <= sc.thresh {
                    break;
                }
            }
            // KKT pass: a zero column outside the swept set whose gradient exceeds lambda
            // violates optimality and joins the set. ||Phi_j E^T|| <= ||Phi_j E_ref^T|| +
            // ||Phi_j|| ||E - E_ref||_F (Cauchy-Schwarz) certifies most columns without
            // touching them; the others get their exact gradient, and when they are more
            // than a quarter of all the pass is a full one that renews the reference.
            if sweeps >= max_iter {
                return Ok((sweeps, false));
            }
            sweeps += 1;
            let drift = self
                .e
                .iter()
                .zip(&self.e_ref)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                .sqrt();
            // one scan for the columns the bound does not certify (ascending)
            self.open.clear();
            for j in 0..q {
                if !self.fixed[j]
                    && !self.in_set[j]
                    && self.g_ref[j] + self.norm[j] * drift > lambda
                {
                    self.open.push(j);
                }
            }
            let full = 4 * self.open.len() > q;
            if full {
                self.e_ref.copy_from_slice(self.e);
            }
            let mut added = 0;
            let count = if full { q } else { self.open.len() };
            for i in 0..count {
                let j = if full { i } else { self.open[i] };
                if self.fixed[j] {
                    continue;
                }
                self.gradient(j);
                let norm = self.grad.iter().map(|v| v * v).sum::<f64>().sqrt();
                gnorm[j] = norm;
                if full {
                    self.g_ref[j] = norm;
                }
                if !self.in_set[j] && norm > lambda {
                    self.add(j);
                    added += 1;
                }
            }
            if added == 0 {
                return Ok((sweeps, true));
            }
        }
    }

    /// Largest KKT violation relative to max_j ||C_j|| (exact for the swept columns, from
    /// the gradient norms for the others, which are zero), and the number of non-zero
    /// columns.
    fn certificate(
        &mut self,
        lambda: f64,
        theta: &[f64],
        gnorm: &[f64],
        sc: &Scale,
    ) -> (f64, usize) {
        let (l, q) = (self.l, self.q);
        let mut viol = (0..q)
            .filter(|&j| !self.in_set[j] && !self.fixed[j])
            .map(|j| gnorm[j] - lambda)
            .fold(0.0f64, f64::max);
        let mut active = 0;
        for k in 0..self.set.len() {
            let j = self.set[k];
            let nt = (0..l).map(|o| theta[o * q + j].powi(2)).sum::<f64>().sqrt();
            self.gradient(j);
            if nt > 0.0 {
                active += 1;
                let v2: f64 = (0..l)
                    .map(|o| (self.grad[o] - lambda * theta[o * q + j] / nt).powi(2))
                    .sum();
                viol = viol.max(v2.sqrt());
            } else {
                let n2: f64 = self.grad.iter().map(|v| v * v).sum();
                viol = viol.max(n2.sqrt() - lambda);
            }
        }
        let denom = if sc.cmax > 0.0 { sc.cmax } else { 1.0 };
        (viol / denom, active)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lpvid::lasso::{CoordinateDescent, Penalty, Problem};
    use lpvid::{PbsidDims, Slab};

    /// The two engines solve the same problems: on a q > N group-lasso path (r = l = 2,
    /// p = 4: q = 122 + 2 regressors for 36 windows, two outputs) every point's objective
    /// agrees to 1e-6 relative, with the same number of active columns, and the KKT
    /// certificate of the sample-space engine is small at every point.
    #[test]
    fn sample_space_path_equals_covariance_path() {
        let (r, l, s, p) = (2usize, 2usize, 1usize, 4usize);
        let dims = PbsidDims::new(r, l, s, p).unwrap();
        let m = dims.m();
        let n = 40;
        let rows = crate::kernel_sweep::tests::record(r, l, m, n);
        let slab = Slab::new(&rows, r, l, m).unwrap();
        let windows: Vec<usize> = (0..n - p).collect();
        let (g, y) = LazyGram::build(&dims, &slab, &windows, true).unwrap();
        let q = g.regressors();
        assert!(q > g.windows());
        let cross = g.cross(&y, l);
        let settings = Settings {
            max_iter: 10_000,
            tol: 1e-12,
            n_lambda: 30,
            lambda_min_ratio: 1e-3,
        };
        let mut cov = Vec::new();
        let prob = Problem::new(&g, &cross, l, Penalty::Group).unwrap();
        let mut cd = CoordinateDescent::new(l, q, vec![0.0; lpvid::lasso::work_len(l, q)]).unwrap();
        let mut theta = vec![0.0; l * q];
        cd.path(&prob, &settings, &mut theta, |fit, _| {
            cov.push(*fit);
            ControlFlow::Continue(())
        })
        .unwrap();
        let mut smp = Vec::new();
        let mut theta = vec![0.0; l * q];
        let points = path(&g, &y, &cross, l, &settings, &mut theta, |fit, _| {
            smp.push(*fit);
            ControlFlow::Continue(())
        })
        .unwrap();
        assert_eq!(points, cov.len());
        for (a, b) in cov.iter().zip(&smp) {
            assert!(
                (a.lambda - b.lambda).abs() <= 1e-12 * a.lambda,
                "{a:?} {b:?}"
            );
            let scale = a.objective.abs().max(1e-300);
            assert!(
                (a.objective - b.objective).abs() <= 1e-6 * scale,
                "point {}: objective {} vs {}",
                a.index,
                a.objective,
                b.objective
            );
            assert!(b.converged && b.kkt < 1e-5, "{b:?}");
            assert_eq!(a.active, b.active, "point {}", a.index);
        }
        assert!(smp.last().unwrap().active > 10);
    }
}
