//! Realization (kernel paper, `papers/lpv-pbsid-kernel-automatica2009.md`, sections 4.2-4.3):
//! Gamma^p K^p from the estimate of C K^p (eq. (14)), the SVD of Gamma^p K^p Z (15), the
//! state sequence (16), then C, D and A^(i), B^(i), K^(i) by least squares from the states
//! (section 4.3), from the data or from statistics alone.

use lpvid::{packed_len, Gram, PbsidDims, Samples, Slab};
use nalgebra::DMatrix;

use super::error::FitError;
use crate::linalg::{min_norm_from_normal, sym_eig, LinalgError};
use crate::lpvss::LpvSs;

/// Kernel paper, eq. (14): Gamma^p K^p from the estimate of C K^p (l x q): row block i, column block j
/// (j >= i) is C (A~^(1))^{i-1} L_{p-j+1}, the leading m^{p-j+1}(r+l) columns of block
/// (j - i + 1) of C K^p (Definitions 2 and 4); blocks with j < i are zero.
pub fn gamma_k(dims: &PbsidDims, f: usize, ck: &DMatrix<f64>) -> DMatrix<f64> {
    let (p, l) = (dims.p, dims.l);
    let q = ck.ncols();
    let mut m = DMatrix::zeros(f * l, q);
    for i in 1..=f {
        for j in i..=p {
            let len = dims.block_len(j);
            let dst = dims.block_offset(j);
            let src = dims.block_offset(j - i + 1);
            m.view_mut(((i - 1) * l, dst), (l, len))
                .copy_from(&ck.view((0, src), (l, len)));
        }
    }
    m
}

/// Kernel paper, eq. (15): the SVD of Gamma^p K^p Z through the eigendecomposition of its Gram
/// (Gamma K Z)(Gamma K Z)^T, which both forms can build. Returns the singular values and
/// the left singular vectors.
pub(crate) fn svd_left(w: &DMatrix<f64>) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
    let (vals, vecs) = sym_eig(w)?;
    let sv = vals.iter().map(|v| v.max(0.0).sqrt()).collect();
    Ok((sv, vecs))
}

/// Kernel paper, eq. (15)-(16), on an explicit Gamma K Z (windows 0..=N-p): the SVD from its first
/// `windows` columns (the regression windows), state candidates U^T Gamma K Z for all.
pub(crate) fn states_from_gkz(
    gkz: &DMatrix<f64>,
    windows: usize,
) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
    let reg_cols = gkz.columns(0, windows);
    let (sv, u) = svd_left(&(reg_cols * reg_cols.transpose()))?;
    Ok((sv, u.transpose() * gkz))
}

/// Kernel paper, section 4.3 with eq. (2), the output equation: C and D from the normal
/// equations of
/// y_k = C x_k + D u_k + e_k (regressors [x; u] or [x] without feedthrough).
pub(crate) fn solve_cd(
    s_ff: &DMatrix<f64>,
    s_fy: &DMatrix<f64>,
    n: usize,
    r: usize,
    feedthrough: bool,
) -> Result<(DMatrix<f64>, DMatrix<f64>), FitError> {
    let (cd, _) = min_norm_from_normal(s_ff, &s_fy.transpose(), 1e-12)?;
    let l = cd.nrows();
    let c = cd.columns(0, n).into_owned();
    let d = if feedthrough {
        cd.columns(n, r).into_owned()
    } else {
        DMatrix::zeros(l, r)
    };
    Ok((c, d))
}

