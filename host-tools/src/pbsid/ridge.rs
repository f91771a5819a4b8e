//! The ridge step of regression (13) shared by the primal, the dual (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, eq. (19)-(22)) and the selected-rows forms:
//! the minimum-norm solution (eq. (18)) or Tikhonov with the parameter chosen by generalised
//! cross-validation (section 5.3), computed on one [`Spectrum`] so that GCV is the same
//! number whichever form was solved.

use nalgebra::DMatrix;

use super::error::FitError;
use super::settings::Reg;
use crate::linalg::{sym_eig, Tridiagonal};

/// Spectrum of a ridge problem in the form shared by the primal and the dual: eigenvalues
/// lambda_i of the Gram (equal nonzero eigenvalues either way), the energy c_i of the
/// targets along each (dual coordinates), the total target energy and the row count. GCV
/// computed from this is the same number whichever form was solved.
pub(crate) struct Spectrum {
    pub(crate) vals: Vec<f64>,
    pub(crate) energy: Vec<f64>,
    pub(crate) total: f64,
    pub(crate) rows: f64,
}

impl Spectrum {
    /// Residual sum of squares and effective degrees of freedom at ridge parameter `lam`
    /// (lam = 0: minimum norm with eigenvalues below `cut` dropped).
    pub(crate) fn rss_dof(&self, lam: f64, cut: f64) -> (f64, f64) {
        let (rss, deficit) = self.rss_deficit(lam, cut);
        (rss, self.rows - deficit)
    }

    /// RSS and rows - dof, each computed without cancellation: the residual factor of
    /// component i is lam / (lambda_i + lam), and dropped components count fully.
    fn rss_deficit(&self, lam: f64, cut: f64) -> (f64, f64) {
        // energy outside the Gram's range (zero in the dual); clamp the cancellation error
        let mut rss = (self.total - self.energy.iter().sum::<f64>()).max(0.0);
        let mut deficit = self.rows;
        for (&v, &c) in self.vals.iter().zip(&self.energy) {
            if v <= cut {
                rss += c;
                continue;
            }
            let g = residual_factor(v, lam);
            rss += c * g * g;
            deficit -= 1.0 - g;
        }
        (rss.max(0.0), deficit.max(0.0))
    }

    /// GCV(lam) = rows * RSS / (rows - dof)^2.
    fn gcv(&self, lam: f64, cut: f64) -> f64 {
        let (rss, deficit) = self.rss_deficit(lam, cut);
        if deficit <= 0.0 {
            return f64::INFINITY;
        }
        self.rows * rss / (deficit * deficit)
    }

    /// Ridge parameter minimising GCV (see [`gcv_minimiser`]).
    fn gcv_lambda(&self, cut: f64) -> f64 {
        let vmax = self.vals.iter().copied().fold(0.0, f64::max);
        gcv_minimiser(vmax, |lam| self.gcv(lam, cut))
    }
}

/// Ridge parameter minimising `gcv(lam)`: a log grid over 14 decades below the largest
/// eigenvalue `vmax`, refined by golden-section search in log(lam).
pub(crate) fn gcv_minimiser(vmax: f64, gcv: impl Fn(f64) -> f64) -> f64 {
    let vmax = vmax.max(1e-300);
    let f = |e: f64| gcv(vmax * 10f64.powf(e));
    let (lo, hi, step) = (-14.0, 1.0, 0.25);
    let mut best = (lo, f(lo));
    let mut e = lo;
    while e <= hi {
        let g = f(e);
        if g < best.1 {
            best = (e, g);
        }
        e += step;
    }
    let e = crate::linalg::golden_section(f, best.0 - step, best.0 + step, 40, 0.0);
    let e = if f(e) <= best.1 { e } else { best.0 };
    vmax * 10f64.powf(e)
}

/// Relative eigenvalue cut-off defining the numerical rank of a Gram matrix.
pub(crate) const RANK_TOL: f64 = 1e-11;

/// Pick lambda for the chosen regularisation; returns (lambda, dof, cut).
pub(crate) fn choose_lambda(reg: Reg, spec: &Spectrum) -> (f64, f64, f64) {
    let vmax = spec.vals.iter().copied().fold(0.0, f64::max);
    let cut = vmax * RANK_TOL;
    let lam = match reg {
        Reg::None | Reg::BpdnAic | Reg::BpdnSv => 0.0,
        Reg::TikhonovGcv => spec.gcv_lambda(cut),
        Reg::Tikhonov(rel) => rel * vmax,
    };
    let (_, dof) = spec.rss_dof(lam, cut);
    (lam, dof, cut)
}

/// Filter factor applied to component i: 1/(v + lam), or 0 below the rank cut-off.
pub(crate) fn filter(v: f64, lam: f64, cut: f64) -> f64 {
    if v <= cut {
        0.0
    } else {
        (1.0 - residual_factor(v, lam)) / v
    }
}

/// 1 - phi_i, the part of component i the regularised fit leaves in the residual.
pub(crate) fn residual_factor(v: f64, lam: f64) -> f64 {
    lam / (v + lam)
}

