//! The LPV state-space model in numbers (DESIGN.md section 5, type `lpv-ss`), its free-run
//! simulation and its one-step-ahead predictor (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, eq. (1)-(2) in innovation form, the
//! predictor of section 2; sparse paper, `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md`,
//! eq. (1)-(2)):
//! x_{k+1} = sum_i mu_k^(i) (A^(i) x_k + B^(i) u_k + K^(i) e_k),  y_k = C(mu_k) x_k + D(mu_k) u_k + e_k.

use nalgebra::{DMatrix, DVector};

/// Matrices of an [`LpvSs`] whose shapes do not fit together (n from A, r from B, l from C,
/// m from the number of A's).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ShapeError {
    /// A^(i) are not m matrices of n x n.
    #[error("A must be {m} matrices of {n}x{n}")]
    A {
        /// Local models.
        m: usize,
        /// States.
        n: usize,
    },
    /// B^(i) are not m matrices of n x r.
    #[error("B must be {m} matrices of {n}x{r}")]
    B {
        /// Local models.
        m: usize,
        /// States.
        n: usize,
        /// Inputs.
        r: usize,
    },
    /// K^(i) are not m matrices of n x l.
    #[error("K must be {m} matrices of {n}x{l}")]
    K {
        /// Local models.
        m: usize,
        /// States.
        n: usize,
        /// Outputs.
        l: usize,
    },
    /// C is not one or m matrices of l x n.
    #[error("C must be one or {m} matrices of {l}x{n}")]
    C {
        /// Local models.
        m: usize,
        /// Outputs.
        l: usize,
        /// States.
        n: usize,
    },
    /// D is not one or m matrices of l x r.
    #[error("D must be one or {m} matrices of {l}x{r}")]
    D {
        /// Local models.
        m: usize,
        /// Outputs.
        l: usize,
        /// Inputs.
        r: usize,
    },
}

/// Signals as the identification sees them: one row per sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Signals {
    /// Inputs, N x r.
    pub u: DMatrix<f64>,
    /// Outputs, N x l.
    pub y: DMatrix<f64>,
    /// Scheduling signals p (without the affine 1), N x s.
    pub p: DMatrix<f64>,
}

impl Signals {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.y.nrows()
    }
    /// True when there is no sample.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// mu_k = [1, p_k] as a vector.
    pub fn mu(&self, k: usize) -> DVector<f64> {
        let s = self.p.ncols();
        DVector::from_fn(s + 1, |i, _| if i == 0 { 1.0 } else { self.p[(k, i - 1)] })
    }
    /// Whether input column `j` is constant over the record (to 1e-12 relative): a
    /// constant channel, or an input that never moved (vacuously true for no sample).
    pub fn constant_input(&self, j: usize) -> bool {
        let c = self.u.column(j);
        c.iter()
            .all(|v| (v - c[0]).abs() <= 1e-12 * c[0].abs().max(1e-300))
    }
    /// Samples `range` only.
    pub fn slice(&self, start: usize, len: usize) -> Signals {
        Signals {
            u: self.u.rows(start, len).into_owned(),
            y: self.y.rows(start, len).into_owned(),
            p: self.p.rows(start, len).into_owned(),
        }
    }
}

/// An LPV state-space model with affine scheduling dependence (m = s + 1 local models).
/// `c` and `d` hold one matrix (parameter-independent output equation) or m matrices.
#[derive(Debug, Clone, PartialEq)]
pub struct LpvSs {
    /// A^(1..m), n x n each.
    pub a: Vec<DMatrix<f64>>,
    /// B^(1..m), n x r each.
    pub b: Vec<DMatrix<f64>>,
    /// K^(1..m), n x l each.
    pub k: Vec<DMatrix<f64>>,
    /// C or C^(1..m), l x n each.
    pub c: Vec<DMatrix<f64>>,
    /// D or D^(1..m), l x r each.
    pub d: Vec<DMatrix<f64>>,
}

/// Sum_i mu_i M_i (a single matrix is taken as parameter-independent).
pub fn scheduled(mats: &[DMatrix<f64>], mu: &DVector<f64>) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(mats[0].nrows(), mats[0].ncols());
    scheduled_into(mats, mu.as_slice(), &mut out);
    out
}

/// [`scheduled`] into `out` (the shape of each M_i), without allocating: the loops that
/// form it at every sample ([`crate::sensitivity`]).
pub fn scheduled_into(mats: &[DMatrix<f64>], mu: &[f64], out: &mut DMatrix<f64>) {
    if mats.len() == 1 {
        out.copy_from(&mats[0]);
        return;
    }
    out.fill(0.0);
    for (m, w) in mats.iter().zip(mu) {
        for (o, v) in out.iter_mut().zip(m.iter()) {
            *o += v * w;
        }
    }
}

