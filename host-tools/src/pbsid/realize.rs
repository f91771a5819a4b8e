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
        row[..n].copy_from_slice(states.column(k).as_slice());
        row[n..n + r_ft].copy_from_slice(&slab.u(k + p)[..r_ft]);
        row[n + r_ft..].copy_from_slice(slab.y(k + p));
    })
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
}

impl OrderSweep {
    /// The two Grams of `states` (all candidate rows; column k is x_{k+p} of window k,
    /// windows 0..=N-p, the last one only as a successor).
    pub fn new(
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
            let mu = slab.mu(k + p);
            for i in 0..m {
                for (dst, x) in row[i * dv..(i + 1) * dv].iter_mut().zip(&v) {
                    *dst = mu[i] * x;
                }
            }
            row[m * dv..].copy_from_slice(states.column(k + 1).as_slice());
        })?;
        let full = |g: &Gram<f64, Vec<f64>>| {
            let d = g.dim();
            DMatrix::from_fn(d, d, |i, j| g.get(i, j))
        };
        Ok(OrderSweep {
            nmax,
            r,
            l,
            m,
            r_ft,
            g1: full(&g1),
            g2: full(&g2),
        })
    }

    /// The model of order `n` (1 <= n <= nmax).
    pub fn realize(&self, n: usize) -> Result<LpvSs, FitError> {
        let (abk, c, d) = self.solve_order(n)?;
        Ok(LpvSs::from_abk(&abk, vec![c], vec![d]))
    }

    /// The model of order `n` as [`OrderSweep::realize`] gives it, packed for the free-run
    /// scorer without the intermediate `LpvSs` (the same numbers: BPDN-SV scores every
    /// order of every path point with it).
    pub fn realize_scorer(&self, n: usize) -> Result<FreeRun, FitError> {
        let (abk, c, d) = self.solve_order(n)?;
        Ok(FreeRun::from_abk(&abk, &c, &d))
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