/// Which normal equations a ridge step solves: primal (A = Phi Phi^T, B = Phi Y^T) or dual
/// (A = Phi^T Phi, B = Y^T). The target energy along eigenvector i of A is (V^T B)_i^2 /
/// lambda_i in the primal and (V^T B)_i^2 in the dual.
#[derive(Clone, Copy, PartialEq)]
pub(crate) enum NormalForm {
    Primal,
    Dual,
}

/// Below this fraction of the largest eigenvalue a Tikhonov parameter is solved through the
/// eigendecomposition (with the rank cut-off) rather than the shifted tridiagonal system.
pub(crate) const SHIFTED_SOLVE_MIN: f64 = 1e-10;

/// The ridge step shared by every form of regression (13): X = (A + lam I)^{-1} B, lam
/// chosen by `reg` on the common [`Spectrum`] (so GCV is the same number in the primal and
/// the dual), lam = 0 the minimum-norm solution (eq. (18)). Tikhonov reduces A to
/// tridiagonal form once ([`ridge_tridiagonal`]); the minimum-norm solution is solved by
/// the eigendecomposition of A ([`ridge_eig`]).
pub(crate) fn ridge_solve(
    a: &DMatrix<f64>,
    b: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> Result<(DMatrix<f64>, RegressionInfo), FitError> {
    if matches!(reg, Reg::TikhonovGcv | Reg::Tikhonov(_)) {
        return ridge_tridiagonal(&Tridiagonal::new(a), b, form, total, rows, reg);
    }
    ridge_eig(a, b, form, total, rows, reg)
}

/// The common [`Spectrum`] from eigenvalues and the targets' eigen-coordinates.
fn spectrum(
    form: NormalForm,
    vals: &[f64],
    proj: &DMatrix<f64>,
    total: f64,
    rows: f64,
) -> Spectrum {
    Spectrum {
        energy: vals
            .iter()
            .enumerate()
            .map(|(i, &v)| {
                let e = proj.row(i).norm_squared();
                match form {
                    NormalForm::Dual => e,
                    NormalForm::Primal if v > 0.0 => e / v,
                    NormalForm::Primal => 0.0,
                }
            })
            .collect(),
        vals: vals.to_vec(),
        total,
        rows,
    }
}

/// The ridge step of [`ridge_solve`] on A already reduced to tridiagonal form, B given in
/// A's coordinates. Tikhonov: lambda by `reg` (GCV over the spectrum, O(n) per lambda in the
/// dual), then one shifted tridiagonal solve, O(n^2) after the reduction in all. When
/// lambda is below [`SHIFTED_SOLVE_MIN`] of the largest eigenvalue or T + lambda I is not
/// numerically positive definite, and for the minimum-norm solution: the eigenvectors of T
/// ([`Tridiagonal::eigen`]) with the rank cut-off, as [`ridge_eig`] does with those of A,
/// without reducing A a second time.
pub(crate) fn ridge_tridiagonal(
    tri: &Tridiagonal,
    b: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> Result<(DMatrix<f64>, RegressionInfo), FitError> {
    let bt = tri.to_tridiagonal(b);
    if matches!(reg, Reg::TikhonovGcv | Reg::Tikhonov(_)) {
        if let Some(done) = shifted_ridge(tri, &bt, form, total, rows, reg)? {
            return Ok(done);
        }
    }
    let (vals, vecs) = tri.eigen()?;
    let (x, info) = filtered(&vals, &vecs, &bt, form, total, rows, reg);
    Ok((tri.from_tridiagonal(&x), info))
}

/// The Tikhonov step of [`ridge_tridiagonal`] by one shifted solve, `bt` in the tridiagonal
/// coordinates; None where that solve is not accurate (see there).
fn shifted_ridge(
    tri: &Tridiagonal,
    bt: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> Result<Option<(DMatrix<f64>, RegressionInfo)>, FitError> {
    let (lam, dof, vmax) = match form {
        NormalForm::Primal => {
            // the primal residual needs the energies b_i^2 / lambda_i: eigen-coordinates
            let (vals, proj) = tri.eigen_projection(bt)?;
            let (lam, dof, _) = choose_lambda(reg, &spectrum(form, &vals, &proj, total, rows));
            (lam, dof, vals.first().copied().unwrap_or(0.0).max(0.0))
        }
        NormalForm::Dual => {
            // RSS = lam^2 ||(T + lam I)^{-1} Q^T y||^2 and rows - dof =
            // lam tr((T + lam I)^{-1}): O(n) per lambda, no eigenvalues needed
            let vmax = tri.largest_eigenvalue().max(0.0);
            let curve = |lam: f64| {
                tri.shifted_norm_trace(lam, bt)
                    .map(|(xx, tr)| (lam * lam * xx, lam * tr))
            };
            let lam = match reg {
                Reg::Tikhonov(rel) => rel * vmax,
                _ => gcv_minimiser(vmax, |lam| match curve(lam) {
                    Some((rss, deficit)) if deficit > 0.0 => rows * rss / (deficit * deficit),
                    _ => f64::INFINITY,
                }),
            };
            let dof = curve(lam).map_or(f64::NAN, |(_, deficit)| rows - deficit);
            (lam, dof, vmax)
        }
    };
    if lam > SHIFTED_SOLVE_MIN * vmax && dof.is_finite() {
        if let Some(w) = tri.solve_shifted(lam, bt) {
            let lambda = Some((lam, vmax));
            return Ok(Some((
                tri.from_tridiagonal(&w),
                RegressionInfo { lambda, dof },
            )));
        }
    }
    Ok(None)
}

/// The ridge step of [`ridge_solve`] by the full symmetric eigendecomposition of A (the
/// minimum-norm solution of the primal form).
pub(crate) fn ridge_eig(
    a: &DMatrix<f64>,
    b: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> Result<(DMatrix<f64>, RegressionInfo), FitError> {
    let (vals, vecs) = sym_eig(a)?;
    Ok(filtered(&vals, &vecs, b, form, total, rows, reg))
}

/// X = V diag(phi_i / lambda_i) V^T B from eigenvalues `vals` (descending) and orthonormal
/// eigenvectors `vecs`: lambda chosen by `reg` on their [`Spectrum`], components below the
/// rank cut-off dropped ([`filter`]).
fn filtered(
    vals: &[f64],
    vecs: &DMatrix<f64>,
    b: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> (DMatrix<f64>, RegressionInfo) {
    let tikhonov = matches!(reg, Reg::TikhonovGcv | Reg::Tikhonov(_));
    let mut proj = vecs.tr_mul(b);
    let (lam, dof, cut) = choose_lambda(reg, &spectrum(form, vals, &proj, total, rows));
    for (i, &v) in vals.iter().enumerate() {
        proj.row_mut(i).scale_mut(filter(v, lam, cut));
    }
    let vmax = vals.first().copied().unwrap_or(0.0);
    let lambda = tikhonov.then_some((lam, vmax));
    (vecs * proj, RegressionInfo { lambda, dof })
}

/// Outcome of the regularised regression.
#[derive(Clone)]
pub(crate) struct RegressionInfo {
    /// (lambda, largest Gram eigenvalue), None for the minimum-norm solution.
    pub(crate) lambda: Option<(f64, f64)>,
    /// Effective number of parameters per output.
    pub(crate) dof: f64,
}

impl RegressionInfo {
    pub(crate) fn lambda_rel(&self) -> Option<f64> {
        self.lambda
            .map(|(lam, vmax)| if vmax > 0.0 { lam / vmax } else { 0.0 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Gram of rank `rank` < n (both forms see it: the primal one as is, the dual one as a
    /// kernel) and targets in its range plus `noise`.
    fn low_rank(n: usize, rank: usize, noise: f64) -> (DMatrix<f64>, DMatrix<f64>) {
        let x = DMatrix::from_fn(rank, n, |i, j| ((i * 13 + j * 7) % 17) as f64 / 5.0 - 1.6);
        let coef = DMatrix::from_fn(1, rank, |_, i| (i as f64 * 0.9).cos());
        let y = DMatrix::from_fn(n, 1, |k, _| {
            (coef.clone() * x.column(k))[(0, 0)] + noise * ((k * 7 % 11) as f64 - 5.0)
        });
        (x.transpose() * x, y)
    }

    /// Where the shifted solve declines (GCV at the foot of its range on noise-free targets,
    /// a kernel of rank 30 in 200 windows) and for the minimum-norm solution, the reduced
    /// form gives the solution of the full eigendecomposition of A: same lambda, same cut.
    #[test]
    fn reduced_form_equals_full_eigendecomposition_below_the_shifted_floor() {
        for (reg, noise) in [(Reg::TikhonovGcv, 0.0), (Reg::None, 0.0), (Reg::None, 0.1)] {
            let (k, y) = low_rank(200, 30, noise);
            let total = y.norm_squared();
            let tri = Tridiagonal::new(&k);
            let (x, info) =
                ridge_tridiagonal(&tri, &y, NormalForm::Dual, total, 200.0, reg).unwrap();
            let (x_full, info_full) =
                ridge_eig(&k, &y, NormalForm::Dual, total, 200.0, reg).unwrap();
            if reg == Reg::TikhonovGcv {
                let rel = info.lambda_rel().unwrap();
                assert!(
                    rel < SHIFTED_SOLVE_MIN,
                    "the shifted solve was not declined: {rel}"
                );
            }
            assert!(
                (info.dof - info_full.dof).abs() < 1e-6,
                "{reg:?}: {} {}",
                info.dof,
                info_full.dof
            );
            // the fitted values K x agree (x itself is fixed only up to the cut's rounding)
            let (fit, fit_full) = (&k * &x, &k * &x_full);
            assert!(
                (&fit - &fit_full).norm() <= 1e-8 * y.norm(),
                "{reg:?}: {}",
                (&fit - &fit_full).norm()
            );
            assert!((&x - &x_full).norm() <= 1e-6 * x_full.norm(), "{reg:?}");
        }
    }
}
