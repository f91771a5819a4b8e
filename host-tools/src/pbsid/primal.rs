//! The primal form of regression (13) (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, section 4.1, Algorithm 1 of section 4.5):
//! the normal equations from the core's second-moment statistics of
//! w_k = [z_k^p; u_{k+p}; y_{k+p}], then Gamma^p K^p (14), the SVD (15) through
//! Gamma K S_zz (Gamma K)^T and the state map of (16).

use lpvid::window::write_pbsid_regressor;
use lpvid::{stat_vector_len, write_stat_vector, Gram, PbsidDims, Slab, StatsLayout};
use nalgebra::DMatrix;

use super::error::FitError;
use super::realize::{gamma_k, svd_left};
use super::ridge::{ridge_solve, NormalForm, RegressionInfo};
use super::settings::PbsidOptions;
use crate::kernel_sweep::dot4;

/// Primal path on the (scaled) plain statistics `stats` of w_k = [z_k^p; u_{k+p}; y_{k+p}]:
/// regression (13) from them, Gamma^p K^p by eq. (14), the SVD of Gamma K Z from
/// Gamma K S_zz (Gamma K)^T, and T = U^T Gamma^p K^p so that the state candidates are
/// x_{k+p} = T z_k^p (eq. (16): Sigma_n V = U_n^T Gamma K Z).
pub(crate) fn primal_regression_svd(
    dims: &PbsidDims,
    f: usize,
    stats: &DMatrix<f64>,
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(RegressionInfo, Vec<f64>, DMatrix<f64>), FitError> {
    let (r, l) = (dims.r, dims.l);
    let q = dims.q()?;
    let r_ft = if opts.feedthrough { r } else { 0 };
    let qf = q + r_ft;
    let s_ff = stats.view((0, 0), (qf, qf)).into_owned();
    let s_fy = stats.view((0, q + r), (qf, l)).into_owned();
    let syy: f64 = (0..l).map(|j| stats[(q + r + j, q + r + j)]).sum();
    let (x, info) = ridge_solve(
        &s_ff,
        &s_fy,
        NormalForm::Primal,
        syy,
        windows as f64,
        opts.reg,
    )?;
    let theta = x.transpose(); // l x qf
    let ck = theta.columns(0, q).into_owned();
    let gk = gamma_k(dims, f, &ck);
    let s_zz = stats.view((0, 0), (q, q));
    let w = &gk * s_zz * gk.transpose();
    let (sv, u) = svd_left(&w)?;
    let t = u.transpose() * &gk;
    Ok((info, sv, t))
}

/// Primal path (Algorithm 1) on data: the plain statistics of the scaled windows from the
/// core's Gram, regression (13) and the SVD by [`primal_regression_svd`], and the state
/// candidates x_{k+p} = T z_k^p for windows 0..=N-p.
pub(crate) fn primal_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo), FitError> {
    let q = dims.q()?;
    let len = stat_vector_len(dims, StatsLayout::Plain)?;
    // two halves on two threads when large enough to gain, merged (the statistics are sums)
    let gram = crate::linalg::gram_from_rows_split(
        len,
        windows,
        |k, row| write_stat_vector(dims, StatsLayout::Plain, slab, k, row),
        true,
    )?;
    let stats = dense(&gram, len);
    let (reg, sv, t) = primal_regression_svd(dims, f, &stats, windows, opts)?;
    // x_{k+p} = T z_k^p, one dot product per state row (the rows of T contiguous: T^T's
    // columns) without a temporary per window
    let tt = t.transpose();
    let mut x = DMatrix::zeros(t.nrows(), windows + 1);
    let mut z = vec![0.0; q];
    for k in 0..=windows {
        write_pbsid_regressor(dims, slab, k, &mut z);
        for (i, row) in tt.column_iter().enumerate() {
            x[(i, k)] = dot4(row.as_slice(), &z);
        }
    }
    Ok((sv, x, reg))
}

/// The dense symmetric matrix of a Gram's leading `len` rows and columns: row i of the
/// packed upper triangle (contiguous) is column i of the lower one from the diagonal down
/// and row i of the upper one (the same values as `get(i, j)`, without an index per entry).
pub(crate) fn dense<S: AsRef<[f64]> + AsMut<[f64]>>(g: &Gram<f64, S>, len: usize) -> DMatrix<f64> {
    let dim = g.dim();
    let packed = g.packed();
    let mut m = DMatrix::zeros(len, len);
    let mut off = 0;
    for i in 0..len {
        let row = &packed[off..off + len - i];
        m.column_mut(i).as_mut_slice()[i..].copy_from_slice(row);
        for (j, &v) in row.iter().enumerate().skip(1) {
            m[(i, i + j)] = v;
        }
        off += dim - i;
    }
    m
}