impl LpvSs {
    /// The model from the state equation's stacked parameters
    /// `theta = [A^(1) B^(1) K^(1) | ... | A^(m) B^(m) K^(m)]` (kernel paper, eq. (1): n rows,
    /// m blocks of n + r + l columns) and the output matrices `c`, `d` (one, or one per
    /// scheduling function). The one place where a least-squares solution becomes A, B, K.
    pub fn from_abk(theta: &DMatrix<f64>, c: Vec<DMatrix<f64>>, d: Vec<DMatrix<f64>>) -> Self {
        let (n, l, r) = (theta.nrows(), c[0].nrows(), d[0].ncols());
        let w = n + r + l;
        let m = theta.ncols() / w;
        let block = |i: usize, o: usize, cols: usize| theta.columns(i * w + o, cols).into_owned();
        LpvSs {
            a: (0..m).map(|i| block(i, 0, n)).collect(),
            b: (0..m).map(|i| block(i, n, r)).collect(),
            k: (0..m).map(|i| block(i, n + r, l)).collect(),
            c,
            d,
        }
    }

    /// State dimension n.
    pub fn n(&self) -> usize {
        self.a[0].nrows()
    }
    /// Number of inputs r.
    pub fn r(&self) -> usize {
        self.b[0].ncols()
    }
    /// Number of outputs l.
    pub fn l(&self) -> usize {
        self.c[0].nrows()
    }
    /// Number of local models m.
    pub fn m(&self) -> usize {
        self.a.len()
    }

    /// Check that the matrix shapes agree with each other.
    pub fn validate(&self) -> Result<(), ShapeError> {
        let (n, r, l, m) = (self.n(), self.r(), self.l(), self.m());
        let ok = |v: &[DMatrix<f64>], rows, cols, counts: &[usize]| {
            counts.contains(&v.len()) && v.iter().all(|x| x.nrows() == rows && x.ncols() == cols)
        };
        if !ok(&self.a, n, n, &[m]) {
            return Err(ShapeError::A { m, n });
        }
        if !ok(&self.b, n, r, &[m]) {
            return Err(ShapeError::B { m, n, r });
        }
        if !ok(&self.k, n, l, &[m]) {
            return Err(ShapeError::K { m, n, l });
        }
        if !ok(&self.c, l, n, &[1, m]) {
            return Err(ShapeError::C { m, l, n });
        }
        if !ok(&self.d, l, r, &[1, m]) {
            return Err(ShapeError::D { m, l, r });
        }
        Ok(())
    }

    /// Free-run simulation from x0 = 0 driven by the inputs and scheduling of `sig` (its
    /// outputs are ignored), with optional innovation `e` (N x l) added. Returns N x l.
    pub fn simulate(&self, sig: &Signals, e: Option<&DMatrix<f64>>) -> DMatrix<f64> {
        self.run(sig, e, false)
    }

    /// One-step-ahead predictor: the innovation is replaced by y_k - yhat_k using the
    /// measured outputs of `sig`. Returns N x l predictions.
    pub fn predict(&self, sig: &Signals) -> DMatrix<f64> {
        self.run(sig, None, true)
    }

    /// Free run (`predictor` false) or one-step predictor from the initial state `x0`.
    pub fn run_from(&self, sig: &Signals, x0: &DVector<f64>, predictor: bool) -> DMatrix<f64> {
        self.run_x0(sig, None, predictor, x0.clone())
    }

    fn run(&self, sig: &Signals, e: Option<&DMatrix<f64>>, predictor: bool) -> DMatrix<f64> {
        self.run_x0(sig, e, predictor, DVector::zeros(self.n()))
    }