/// Kernel paper, section 4.3 with eq. (1), the state equation: A^(i), B^(i), K^(i) from
/// the normal equations of
/// x_{k+1} = [A^(1) B^(1) K^(1) | ... | A^(m) B^(m) K^(m)] (mu_k (x) [x_k; u_k; e_k]).
pub(crate) fn solve_abk(
    s_ff: &DMatrix<f64>,
    s_fy: &DMatrix<f64>,
    c: DMatrix<f64>,
    d: DMatrix<f64>,
    m: usize,
) -> Result<LpvSs, FitError> {
    let (l, n) = (c.nrows(), c.ncols());
    let r = d.ncols();
    let nxi = n + r + l;
    let (abk, _) = min_norm_from_normal(s_ff, &s_fy.transpose(), 1e-12)?;
    let mut model = LpvSs {
        a: vec![],
        b: vec![],
        k: vec![],
        c: vec![c],
        d: vec![d],
    };
    for i in 0..m {
        let o = i * nxi;
        model.a.push(abk.columns(o, n).into_owned());
        model.b.push(abk.columns(o + n, r).into_owned());
        model.k.push(abk.columns(o + n + r, l).into_owned());
    }
    Ok(model)
}

/// Section 4.3 with the states at hand: `states` column k is x_{k+p} of window k, for
/// windows 0..=N-p (the last one only as a successor). The normal equations are accumulated
/// with the core's Gram, [`REALIZE_BATCH`] rows per batch update (its register-tiled rank-k
/// product: one pass over the packed matrix per batch instead of one per sample; BPDN-SV
/// realizes hundreds of candidates per fit, `benches/bpdn.rs`, `realize_from_states`).
pub fn realize_from_states(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    states: &DMatrix<f64>,
    feedthrough: bool,
) -> Result<LpvSs, FitError> {
    let (p, r, l, m) = (dims.p, dims.r, dims.l, dims.m());
    let n = states.nrows();
    let nb = states.ncols() - 1;
    let r_ft = if feedthrough { r } else { 0 };
    let dcd = n + r_ft + l;
    let g1 = batched_gram(dcd, nb, |k, row| {
        row[..n].copy_from_slice(states.column(k).as_slice());
        row[n..n + r_ft].copy_from_slice(&slab.u(k + p)[..r_ft]);
        row[n + r_ft..].copy_from_slice(slab.y(k + p));
    })?;
    let (s1_ff, s1_fy) = split_gram(&g1, n + r_ft);
    let (c, d) = solve_cd(&s1_ff, &s1_fy, n, r, feedthrough)?;
    let nxi = n + r + l;
    let dst = m * nxi + n;
    let mut xi = vec![0.0; nxi];
    let g2 = batched_gram(dst, nb, |k, row| {
        let x = states.column(k);
        let u = slab.u(k + p);
        let y = slab.y(k + p);
        xi[..n].copy_from_slice(x.as_slice());
        xi[n..n + r].copy_from_slice(u);
        // innovation e = y - C x - D u, without a temporary per sample
        for o in 0..l {
            let mut cx = 0.0;
            for j in 0..n {
                cx += c[(o, j)] * x[j];
            }
            let mut du = 0.0;
            for j in 0..r {
                du += d[(o, j)] * u[j];
            }
            xi[n + r + o] = (y[o] - cx) - du;
        }
        let mu = slab.mu(k + p);
        for i in 0..m {
            for (dstv, v) in row[i * nxi..(i + 1) * nxi].iter_mut().zip(&xi) {
                *dstv = mu[i] * v;
            }
        }
        row[m * nxi..].copy_from_slice(states.column(k + 1).as_slice());
    })?;
    let (s2_ff, s2_fy) = split_gram(&g2, m * nxi);
    solve_abk(&s2_ff, &s2_fy, c, d, m)
}

/// Rows per batch update of [`realize_from_states`]' normal equations.
pub const REALIZE_BATCH: usize = 64;

/// The core's Gram of `count` vectors of length `dim`, each written by `row(k, dst)`, added
/// [`REALIZE_BATCH`] at a time with `Gram::update_batch` (the same checks as per-sample
/// updates; the sums equal theirs up to the order of the additions).
fn batched_gram(
    dim: usize,
    count: usize,
    mut row: impl FnMut(usize, &mut [f64]),
) -> Result<Gram<f64, Vec<f64>>, lpvid::Error> {
    let mut g = Gram::new(dim, vec![0.0; packed_len(dim)])?;
    let mut buf = vec![0.0; REALIZE_BATCH.min(count) * dim];
    let mut k = 0;
    while k < count {
        let nb = REALIZE_BATCH.min(count - k);
        for (b, dst) in buf.chunks_exact_mut(dim).take(nb).enumerate() {
            row(k + b, dst);
        }
        g.update_batch(&buf[..nb * dim], nb)?;
        k += nb;
    }
    Ok(g)
}

