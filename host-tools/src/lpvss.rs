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
    if mats.len() == 1 {
        return mats[0].clone();
    }
    let mut out = DMatrix::zeros(mats[0].nrows(), mats[0].ncols());
    for (m, w) in mats.iter().zip(mu.iter()) {
        out += m * *w;
    }
    out
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
        for k in 0..n_samples {
            for q in 0..s {
                mu[q + 1] = sig.p[(k, q)];
            }
            for (j, v) in uk.iter_mut().enumerate() {
                *v = sig.u[(k, j)];
            }
            self.output_into(&mu, &x, &uk, &mut yhat);
            for j in 0..l {
                ek[j] = if predictor {
                    sig.y[(k, j)] - yhat[j]
                } else {
                    e.map_or(0.0, |e| e[(k, j)])
                };
                out[(k, j)] = if predictor { yhat[j] } else { yhat[j] + ek[j] };
            }
            let innovation = (predictor || e.is_some()).then_some(&ek[..]);
            self.state_into(&mu, &x, &uk, innovation, &mut xn);
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

    /// The output equation y = C(mu) x + D(mu) u into `y` (one C or D: parameter-independent),
    /// without allocating: every simulation's sample loop (`run_x0`,
    /// `simulate::free_run_ss_into`, the streamed score, BPDN-SV's scorer) is made of this and
    /// [`LpvSs::state_into`].
    pub fn output_into(&self, mu: &[f64], x: &[f64], u: &[f64], y: &mut [f64]) {
        for (j, yj) in y.iter_mut().enumerate() {
            let mut acc = 0.0;
            add_scheduled_row(&mut acc, &self.c, mu, j, x);
            add_scheduled_row(&mut acc, &self.d, mu, j, u);
            *yj = acc;
        }
    }

    /// The state equation x+ = sum_i mu_i (A_i x + B_i u + K_i e) into `xn` (`e` None: no
    /// innovation term), without allocating. This runs once per sample of every simulation
    /// (the initial-state fit runs n + 1 simulations per iteration): the matrices are read as
    /// the column-major slices they are, not through nalgebra's two-index checks, with the
    /// sums formed in the same order as before (bit-identical results).
    pub fn state_into(&self, mu: &[f64], x: &[f64], u: &[f64], e: Option<&[f64]>, xn: &mut [f64]) {
        xn.iter_mut().for_each(|v| *v = 0.0);
        for (i, &w) in mu.iter().enumerate().take(self.m()) {
            if w == 0.0 {
                continue;
            }
            let (a, b, k) = (&self.a[i], &self.b[i], &self.k[i]);
            let (a, b, k, rows) = (a.as_slice(), b.as_slice(), k.as_slice(), a.nrows());
            for (row, v) in xn.iter_mut().enumerate() {
                let mut acc = 0.0;
                for (col, xv) in x.iter().enumerate() {
                    acc += a[col * rows + row] * xv;
                }
                for (col, uv) in u.iter().enumerate() {
                    acc += b[col * rows + row] * uv;
                }
                if let Some(e) = e {
                    for (col, ev) in e.iter().enumerate() {
                        acc += k[col * rows + row] * ev;
                    }
                }
                *v += w * acc;
            }
        }
    }

    /// Frozen-scheduling matrix A(mu) = sum_i mu_i A^(i).
    pub fn a_at(&self, mu: &DVector<f64>) -> DMatrix<f64> {
        scheduled(&self.a, mu)
    }
}

/// acc += sum_i mu_i (M_i v)_j, in the order of i (a single matrix: parameter-independent,
/// weight 1); the output equation's one term ([`LpvSs::output_into`]).
fn add_scheduled_row(acc: &mut f64, mats: &[DMatrix<f64>], mu: &[f64], j: usize, v: &[f64]) {
    let scheduled = mats.len() > 1;
    for (i, m) in mats.iter().enumerate() {
        let w = if scheduled { mu[i] } else { 1.0 };
        if w != 0.0 {
            *acc += w * v
                .iter()
                .enumerate()
                .map(|(a, va)| m[(j, a)] * va)
                .sum::<f64>();
        }
    }
}