    fn run_x0(
        &self,
        sig: &Signals,
        e: Option<&DMatrix<f64>>,
        predictor: bool,
        x0: DVector<f64>,
    ) -> DMatrix<f64> {
        let n_samples = sig.len();
        let (n, r, l, m) = (self.n(), self.r(), self.l(), self.m());
        let s = sig.p.ncols().min(m - 1);
        let mut out = DMatrix::<f64>::zeros(n_samples, l);
        // the sample loop allocates nothing: these are its whole state
        let mut x: Vec<f64> = x0.iter().copied().collect();
        let mut xn = vec![0.0; n];
        let (mut mu, mut uk) = (vec![0.0; m], vec![0.0; r]);
        let (mut yhat, mut ek) = (vec![0.0; l], vec![0.0; l]);
        mu[0] = 1.0;
        let step = self.stepper();
        for k in 0..n_samples {
            for q in 0..s {
                mu[q + 1] = sig.p[(k, q)];
            }
            for (j, v) in uk.iter_mut().enumerate() {
                *v = sig.u[(k, j)];
            }
            step.output_into(&mu, &x, &uk, &mut yhat);
            for j in 0..l {
                ek[j] = if predictor {
                    sig.y[(k, j)] - yhat[j]
                } else {
                    e.map_or(0.0, |e| e[(k, j)])
                };
                out[(k, j)] = if predictor { yhat[j] } else { yhat[j] + ek[j] };
            }
            let innovation = (predictor || e.is_some()).then_some(&ek[..]);
            step.state_into(&mu, &x, &uk, innovation, &mut xn);
            std::mem::swap(&mut x, &mut xn);
            if x.iter().any(|v| !v.is_finite() || v.abs() > 1e150) {
                // diverged: the rest of the output is meaningless; mark it so metrics give 0
                for kk in k + 1..n_samples {
                    for j in 0..l {
                        out[(kk, j)] = f64::NAN;
                    }
                }
                break;
            }
        }
        out
    }

    /// The model laid out for a sample loop ([`Stepper`]): build it once per run.
    pub fn stepper(&self) -> Stepper {
        let (n, r, l) = (self.n(), self.r(), self.l());
        let width = n + r + l;
        let mut state = Vec::with_capacity(self.m() * n * width);
        for ((a, b), k) in self.a.iter().zip(&self.b).zip(&self.k) {
            for row in 0..n {
                state.extend(a.row(row).iter());
                state.extend(b.row(row).iter());
                state.extend(k.row(row).iter());
            }
        }
        let rows = |mats: &[DMatrix<f64>]| -> Vec<f64> {
            let mut out = Vec::with_capacity(mats.iter().map(|m| m.len()).sum());
            for m in mats {
                for j in 0..m.nrows() {
                    out.extend(m.row(j).iter());
                }
            }
            out
        };
        Stepper {
            n,
            r,
            l,
            state,
            c: rows(&self.c),
            c_count: self.c.len(),
            d: rows(&self.d),
            d_count: self.d.len(),
        }
    }

    /// Frozen-scheduling matrix A(mu) = sum_i mu_i A^(i).
    pub fn a_at(&self, mu: &DVector<f64>) -> DMatrix<f64> {
        scheduled(&self.a, mu)
    }
}

/// An [`LpvSs`] laid out for the sample loops: every row of [A^(i) B^(i) K^(i)] and of
/// C^(i), D^(i) one contiguous slice, so each of a sample's sums is a dot product along a
/// slice (nalgebra stores columns: a row is strided and every entry bounds-checked). Every
/// simulation's sample loop ([`LpvSs::run_from`], `simulate::free_run_ss_into`, the streamed
/// score) is made of [`Stepper::output_into`] and [`Stepper::state_into`], which allocate
/// nothing; `benches/simulate.rs` measures them. (Adding the columns into the n sums side
/// by side, the same sums in the same order, measured slower at n = 6 there.)
#[derive(Debug, Clone, PartialEq)]
pub struct Stepper {
    n: usize,
    r: usize,
    l: usize,
    /// Per local model, n rows of [A^(i) B^(i) K^(i)] (n + r + l values each).
    state: Vec<f64>,
    /// Per C^(i), l rows of n values.
    c: Vec<f64>,
    /// Matrices in `c` (1: parameter-independent).
    c_count: usize,
    /// Per D^(i), l rows of r values.
    d: Vec<f64>,
    /// Matrices in `d` (1: parameter-independent).
    d_count: usize,
}

impl Stepper {
    /// The output equation y = C(mu) x + D(mu) u into `y` (one C or D: parameter-independent).
    pub fn output_into(&self, mu: &[f64], x: &[f64], u: &[f64], y: &mut [f64]) {
        let (n, r, l) = (self.n, self.r, self.l);
        for (j, yj) in y.iter_mut().enumerate() {
            let mut acc = 0.0;
            add_scheduled_row(&mut acc, &self.c, self.c_count, l, n, mu, j, x);
            add_scheduled_row(&mut acc, &self.d, self.d_count, l, r, mu, j, u);
            *yj = acc;
        }
    }