/// Section 4.3 from statistics: with x_{k+p} = T z_k^p, every regressor and target of the
/// two least-squares problems is a linear map of v_k = mu_{k+p} (x) w_k (block 0 is w_k;
/// z_{k+1}^p is a selection of v_k), so their normal equations are L G_v L^T.
pub fn realize_from_stats(
    dims: &PbsidDims,
    t: &DMatrix<f64>,
    gv: &DMatrix<f64>,
    feedthrough: bool,
) -> Result<LpvSs, FitError> {
    let (r, l, m) = (dims.r, dims.l, dims.m());
    let q = dims.q()?;
    let d = q + r + l;
    let n = t.nrows();
    let r_ft = if feedthrough { r } else { 0 };
    let sww = gv.view((0, 0), (d, d));
    // output equation: [x; u] = L1 w, y = Ly w
    let mut l1 = DMatrix::zeros(n + r_ft, d);
    l1.view_mut((0, 0), (n, q)).copy_from(t);
    for j in 0..r_ft {
        l1[(n + j, q + j)] = 1.0;
    }
    let mut ly = DMatrix::zeros(l, d);
    for j in 0..l {
        ly[(j, q + r + j)] = 1.0;
    }
    let s1_ff = &l1 * sww * l1.transpose();
    let s1_fy = &l1 * sww * ly.transpose();
    let (c, dm) = solve_cd(&s1_ff, &s1_fy, n, r, feedthrough)?;
    // xi = [x; u; e] = Xi w with e = y - C x - D u
    let nxi = n + r + l;
    let mut xi = DMatrix::zeros(nxi, d);
    xi.view_mut((0, 0), (n, q)).copy_from(t);
    for j in 0..r {
        xi[(n + j, q + j)] = 1.0;
    }
    let ct = &c * t;
    for j in 0..l {
        for i in 0..q {
            xi[(n + r + j, i)] = -ct[(j, i)];
        }
        for i in 0..r {
            xi[(n + r + j, q + i)] = -dm[(j, i)];
        }
        xi[(n + r + j, q + r + j)] = 1.0;
    }
    // regressors: block i of mu (x) xi = Xi (block i of v)
    let vlen = d * m;
    let mut phi = DMatrix::zeros(m * nxi, vlen);
    for i in 0..m {
        phi.view_mut((i * nxi, i * d), (nxi, d)).copy_from(&xi);
    }
    // target: x_{k+p+1} = T z_{k+1}^p, z_{k+1}^p a selection of v
    let mut x2 = DMatrix::zeros(n, vlen);
    let nz = dims.nz();
    for j in 1..=dims.p {
        let dst0 = dims.block_offset(j);
        let (src_off, inner) = if j < dims.p {
            (dims.block_offset(j + 1), dims.block_len(j + 1))
        } else {
            (q, nz)
        };
        for i in 0..m {
            for tt in 0..inner {
                let dst = dst0 + i * inner + tt;
                let src = i * d + src_off + tt;
                for row in 0..n {
                    x2[(row, src)] += t[(row, dst)];
                }
            }
        }
    }
    let s2_ff = &phi * gv * phi.transpose();
    let s2_fy = &phi * gv * x2.transpose();
    solve_abk(&s2_ff, &s2_fy, c, dm, m)
}

/// Split a Gram of [phi; target] into (S_phiphi, S_phitarget).
pub(crate) fn split_gram(g: &Gram<f64, Vec<f64>>, nphi: usize) -> (DMatrix<f64>, DMatrix<f64>) {
    let d = g.dim();
    let s_ff = DMatrix::from_fn(nphi, nphi, |i, j| g.get(i, j));
    let s_fy = DMatrix::from_fn(nphi, d - nphi, |i, j| g.get(i, nphi + j));
    (s_ff, s_fy)
}
