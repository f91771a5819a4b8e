//! Forward sensitivities of the state-space free run through the model's own-output
//! feedback: the exact Jacobian d yhat / d theta that the output-error refinement
//! ([`crate::refine`]) descends with, in one run instead of one run per parameter.
//!
//! The free run of [`crate::simulate::free_run_ss_into`] is differentiated sample by sample
//! (the model of DESIGN.md section 5; issue 14's refinement through the feedback):
//!
//! - y_k = sum_i mu_i (C_i x_k + D_i u_k), with the loops that read outputs before k;
//! - x_{k+1} = sum_i mu_i (A_i x_k + B_i u_k), with the loops that read y_k too,
//!
//! where a loop (an input channel or a scheduling function that reads the model's own
//! output) is a product of data and of factors f(y_{k-d}). Its derivative is the chain rule
//! through [`crate::model::Factor::slope`] and the sensitivities of the outputs it reads,
//! which are earlier rows of the Jacobian being built. The state's sensitivity X_k = dx_k /
//! d theta (n x parameters) is carried along: X_{k+1} = A(mu_k) X_k + B(mu_k) dU_k + the
//! loops' d mu_k terms + the entries' own partials. Per sample this costs n^2 products per
//! parameter, vectorised over the parameters, where the forward-difference Jacobian ran the
//! whole feedback machinery once per parameter: 75 % of the unbalanced disk's diagnosis
//! (docs/bench-diagnose.md, thirty-ninth session).

use nalgebra::DMatrix;

use crate::lpvss::{scheduled_into, LpvSs, Signals};
use crate::model::{Feedback, Loop};

/// Where a model's entries sit among the parameters, in the order of the refinement's
/// packing: every entry of each A^(i), B^(i), C^(i) (column-major), the columns `d_cols` of
/// each D^(i), then the initial state. The entries the feedback holds at zero (D columns of
/// channels that read the output at the same sample, `zero_d`; C^(q), D^(q) of such
/// scheduling functions, `zero_q`, when the output equation is scheduled) are parameters
/// whose columns are zero, as the refinement unpacks them to zero.
#[derive(Debug, Clone)]
pub struct Params<'a> {
    /// D's columns among the parameters.
    pub d_cols: &'a [usize],
    /// Input channels whose D columns are held at zero.
    pub zero_d: &'a [usize],
    /// Scheduling basis functions whose C^(q), D^(q) are held at zero.
    pub zero_q: &'a [usize],
}

/// Offsets of the blocks of parameters of a model (see [`Params`]).
struct Offsets {
    n: usize,
    r: usize,
    l: usize,
    b: usize,
    c: usize,
    d: usize,
    dc: usize,
    x0: usize,
    count: usize,
}

impl Offsets {
    fn new(m: &LpvSs, d_cols: usize) -> Self {
        let (n, r, l) = (m.n(), m.r(), m.l());
        let b = m.a.len() * n * n;
        let c = b + m.b.len() * n * r;
        let d = c + m.c.len() * l * n;
        let x0 = d + m.d.len() * d_cols * l;
        Offsets {
            n,
            r,
            l,
            b,
            c,
            d,
            dc: d_cols,
            x0,
            count: x0 + n,
        }
    }
    fn a(&self, i: usize, row: usize, col: usize) -> usize {
        i * self.n * self.n + col * self.n + row
    }
    fn b(&self, i: usize, row: usize, col: usize) -> usize {
        self.b + i * self.n * self.r + col * self.n + row
    }
    fn c(&self, i: usize, row: usize, col: usize) -> usize {
        self.c + i * self.l * self.n + col * self.l + row
    }
    fn d(&self, i: usize, row: usize, col_index: usize) -> usize {
        self.d + (i * self.dc + col_index) * self.l + row
    }
}

/// The number of parameters of `m` with `d_cols` free columns of D (with the initial state).
pub fn parameter_count(m: &LpvSs, d_cols: usize) -> usize {
    Offsets::new(m, d_cols).count
}

/// y += a x over the parameters (the one inner loop of the sensitivities).
#[inline]
fn axpy(y: &mut [f64], a: f64, x: &[f64]) {
    if a != 0.0 {
        for (y, x) in y.iter_mut().zip(x) {
            *y += a * x;
        }
    }
}

/// `out` = M X for X (`k` rows of `np` values, row-major, as `out`) and M (`rows` x `k`):
/// faer's product of the transposes, X^T M^T, whose column-major layouts are the row-major
/// ones of X and `out` (SIMD chosen at run time; the crate is built for plain x86-64).
fn times(out: &mut [f64], x: &[f64], m: &DMatrix<f64>, np: usize) {
    let (rows, k) = m.shape();
    if k == 0 || np == 0 {
        out.iter_mut().for_each(|v| *v = 0.0);
        return;
    }
    faer::linalg::matmul::matmul(
        faer::MatMut::from_column_major_slice_mut(out, np, rows),
        faer::Accum::Replace,
        faer::MatRef::from_column_major_slice(x, np, k),
        faer::MatRef::from_column_major_slice(m.as_slice(), rows, k).transpose(),
        1.0,
        faer::Par::Seq,
    );
}