    /// The state equation x+ = sum_i mu_i (A_i x + B_i u + K_i e) into `xn` (`e` None: no
    /// innovation term).
    pub fn state_into(&self, mu: &[f64], x: &[f64], u: &[f64], e: Option<&[f64]>, xn: &mut [f64]) {
        let (n, r) = (self.n, self.r);
        let width = n + r + self.l;
        xn.iter_mut().for_each(|v| *v = 0.0);
        if n == 0 {
            return;
        }
        for (&w, block) in mu.iter().zip(self.state.chunks_exact(n * width)) {
            if w == 0.0 {
                continue;
            }
            for (row, v) in block.chunks_exact(width).zip(xn.iter_mut()) {
                let (a, rest) = row.split_at(n);
                let (b, k) = rest.split_at(r);
                let mut acc = 0.0;
                for (a, xv) in a.iter().zip(x) {
                    acc += a * xv;
                }
                for (b, uv) in b.iter().zip(u) {
                    acc += b * uv;
                }
                if let Some(e) = e {
                    for (k, ev) in k.iter().zip(e) {
                        acc += k * ev;
                    }
                }
                *v += w * acc;
            }
        }
    }
}

/// acc += sum_i mu_i (M_i v)_j, in the order of i (`count` matrices of `rows` rows of `cols`
/// values, one after the other in `mats`; a single matrix: parameter-independent, weight 1):
/// the output equation's one term ([`Stepper::output_into`]).
#[allow(clippy::too_many_arguments)]
fn add_scheduled_row(
    acc: &mut f64,
    mats: &[f64],
    count: usize,
    rows: usize,
    cols: usize,
    mu: &[f64],
    j: usize,
    v: &[f64],
) {
    if cols == 0 {
        return;
    }
    let scheduled = count > 1;
    for (i, m) in mats.chunks_exact(rows * cols).take(count).enumerate() {
        let w = if scheduled { mu[i] } else { 1.0 };
        if w != 0.0 {
            *acc += w * m[j * cols..(j + 1) * cols]
                .iter()
                .zip(v)
                .map(|(m, va)| m * va)
                .sum::<f64>();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model of two local models with two states, three inputs, two outputs, K and a
    /// scheduled C and D, entries from a fixed sequence.
    fn scheduled_model() -> LpvSs {
        let mut v = 0.37f64;
        let mut next = move || {
            v = (v * 9.1 + 0.13).fract();
            v - 0.5
        };
        let mut mats = |rows: usize, cols: usize| -> Vec<DMatrix<f64>> {
            (0..2)
                .map(|_| DMatrix::from_fn(rows, cols, |_, _| next()))
                .collect()
        };
        LpvSs {
            a: mats(2, 2),
            b: mats(2, 3),
            k: mats(2, 2),
            c: mats(2, 2),
            d: mats(2, 3),
        }
    }

    /// The stepper's two equations are the model's: A(mu) x + B(mu) u + K(mu) e and
    /// C(mu) x + D(mu) u by nalgebra's products, with and without the innovation term.
    #[test]
    fn the_stepper_computes_the_model_equations() {
        let m = scheduled_model();
        let step = m.stepper();
        let (mu, x, u, e) = ([1.0, -0.7], [0.3, -1.1], [0.5, 2.0, -0.25], [0.1, -0.4]);
        let mu_v = DVector::from_column_slice(&mu);
        let (xv, uv, ev) = (
            DVector::from_column_slice(&x),
            DVector::from_column_slice(&u),
            DVector::from_column_slice(&e),
        );
        let scheduled_k = scheduled(&m.k, &mu_v);
        let without = m.a_at(&mu_v) * &xv + scheduled(&m.b, &mu_v) * &uv;
        let with = &without + scheduled_k * &ev;
        let y = scheduled(&m.c, &mu_v) * &xv + scheduled(&m.d, &mu_v) * &uv;
        let mut xn = [0.0; 2];
        step.state_into(&mu, &x, &u, None, &mut xn);
        assert!((DVector::from_column_slice(&xn) - without).amax() < 1e-14);
        step.state_into(&mu, &x, &u, Some(&e), &mut xn);
        assert!((DVector::from_column_slice(&xn) - with).amax() < 1e-14);
        let mut yk = [0.0; 2];
        step.output_into(&mu, &x, &u, &mut yk);
        assert!((DVector::from_column_slice(&yk) - y).amax() < 1e-14);
        // a single C and D are parameter-independent (weight 1 whatever mu)
        let mut single = m.clone();
        single.c.truncate(1);
        single.d.truncate(1);
        single.stepper().output_into(&mu, &x, &u, &mut yk);
        let y1 = &single.c[0] * &xv + &single.d[0] * &uv;
        assert!((DVector::from_column_slice(&yk) - y1).amax() < 1e-14);
    }
}
