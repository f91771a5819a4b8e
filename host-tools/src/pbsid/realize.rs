//! Realization (kernel paper, `papers/lpv-pbsid-kernel-automatica2009.md`, sections 4.2-4.3):
//! Gamma^p K^p from the estimate of C K^p (eq. (14)), the SVD of Gamma^p K^p Z (15), the
//! state sequence (16), then C, D and A^(i), B^(i), K^(i) by least squares from the states
//! (section 4.3), from the data or from statistics alone.

use lpvid::{packed_len, Gram, PbsidDims, Samples, Slab};
use nalgebra::DMatrix;

use super::bpdn::FreeRun;
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
pub fn states_from_gkz(
    gkz: &DMatrix<f64>,
    windows: usize,
) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
    let reg_cols = gkz.columns(0, windows);
    let (sv, u) = svd_left(&(reg_cols * reg_cols.transpose()))?;
    Ok((sv, u.transpose() * gkz))
}

/// [`states_from_gkz`] on a row-major Gamma K Z (`rows` rows of `windows` + 1 values):
/// the Gram of the regression columns by [`crate::kernel_sweep::dot4`], the states
/// U^T Gamma K Z row-major, each entry summed over the rows of Gamma K Z in order (the
/// same values to rounding; BPDN-SV forms these at every path point).
pub fn states_from_gkz_rows(
    gkz: &[f64],
    rows: usize,
    windows: usize,
) -> Result<(Vec<f64>, Vec<f64>), LinalgError> {
    let w = windows + 1;
    let row = |a: usize| &gkz[a * w..a * w + windows];
    let mut gram = DMatrix::zeros(rows, rows);
    for b in 0..rows {
        for a in 0..=b {
            let v = crate::kernel_sweep::dot4(row(a), row(b));
            gram[(a, b)] = v;
            gram[(b, a)] = v;
        }
    }
    let (sv, u) = svd_left(&gram)?;
    let mut x = vec![0.0; rows * w];
    for (i, xi) in x.chunks_exact_mut(w).enumerate() {
        for j in 0..rows {
            let c = u[(j, i)];
            for (d, v) in xi.iter_mut().zip(&gkz[j * w..(j + 1) * w]) {
                *d += c * v;
            }
        }
    }
    Ok((sv, x))
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
    let (abk, _) = min_norm_from_normal(s_ff, &s_fy.transpose(), 1e-12)?;
    debug_assert_eq!(abk.ncols(), m * (c.ncols() + d.ncols() + c.nrows()));
    Ok(LpvSs::from_abk(&abk, vec![c], vec![d]))
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
    let g1 = output_gram(p, slab, states, r_ft)?;
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
        state_row(row, slab.mu(k + p), &xi, states.column(k + 1).as_slice());
    })?;
    let (s2_ff, s2_fy) = split_gram(&g2, m * nxi);
    solve_abk(&s2_ff, &s2_fy, c, d, m)
}

/// The Gram of the output equation's rows [x_k; u_k (first `r_ft`); y_k] over the windows
/// of `states` (section 4.3 with eq. (2)): shared by [`realize_from_states`] and
/// [`OrderSweep`].
fn output_gram(
    p: usize,
    slab: &Slab<'_, f64>,
    states: &DMatrix<f64>,
    r_ft: usize,
) -> Result<Gram<f64, Vec<f64>>, lpvid::Error> {
    let n = states.nrows();
    let dim = n + r_ft + slab.y(p).len();
    batched_gram(dim, states.ncols() - 1, |k, row| {
        output_row(
            row,
            states.column(k).as_slice(),
            slab.u(k + p),
            slab.y(k + p),
            r_ft,
        );
    })
}

/// One row [x_k; u_k (its first `r_ft` entries); y_k] of the output equation's normal
/// equations (section 4.3), in memory and streamed (`super::stream::PassTwo`).
pub(crate) fn output_row(row: &mut [f64], x: &[f64], u: &[f64], y: &[f64], r_ft: usize) {
    let n = x.len();
    row[..n].copy_from_slice(x);
    row[n..n + r_ft].copy_from_slice(&u[..r_ft]);
    row[n + r_ft..].copy_from_slice(y);
}

