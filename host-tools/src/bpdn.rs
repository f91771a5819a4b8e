//! Sparse estimation of [C K^p, D] (sparse paper section 4.2): the l2,1-penalised form of
//! BPDN problem (33), solved along a decreasing lambda path by the core's coordinate-descent
//! engine (`lpvid::lasso`, group penalty: one group per column of [C K^p, D], shared by the
//! outputs). The path point is chosen by the AIC rule (34) (BPDN-AIC) or by the smallest
//! prediction error on validation data (BPDN-SV, Algorithm 1), computed from validation
//! statistics. With q up to m^p (r + l) the Gram matrices are never formed: [`LazyGram`]
//! evaluates the columns the solver touches and keeps them.

use std::cell::RefCell;
use std::collections::HashMap;
use std::ops::ControlFlow;
use std::rc::Rc;

use lpvid::lasso::{CoordinateDescent, Penalty, Problem, Settings, SymMatrix};
use lpvid::window::write_pbsid_regressor;
use lpvid::{PbsidDims, Samples, Slab};

/// Regressors of windows laid out row-wise (row j = regressor j over the windows), with the
/// Gram G = Phi Phi^T evaluated lazily: a column is computed on first use (O(q N)) and
/// cached, so a sparse solution with a few active columns costs a few columns.
pub struct LazyGram {
    rows: Vec<f64>,
    n: usize,
    q: usize,
    diag: Vec<f64>,
    cache: RefCell<HashMap<usize, Rc<Vec<f64>>>>,
}

impl LazyGram {
    /// The regressors [z_k^p; u_{k+p} (if `feedthrough`)] of `windows` (window starts) of
    /// `slab`, and the targets y_{k+p} (l x N, row-major).
    pub fn build(
        dims: &PbsidDims,
        slab: &Slab<'_, f64>,
        windows: &[usize],
        feedthrough: bool,
    ) -> Result<(LazyGram, Vec<f64>), String> {
        let q = dims.q().map_err(|e| e.to_string())?;
        let qf = q + if feedthrough { dims.r } else { 0 };
        let n = windows.len();
        let size = qf.checked_mul(n).filter(|&v| v <= 400_000_000).ok_or_else(|| {
            format!("the sparse form needs {qf} regressors x {n} windows: too large; use a smaller past window")
        })?;
        let mut rows = vec![0.0; size];
        let mut z = vec![0.0; q];
        let mut y = vec![0.0; dims.l * n];
        for (c, &k) in windows.iter().enumerate() {
            write_pbsid_regressor(dims, slab, k, &mut z);
            for (j, v) in z.iter().enumerate() {
                rows[j * n + c] = *v;
            }
            if feedthrough {
                for (j, v) in slab.u(k + dims.p).iter().enumerate() {
                    rows[(q + j) * n + c] = *v;
                }
            }
            for (o, v) in slab.y(k + dims.p).iter().enumerate() {
                y[o * n + c] = *v;
            }
        }
        let diag = (0..qf)
            .map(|j| rows[j * n..(j + 1) * n].iter().map(|v| v * v).sum())
            .collect();
        Ok((
            LazyGram {
                rows,
                n,
                q: qf,
                diag,
                cache: RefCell::new(HashMap::new()),
            },
            y,
        ))
    }

    fn row(&self, j: usize) -> &[f64] {
        &self.rows[j * self.n..(j + 1) * self.n]
    }

    fn column(&self, j: usize) -> Rc<Vec<f64>> {
        if let Some(c) = self.cache.borrow().get(&j) {
            return c.clone();
        }
        let rj = self.row(j);
        let col: Vec<f64> = (0..self.q)
            .map(|k| self.row(k).iter().zip(rj).map(|(a, b)| a * b).sum())
            .collect();
        let col = Rc::new(col);
        self.cache.borrow_mut().insert(j, col.clone());
        col
    }