/// The derivative of `lp`'s value at sample k with respect to the parameters into `dv`
/// (zeroed first): the factors that read outputs `start <= j < avail` (the rows of `jac`,
/// `np` values per output row) by the product rule. Rows before `start` are measured (no
/// sensitivity), rows from `avail` on are not known yet (the loop reads 0 there). A factor's
/// slope that is not finite (sqrt|y| at y = 0) contributes nothing.
#[allow(clippy::too_many_arguments)]
fn loop_slope(
    lp: &Loop,
    k: usize,
    y: &DMatrix<f64>,
    avail: usize,
    start: usize,
    jac: &[f64],
    np: usize,
    dv: &mut [f64],
) {
    dv.iter_mut().for_each(|v| *v = 0.0);
    let l = y.ncols();
    let read = |d: usize| match k.checked_sub(d) {
        Some(j) if j < avail => Some(j),
        _ => None,
    };
    for (o, own) in lp.own.iter().enumerate() {
        let Some(j) = read(own.factor.delay).filter(|&j| j >= start) else {
            continue;
        };
        let mut coef = lp.data[k] * own.factor.slope(y[(j, own.output)]);
        for (o2, other) in lp.own.iter().enumerate() {
            if o2 != o {
                let v = read(other.factor.delay).map_or(0.0, |j2| y[(j2, other.output)]);
                coef *= other.factor.apply(v);
            }
        }
        if coef.is_finite() {
            let row = ((j - start) * l + own.output) * np;
            axpy(dv, coef, &jac[row..row + np]);
        }
    }
}