/// One row [mu_k (x) xi_k; x_{k+1}] of the state equation's normal equations (section 4.3):
/// xi_k = [x; u; e] in [`realize_from_states`], [x; u; y] in [`OrderSweep`] and streamed
/// (mapped to e after the sums).
pub(crate) fn state_row(row: &mut [f64], mu: &[f64], xi: &[f64], x_next: &[f64]) {
    let nxi = xi.len();
    for (i, w) in mu.iter().enumerate() {
        for (dst, v) in row[i * nxi..(i + 1) * nxi].iter_mut().zip(xi) {
            *dst = w * v;
        }
    }
    row[mu.len() * nxi..].copy_from_slice(x_next);
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

/// X = B A^{-1} (B: k x d) for a symmetric A whose Cholesky factor proves it well inside
/// the full-rank case of `min_norm_from_normal(A, B, rel_tol)`: with A = L L^T,
/// lambda_max <= tr(A) and lambda_min >= 1 / tr(A^{-1}) = 1 / ||L^{-1}||_F^2, so when
/// 1 / ||L^{-1}||_F^2 > 1e3 rel_tol tr(A) every eigenvalue is kept by the eigenvalue
/// form (margin 1e3 for the rounding of both) and its minimum-norm solution is the
/// unique solution B A^{-1}, here without the eigendecomposition. `None` otherwise (the
/// caller falls back to the eigenvalue form). The two differ by rounding only.
fn spd_solve(a: &DMatrix<f64>, b: &DMatrix<f64>, rel_tol: f64) -> Option<DMatrix<f64>> {
    let d = a.nrows();
    let mut l = DMatrix::<f64>::zeros(d, d);
    for j in 0..d {
        let mut s = a[(j, j)];
        for k in 0..j {
            s -= l[(j, k)] * l[(j, k)];
        }
        if !(s > 0.0 && s.is_finite()) {
            return None;
        }
        let ljj = s.sqrt();
        l[(j, j)] = ljj;
        for i in j + 1..d {
            let mut s = a[(i, j)];
            for k in 0..j {
                s -= l[(i, k)] * l[(j, k)];
            }
            l[(i, j)] = s / ljj;
        }
    }
    // L^{-1}, lower triangular, column by column
    let mut li = DMatrix::<f64>::zeros(d, d);
    for j in 0..d {
        li[(j, j)] = 1.0 / l[(j, j)];
        for i in j + 1..d {
            let mut s = 0.0;
            for k in j..i {
                s += l[(i, k)] * li[(k, j)];
            }
            li[(i, j)] = -s / l[(i, i)];
        }
    }
    let trace_inv = li.norm_squared();
    let trace = a.trace();
    if !(trace_inv.is_finite() && 1.0 / trace_inv > 1e3 * rel_tol * trace) {
        return None;
    }
    let ainv = li.transpose() * &li;
    Some(b * ainv)
}

/// The least-squares solution of [`min_norm_from_normal`] (normal matrix `s_ff`, cross
/// products `s_fy`, relative rank tolerance 1e-12 as in [`solve_cd`] / [`solve_abk`]):
/// by [`spd_solve`] when the Cholesky factor proves full rank, else by the
/// eigendecomposition.
fn solve_normal(s_ff: &DMatrix<f64>, s_fy: &DMatrix<f64>) -> Result<DMatrix<f64>, FitError> {
    let b = s_fy.transpose();
    if let Some(x) = spd_solve(s_ff, &b, 1e-12) {
        return Ok(x);
    }
    Ok(min_norm_from_normal(s_ff, &b, 1e-12)?.0)
}

/// [A^(1) B^(1) K^(1) | ...], C and D of one order, as solved by [`OrderSweep`].
type Solved = (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>);

/// Section 4.3 for every order n <= `nmax` of one state sequence (BPDN-SV realizes each
/// path point at all candidate orders): the states of order n are the first n rows of
/// those of order `nmax` (eq. (16), U^T Gamma K Z), so both normal equations of every
/// order are linear maps of two Grams accumulated once,
/// G1 of [x^(nmax); u (with feedthrough); y] and G2 of [mu (x) [x^(nmax); u; y]; x^(nmax)_{k+1}]
/// (the innovation e = y - C x - D u of order n is a combination of x, u, y). Per order
/// only the small normal matrices are formed and solved ([`spd_solve`], with the
/// eigenvalue form as fallback). The model equals [`realize_from_states`] on the first n
/// rows up to rounding (`orders_share_one_gram` checks it).
pub struct OrderSweep {
    nmax: usize,
    r: usize,
    l: usize,
    m: usize,
    r_ft: usize,
    g1: DMatrix<f64>,
    g2: DMatrix<f64>,
    /// The output equation's normal matrix with the regressors in nested order [u; x]
    /// (order n: the leading r_ft + n), factored once for all orders.
    out: NestedChol,
    /// The state equation's, regressors mu (x) [x; u; y] in nested order (all mu (x) [u; y],
    /// then mu (x) x_1, mu (x) x_2, ...; order n: the leading m (r + l + n)).
    state: NestedChol,
}

/// A Cholesky factor L of a normal matrix A whose regressors are ordered so that every
/// candidate order uses a leading block: the factor of a leading k x k block is the leading
/// block of L, and so are L^{-1} and the forward-substituted cross products L^{-1} b. With
/// the running ||L_k^{-1}||_F^2 and tr(A_k), the full-rank proof of [`spd_solve`] and the
/// solution of every leading size cost one back substitution each.
struct NestedChol {
    d: usize,
    /// L, row-major (lower triangle).
    l: Vec<f64>,
    /// Leading sizes up to `ok` have positive, finite pivots.
    ok: usize,
    /// ||L_k^{-1}||_F^2 for k = 0..=ok.
    inv2: Vec<f64>,
    /// tr(A_k) for k = 0..=ok.
    trace: Vec<f64>,
    /// L^{-1} b_t of target t at t d .. (t + 1) d (entries below `ok` valid).
    fwd: Vec<f64>,
}

impl NestedChol {
    /// Factor the d x d matrix `a(i, j)` with cross products `b(i, t)` of `targets`
    /// targets (indices in the nested order).
    fn new(
        d: usize,
        targets: usize,
        a: impl Fn(usize, usize) -> f64,
        b: impl Fn(usize, usize) -> f64,
    ) -> Self {
        let mut l = vec![0.0; d * d];
        let mut ok = d;
        for j in 0..d {
            let mut s = a(j, j);
            for k in 0..j {
                s -= l[j * d + k] * l[j * d + k];
            }
            if !(s > 0.0 && s.is_finite()) {
                ok = j;
                break;
            }
            let ljj = s.sqrt();
            l[j * d + j] = ljj;
            for i in j + 1..d {
                let mut s = a(i, j);
                for k in 0..j {
                    s -= l[i * d + k] * l[j * d + k];
                }
                l[i * d + j] = s / ljj;
            }
        }
        // rows of L^{-1} (row i needs rows < i only: nested), their running squared norm
        let mut li = vec![0.0; d * d];
        let mut inv2 = vec![0.0; ok + 1];
        let mut trace = vec![0.0; ok + 1];
        for i in 0..ok {
            let lii = l[i * d + i];
            li[i * d + i] = 1.0 / lii;
            for j in 0..i {
                let mut s = 0.0;
                for k in j..i {
                    s += l[i * d + k] * li[k * d + j];
                }
                li[i * d + j] = -s / lii;
            }
            let row: f64 = li[i * d..i * d + i + 1].iter().map(|v| v * v).sum();
            inv2[i + 1] = inv2[i] + row;
            trace[i + 1] = trace[i] + a(i, i);
        }
        let mut fwd = vec![0.0; targets * d];
        for t in 0..targets {
            let f = &mut fwd[t * d..(t + 1) * d];
            for i in 0..ok {
                let mut s = b(i, t);
                for k in 0..i {
                    s -= l[i * d + k] * f[k];
                }
                f[i] = s / l[i * d + i];
            }
        }
        NestedChol {
            d,
            l,
            ok,
            inv2,
            trace,
            fwd,
        }
    }

    /// Whether the leading k x k block is proven well inside the full-rank case of
    /// `min_norm_from_normal(A_k, B, 1e-12)` (the test of [`spd_solve`]).
    fn proven(&self, k: usize) -> bool {
        k >= 1
            && k <= self.ok
            && self.inv2[k].is_finite()
            && 1.0 / self.inv2[k] > 1e3 * 1e-12 * self.trace[k]
    }

    /// The solution x = A_k^{-1} b_t (leading size k) into `x[..k]`.
    fn solve(&self, k: usize, t: usize, x: &mut [f64]) {
        let (d, l) = (self.d, &self.l);
        let f = &self.fwd[t * d..];
        for i in (0..k).rev() {
            let mut s = f[i];
            for j in i + 1..k {
                s -= l[j * d + i] * x[j];
            }
            x[i] = s / l[i * d + i];
        }
    }
}

impl OrderSweep {
    /// The sweep of the two Grams, with both normal equations factored in nested order.
    fn from_grams(
        (nmax, r, l, m, r_ft): (usize, usize, usize, usize, usize),
        g1: DMatrix<f64>,
        g2: DMatrix<f64>,
    ) -> Self {
        // output equation: [u (feedthrough); x_1..x_nmax] against y
        let idx1: Vec<usize> = (nmax..nmax + r_ft).chain(0..nmax).collect();
        let out = NestedChol::new(
            idx1.len(),
            l,
            |i, j| g1[(idx1[i], idx1[j])],
            |i, o| g1[(idx1[i], nmax + r_ft + o)],
        );
        // state equation: mu (x) [u; y], then mu (x) x_a for a = 1..nmax
        let dv = nmax + r + l;
        let idx2: Vec<usize> = (0..m)
            .flat_map(|i| (0..r + l).map(move |j| i * dv + nmax + j))
            .chain((0..nmax).flat_map(|a| (0..m).map(move |i| i * dv + a)))
            .collect();
        let state = NestedChol::new(
            idx2.len(),
            nmax,
            |i, j| g2[(idx2[i], idx2[j])],
            |i, t| g2[(idx2[i], m * dv + t)],
        );
        OrderSweep {
            nmax,
            r,
            l,
            m,
            r_ft,
            g1,
            g2,
            out,
            state,
        }
    }

    /// The two Grams of `states` (all candidate rows; column k is x_{k+p} of window k,
    /// windows 0..=N-p, the last one only as a successor), each entry one dot product over
    /// the windows in four lanes ([`crate::kernel_sweep::dot4`]) of a row-major copy of the
    /// regressor rows: G2's 19 x 19 at B2 p = 5 cost about 80 000 instructions per path
    /// point through the core's checked, tiled batch update ([`OrderSweep::with_core_grams`],
    /// the same sums in another order: the Grams agree to rounding). With mu_0 = 1 on every
    /// window (the affine scheduling of every record) G1 is read from G2's first block.
    pub fn new(
        dims: &PbsidDims,
        slab: &Slab<'_, f64>,
        states: &DMatrix<f64>,
        feedthrough: bool,
    ) -> Result<Self, FitError> {
        let rows: Vec<f64> = states.transpose().as_slice().to_vec();
        Self::from_rows(dims, slab, &rows, states.nrows(), feedthrough)
    }

    /// [`OrderSweep::new`] with the states row-major (`nmax` rows of N - p + 1 values).
    pub fn from_rows(
        dims: &PbsidDims,
        slab: &Slab<'_, f64>,
        states: &[f64],
        nmax: usize,
        feedthrough: bool,
    ) -> Result<Self, FitError> {
        let (p, r, l, m) = (dims.p, dims.r, dims.l, dims.m());
        let ns = states.len() / nmax.max(1);
        let nb = ns - 1;
        let r_ft = if feedthrough { r } else { 0 };
        let dv = nmax + r + l;
        let d2 = m * dv + nmax;
        // row-major rows over the windows: [mu (x) [x; u; y]; x_{k+1}]
        let mut rows = vec![0.0; d2 * nb];
        let mut mu = vec![0.0; m * nb];
        let mut unit = true;
        for k in 0..nb {
            let (u, y, muk) = (slab.u(k + p), slab.y(k + p), slab.mu(k + p));
            unit &= muk[0] == 1.0;
            for i in 0..m {
                mu[i * nb + k] = muk[i];
                for a in 0..r {
                    rows[(i * dv + nmax + a) * nb + k] = muk[i] * u[a];
                }
                for a in 0..l {
                    rows[(i * dv + nmax + r + a) * nb + k] = muk[i] * y[a];
                }
            }
        }
        for a in 0..nmax {
            let xa = &states[a * ns..(a + 1) * ns];
            for i in 0..m {
                let dst = &mut rows[(i * dv + a) * nb..(i * dv + a + 1) * nb];
                for ((d, x), w) in dst.iter_mut().zip(xa).zip(&mu[i * nb..(i + 1) * nb]) {
                    *d = w * x;
                }
            }
            rows[(m * dv + a) * nb..(m * dv + a + 1) * nb].copy_from_slice(&xa[1..]);
        }
        let g2 = DMatrix::from_vec(d2, d2, crate::kernel_sweep::row_gram(&rows, d2, nb));
        // a non-finite row, or products that overflow, leave a non-finite entry (the
        // core's batch update refuses both)
        if let Some(index) = g2.iter().position(|v| !v.is_finite()) {
            return Err(lpvid::Error::NonFinite {
                field: lpvid::Field::Regressor,
                index,
            }
            .into());
        }
        // G1 of [x; u (feedthrough); y]: the raw rows, block 0 of the rows above when mu_0 = 1
        let idx: Vec<usize> = (0..nmax)
            .chain(nmax..nmax + r_ft)
            .chain(nmax + r..nmax + r + l)
            .collect();
        let g1 = if unit {
            DMatrix::from_fn(idx.len(), idx.len(), |a, b| g2[(idx[a], idx[b])])
        } else {
            let raw: Vec<Vec<f64>> = idx
                .iter()
                .map(|&a| {
                    (0..nb)
                        .map(|k| {
                            let (u, y) = (slab.u(k + p), slab.y(k + p));
                            if a < nmax {
                                states[a * ns + k]
                            } else if a < nmax + r {
                                u[a - nmax]
                            } else {
                                y[a - nmax - r]
                            }
                        })
                        .collect()
                })
                .collect();
            let mut g = DMatrix::zeros(idx.len(), idx.len());
            for b in 0..idx.len() {
                for a in 0..=b {
                    let v = crate::kernel_sweep::dot4(&raw[a], &raw[b]);
                    g[(a, b)] = v;
                    g[(b, a)] = v;
                }
            }
            g
        };
        Ok(OrderSweep::from_grams((nmax, r, l, m, r_ft), g1, g2))
    }

    /// [`OrderSweep::new`] with both Grams accumulated by the core's `Gram::update_batch`
    /// ([`REALIZE_BATCH`] rows per batch; the sweep before, kept for `benches/bpdn.rs`,
    /// group `order_sweep_grams`, and the test that the two agree).
    pub fn with_core_grams(
        dims: &PbsidDims,
        slab: &Slab<'_, f64>,
        states: &DMatrix<f64>,
        feedthrough: bool,
    ) -> Result<Self, FitError> {
        let (p, r, l, m) = (dims.p, dims.r, dims.l, dims.m());
        let nmax = states.nrows();
        let nb = states.ncols() - 1;
        let r_ft = if feedthrough { r } else { 0 };
        let g1 = output_gram(p, slab, states, r_ft)?;
        let dv = nmax + r + l;
        let mut v = vec![0.0; dv];
        let g2 = batched_gram(m * dv + nmax, nb, |k, row| {
            v[..nmax].copy_from_slice(states.column(k).as_slice());
            v[nmax..nmax + r].copy_from_slice(slab.u(k + p));
            v[nmax + r..].copy_from_slice(slab.y(k + p));
            state_row(row, slab.mu(k + p), &v, states.column(k + 1).as_slice());
        })?;
        let full = |g: &Gram<f64, Vec<f64>>| {
            let d = g.dim();
            DMatrix::from_fn(d, d, |i, j| g.get(i, j))
        };
        Ok(OrderSweep::from_grams(
            (nmax, r, l, m, r_ft),
            full(&g1),
            full(&g2),
        ))
    }

    /// The model of order `n` (1 <= n <= nmax).
    pub fn realize(&self, n: usize) -> Result<LpvSs, FitError> {
        let (abk, c, d) = match self.solve_nested(n) {
            Some(v) => v,
            None => self.solve_order(n)?,
        };
        Ok(LpvSs::from_abk(&abk, vec![c], vec![d]))
    }

    /// The model of order `n` as [`OrderSweep::realize`] gives it, packed for the free-run
    /// scorer without the intermediate `LpvSs` (the same numbers: BPDN-SV scores every
    /// order of every path point with it).
    pub fn realize_scorer(&self, n: usize) -> Result<FreeRun, FitError> {
        let (abk, c, d) = match self.solve_nested(n) {
            Some(v) => v,
            None => self.solve_order(n)?,
        };
        Ok(FreeRun::from_abk(&abk, &c, &d))
    }

    /// [`OrderSweep::realize_scorer`] with the normal equations of order `n` formed in the
    /// innovation basis [x; u; e] and solved on their own (the sweep before the nested
    /// factors; kept for `benches/bpdn.rs`, group `realize_for_scoring`).
    pub fn realize_scorer_per_order(&self, n: usize) -> Result<FreeRun, FitError> {
        let (abk, c, d) = self.solve_order(n)?;
        Ok(FreeRun::from_abk(&abk, &c, &d))
    }

    /// Order `n` from the nested factors, when both leading blocks are proven full rank
    /// (then the least-squares solution is unique and equals [`OrderSweep::solve_order`]'s
    /// up to rounding); `None` otherwise. The state equation is solved in the regressors
    /// mu (x) [x; u; y], which span what mu (x) [x; u; e] spans (e = y - C x - D u), and
    /// mapped back: x+ = sum_i mu_i ((A_i - K_i C) x + (B_i - K_i D) u + K_i y), so
    /// A_i = A'_i + K_i C and B_i = B'_i + K_i D.
    fn solve_nested(&self, n: usize) -> Option<Solved> {
        let (r, l, m, r_ft) = (self.r, self.l, self.m, self.r_ft);
        assert!(n <= self.nmax, "order beyond the states");
        let k1 = r_ft + n;
        let k2 = m * (r + l + n);
        if !self.out.proven(k1) || !self.state.proven(k2) {
            return None;
        }
        let mut x = vec![0.0; k1.max(k2)];
        let mut c = DMatrix::zeros(l, n);
        let mut d = DMatrix::zeros(l, r);
        for o in 0..l {
            self.out.solve(k1, o, &mut x);
            for j in 0..r_ft {
                d[(o, j)] = x[j];
            }
            for a in 0..n {
                c[(o, a)] = x[r_ft + a];
            }
        }
        let wb = n + r + l;
        let mut abk = DMatrix::zeros(n, m * wb);
        for t in 0..n {
            self.state.solve(k2, t, &mut x);
            for i in 0..m {
                let col = i * wb;
                // K_i, B'_i from mu_i (x) [u; y], A'_i from mu_i (x) x_a
                let uy = &x[i * (r + l)..(i + 1) * (r + l)];
                for o in 0..l {
                    abk[(t, col + n + r + o)] = uy[r + o];
                }
                for a in 0..n {
                    let mut v = x[m * (r + l) + a * m + i];
                    for o in 0..l {
                        v += uy[r + o] * c[(o, a)];
                    }
                    abk[(t, col + a)] = v;
                }
                for j in 0..r {
                    let mut v = uy[j];
                    for o in 0..l {
                        v += uy[r + o] * d[(o, j)];
                    }
                    abk[(t, col + n + j)] = v;
                }
            }
        }
        Some((abk, c, d))
    }

    /// [A^(1) B^(1) K^(1) | ...], C and D of order `n`: the two normal equations formed from
    /// the Grams and solved. The sums are those of the combinations below, in the same order
    /// (read from the Grams' column-major storage).
    fn solve_order(&self, n: usize) -> Result<Solved, FitError> {
        let (nmax, r, l, m, r_ft) = (self.nmax, self.r, self.l, self.m, self.r_ft);
        assert!(n <= nmax, "order beyond the states");
        // output equation: regressors x_1..x_n and u (feedthrough), targets y
        let idx1: Vec<usize> = (0..n).chain(nmax..nmax + r_ft).collect();
        let k1 = idx1.len();
        let s1_ff = DMatrix::from_fn(k1, k1, |a, b| self.g1[(idx1[a], idx1[b])]);
        let s1_fy = DMatrix::from_fn(k1, l, |a, o| self.g1[(idx1[a], nmax + r_ft + o)]);
        let cd = solve_normal(&s1_ff, &s1_fy)?;
        let c = cd.columns(0, n).into_owned();
        let d = if r_ft > 0 {
            cd.columns(n, r).into_owned()
        } else {
            DMatrix::zeros(l, r)
        };
        // xi = [x; u; e] of order n as combinations of v = [x^(nmax); u; y]: entry alpha
        // is the terms start[alpha]..start[alpha + 1] of (index into v, coefficient)
        let dv = nmax + r + l;
        let nxi = n + r + l;
        let mut terms: Vec<(usize, f64)> = Vec::with_capacity(n + r + l * (1 + n + r));
        let mut start = Vec::with_capacity(nxi + 1);
        for a in 0..n {
            start.push(terms.len());
            terms.push((a, 1.0));
        }
        for j in 0..r {
            start.push(terms.len());
            terms.push((nmax + j, 1.0));
        }
        for o in 0..l {
            start.push(terms.len());
            terms.push((nmax + r + o, 1.0));
            terms.extend((0..n).map(|a| (a, -c[(o, a)])));
            terms.extend((0..r).map(|j| (nmax + j, -d[(o, j)])));
        }
        start.push(terms.len());
        let comb = |alpha: usize| &terms[start[alpha]..start[alpha + 1]];
        let g2 = self.g2.as_slice();
        let ld = self.g2.nrows();
        let k2 = m * nxi;
        let mut s2_ff = DMatrix::zeros(k2, k2);
        for bj in 0..k2 {
            let (j, beta) = (bj / nxi, bj % nxi);
            let cb_terms = comb(beta);
            for ai in 0..=bj {
                let (i, alpha) = (ai / nxi, ai % nxi);
                let mut s = 0.0;
                for &(a, ca) in comb(alpha) {
                    let row = i * dv + a;
                    for &(b, cb) in cb_terms {
                        // g2[(row, j dv + b)], column-major
                        s += ca * cb * g2[(j * dv + b) * ld + row];
                    }
                }
                s2_ff[(ai, bj)] = s;
                s2_ff[(bj, ai)] = s;
            }
        }
        let s2_fy = DMatrix::from_fn(k2, n, |ai, t| {
            let (i, alpha) = (ai / nxi, ai % nxi);
            let col = &g2[(m * dv + t) * ld..(m * dv + t + 1) * ld];
            comb(alpha)
                .iter()
                .map(|&(a, ca)| ca * col[i * dv + a])
                .sum()
        });
        let abk = solve_normal(&s2_ff, &s2_fy)?;
        Ok((abk, c, d))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The B2 training record (75 samples, 25 dB) and its sample rows [u, y, 1, p] for a
    /// slab with mu = [1, p].
    fn b2_rows() -> (crate::lpvss::Signals, Vec<f64>) {
        let t = crate::systems::b2(75, 25.0, 5).train;
        let rows = (0..t.len())
            .flat_map(|k| [t.u[(k, 0)], t.y[(k, 0)], 1.0, t.p[(k, 0)]])
            .collect();
        (t, rows)
    }

    /// The scorer's packing straight from the least-squares solution equals the packing of
    /// the realized model, and so does its score to the bit (B2 record, orders 1..=4, with
    /// and without feedthrough).
    #[test]
    fn scorer_packing_equals_the_model_packing() {
        let (t, rows) = b2_rows();
        let slab = Slab::new(&rows, 1, 1, 2).unwrap();
        let p = 4;
        let dims = PbsidDims::new(1, 1, 1, p).unwrap();
        let cols = slab.len() - p + 1;
        let states = DMatrix::from_fn(4, cols, |i, k| {
            (0..p)
                .map(|j| ((i * 5 + j * 2) as f64 * 0.41).cos() * slab.y(k + j)[0])
                .sum::<f64>()
        });
        let record = crate::pbsid::bpdn::ScoredRecord::new(&t, 2);
        for feedthrough in [true, false] {
            let sweep = OrderSweep::new(&dims, &slab, &states, feedthrough).unwrap();
            for n in 1..=4 {
                let model = sweep.realize(n).unwrap();
                let a = FreeRun::new(&model);
                let b = sweep.realize_scorer(n).unwrap();
                let (sa, sb) = (
                    a.error_below(&record, f64::INFINITY),
                    b.error_below(&record, f64::INFINITY),
                );
                assert_eq!(sa.to_bits(), sb.to_bits(), "n = {n}, {feedthrough}");
                assert!(a.same_packing(&b), "n = {n}, {feedthrough}");
            }
        }
    }

    /// The nested factors give every order of the sweep the model of its own normal
    /// equations in the innovation basis (`solve_order`), to 1e-10 relative, and the Grams
    /// by dot products equal the core's batch update to 1e-13 (B2 record, p = 4 states, with
    /// and without feedthrough); a singular order, or a state row of zeros, leaves the orders
    /// that use it to the per-order solve (not proven full rank).
    #[test]
    fn nested_orders_equal_per_order_solves() {
        let (_, rows) = b2_rows();
        let slab = Slab::new(&rows, 1, 1, 2).unwrap();
        let p = 4;
        let dims = PbsidDims::new(1, 1, 1, p).unwrap();
        let cols = slab.len() - p + 1;
        let nmax = 4;
        let states = DMatrix::from_fn(nmax, cols, |i, k| {
            (0..p)
                .map(|j| {
                    ((i * 5 + j * 3) as f64 * 0.29).sin() * slab.y(k + j)[0]
                        + 0.1 * slab.u(k + j)[0]
                })
                .sum::<f64>()
        });
        for feedthrough in [true, false] {
            let sweep = OrderSweep::new(&dims, &slab, &states, feedthrough).unwrap();
            let core = OrderSweep::with_core_grams(&dims, &slab, &states, feedthrough).unwrap();
            for (a, b) in [(&sweep.g1, &core.g1), (&sweep.g2, &core.g2)] {
                assert!((a - b).amax() <= 1e-13 * b.amax(), "{feedthrough}");
            }
            // order 4 of these states is singular (the last pivot of its state equation)
            assert!(sweep.solve_nested(nmax).is_none());
            for n in 1..nmax {
                let (abk, c, d) = sweep.solve_nested(n).expect("full rank");
                let (abk0, c0, d0) = sweep.solve_order(n).unwrap();
                for (g, w) in [(&abk, &abk0), (&c, &c0), (&d, &d0)] {
                    let err = (g - w).amax();
                    assert!(
                        err <= 1e-10 * w.amax().max(1.0),
                        "n = {n}, {feedthrough}: {err}"
                    );
                }
            }
        }
        let mut flat = states.clone();
        flat.row_mut(2).fill(0.0);
        let sweep = OrderSweep::new(&dims, &slab, &flat, true).unwrap();
        assert!(sweep.solve_nested(2).is_some());
        assert!(sweep.solve_nested(3).is_none() && sweep.solve_nested(4).is_none());
        assert!(sweep.realize(3).is_ok());
    }

    /// Every order of an [`OrderSweep`] equals [`realize_from_states`] on the first n rows
    /// of the same states (B2 record, states of a p = 4 regression with random-like
    /// mixing, with and without feedthrough), to 1e-9 relative.
    #[test]
    fn orders_share_one_gram() {
        let (_, rows) = b2_rows();
        let slab = Slab::new(&rows, 1, 1, 2).unwrap();
        let p = 4;
        let dims = PbsidDims::new(1, 1, 1, p).unwrap();
        let cols = slab.len() - p + 1;
        let nmax = 4;
        // states: smooth mixtures of past outputs and inputs (a realistic, full-rank set)
        let states = DMatrix::from_fn(nmax, cols, |i, k| {
            let mut s = 0.0;
            for j in 0..p {
                let w = ((i * 7 + j * 3) as f64 * 0.37).sin();
                s += w * slab.y(k + j)[0] + 0.5 * w * w * slab.u(k + j)[0];
            }
            s
        });
        for feedthrough in [true, false] {
            let sweep = OrderSweep::new(&dims, &slab, &states, feedthrough).unwrap();
            for n in 1..=nmax {
                let want =
                    realize_from_states(&dims, &slab, &states.rows(0, n).into_owned(), feedthrough)
                        .unwrap();
                let got = sweep.realize(n).unwrap();
                let pairs = want
                    .a
                    .iter()
                    .zip(&got.a)
                    .chain(want.b.iter().zip(&got.b))
                    .chain(want.k.iter().zip(&got.k))
                    .chain(want.c.iter().zip(&got.c))
                    .chain(want.d.iter().zip(&got.d));
                for (w, g) in pairs {
                    let err = (w - g).amax();
                    assert!(
                        err <= 1e-9 * w.amax().max(1.0),
                        "n = {n}, feedthrough {feedthrough}: {err}"
                    );
                }
            }
        }
    }
}