    /// C = Y Phi^T (l x q, row-major) for targets `y` (l x N, row-major).
    pub fn cross(&self, y: &[f64], l: usize) -> Vec<f64> {
        let mut c = vec![0.0; l * self.q];
        for o in 0..l {
            let yo = &y[o * self.n..(o + 1) * self.n];
            for j in 0..self.q {
                c[o * self.q + j] = self.row(j).iter().zip(yo).map(|(a, b)| a * b).sum();
            }
        }
        c
    }

    /// ||Y - Theta Phi||_F^2 from the statistics: yy - 2 tr(Theta C^T) + tr(Theta G Theta^T),
    /// touching only the columns where Theta is non-zero.
    pub fn residual(&self, theta: &[f64], cross: &[f64], yy: f64, l: usize) -> f64 {
        let q = self.q;
        let support: Vec<usize> = (0..q)
            .filter(|&j| (0..l).any(|o| theta[o * q + j] != 0.0))
            .collect();
        let mut r = yy;
        for o in 0..l {
            for &j in &support {
                r -= 2.0 * theta[o * q + j] * cross[o * q + j];
            }
        }
        for &j in &support {
            let col = self.column(j);
            for o in 0..l {
                let tj = theta[o * q + j];
                for &i in &support {
                    r += tj * theta[o * q + i] * col[i];
                }
            }
        }
        r.max(0.0)
    }
}

impl SymMatrix<f64> for LazyGram {
    fn dim(&self) -> usize {
        self.q
    }
    fn get(&self, i: usize, j: usize) -> f64 {
        if i == j {
            return self.diag[i];
        }
        if let Some(c) = self.cache.borrow().get(&j) {
            return c[i];
        }
        if let Some(c) = self.cache.borrow().get(&i) {
            return c[j];
        }
        self.column(j)[i]
    }
    fn add_scaled_column(&self, j: usize, alpha: f64, out: &mut [f64]) {
        let col = self.column(j);
        for (o, c) in out.iter_mut().zip(col.iter()) {
            *o += alpha * c;
        }
    }
}

/// How the path point is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    /// Rule (34): the sparsest point whose residual norm is within (1 + 2 q~ / N) of the
    /// unregularised residual.
    Aic,
    /// Algorithm 1: the smallest prediction error on validation data.
    Sv,
}

/// The chosen point of the path.
pub struct Selection {
    /// [C K^p, D] (l x q, row-major).
    pub theta: Vec<f64>,
    /// Lambda of the point relative to lambda_max (the first point of the path).
    pub lambda: f64,
    /// Lambda of the point in the engine's units (for a refit at the same penalty).
    pub lambda_abs: f64,
    /// Number of non-zero columns.
    pub active: usize,
    /// Path points visited.
    pub points: usize,
    /// Why this point.
    pub reason: String,
}