/// The free run of `m` over the samples `range` = `start..upto` of `sig` from the state
/// `x0`, through the feedback `fb`, and its sensitivities to the parameters of [`Params`]:
/// the outputs are written into rows `start..upto` of `y` (whose rows before `start` hold the outputs the
/// feedback reads there: measured, without sensitivity), and d yhat / d theta is returned
/// row-major, one row of [`parameter_count`] values per output and sample (sample-major, as
/// the refinement stacks its residual). The outputs are those of
/// [`crate::simulate::free_run_ss_into`], the same sums in the same order. None when the run
/// diverges (a non-finite output or a state beyond 1e150, as there).
pub fn free_run_sensitivity(
    m: &LpvSs,
    sig: &Signals,
    fb: &Feedback,
    x0: &[f64],
    range: std::ops::Range<usize>,
    y: &mut DMatrix<f64>,
    params: &Params<'_>,
) -> Option<Vec<f64>> {
    let (start, upto) = (range.start, range.end.min(sig.len()));
    let off = Offsets::new(m, params.d_cols.len());
    let (n, r, l, mm) = (off.n, off.r, off.l, m.m());
    let np = off.count;
    let s = sig.p.ncols().min(mm - 1);
    let (mc, md) = (m.c.len(), m.d.len());
    let step = m.stepper();
    // the loops that enter the model: input channels, and scheduling functions below s
    let in_loops: Vec<&(usize, Loop)> = fb.inputs.iter().filter(|(i, _)| *i < r).collect();
    let sc_loops: Vec<&(usize, Loop)> = fb.scheduling.iter().filter(|(q, _)| *q < s).collect();
    let held_q = |i: usize, count: usize| count > 1 && params.zero_q.contains(&i);
    let rows = upto.saturating_sub(start);
    let mut jac = vec![0.0; rows * l * np];
    // X = dx/dtheta, n rows of np; the initial state's own columns are the identity
    let mut sx = vec![0.0; n * np];
    for a in 0..n {
        sx[a * np + off.x0 + a] = 1.0;
    }
    let mut sxn = vec![0.0; n * np];
    let mut du = vec![0.0; in_loops.len() * np];
    let mut dmu = vec![0.0; sc_loops.len() * np];
    let mut x = x0.to_vec();
    let mut xn = vec![0.0; n];
    let mut uk = vec![0.0; r];
    let mut yk = vec![0.0; l];
    let mut mu = vec![1.0; mm];
    // A(mu), B(mu), C(mu), D(mu) of the sample
    let mut amu = DMatrix::zeros(n, n);
    let mut bmu = DMatrix::zeros(n, r);
    let mut cmu = DMatrix::zeros(l, n);
    let mut dmat = DMatrix::zeros(l, r);
    // the loops' derivatives at sample k with the outputs before `avail` known
    let loop_slopes =
        |k: usize, avail: usize, y: &DMatrix<f64>, jac: &[f64], du: &mut [f64], dmu: &mut [f64]| {
            for ((_, lp), dv) in in_loops.iter().zip(du.chunks_exact_mut(np)) {
                loop_slope(lp, k, y, avail, start, jac, np, dv);
            }
            for ((_, lp), dv) in sc_loops.iter().zip(dmu.chunks_exact_mut(np)) {
                loop_slope(lp, k, y, avail, start, jac, np, dv);
            }
        };
    for k in start..upto {
        for q in 0..s {
            mu[q + 1] = sig.p[(k, q)];
        }
        for (j, v) in uk.iter_mut().enumerate() {
            *v = sig.u[(k, j)];
        }
        // the output equation, with the loops that read outputs before k
        if !fb.is_empty() {
            fb.fill_sample(k, y, k, &mut uk, &mut mu[1..=s]);
            loop_slopes(k, k, y, &jac, &mut du, &mut dmu);
        }
        step.output_into(&mu, &x, &uk, &mut yk);
        let finite = yk.iter().all(|v| v.is_finite());
        for (j, v) in yk.iter().enumerate() {
            y[(k, j)] = *v;
        }
        let w_c = |i: usize| if mc > 1 { mu[i] } else { 1.0 };
        let w_d = |i: usize| if md > 1 { mu[i] } else { 1.0 };
        scheduled_into(&m.c, &mu, &mut cmu);
        scheduled_into(&m.d, &mu, &mut dmat);
        let row0 = (k - start) * l * np;
        // Y_k = C(mu) X_k
        times(&mut jac[row0..row0 + l * np], &sx, &cmu, np);
        for a in 0..l {
            let yr = &mut jac[row0 + a * np..row0 + (a + 1) * np];
            for ((i, _), dv) in in_loops.iter().zip(du.chunks_exact(np)) {
                axpy(yr, dmat[(a, *i)], dv);
            }
            for ((q, _), dv) in sc_loops.iter().zip(dmu.chunks_exact(np)) {
                // d y / d mu_{q+1} = C^(q+1) x + D^(q+1) u where the output equation is scheduled
                let mut g = 0.0;
                if mc > 1 {
                    g += (0..n).map(|b| m.c[q + 1][(a, b)] * x[b]).sum::<f64>();
                }
                if md > 1 {
                    g += (0..r).map(|j| m.d[q + 1][(a, j)] * uk[j]).sum::<f64>();
                }
                axpy(yr, g, dv);
            }
            // the entries' own partials
            for i in 0..mc {
                if held_q(i, mc) {
                    continue;
                }
                for b in 0..n {
                    yr[off.c(i, a, b)] += w_c(i) * x[b];
                }
            }
            for i in 0..md {
                if held_q(i, md) {
                    continue;
                }
                for (jj, &j) in params.d_cols.iter().enumerate() {
                    if !params.zero_d.contains(&j) {
                        yr[off.d(i, a, jj)] += w_d(i) * uk[j];
                    }
                }
            }
        }
        // ... then the state equation with y_k known
        if !fb.is_empty() {
            fb.fill_sample(k, y, k + 1, &mut uk, &mut mu[1..=s]);
            loop_slopes(k, k + 1, y, &jac, &mut du, &mut dmu);
        }
        step.state_into(&mu, &x, &uk, None, &mut xn);
        scheduled_into(&m.a, &mu, &mut amu);
        scheduled_into(&m.b, &mu, &mut bmu);
        // X_{k+1} = A(mu) X_k + ...
        times(&mut sxn, &sx, &amu, np);
        for a in 0..n {
            let xr = &mut sxn[a * np..(a + 1) * np];
            for ((i, _), dv) in in_loops.iter().zip(du.chunks_exact(np)) {
                axpy(xr, bmu[(a, *i)], dv);
            }
            for ((q, _), dv) in sc_loops.iter().zip(dmu.chunks_exact(np)) {
                let g = (0..n).map(|b| m.a[q + 1][(a, b)] * x[b]).sum::<f64>()
                    + (0..r).map(|j| m.b[q + 1][(a, j)] * uk[j]).sum::<f64>();
                axpy(xr, g, dv);
            }
            for (i, w) in mu.iter().enumerate() {
                for b in 0..n {
                    xr[off.a(i, a, b)] += w * x[b];
                }
                for j in 0..r {
                    xr[off.b(i, a, j)] += w * uk[j];
                }
            }
        }
        std::mem::swap(&mut sx, &mut sxn);
        std::mem::swap(&mut x, &mut xn);
        if !finite || x.iter().any(|v| !v.is_finite() || v.abs() > 1e150) {
            return None;
        }
    }
    Some(jac)
}