/// Run the group-lasso path on the identification windows and pick a point by `rule`.
/// `val` are the validation regressors/targets for BPDN-SV; `rss_unreg` the residual sum
/// of squares of the unregularised solution for BPDN-AIC.
pub fn select(
    id: &LazyGram,
    y_id: &[f64],
    l: usize,
    rule: Rule,
    val: Option<(&LazyGram, &[f64])>,
    rss_unreg: f64,
) -> Result<Selection, String> {
    let q = id.q;
    let cross = id.cross(y_id, l);
    let prob = Problem::new(id, &cross, l, Penalty::Group).map_err(|e| e.to_string())?;
    // Algorithm 1 needs the path only approximately (the paper's SPGL1 steps stop early);
    // a 1e-7 relative max-change keeps each point cheap on strongly correlated columns.
    let settings = Settings {
        max_iter: 300,
        tol: 1e-7,
        n_lambda: 50,
        lambda_min_ratio: 1e-4,
    };
    let mut engine = CoordinateDescent::new(l, q, vec![0.0; lpvid::lasso::work_len(l, q)])
        .map_err(|e| e.to_string())?;
    let mut theta = vec![0.0; l * q];
    let val_stats = val.map(|(g, y)| {
        let c = g.cross(y, l);
        let yy: f64 = y.iter().map(|v| v * v).sum();
        (g, c, yy)
    });
    let n = id.n as f64;
    let sigma2 = {
        let factor = 1.0 + 2.0 * (q * l) as f64 / n;
        factor * factor * rss_unreg
    };
    let mut best: Option<(f64, Vec<f64>, f64, usize, usize)> = None;
    let mut lmax = 0.0;
    let mut rising = 0usize;
    let mut err_msg = None;
    let points = engine
        .path(&prob, &settings, &mut theta, |fit, th| {
            if fit.index == 0 {
                lmax = fit.lambda;
            }
            let score = match rule {
                Rule::Sv => {
                    let (g, c, yy) = val_stats.as_ref().expect("validation statistics");
                    g.residual(th, c, *yy, l)
                }
                Rule::Aic => id.residual(th, &cross, y_id.iter().map(|v| v * v).sum(), l),
            };
            if !score.is_finite() {
                err_msg = Some("non-finite residual on the path".to_string());
                return ControlFlow::Break(());
            }
            match rule {
                Rule::Aic => {
                    // the first (sparsest) point inside the AIC ball
                    best = Some((score, th.to_vec(), fit.lambda, fit.active, fit.index));
                    if score <= sigma2 {
                        return ControlFlow::Break(());
                    }
                }
                Rule::Sv => {
                    let better = best.as_ref().map(|b| score < b.0).unwrap_or(true);
                    if better {
                        best = Some((score, th.to_vec(), fit.lambda, fit.active, fit.index));
                        rising = 0;
                    } else {
                        rising += 1;
                        // the validation error has turned: Algorithm 1 stops here
                        if rising >= 8 {
                            return ControlFlow::Break(());
                        }
                    }
                }
            }
            ControlFlow::Continue(())
        })
        .map_err(|e| format!("group-lasso path failed: {e}"))?;
    if let Some(m) = err_msg {
        return Err(m);
    }
    let (score, theta, lambda_abs, active, index) = best.ok_or("empty lasso path")?;
    let lambda = if lmax > 0.0 { lambda_abs / lmax } else { 0.0 };
    let reason = match rule {
        Rule::Sv => format!(
            "BPDN-SV: point {index} of the path (lambda = {lambda:.3e} lambda_max, {active} active columns) has the smallest validation prediction error {:.4e}",
            score.sqrt()
        ),
        Rule::Aic => format!(
            "BPDN-AIC (34): point {index} (lambda = {lambda:.3e} lambda_max, {active} active columns) is the sparsest with residual {:.4e} <= sigma = {:.4e}",
            score.sqrt(),
            sigma2.sqrt()
        ),
    };
    Ok(Selection {
        theta,
        lambda,
        lambda_abs,
        active,
        points,
        reason,
    })
}

/// The group-lasso solution on `g` at engine lambda `lambda`, warm-started from `theta`
/// (the refit of BPDN-SV on all windows at the penalty chosen on the split).
pub fn solve_at(
    g: &LazyGram,
    y: &[f64],
    l: usize,
    lambda: f64,
    theta: &mut [f64],
) -> Result<usize, String> {
    let q = g.q;
    let cross = g.cross(y, l);
    let prob = Problem::new(g, &cross, l, Penalty::Group).map_err(|e| e.to_string())?;
    let settings = Settings {
        max_iter: 1_000,
        tol: 1e-8,
        ..Settings::default()
    };
    let mut engine = CoordinateDescent::new(l, q, vec![0.0; lpvid::lasso::work_len(l, q)])
        .map_err(|e| e.to_string())?;
    let fit = engine
        .solve(&prob, lambda, theta, &settings)
        .map_err(|e| format!("group-lasso refit failed: {e}"))?;
    Ok(fit.active)
}
