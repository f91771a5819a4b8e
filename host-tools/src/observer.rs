//! H-infinity observer gains for an identified LPV model (sparse paper,
//! `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md` section 3.4 and Appendix A): noise
//! covariances from the least-squares residuals (eq. (24)-(25)), the LMI problem (30) over
//! the vertices of the scheduling box solved with clarabel (PSD cones), the gains (31), an
//! independent eigenvalue certificate of the solution, and the frozen-scheduling stability
//! region of the predictor A(mu) - K(mu) C (Table 1).
//!
//! # What is solved, exactly
//!
//! Variables: the symmetric Lyapunov matrix P (n x n) and t = gamma^2. For every vertex
//! mu of the box, with Abar(mu) = sum_i mu^(i) A^(i) - S R^-1 C, G = Qx^{1/2}
//! (Qx = Q - S R^-1 S^T) and H = C^T R^-1 C,
//! ```text
//! M(mu) = [ P   0   P Abar(mu)   P G ]
//!         [ *   I   I            0   ]
//!         [ *   *   P + t H      0   ]   >  0,          P > I,          minimise t.
//!         [ *   *   *            t I ]
//! ```
//! Strict inequalities are imposed with an explicit margin delta: `M(mu) - delta I` and
//! `P - (1 + delta) I` in the PSD cone ([`HinfOptions::margin`], default
//! [`DEFAULT_MARGIN`] = 1e-6, in the normalised units below). If our own eigenvalue check
//! rejects the solver's answer, the design is repeated with the margin x100 (at most twice);
//! the margin actually used is recorded.
//!
//! **Normalisation.** Q, S, R are divided by c = lambda_max([Q S; S^T R]) before solving.
//! (30) is exactly invariant under (Q, S, R, t) -> (Q, S, R, t)/c (a congruence with
//! diag(I, I, I, sqrt(c) I)), P and the gains are unchanged, and gamma^2 = c t. All
//! eigenvalues reported by the certificate are of the normalised matrices.
//!
//! **Gains (31).** At a frozen mu the gain that the vertex condition certifies is
//! K(mu) = (t A(mu) C_P + S)(t C C_P + R)^-1, C_P = (P - I)^-1 C^T, affine in mu. Written
//! as sum_i mu^(i) K^(i) with mu^(1) = 1, the constant S belongs to the affine term:
//! K^(1) = (t A^(1) C_P + S) M^-1, K^(i) = t A^(i) C_P M^-1 for i >= 2, M = t C C_P + R.
//! (Eq. (31) as printed puts S in every K^(i); that gives (sum_i mu^(i)) S, which is not the
//! gain the vertex condition certifies unless m = 1. Appendix A's form, with the noise
//! entering outside the scheduling sum as in eq. (26), is the one implemented.)
//!
//! **Certificate** ([`certify`]), from our own symmetric eigenvalues (faer), never the
//! solver's claim: P - I > 0; M(mu) > 0 at every vertex; and on a dense grid of the box the
//! bounded-real matrix of the closed-loop error system (29),
//! ```text
//! [ P   P Acl(mu)   P Bcl(mu) ]
//! [ *   P - I       0         ]  > 0,   Acl = A(mu) - K(mu) C,
//! [ *   0           t I       ]         Bcl = [ (S R^-1 - K(mu)) R^{1/2},  Qx^{1/2} ],
//! ```
//! which says that V(x) = x^T P x is a common Lyapunov function of the error system over
//! the whole box with V(x+) - V(x) < -|x|^2 + gamma^2 |eps|^2 (so ||E||_inf < gamma and the
//! predictor A(mu) - K(mu) C is stable for every frozen or varying mu in the box).
//!
//! **Residuals (24)-(25).** As the paper: A^(i), B^(i) are re-estimated by least squares from
//! the identified state sequence *without* the innovation regressors (eq. (24) left; the
//! realization of [`crate::pbsid`] estimates them jointly with K^(i), eq. (6)-(7)); C and D
//! are the realization's least-squares estimates (eq. (24) right). W = x_{k+1} -
//! sum_i mu^(i) (A^(i) x_k + B^(i) u_k), V = y_k - C x_k - D u_k, and
//! [Q S; S^T R] = [W; V][W; V]^T / (columns - 1) (the paper's 1/(N - p - 2)). The
//! H-infinity model is (A, B from (24), C, D, K from (31)); when the design fails the
//! least-squares model is kept whole.
//!
//! **After an output-error refinement** (`lpvid pbsid --refine`, [`crate::refine`]; the
//! refinement runs inside the fit, so before this step): (24) would re-estimate A, B from
//! the subspace states and bring back the finite-past-window bias the refinement removed
//! (on B2 at p = 5 and 75-100 dB it caps the predictor VAF near 98.5, below Table 1's 99.5
//! and 99.7). [`hinf_observer_refined`] keeps the refined A, B, C, D, moves the states into
//! the refined model's basis ([`align_states`]), takes Q, S, R from their residuals
//! ([`noise_covariance`], eq. (25)) and solves (30)-(31) for that model.

use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT::PSDTriangleConeT,
};
use nalgebra::{DMatrix, DVector};
use serde_json::{json, Value};

use crate::linalg::{schur_spectral_radius, spectral_radius, sym_eig, LinalgError, SmallEig};
use crate::lpvss::{scheduled, LpvSs, ShapeError, Signals};

/// Default strictness margin delta of the LMIs (normalised units, see the module docs).
pub const DEFAULT_MARGIN: f64 = 1e-6;

/// Default number of grid points per scheduling signal in the certificate (at most
/// [`MAX_GRID_POINTS`] in total).
pub const DEFAULT_GRID: usize = 1001;

/// Largest total number of grid points of the certificate.
pub const MAX_GRID_POINTS: usize = 10_000;

/// Why an observer design, a scheduling box or a stability report was not made. The text
/// of each variant is the message `lpvid pbsid` / `lpvid stability` print.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ObserverError {
    /// The model's matrices do not fit together.
    #[error("H-infinity observer: {0}")]
    Model(#[from] ShapeError),
    /// The state sequence has another dimension than the model.
    #[error("H-infinity observer: the state sequence has {rows} rows, the model {states} states")]
    StateDimension {
        /// Rows of the state sequence.
        rows: usize,
        /// The model's order n.
        states: usize,
    },
    /// The data's inputs, outputs or scheduling signals differ from the model's.
    #[error("H-infinity observer: the data's channels do not match the model")]
    Channels,
    /// Too few residual columns for (25), or states longer than the data.
    #[error("H-infinity observer: {columns} residual columns from {samples} samples and past window {past}: too few, or the states do not match the data")]
    ResidualColumns {
        /// Residual columns (states - 1).
        columns: usize,
        /// Samples in the data.
        samples: usize,
        /// Past window p.
        past: usize,
    },
    /// A fit from statistics has no state sequence to take the residuals (25) from.
    #[error("H-infinity observer: no state sequence (a fit from statistics): the residuals (25) need the states")]
    NoStates,
    /// NaN or infinity in the named quantity.
    #[error("H-infinity observer: {0}")]
    NonFinite(&'static str),
    /// A least-squares step failed (`step`: which one; `reason`: nalgebra's).
    #[error("H-infinity observer: {step}: {reason}")]
    LeastSquares {
        /// "least squares (24)" or "state alignment".
        step: &'static str,
        /// Why.
        reason: &'static str,
    },
    /// The state alignment's metric is not positive definite.
    #[error(
        "H-infinity observer: state alignment: the {0} has no positive definite second moment"
    )]
    SecondMoment(&'static str),
    /// The states do not determine the refined model's basis.
    #[error("H-infinity observer: the state sequence does not determine the refined model's basis (rank-deficient alignment)")]
    AlignmentRank,
    /// An eigendecomposition failed.
    #[error("H-infinity observer: {0}")]
    Linalg(#[from] LinalgError),
    /// [Q S; S^T R] is zero: an exact fit leaves (30) without R > 0.
    #[error(
        "H-infinity observer: the residual covariance is zero (an exact fit): (30) needs R > 0"
    )]
    ZeroNoise,
    /// R is singular (its smallest normalised eigenvalue).
    #[error("H-infinity observer: the output residual covariance R is singular (smallest eigenvalue {0:.3e} of the normalised R): (30) needs R > 0")]
    SingularR(f64),
    /// C or D depend on the scheduling.
    #[error("H-infinity observer: LMI (30) needs a parameter-independent output equation (one C and one D)")]
    ScheduledOutput,
    /// The box has another number of scheduling signals than the model.
    #[error("H-infinity observer: the scheduling box has {box_signals} signals, the model {model_signals}")]
    BoxSignals {
        /// Signals of the box.
        box_signals: usize,
        /// Scheduling signals of the model.
        model_signals: usize,
    },
    /// Q or R have other dimensions than the model.
    #[error("H-infinity observer: noise covariances do not match the model")]
    NoiseDimension,
    /// The strictness margin is not positive and finite.
    #[error("H-infinity observer: the margin must be positive, got {0}")]
    Margin(f64),
    /// The LMI problem (30) has no solution (solver certificate of infeasibility).
    #[error(
        "H-infinity observer: the LMI problem (30) is infeasible over the scheduling box ({0})"
    )]
    Infeasible(String),
    /// The solver stopped without a solution.
    #[error("H-infinity observer: the SDP solver failed ({0})")]
    SolverFailed(String),
    /// The SDP solver's BLAS/LAPACK (the system OpenBLAS) is not installed.
    #[error("H-infinity observer: {0}")]
    Blas(#[from] crate::blas::BlasUnavailable),
    /// A `NAME=LO:HI` scheduling range without `=`.
    #[error("scheduling range '{0}': expected NAME=LO:HI, e.g. p1=-0.8:1.2")]
    RangeSyntax(String),
    /// A scheduling range for a signal the model does not have.
    #[error(
        "scheduling range '{spec}': the model has no scheduling signal '{name}' (it has: {known})"
    )]
    RangeSignal {
        /// The range as given.
        spec: String,
        /// The unknown name.
        name: String,
        /// The model's scheduling signals, comma-separated ("none" for an LTI model).
        known: String,
    },
    /// A scheduling range without `LO:HI` after `=`.
    #[error("scheduling range '{0}': expected LO:HI after '='")]
    RangeBounds(String),
    /// A bound that is not a finite number.
    #[error("scheduling range '{spec}': '{value}' is not a finite number")]
    RangeNumber {
        /// The range as given.
        spec: String,
        /// The bound as given.
        value: String,
    },
    /// LO > HI.
    #[error("scheduling range '{0}': lower bound above upper bound")]
    RangeOrder(String),
    /// The stability report got another number of scheduling names than the model has.
    #[error("the model has {signals} scheduling signals but {names} names")]
    SchedulingNames {
        /// The model's scheduling signals s.
        signals: usize,
        /// Names given.
        names: usize,
    },
    /// Neither data, nor the model's record, nor a range give a signal's operating range.
    #[error("no operating range for scheduling signal {0}: give --data or --range {0}=LO:HI")]
    NoOperatingRange(String),
    /// The model's matrices do not fit together (the stability report's check).
    #[error(transparent)]
    Shape(ShapeError),
    /// The solver returned a point our own eigenvalue check rejects.
    #[error(
        "H-infinity observer: the solver's solution fails the independent eigenvalue check ({0})"
    )]
    Certificate(String),
}

/// Process/measurement noise covariances of eq. (4), estimated by eq. (25).
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseCov {
    /// Q (n x n): state-equation residual covariance.
    pub q: DMatrix<f64>,
    /// S (n x l): cross covariance.
    pub s: DMatrix<f64>,
    /// R (l x l): output residual covariance.
    pub r: DMatrix<f64>,
    /// Number of residual columns used.
    pub columns: usize,
}

/// The joint covariance [Q S; S^T R].
fn joint(nc: &NoiseCov) -> DMatrix<f64> {
    let (n, l) = (nc.q.nrows(), nc.r.nrows());
    let mut j = DMatrix::zeros(n + l, n + l);
    j.view_mut((0, 0), (n, n)).copy_from(&nc.q);
    j.view_mut((0, n), (n, l)).copy_from(&nc.s);
    j.view_mut((n, 0), (l, n)).copy_from(&nc.s.transpose());
    j.view_mut((n, n), (l, l)).copy_from(&nc.r);
    j
}

/// Eq. (24)-(25): [A^(1..m), B^(1..m)] by least squares from the state sequence without
/// innovation regressors, C and D of `model` (the realization's least-squares estimates of
/// the output equation, which (24) right repeats), and the noise covariances from the
/// residuals. `states` column j is x_{past+j} ([`crate::pbsid::PbsidFit::states`]), in the
/// model's basis and units. Returns the model with these A, B (and K = 0) and the
/// covariances.
pub fn residual_model(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
) -> Result<(LpvSs, NoiseCov), ObserverError> {
    let cols = residual_columns(model, sig, states, past)?;
    let (n, r, l, m) = (model.n(), model.r(), model.l(), model.m());
    // (24) left: x_{k+1} = [A, B] [mu_k (x) x_k; mu_k (x) u_k], rows = samples
    let d = m * (n + r);
    let mut phi = DMatrix::<f64>::zeros(cols, d);
    let mut tgt = DMatrix::<f64>::zeros(cols, n);
    for j in 0..cols {
        let k = past + j;
        let mu = sig.mu(k);
        for i in 0..m {
            for a in 0..n {
                phi[(j, i * (n + r) + a)] = mu[i] * states[(a, j)];
            }
            for b in 0..r {
                phi[(j, i * (n + r) + n + b)] = mu[i] * sig.u[(k, b)];
            }
        }
        for a in 0..n {
            tgt[(j, a)] = states[(a, j + 1)];
        }
    }
    if !phi.iter().chain(tgt.iter()).all(|v| v.is_finite()) {
        return Err(ObserverError::NonFinite("non-finite states or data"));
    }
    let svd = phi.svd(true, true);
    let smax = svd.singular_values.max();
    let sol = svd
        .solve(&tgt, 1e-12 * smax)
        .map_err(|reason| ObserverError::LeastSquares {
            step: "least squares (24)",
            reason,
        })?;
    let solt = sol.transpose();
    let mut out = LpvSs {
        a: Vec::with_capacity(m),
        b: Vec::with_capacity(m),
        k: vec![DMatrix::zeros(n, l); m],
        c: model.c.clone(),
        d: model.d.clone(),
    };
    for i in 0..m {
        out.a.push(solt.columns(i * (n + r), n).into_owned());
        out.b.push(solt.columns(i * (n + r) + n, r).into_owned());
    }
    let nc = noise_covariance(&out, sig, states, past)?;
    Ok((out, nc))
}

/// Check that `states` (column j = x_{past+j}) fit `model` and `sig`; the number of
/// residual columns of (25) (one less than the number of states).
fn residual_columns(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
) -> Result<usize, ObserverError> {
    model.validate()?;
    let (n, r, l, m) = (model.n(), model.r(), model.l(), model.m());
    if states.nrows() != n {
        return Err(ObserverError::StateDimension {
            rows: states.nrows(),
            states: n,
        });
    }
    if sig.p.ncols() + 1 != m || sig.u.ncols() != r || sig.y.ncols() != l {
        return Err(ObserverError::Channels);
    }
    let cols = states.ncols().saturating_sub(1);
    if cols < 3 || past + cols > sig.len() {
        return Err(ObserverError::ResidualColumns {
            columns: cols,
            samples: sig.len(),
            past,
        });
    }
    Ok(cols)
}

/// Eq. (25) for a given model: W = x_{k+1} - sum_i mu^(i) (A^(i) x_k + B^(i) u_k),
/// V = y_k - C x_k - D u_k over the state sequence (column j = x_{past+j}), and
/// [Q S; S^T R] = [W; V][W; V]^T / (columns - 1) (the paper's 1/(N - p - 2)).
pub fn noise_covariance(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
) -> Result<NoiseCov, ObserverError> {
    let cols = residual_columns(model, sig, states, past)?;
    let (n, l) = (model.n(), model.l());
    let mut wv = DMatrix::<f64>::zeros(n + l, cols);
    for j in 0..cols {
        let k = past + j;
        let mu = sig.mu(k);
        let x = states.column(j);
        let u = sig.u.row(k).transpose();
        let y = sig.y.row(k).transpose();
        let w = states.column(j + 1) - model.a_at(&mu) * x - scheduled(&model.b, &mu) * &u;
        let v = y - scheduled(&model.c, &mu) * x - scheduled(&model.d, &mu) * &u;
        wv.view_mut((0, j), (n, 1)).copy_from(&w);
        wv.view_mut((n, j), (l, 1)).copy_from(&v);
    }
    if !wv.iter().all(|v| v.is_finite()) {
        return Err(ObserverError::NonFinite(
            "non-finite residuals (the model or states are not finite)",
        ));
    }
    let cov = &wv * wv.transpose() / (cols as f64 - 1.0);
    Ok(NoiseCov {
        q: cov.view((0, 0), (n, n)).into_owned(),
        s: cov.view((0, n), (n, l)).into_owned(),
        r: cov.view((n, n), (l, l)).into_owned(),
        columns: cols,
    })
}

/// The subspace state sequence expressed in the basis of a model that was changed after the
/// realization (the output-error refinement of [`crate::refine`] moves A, B, C, D, and with
/// them, freely, the state basis). Returns T X with the n x n matrix
/// ```text
/// T = argmin_T sum_k |Lx^-1 (T x_{k+1} - A(mu_k) T x_k - B(mu_k) u_k)|^2
///                  + |Ly^-1 (y_k - C T x_k - D u_k)|^2,
/// ```
/// i.e. the basis in which the states best satisfy the model's own equations, so that the
/// residuals (25) measure noise and not a change of coordinates. Lx Lx^T is the second
/// moment of the model's own free-run state (from x = 0 over `sig`) and Ly Ly^T that of the
/// measured output: each equation's residual is measured relative to its signal, which makes
/// the criterion, and so the aligned states, independent of the basis the model is given in
/// (a model T0 A T0^-1, T0 B, C T0^-1 gets T0 T X). The criterion is linear in vec(T)
/// (vec(A T x) = (x^T (x) A) vec(T)): one weighted least-squares problem with n^2 unknowns.
pub fn align_states(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
) -> Result<DMatrix<f64>, ObserverError> {
    let cols = residual_columns(model, sig, states, past)?;
    let (n, l) = (model.n(), model.l());
    // the metric of each equation: inverse Cholesky factors of the signals' second moments
    let mut x = DVector::<f64>::zeros(n);
    let mut sxx = DMatrix::<f64>::zeros(n, n);
    for k in 0..sig.len() {
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        x = model.a_at(&mu) * &x + scheduled(&model.b, &mu) * &u;
        sxx += &x * x.transpose();
    }
    let syy = sig.y.transpose() * &sig.y;
    let inv_factor = |m: DMatrix<f64>, what: &'static str| -> Result<DMatrix<f64>, ObserverError> {
        let bad = || ObserverError::SecondMoment(what);
        if !m.iter().all(|v| v.is_finite()) {
            return Err(bad());
        }
        let ch = m.cholesky().ok_or_else(bad)?;
        ch.l().try_inverse().ok_or_else(bad)
    };
    let wx = inv_factor(sxx, "model's free-run state")?;
    let wy = inv_factor(syy, "measured output")?;
    let rows = cols * (n + l);
    let mut lhs = DMatrix::<f64>::zeros(rows, n * n);
    let mut rhs = DVector::<f64>::zeros(rows);
    let mut blk_x = DMatrix::<f64>::zeros(n, n * n);
    let mut blk_y = DMatrix::<f64>::zeros(l, n * n);
    for j in 0..cols {
        let k = past + j;
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        let a = model.a_at(&mu);
        let c = scheduled(&model.c, &mu);
        let bu = scheduled(&model.b, &mu) * &u;
        let ydu = sig.y.row(k).transpose() - scheduled(&model.d, &mu) * &u;
        let (x0, x1) = (states.column(j), states.column(j + 1));
        // vec(T) index of T[p, q] is p + q n (column-major)
        for q in 0..n {
            for p in 0..n {
                let col = p + q * n;
                for i in 0..n {
                    // state equation row i: (T x1)_i - (A T x0)_i = (B u)_i
                    let mut v = -a[(i, p)] * x0[q];
                    if i == p {
                        v += x1[q];
                    }
                    blk_x[(i, col)] = v;
                }
                for i in 0..l {
                    // output equation row i: (C T x0)_i = (y - D u)_i
                    blk_y[(i, col)] = c[(i, p)] * x0[q];
                }
            }
        }
        let base = j * (n + l);
        lhs.view_mut((base, 0), (n, n * n))
            .copy_from(&(&wx * &blk_x));
        lhs.view_mut((base + n, 0), (l, n * n))
            .copy_from(&(&wy * &blk_y));
        rhs.rows_mut(base, n).copy_from(&(&wx * bu));
        rhs.rows_mut(base + n, l).copy_from(&(&wy * ydu));
    }
    if !lhs.iter().chain(rhs.iter()).all(|v| v.is_finite()) {
        return Err(ObserverError::NonFinite("non-finite states or data"));
    }
    let svd = lhs.svd(true, true);
    let smax = svd.singular_values.max();
    let smin = svd.singular_values.min();
    if smin <= 1e-10 * smax {
        return Err(ObserverError::AlignmentRank);
    }
    let t = svd
        .solve(&rhs, 0.0)
        .map_err(|reason| ObserverError::LeastSquares {
            step: "state alignment",
            reason,
        })?;
    let t = DMatrix::from_column_slice(n, n, t.as_slice());
    Ok(t * states)
}

/// The whole of section 3.4 for an identified model: (24)-(25) from its state sequence, the
/// LMI (30) over the vertices of `sbox`, the gains (31), certified. Returns the observer
/// model (A, B from (24), C, D of `model`, K from (31)), the noise covariances and the
/// design. On any error the caller keeps its least-squares model.
pub fn hinf_observer(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
    sbox: &SchedBox,
    opts: &HinfOptions,
) -> Result<(LpvSs, NoiseCov, HinfDesign), ObserverError> {
    let (out, nc) = residual_model(model, sig, states, past)?;
    with_hinf_gains(out, nc, sbox, opts)
}

/// Section 3.4 for a model whose A, B, C, D were refined after the realization
/// ([`crate::refine::refine_output_error`]): the refined matrices are kept (re-estimating
/// A, B by (24) from the subspace states would bring back the finite-past-window bias that
/// the refinement removed), the state sequence is moved into the refined model's basis
/// ([`align_states`]), Q, S, R come from its residuals (eq. (25), [`noise_covariance`]),
/// and the gains from the LMI (30) and (31). Returns the observer model (the refined A, B,
/// C, D with K from (31)), the noise covariances and the design.
pub fn hinf_observer_refined(
    model: &LpvSs,
    sig: &Signals,
    states: &DMatrix<f64>,
    past: usize,
    sbox: &SchedBox,
    opts: &HinfOptions,
) -> Result<(LpvSs, NoiseCov, HinfDesign), ObserverError> {
    let aligned = align_states(model, sig, states, past)?;
    let nc = noise_covariance(model, sig, &aligned, past)?;
    with_hinf_gains(model.clone(), nc, sbox, opts)
}

/// Eq. (30)-(31) for `model` and its noise `nc`: the certified design, and the model with
/// K replaced by its gains.
fn with_hinf_gains(
    mut model: LpvSs,
    nc: NoiseCov,
    sbox: &SchedBox,
    opts: &HinfOptions,
) -> Result<(LpvSs, NoiseCov, HinfDesign), ObserverError> {
    let design = design_hinf(&model, &nc, sbox, opts)?;
    model.k = design.k.clone();
    Ok((model, nc, design))
}

/// The operating region of the scheduling: a box, one interval per scheduling signal.
#[derive(Debug, Clone, PartialEq)]
pub struct SchedBox {
    /// Names of the scheduling signals (the model's scheduling basis functions after the
    /// constant, e.g. `p1`).
    pub names: Vec<String>,
    /// Lower bounds.
    pub lo: Vec<f64>,
    /// Upper bounds.
    pub hi: Vec<f64>,
    /// Where each interval came from (`data` or `--scheduling-range`).
    pub source: Vec<String>,
}

impl SchedBox {
    /// The data's range of each scheduling signal (columns of `sig.p`).
    pub fn from_signals(names: &[String], sig: &Signals) -> SchedBox {
        let s = sig.p.ncols();
        let (mut lo, mut hi) = (vec![0.0; s], vec![0.0; s]);
        for j in 0..s {
            let c = sig.p.column(j);
            lo[j] = c.min();
            hi[j] = c.max();
        }
        SchedBox {
            names: names.to_vec(),
            lo,
            hi,
            source: vec!["data".into(); s],
        }
    }

    /// Number of scheduling signals s.
    pub fn dim(&self) -> usize {
        self.lo.len()
    }

    /// Apply `name=lo:hi` overrides (several may be given, comma-separated or repeated).
    pub fn apply_ranges(&mut self, specs: &[String]) -> Result<(), ObserverError> {
        for spec in specs.iter().flat_map(|s| s.split(',')) {
            let spec = spec.trim();
            if spec.is_empty() {
                continue;
            }
            let (name, range) = spec
                .split_once('=')
                .ok_or_else(|| ObserverError::RangeSyntax(spec.to_string()))?;
            let j = self
                .names
                .iter()
                .position(|n| n == name.trim())
                .ok_or_else(|| ObserverError::RangeSignal {
                    spec: spec.to_string(),
                    name: name.trim().to_string(),
                    known: if self.names.is_empty() {
                        "none".to_string()
                    } else {
                        self.names.join(", ")
                    },
                })?;
            let (a, b) = range
                .split_once(':')
                .ok_or_else(|| ObserverError::RangeBounds(spec.to_string()))?;
            let parse = |v: &str| {
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| ObserverError::RangeNumber {
                        spec: spec.to_string(),
                        value: v.to_string(),
                    })
            };
            let (a, b) = (parse(a)?, parse(b)?);
            if a > b {
                return Err(ObserverError::RangeOrder(spec.to_string()));
            }
            self.lo[j] = a;
            self.hi[j] = b;
            self.source[j] = "--scheduling-range".into();
        }
        Ok(())
    }

    /// The 2^s vertices as mu = [1, p1, ..., ps] (duplicates of a degenerate interval
    /// removed).
    pub fn vertices(&self) -> Vec<DVector<f64>> {
        let s = self.dim();
        let mut out: Vec<DVector<f64>> = Vec::new();
        for v in 0..(1usize << s) {
            let mu = DVector::from_fn(s + 1, |i, _| {
                if i == 0 {
                    1.0
                } else if v >> (i - 1) & 1 == 1 {
                    self.hi[i - 1]
                } else {
                    self.lo[i - 1]
                }
            });
            if !out.contains(&mu) {
                out.push(mu);
            }
        }
        out
    }

    /// A grid of the box with about `per_dim` points per signal (capped at
    /// [`MAX_GRID_POINTS`] in total), as mu vectors.
    pub fn grid(&self, per_dim: usize) -> Vec<DVector<f64>> {
        let s = self.dim();
        if s == 0 {
            return vec![DVector::from_element(1, 1.0)];
        }
        let mut g = per_dim.max(2);
        while g.saturating_pow(s as u32) > MAX_GRID_POINTS && g > 2 {
            g -= 1;
        }
        let total = g.pow(s as u32);
        (0..total)
            .map(|mut idx| {
                let mut mu = DVector::from_element(s + 1, 1.0);
                for j in 0..s {
                    let t = (idx % g) as f64 / (g - 1) as f64;
                    idx /= g;
                    mu[j + 1] = self.lo[j] + t * (self.hi[j] - self.lo[j]);
                }
                mu
            })
            .collect()
    }
}

/// Settings of the H-infinity design.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HinfOptions {
    /// Strictness margin delta (normalised units).
    pub margin: f64,
    /// Certificate grid points per scheduling signal.
    pub grid: usize,
}

impl Default for HinfOptions {
    fn default() -> Self {
        HinfOptions {
            margin: DEFAULT_MARGIN,
            grid: DEFAULT_GRID,
        }
    }
}

/// The independent check of a design (eigenvalues from our own code).
#[derive(Debug, Clone, PartialEq)]
pub struct Certificate {
    /// Smallest eigenvalue of P - I.
    pub min_eig_p_minus_i: f64,
    /// Smallest eigenvalue of the LMI matrix (30) at each vertex (normalised units).
    pub min_eig_vertex: Vec<f64>,
    /// Number of grid points of the box checked.
    pub grid_points: usize,
    /// Smallest eigenvalue of the error system's bounded-real matrix over the grid.
    pub min_eig_grid: f64,
    /// Largest spectral radius of A(mu) - K(mu) C over the grid.
    pub max_rho_grid: f64,
}

impl Certificate {
    /// Every check passed.
    pub fn ok(&self) -> bool {
        self.min_eig_p_minus_i > 0.0
            && self.min_eig_vertex.iter().all(|&v| v > 0.0)
            && self.min_eig_grid > 0.0
            && self.max_rho_grid < 1.0
    }

    /// As JSON.
    pub fn to_json(&self) -> Value {
        json!({
            "ok": self.ok(),
            "min_eig_p_minus_i": self.min_eig_p_minus_i,
            "min_eig_vertex_lmi": self.min_eig_vertex,
            "grid_points": self.grid_points,
            "min_eig_grid_bounded_real": self.min_eig_grid,
            "max_spectral_radius_grid": self.max_rho_grid,
        })
    }
}

/// A solved and certified design.
#[derive(Debug, Clone, PartialEq)]
pub struct HinfDesign {
    /// gamma: bound on the H-infinity norm of the error system (29), model units.
    pub gamma: f64,
    /// t = gamma^2 / c in the normalised problem.
    pub gamma2_normalised: f64,
    /// The noise normalisation c.
    pub noise_scale: f64,
    /// The Lyapunov matrix P (> I).
    pub p: DMatrix<f64>,
    /// Observer gains K^(1..m).
    pub k: Vec<DMatrix<f64>>,
    /// The vertices used (mu = [1, p1, ..]).
    pub vertices: Vec<DVector<f64>>,
    /// The strictness margin actually used.
    pub margin: f64,
    /// clarabel's status.
    pub solver_status: String,
    /// Interior-point iterations.
    pub iterations: u32,
    /// Solver time in seconds (clarabel's own timer).
    pub solve_time: f64,
    /// The independent check (passed).
    pub certificate: Certificate,
}

impl HinfDesign {
    /// The record that goes into the model's `fit`.
    pub fn to_json(&self, sbox: &SchedBox) -> Value {
        json!({
            "method": "hinf-lmi",
            "reference": "sparse paper section 3.4, LMI (30) over the vertices, gains (31); S in the affine term K^(1)",
            "gamma": self.gamma,
            "gamma2": self.gamma * self.gamma,
            "gamma2_normalised": self.gamma2_normalised,
            "noise_scale": self.noise_scale,
            "margin": self.margin,
            "margin_meaning": "LMI (30) - margin*I and P - (1+margin)*I in the PSD cone, with [Q S; S' R] divided by noise_scale",
            "vertices": self.vertices.iter().map(|v| v.iter().copied().collect::<Vec<_>>()).collect::<Vec<_>>(),
            "scheduling_box": box_json(sbox),
            "lyapunov_p": rows(&self.p),
            "solver": "clarabel",
            "solver_status": self.solver_status,
            "iterations": self.iterations,
            "solve_time_s": self.solve_time,
            "certificate": self.certificate.to_json(),
        })
    }
}

/// A box as JSON.
pub fn box_json(sbox: &SchedBox) -> Value {
    json!({
        "names": sbox.names,
        "lo": sbox.lo,
        "hi": sbox.hi,
        "source": sbox.source,
    })
}

fn rows(m: &DMatrix<f64>) -> Vec<Vec<f64>> {
    (0..m.nrows())
        .map(|i| m.row(i).iter().copied().collect())
        .collect()
}

/// The problem data in normalised units.
struct Normalised {
    c_scale: f64,
    s: DMatrix<f64>,
    r: DMatrix<f64>,
    r_inv: DMatrix<f64>,
    r_half: DMatrix<f64>,
    qx_half: DMatrix<f64>,
}

fn sym_fn(m: &DMatrix<f64>, f: impl Fn(f64) -> f64) -> Result<DMatrix<f64>, ObserverError> {
    let (vals, vecs) = sym_eig(m)?;
    let d = DMatrix::from_diagonal(&DVector::from_iterator(
        vals.len(),
        vals.iter().map(|&v| f(v)),
    ));
    Ok(&vecs * d * vecs.transpose())
}

fn min_eig(m: &DMatrix<f64>) -> f64 {
    match sym_eig(m) {
        Ok((vals, _)) => vals.last().copied().unwrap_or(f64::INFINITY),
        Err(_) => f64::NAN,
    }
}

fn normalise(nc: &NoiseCov) -> Result<Normalised, ObserverError> {
    let j = joint(nc);
    if !j.iter().all(|v| v.is_finite()) {
        return Err(ObserverError::NonFinite("non-finite noise covariance"));
    }
    let (vals, _) = sym_eig(&j)?;
    let c = vals.first().copied().unwrap_or(0.0);
    if c <= 0.0 || c.is_nan() {
        return Err(ObserverError::ZeroNoise);
    }
    let r = &nc.r / c;
    let rmin = min_eig(&r);
    if rmin.is_nan() || rmin <= 1e-12 {
        return Err(ObserverError::SingularR(rmin));
    }
    let r_inv = sym_fn(&r, |v| 1.0 / v)?;
    let r_half = sym_fn(&r, f64::sqrt)?;
    let s = &nc.s / c;
    let q = &nc.q / c;
    let qx = &q - &s * &r_inv * s.transpose();
    let qx_half = sym_fn(&qx, |v| v.max(0.0).sqrt())?;
    Ok(Normalised {
        c_scale: c,
        s,
        r,
        r_inv,
        r_half,
        qx_half,
    })
}

/// Index of P_ij (i <= j) among the variables: upper triangle, column-major.
fn pvar(i: usize, j: usize) -> usize {
    let (i, j) = if i <= j { (i, j) } else { (j, i) };
    j * (j + 1) / 2 + i
}

/// Symmetric basis matrix of variable P_ij.
fn basis(n: usize, i: usize, j: usize) -> DMatrix<f64> {
    let mut e = DMatrix::zeros(n, n);
    e[(i, j)] = 1.0;
    e[(j, i)] = 1.0;
    e
}

/// The affine matrix function F(x) = F0 + sum_k x_k F_k of one LMI.
struct AffineLmi {
    f0: DMatrix<f64>,
    fk: Vec<DMatrix<f64>>,
}

impl AffineLmi {
    fn eval(&self, x: &[f64]) -> DMatrix<f64> {
        let mut m = self.f0.clone();
        for (f, v) in self.fk.iter().zip(x) {
            m += f * *v;
        }
        m
    }
}

/// LMI (30) at the frozen A(mu) (normalised noise), as an affine function of
/// x = [P_ij (i <= j, column-major); t].
fn lmi30(amu: &DMatrix<f64>, c: &DMatrix<f64>, nz: &Normalised) -> AffineLmi {
    let n = amu.nrows();
    let abar = amu - &nz.s * &nz.r_inv * c;
    let h = c.transpose() * &nz.r_inv * c;
    let g = &nz.qx_half;
    let dim = 4 * n;
    let mut f0 = DMatrix::zeros(dim, dim);
    for i in 0..n {
        f0[(n + i, n + i)] = 1.0;
        f0[(n + i, 2 * n + i)] = 1.0;
        f0[(2 * n + i, n + i)] = 1.0;
    }
    let nvar = n * (n + 1) / 2 + 1;
    let mut fk = vec![DMatrix::zeros(dim, dim); nvar];
    for j in 0..n {
        for i in 0..=j {
            let e = basis(n, i, j);
            let f = &mut fk[pvar(i, j)];
            f.view_mut((0, 0), (n, n)).copy_from(&e);
            let ea = &e * &abar;
            f.view_mut((0, 2 * n), (n, n)).copy_from(&ea);
            f.view_mut((2 * n, 0), (n, n)).copy_from(&ea.transpose());
            let eg = &e * g;
            f.view_mut((0, 3 * n), (n, n)).copy_from(&eg);
            f.view_mut((3 * n, 0), (n, n)).copy_from(&eg.transpose());
            f.view_mut((2 * n, 2 * n), (n, n)).copy_from(&e);
        }
    }
    let ft = &mut fk[nvar - 1];
    ft.view_mut((2 * n, 2 * n), (n, n)).copy_from(&h);
    for i in 0..n {
        ft[(3 * n + i, 3 * n + i)] = 1.0;
    }
    AffineLmi { f0, fk }
}

/// P - I as an affine function of x.
fn lmi_p(n: usize) -> AffineLmi {
    let nvar = n * (n + 1) / 2 + 1;
    let mut fk = vec![DMatrix::zeros(n, n); nvar];
    for j in 0..n {
        for i in 0..=j {
            fk[pvar(i, j)] = basis(n, i, j);
        }
    }
    AffineLmi {
        f0: -DMatrix::identity(n, n),
        fk,
    }
}

/// Outcome of one SDP solve.
struct SdpSolution {
    x: Vec<f64>,
    status: SolverStatus,
    iterations: u32,
    solve_time: f64,
}

/// min c^T x s.t. F_j(x) - margin I in the PSD cone for every LMI j, with clarabel: rows of
/// the upper triangle in column-major order, off-diagonal entries scaled by sqrt(2), and
/// `b - A x` in the cone (RECIPES.md).
fn solve_sdp(lmis: &[AffineLmi], cost: &[f64], margin: f64) -> SdpSolution {
    let nvar = cost.len();
    let sqrt2 = std::f64::consts::SQRT_2;
    let (mut ri, mut ci, mut vv) = (Vec::new(), Vec::new(), Vec::new());
    let mut b = Vec::new();
    let mut cones = Vec::new();
    let mut row = 0usize;
    for lmi in lmis {
        let d = lmi.f0.nrows();
        for j in 0..d {
            for i in 0..=j {
                let sc = if i == j { 1.0 } else { sqrt2 };
                let f0 = lmi.f0[(i, j)] - if i == j { margin } else { 0.0 };
                b.push(sc * f0);
                for (k, f) in lmi.fk.iter().enumerate() {
                    let v = f[(i, j)];
                    if v != 0.0 {
                        ri.push(row);
                        ci.push(k);
                        vv.push(-sc * v);
                    }
                }
                row += 1;
            }
        }
        cones.push(PSDTriangleConeT(d));
    }
    let a = CscMatrix::new_from_triplets(row, nvar, ri, ci, vv);
    let p = CscMatrix::zeros((nvar, nvar));
    let settings = DefaultSettings::<f64> {
        verbose: false,
        max_iter: 200,
        ..DefaultSettings::default()
    };
    match DefaultSolver::new(&p, cost, &a, &b, &cones, settings) {
        Ok(mut solver) => {
            solver.solve();
            let s = &solver.solution;
            SdpSolution {
                x: s.x.clone(),
                status: s.status,
                iterations: s.iterations,
                solve_time: s.solve_time,
            }
        }
        Err(_) => SdpSolution {
            x: vec![f64::NAN; nvar],
            status: SolverStatus::NumericalError,
            iterations: 0,
            solve_time: 0.0,
        },
    }
}

fn unpack_p(x: &[f64], n: usize) -> DMatrix<f64> {
    DMatrix::from_fn(n, n, |i, j| x[pvar(i, j)])
}

/// Gains (31) from (P, t) in normalised units, K^(1) carrying S (see the module docs).
fn gains(
    a: &[DMatrix<f64>],
    c: &DMatrix<f64>,
    nz: &Normalised,
    p: &DMatrix<f64>,
    t: f64,
) -> Result<Vec<DMatrix<f64>>, ObserverError> {
    let n = p.nrows();
    let pm = p - DMatrix::identity(n, n);
    let pm_inv = pm
        .try_inverse()
        .ok_or_else(|| ObserverError::Certificate("P - I is singular".into()))?;
    let cp = pm_inv * c.transpose();
    let m = (c * &cp) * t + &nz.r;
    let m_inv = m
        .try_inverse()
        .ok_or_else(|| ObserverError::Certificate("t C C_P + R is singular".into()))?;
    Ok(a.iter()
        .enumerate()
        .map(|(i, ai)| {
            let mut num = ai * &cp * t;
            if i == 0 {
                num += &nz.s;
            }
            num * &m_inv
        })
        .collect())
}

/// The bounded-real matrix of the error system (29) at mu with gains `k` (normalised
/// units); see the module docs.
fn bounded_real(
    a: &[DMatrix<f64>],
    k: &[DMatrix<f64>],
    c: &DMatrix<f64>,
    nz: &Normalised,
    p: &DMatrix<f64>,
    t: f64,
    mu: &DVector<f64>,
) -> (DMatrix<f64>, f64) {
    let n = p.nrows();
    let l = c.nrows();
    let kmu = scheduled(k, mu);
    let acl = scheduled(a, mu) - &kmu * c;
    let rho = spectral_radius(&acl);
    let mut bcl = DMatrix::zeros(n, l + n);
    bcl.view_mut((0, 0), (n, l))
        .copy_from(&((&nz.s * &nz.r_inv - &kmu) * &nz.r_half));
    bcl.view_mut((0, l), (n, n)).copy_from(&nz.qx_half);
    let dim = 3 * n + l;
    let mut m = DMatrix::zeros(dim, dim);
    m.view_mut((0, 0), (n, n)).copy_from(p);
    let pa = p * &acl;
    let pb = p * &bcl;
    m.view_mut((0, n), (n, n)).copy_from(&pa);
    m.view_mut((n, 0), (n, n)).copy_from(&pa.transpose());
    m.view_mut((0, 2 * n), (n, l + n)).copy_from(&pb);
    m.view_mut((2 * n, 0), (l + n, n))
        .copy_from(&pb.transpose());
    m.view_mut((n, n), (n, n))
        .copy_from(&(p - DMatrix::identity(n, n)));
    for i in 0..l + n {
        m[(2 * n + i, 2 * n + i)] = t;
    }
    (m, rho)
}

/// Independent check of a solution (P, t, gains) over the box: our own eigenvalues.
fn certify_normalised(
    a: &[DMatrix<f64>],
    c: &DMatrix<f64>,
    nz: &Normalised,
    (p, t, k): (&DMatrix<f64>, f64, &[DMatrix<f64>]),
    sbox: &SchedBox,
    grid: usize,
) -> Certificate {
    let n = p.nrows();
    let min_eig_p_minus_i = min_eig(&(p - DMatrix::identity(n, n)));
    let mut x: Vec<f64> = (0..n * (n + 1) / 2).map(|_| 0.0).collect();
    for j in 0..n {
        for i in 0..=j {
            x[pvar(i, j)] = p[(i, j)];
        }
    }
    x.push(t);
    let min_eig_vertex = sbox
        .vertices()
        .iter()
        .map(|mu| min_eig(&lmi30(&scheduled(a, mu), c, nz).eval(&x)))
        .collect();
    let pts = sbox.grid(grid);
    let mut min_eig_grid = f64::INFINITY;
    let mut max_rho_grid: f64 = 0.0;
    for mu in &pts {
        let (m, rho) = bounded_real(a, k, c, nz, p, t, mu);
        min_eig_grid = min_eig_grid.min(min_eig(&m));
        max_rho_grid = max_rho_grid.max(rho);
    }
    Certificate {
        min_eig_p_minus_i,
        min_eig_vertex,
        grid_points: pts.len(),
        min_eig_grid,
        max_rho_grid,
    }
}

/// Independent check of a design made for `model` (A^(i), C) and noise `nc` over `sbox`:
/// recomputes every eigenvalue with our own code from (P, gamma, K).
pub fn certify(
    model: &LpvSs,
    nc: &NoiseCov,
    design: &HinfDesign,
    sbox: &SchedBox,
    grid: usize,
) -> Result<Certificate, ObserverError> {
    let nz = normalise(nc)?;
    let t = design.gamma * design.gamma / nz.c_scale;
    Ok(certify_normalised(
        &model.a,
        &model.c[0],
        &nz,
        (&design.p, t, &design.k),
        sbox,
        grid,
    ))
}

/// Solve (30) over the vertices of `sbox` for the identified `model` and noise `nc`, compute
/// the gains (31) and certify them. The model's own K is not used.
pub fn design_hinf(
    model: &LpvSs,
    nc: &NoiseCov,
    sbox: &SchedBox,
    opts: &HinfOptions,
) -> Result<HinfDesign, ObserverError> {
    model.validate()?;
    if model.c.len() != 1 || model.d.len() != 1 {
        return Err(ObserverError::ScheduledOutput);
    }
    let (n, l, m) = (model.n(), model.l(), model.m());
    if sbox.dim() + 1 != m {
        return Err(ObserverError::BoxSignals {
            box_signals: sbox.dim(),
            model_signals: m - 1,
        });
    }
    if nc.q.nrows() != n || nc.r.nrows() != l {
        return Err(ObserverError::NoiseDimension);
    }
    if !(opts.margin > 0.0 && opts.margin.is_finite()) {
        return Err(ObserverError::Margin(opts.margin));
    }
    crate::blas::load()?;
    let c = &model.c[0];
    let nz = normalise(nc)?;
    let vertices = sbox.vertices();
    let mut lmis = vec![lmi_p(n)];
    for mu in &vertices {
        lmis.push(lmi30(&model.a_at(mu), c, &nz));
    }
    let nvar = n * (n + 1) / 2 + 1;
    let mut cost = vec![0.0; nvar];
    cost[nvar - 1] = 1.0;
    let mut margin = opts.margin;
    let mut last_err = None;
    for _attempt in 0..3 {
        let sol = solve_sdp(&lmis, &cost, margin);
        match sol.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            SolverStatus::PrimalInfeasible | SolverStatus::AlmostPrimalInfeasible => {
                return Err(ObserverError::Infeasible(format!(
                    "clarabel: {:?} after {} iterations, margin {margin:e}",
                    sol.status, sol.iterations
                )))
            }
            other => {
                return Err(ObserverError::SolverFailed(format!(
                    "clarabel: {other:?} after {} iterations",
                    sol.iterations
                )))
            }
        }
        let p = unpack_p(&sol.x, n);
        let t = sol.x[nvar - 1];
        if !(t.is_finite() && t > 0.0 && p.iter().all(|v| v.is_finite())) {
            return Err(ObserverError::SolverFailed(format!(
                "clarabel returned {:?} with gamma^2 = {t}",
                sol.status
            )));
        }
        let k = match gains(&model.a, c, &nz, &p, t) {
            Ok(k) => k,
            Err(e) => {
                last_err = Some(e);
                margin *= 100.0;
                continue;
            }
        };
        let cert = certify_normalised(&model.a, c, &nz, (&p, t, &k), sbox, opts.grid);
        if cert.ok() {
            return Ok(HinfDesign {
                gamma: (t * nz.c_scale).sqrt(),
                gamma2_normalised: t,
                noise_scale: nz.c_scale,
                p,
                k,
                vertices,
                margin,
                solver_status: format!("{:?}", sol.status),
                iterations: sol.iterations,
                solve_time: sol.solve_time,
                certificate: cert,
            });
        }
        last_err = Some(ObserverError::Certificate(format!(
            "margin {margin:e}: min eig(P - I) {:.3e}, min eig of (30) over the vertices {:.3e}, min eig of the bounded-real matrix over {} grid points {:.3e}, max spectral radius {:.4}",
            cert.min_eig_p_minus_i,
            cert.min_eig_vertex.iter().copied().fold(f64::INFINITY, f64::min),
            cert.grid_points,
            cert.min_eig_grid,
            cert.max_rho_grid
        )));
        margin *= 100.0;
    }
    Err(last_err.unwrap_or_else(|| ObserverError::SolverFailed("no attempt made".into())))
}

/// The frozen predictor matrix A(mu) - K(mu) C(mu).
pub fn predictor_matrix(model: &LpvSs, mu: &DVector<f64>) -> DMatrix<f64> {
    model.a_at(mu) - scheduled(&model.k, mu) * scheduled(&model.c, mu)
}

/// The frozen predictor A(mu) - K(mu) C(mu) = sum_i w_i A_i - sum_ij w_i w_j K_i C_j with the
/// products K_i C_j formed once, evaluated into a reused buffer and its spectral radius
/// taken by [`SmallEig`]: the stability region and the box maximum evaluate it thousands of
/// times, each a few hundred flops instead of several allocating matrix products and a
/// Schur decomposition.
struct PredictorFamily {
    n: usize,
    /// A_i and -K_i C_j with their weights.
    terms: Vec<Term>,
    eig: SmallEig,
}

/// One term of [`PredictorFamily`]: the weights' indices into mu (None: weight 1) and the
/// signed matrix, row-major.
type Term = (Option<usize>, Option<usize>, Vec<f64>);

impl PredictorFamily {
    fn new(model: &LpvSs) -> PredictorFamily {
        let n = model.n();
        let weight = |len: usize, i: usize| (len > 1).then_some(i);
        let row_major = |m: &DMatrix<f64>, sign: f64| {
            let mut v = vec![0.0; n * n];
            for i in 0..n {
                for j in 0..n {
                    v[i * n + j] = sign * m[(i, j)];
                }
            }
            v
        };
        let mut terms = Vec::new();
        for (i, a) in model.a.iter().enumerate() {
            terms.push((weight(model.a.len(), i), None, row_major(a, 1.0)));
        }
        for (i, k) in model.k.iter().enumerate() {
            for (j, c) in model.c.iter().enumerate() {
                let kc = k * c;
                terms.push((
                    weight(model.k.len(), i),
                    weight(model.c.len(), j),
                    row_major(&kc, -1.0),
                ));
            }
        }
        PredictorFamily {
            n,
            terms,
            eig: SmallEig::default(),
        }
    }

    /// Spectral radius of A(mu) - K(mu) C(mu) (`mu` = [1, p1, ..., ps]).
    fn rho(&mut self, mu: &[f64]) -> f64 {
        let n = self.n;
        Self::fill(&self.terms, self.eig.load(n), mu);
        self.eig.spectral_radius(n).unwrap_or_else(|| {
            let mut buf = vec![0.0; n * n];
            Self::fill(&self.terms, &mut buf, mu);
            schur_spectral_radius(&DMatrix::from_row_slice(n, n, &buf))
        })
    }

    /// Write the predictor matrix at `mu` (row-major) into `buf`.
    fn fill(terms: &[Term], buf: &mut [f64], mu: &[f64]) {
        buf.fill(0.0);
        let at = |i: &Option<usize>| i.map_or(1.0, |i| mu.get(i).copied().unwrap_or(0.0));
        for (i, j, m) in terms {
            let w = at(i) * at(j);
            for (b, x) in buf.iter_mut().zip(m) {
                *b += w * x;
            }
        }
    }
}

/// Largest spectral radius of the frozen predictor over a grid of the box: the lattice of
/// [`SchedBox::grid`] (`per_dim` points per signal, capped at [`MAX_GRID_POINTS`]).
///
/// The lattice is not visited point by point: every [`CLIMB_STRIDE`]-th point of it (edges
/// included) is evaluated, and from the best [`CLIMB_STARTS`] of those a steepest ascent
/// over the lattice's neighbours (all 3^s - 1 of them) climbs to a lattice maximum. The
/// answer is a lattice point's value like the dense sweep's, and the same whenever the
/// largest value lies on a hill the coarse lattice sees (the spectral radius is continuous
/// in mu); [`max_predictor_radius_dense`] is the sweep of every point it is checked against.
pub fn max_predictor_radius(model: &LpvSs, sbox: &SchedBox, per_dim: usize) -> f64 {
    let mut fam = PredictorFamily::new(model);
    let s = sbox.dim();
    if s == 0 {
        return fam.rho(&[1.0]);
    }
    let g = lattice_side(s, per_dim);
    let coarse: Vec<usize> = (0..g)
        .step_by(CLIMB_STRIDE)
        .chain(((g - 1) % CLIMB_STRIDE != 0).then_some(g - 1))
        .collect();
    let mut mu = vec![1.0; s + 1];
    let mut eval = |idx: &[usize], fam: &mut PredictorFamily| {
        for j in 0..s {
            let t = idx[j] as f64 / (g - 1) as f64;
            mu[j + 1] = sbox.lo[j] + t * (sbox.hi[j] - sbox.lo[j]);
        }
        fam.rho(&mu)
    };
    // the coarse lattice, best first
    let mut best: Vec<(f64, Vec<usize>)> = Vec::new();
    let mut idx = vec![0; s];
    for mut c in 0..coarse.len().pow(s as u32) {
        for v in idx.iter_mut() {
            *v = coarse[c % coarse.len()];
            c /= coarse.len();
        }
        let r = eval(&idx, &mut fam);
        best.push((if r.is_nan() { f64::NEG_INFINITY } else { r }, idx.clone()));
    }
    best.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut worst = best[0].0.max(0.0);
    let mut seen = std::collections::HashMap::new();
    for (r0, start) in best.into_iter().take(CLIMB_STARTS) {
        let (mut here, mut at) = (r0, start);
        loop {
            let mut step: Option<(f64, Vec<usize>)> = None;
            for code in 0..3usize.pow(s as u32) {
                let mut nb = at.clone();
                let mut c = code;
                let mut moved = false;
                let mut inside = true;
                for v in nb.iter_mut() {
                    match c % 3 {
                        1 if *v + 1 < g => *v += 1,
                        2 if *v > 0 => *v -= 1,
                        0 => {}
                        _ => inside = false,
                    }
                    moved |= c % 3 != 0;
                    c /= 3;
                }
                if !moved || !inside {
                    continue;
                }
                let r = *seen
                    .entry(nb.clone())
                    .or_insert_with(|| eval(&nb, &mut fam));
                let r = if r.is_nan() { f64::NEG_INFINITY } else { r };
                if r > step.as_ref().map_or(here, |b| b.0) {
                    step = Some((r, nb));
                }
            }
            match step {
                Some((r, nb)) => (here, at) = (r, nb),
                None => break,
            }
        }
        worst = worst.max(here);
    }
    worst
}

/// The dense sweep [`max_predictor_radius`] replaces: every point of the lattice.
pub fn max_predictor_radius_dense(model: &LpvSs, sbox: &SchedBox, per_dim: usize) -> f64 {
    let mut fam = PredictorFamily::new(model);
    let s = sbox.dim();
    if s == 0 {
        return fam.rho(&[1.0]);
    }
    let g = lattice_side(s, per_dim);
    let mut mu = vec![1.0; s + 1];
    let mut worst: f64 = 0.0;
    for mut idx in 0..g.pow(s as u32) {
        for j in 0..s {
            let t = (idx % g) as f64 / (g - 1) as f64;
            idx /= g;
            mu[j + 1] = sbox.lo[j] + t * (sbox.hi[j] - sbox.lo[j]);
        }
        worst = worst.max(fam.rho(&mu));
    }
    worst
}

/// Points per signal of the lattice [`SchedBox::grid`] builds for `per_dim`.
fn lattice_side(s: usize, per_dim: usize) -> usize {
    let mut g = per_dim.max(2);
    while g.saturating_pow(s as u32) > MAX_GRID_POINTS && g > 2 {
        g -= 1;
    }
    g
}

/// Lattice stride of the first pass of [`max_predictor_radius`].
pub const CLIMB_STRIDE: usize = 4;

/// Coarse points [`max_predictor_radius`] climbs from.
pub const CLIMB_STARTS: usize = 3;

/// The frozen-scheduling stability region of the predictor along one scheduling signal.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    /// The signal's name.
    pub signal: String,
    /// The signal's index among the scheduling signals (0-based).
    pub index: usize,
    /// Where the other signals are held (their means) and where the search starts (this
    /// signal's mean).
    pub reference: Vec<f64>,
    /// The interval of this signal containing its reference over which the spectral radius
    /// of A(mu) - K(mu) C is below 1; `None` when the predictor is unstable at the reference.
    pub interval: Option<(f64, f64)>,
    /// Whether the interval reached the edge of the search window (lower, upper): the
    /// region extends at least that far.
    pub open: (bool, bool),
    /// The operating interval of this signal (the box).
    pub operating: (f64, f64),
    /// The operating interval lies inside the stability interval.
    pub covers_operating: bool,
}

impl Region {
    /// As JSON.
    pub fn to_json(&self) -> Value {
        json!({
            "signal": self.signal,
            "reference": self.reference,
            "stable_interval": self.interval.map(|(a, b)| vec![a, b]),
            "open_ended": [self.open.0, self.open.1],
            "operating_interval": [self.operating.0, self.operating.1],
            "covers_operating_interval": self.covers_operating,
        })
    }

    /// One line of text, e.g. `p1 in [-2.71, 3.69] (operating [-0.80, 1.20]: stable)`.
    pub fn describe(&self) -> String {
        let op = format!("[{:.2}, {:.2}]", self.operating.0, self.operating.1);
        match self.interval {
            None => format!(
                "{}: unstable at the reference {:.3} (operating {op}: NOT stable)",
                self.signal,
                self.reference_value()
            ),
            Some((a, b)) => format!(
                "{} in [{}{a:.2}, {b:.2}{}] (operating {op}: {})",
                self.signal,
                if self.open.0 { "<=" } else { "" },
                if self.open.1 { "+" } else { "" },
                if self.covers_operating {
                    "stable"
                } else {
                    "NOT stable"
                }
            ),
        }
    }

    fn reference_value(&self) -> f64 {
        self.reference.get(self.index).copied().unwrap_or(0.0)
    }
}

/// For each scheduling signal j (the others at `reference`), the interval around
/// `reference[j]` where the frozen predictor is stable (spectral radius < 1), searched over
/// the operating interval widened by `widen` times its width on each side (at least 1),
/// with a step of 1/200 of the operating width where the radius is near 1 (up to
/// [`MARCH_GROWTH`] times that where it is well below 1 and not rising fast) and the edges
/// refined by bisection to 1e-6.
pub fn stability_regions(
    model: &LpvSs,
    sbox: &SchedBox,
    reference: &[f64],
    widen: f64,
) -> Vec<Region> {
    let s = sbox.dim();
    (0..s)
        .map(|j| {
            let (lo, hi) = (sbox.lo[j], sbox.hi[j]);
            let w = (hi - lo).abs().max(1e-3);
            let (wlo, whi) = (
                lo.min(reference[j]) - widen.max(1.0) * w,
                hi.max(reference[j]) + widen.max(1.0) * w,
            );
            let fam = std::cell::RefCell::new(PredictorFamily::new(model));
            let rho = |v: f64| {
                let mut mu = vec![1.0; s + 1];
                for i in 0..s {
                    mu[i + 1] = if i == j { v } else { reference[i] };
                }
                fam.borrow_mut().rho(&mu)
            };
            let stable = |v: f64| rho(v) < 1.0;
            let v0 = reference[j];
            let mut region = Region {
                signal: sbox
                    .names
                    .get(j)
                    .cloned()
                    .unwrap_or_else(|| format!("p{}", j + 1)),
                index: j,
                reference: reference.to_vec(),
                interval: None,
                open: (false, false),
                operating: (lo, hi),
                covers_operating: false,
            };
            if !stable(v0) {
                return region;
            }
            let step = w / 200.0;
            let bisect = |mut good: f64, mut bad: f64| -> (f64, bool) {
                while (good - bad).abs() > 1e-6 * (1.0 + good.abs()) {
                    let mid = 0.5 * (good + bad);
                    if stable(mid) {
                        good = mid;
                    } else {
                        bad = mid;
                    }
                }
                (good, false)
            };
            // March out from the reference. Where the radius is well below 1 and not rising
            // fast the step grows (up to MARCH_GROWTH fine steps), to half the distance at
            // which the last two values extrapolate to 1; near the edge it is the fine step.
            let edge = |dir: f64, limit: f64| -> (f64, bool) {
                let mut inside = v0;
                let mut r_in = rho(v0);
                let mut slope = 0.0f64;
                loop {
                    let room = if slope > 0.0 {
                        0.5 * (1.0 - r_in) / slope
                    } else {
                        f64::INFINITY
                    };
                    let h = room.clamp(step, MARCH_GROWTH * step);
                    let h = if 1.0 - r_in < MARCH_NEAR { step } else { h };
                    let next = inside + dir * h;
                    if (dir > 0.0 && next > limit) || (dir < 0.0 && next < limit) {
                        return if stable(limit) {
                            (limit, true)
                        } else {
                            bisect(inside, limit)
                        };
                    }
                    let r_next = rho(next);
                    if !stable_value(r_next) {
                        return bisect(inside, next);
                    }
                    slope = (r_next - r_in) / h;
                    inside = next;
                    r_in = r_next;
                }
            };
            let (a, oa) = edge(-1.0, wlo);
            let (b, ob) = edge(1.0, whi);
            region.interval = Some((a, b));
            region.open = (oa, ob);
            region.covers_operating = a <= lo && b >= hi;
            region
        })
        .collect()
}

/// A spectral radius that counts as stable (below 1; NaN is not).
fn stable_value(r: f64) -> bool {
    r < 1.0
}

/// Largest step of the stability-region march, in fine steps (1/200 of the operating width).
pub const MARCH_GROWTH: f64 = 8.0;

/// Within this of a spectral radius of 1 the march takes fine steps only.
pub const MARCH_NEAR: f64 = 0.05;

/// What `lpvid pbsid --observer ...` asks for.
#[derive(Debug, Clone, Default)]
pub struct ObserverRequest {
    /// Design the H-infinity gains (otherwise keep the least-squares K).
    pub hinf: bool,
    /// `name=lo:hi` overrides of the scheduling box (default: the training data's range).
    pub ranges: Vec<String>,
    /// Design settings.
    pub opts: HinfOptions,
}

/// Where the stability-region search looks: the operating interval widened by this many
/// widths on each side.
pub const REGION_WIDEN: f64 = 10.0;

/// Grid points per scheduling signal for the largest predictor spectral radius reported.
pub const REPORT_GRID: usize = 201;

/// The observer step of a pbsid run: the model to write and what to record and print.
#[derive(Debug, Clone)]
pub struct ObserverStep {
    /// The model to write (the least-squares one, or A, B from (24) with the H-infinity K).
    pub model: LpvSs,
    /// "ls" or "hinf": the gain actually in `model`.
    pub used: &'static str,
    /// The record for the model's `fit.observer`.
    pub record: Value,
    /// The training data's scheduling (names, min, max, mean) for `fit.scheduling`.
    pub scheduling: Value,
    /// Stability region of the written model's predictor, one per scheduling signal.
    pub regions: Vec<Region>,
    /// Stability region of the least-squares predictor when the H-infinity gain replaced it.
    pub regions_ls: Option<Vec<Region>>,
    /// Largest spectral radius of the written predictor over a grid of the box.
    pub max_rho: f64,
    /// The box the regions and the design used.
    pub sbox: SchedBox,
    /// Human summary lines.
    pub lines: Vec<String>,
}

impl ObserverStep {
    /// Put the observer record, the scheduling statistics and the stability report into a
    /// model's `fit` object.
    pub fn annotate(&self, fit: &mut Value) {
        if let Value::Object(o) = fit {
            o.insert("observer".into(), self.record.clone());
            o.insert("scheduling".into(), self.scheduling.clone());
            o.insert("stability_region".into(), self.stability_json());
        }
    }

    /// The stability report as JSON.
    pub fn stability_json(&self) -> Value {
        json!({
            "predictor": "A(mu) - K(mu) C, frozen scheduling, others at their training mean",
            "regions": self.regions.iter().map(Region::to_json).collect::<Vec<_>>(),
            "regions_least_squares_gain": self.regions_ls.as_ref().map(|r| r.iter().map(Region::to_json).collect::<Vec<_>>()),
            "max_spectral_radius_over_box": self.max_rho,
            "box": box_json(&self.sbox),
        })
    }
}

/// Names, range and mean of the scheduling signals of `sig`.
pub fn scheduling_json(names: &[String], sig: &Signals) -> Value {
    let s = sig.p.ncols();
    let mean: Vec<f64> = (0..s).map(|j| sig.p.column(j).mean()).collect();
    let sbox = SchedBox::from_signals(names, sig);
    json!({"names": names, "min": sbox.lo, "max": sbox.hi, "mean": mean})
}

/// The observer step of `lpvid pbsid`: with `req.hinf`, design the H-infinity gains from the
/// fit's states (keeping the least-squares model, and saying why, if the design fails);
/// always report the stability region. Errors only for a malformed `--scheduling-range`.
///
/// `refined`: `ls_model`'s A, B, C, D were replaced by the output-error refinement after the
/// realization (`lpvid pbsid --refine`; the refinement runs first, then this step). Its
/// matrices are then kept and the states aligned to its basis ([`hinf_observer_refined`]);
/// otherwise A, B are re-estimated by (24) as in the paper ([`hinf_observer`]).
pub fn observer_step(
    ls_model: &LpvSs,
    states: Option<&DMatrix<f64>>,
    sig: &Signals,
    past: usize,
    names: &[String],
    req: &ObserverRequest,
    refined: bool,
) -> Result<ObserverStep, ObserverError> {
    let mut sbox = SchedBox::from_signals(names, sig);
    sbox.apply_ranges(&req.ranges)?;
    let reference: Vec<f64> = (0..sig.p.ncols()).map(|j| sig.p.column(j).mean()).collect();
    let mut lines = Vec::new();
    let (model, used, record, regions_ls) = if req.hinf {
        let attempt = match states {
            Some(x) if refined => hinf_observer_refined(ls_model, sig, x, past, &sbox, &req.opts),
            Some(x) => hinf_observer(ls_model, sig, x, past, &sbox, &req.opts),
            None => Err(ObserverError::NoStates),
        };
        match attempt {
            Ok((m, nc, d)) => {
                lines.push(format!(
                    "observer: H-infinity (LMI (30) over {} vertices, clarabel {} in {} iterations, {:.2} ms): gamma = {:.4e}, margin {:e}",
                    d.vertices.len(),
                    d.solver_status,
                    d.iterations,
                    d.solve_time * 1e3,
                    d.gamma,
                    d.margin
                ));
                lines.push(format!(
                    "  certificate (own eigenvalues): min eig(P - I) {:.2e}, min eig (30) at vertices {:.2e}, bounded-real matrix > 0 on {} grid points (min eig {:.2e}), predictor spectral radius <= {:.4} over the box",
                    d.certificate.min_eig_p_minus_i,
                    d.certificate.min_eig_vertex.iter().copied().fold(f64::INFINITY, f64::min),
                    d.certificate.grid_points,
                    d.certificate.min_eig_grid,
                    d.certificate.max_rho_grid
                ));
                lines.push(if refined {
                    "  model: A, B, C, D of the output-error refinement (--refine ran first), Q, S, R (25) from its residuals".to_string()
                } else {
                    "  model: A, B re-estimated by (24); --refine removes the finite-past-window bias before the design".to_string()
                });
                let mut rec = d.to_json(&sbox);
                if let Value::Object(o) = &mut rec {
                    o.insert("requested".into(), "hinf".into());
                    o.insert("used".into(), "hinf".into());
                    o.insert(
                        "noise_covariance".into(),
                        json!({"Q": rows(&nc.q), "S": rows(&nc.s), "R": rows(&nc.r), "columns": nc.columns,
                               "estimate": if refined {
                                   "eq. (25): residuals of the refined model over the state sequence (aligned to its basis), divided by columns - 1"
                               } else {
                                   "eq. (25): residuals of (24) over the state sequence, divided by columns - 1"
                               }}),
                    );
                    o.insert(
                        "model_matrices".into(),
                        if refined {
                            "A, B, C, D of the output-error refinement; K from (31)"
                        } else {
                            "A, B re-estimated by (24) without innovation regressors; C, D from the realization; K from (31)"
                        }
                        .into(),
                    );
                }
                let regions_ls = stability_regions(ls_model, &sbox, &reference, REGION_WIDEN);
                (m, "hinf", rec, Some(regions_ls))
            }
            Err(e) => {
                lines.push(format!(
                    "WARNING: {e}; keeping the least-squares observer gain (the model claims no gamma)"
                ));
                (
                    ls_model.clone(),
                    "ls",
                    json!({"requested": "hinf", "used": "ls", "error": e.to_string(), "scheduling_box": box_json(&sbox)}),
                    None,
                )
            }
        }
    } else {
        lines.push(LS_LINE.into());
        (
            ls_model.clone(),
            "ls",
            json!({"requested": "ls", "used": "ls"}),
            None,
        )
    };
    let scheduling = scheduling_json(names, sig);
    Ok(finish_step(
        model, used, record, regions_ls, sbox, &reference, lines, scheduling,
    ))
}

/// The summary line of the least-squares observer.
const LS_LINE: &str = "observer: least-squares K (eq. (6)-(7) with the innovation estimates)";

/// The observer step of a fit whose data were streamed, not kept (`lpvid pbsid` in constant
/// memory): the least-squares K only (the H-infinity design needs the state sequence), the
/// box from the data's range `lo`..`hi` of each scheduling signal (then `req.ranges`), the
/// others held at their `mean`.
pub fn observer_step_streamed(
    ls_model: &LpvSs,
    names: &[String],
    lo: &[f64],
    hi: &[f64],
    mean: &[f64],
    req: &ObserverRequest,
) -> Result<ObserverStep, ObserverError> {
    if req.hinf {
        return Err(ObserverError::NoStates);
    }
    let mut sbox = SchedBox {
        names: names.to_vec(),
        lo: lo.to_vec(),
        hi: hi.to_vec(),
        source: vec!["data".into(); lo.len()],
    };
    let scheduling = json!({"names": names, "min": sbox.lo, "max": sbox.hi, "mean": mean});
    sbox.apply_ranges(&req.ranges)?;
    Ok(finish_step(
        ls_model.clone(),
        "ls",
        json!({"requested": "ls", "used": "ls"}),
        None,
        sbox,
        mean,
        vec![LS_LINE.into()],
        scheduling,
    ))
}

/// The stability report and summary lines common to every observer step.
#[allow(clippy::too_many_arguments)]
fn finish_step(
    model: LpvSs,
    used: &'static str,
    record: Value,
    regions_ls: Option<Vec<Region>>,
    sbox: SchedBox,
    reference: &[f64],
    mut lines: Vec<String>,
    scheduling: Value,
) -> ObserverStep {
    // the regions and the box maximum are independent: with two or more scheduling signals
    // (a lattice of 21^s points, a millisecond) and a core to spare, side by side (the same
    // computations either way)
    let (regions, max_rho) = if sbox.lo.len() >= 2 && crate::linalg::spare_core() {
        std::thread::scope(|sc| {
            let rho = sc.spawn(|| max_predictor_radius(&model, &sbox, REPORT_GRID));
            let regions = stability_regions(&model, &sbox, reference, REGION_WIDEN);
            let rho = rho.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
            (regions, rho)
        })
    } else {
        (
            stability_regions(&model, &sbox, reference, REGION_WIDEN),
            max_predictor_radius(&model, &sbox, REPORT_GRID),
        )
    };
    if !regions.is_empty() {
        lines.push(format!(
            "stability region of the predictor A(mu) - K(mu) C (others at their mean): max spectral radius {max_rho:.4} over the box"
        ));
        for r in &regions {
            lines.push(format!("  {}", r.describe()));
        }
        if let Some(rl) = &regions_ls {
            lines.push("  with the least-squares gain instead:".into());
            for r in rl {
                lines.push(format!("    {}", r.describe()));
            }
        }
    } else {
        lines.push(format!(
            "predictor A - K C (no scheduling): spectral radius {max_rho:.4}"
        ));
    }
    ObserverStep {
        model,
        used,
        record,
        scheduling,
        regions,
        regions_ls,
        max_rho,
        sbox,
        lines,
    }
}

/// The report of `lpvid stability`.
#[derive(Debug, Clone)]
pub struct StabilityReport {
    /// The box searched around and reported on.
    pub sbox: SchedBox,
    /// Where the other signals are held.
    pub reference: Vec<f64>,
    /// Where the reference came from.
    pub reference_source: String,
    /// One region per scheduling signal.
    pub regions: Vec<Region>,
    /// Largest spectral radius of the predictor over a grid of the box.
    pub max_rho: f64,
}

impl StabilityReport {
    /// As JSON.
    pub fn to_json(&self) -> Value {
        json!({
            "predictor": "A(mu) - K(mu) C(mu), frozen scheduling",
            "reference": self.reference,
            "reference_source": self.reference_source,
            "box": box_json(&self.sbox),
            "regions": self.regions.iter().map(Region::to_json).collect::<Vec<_>>(),
            "max_spectral_radius_over_box": self.max_rho,
            "stable_over_box": self.max_rho < 1.0,
        })
    }
}

fn f64_list(v: Option<&Value>) -> Option<Vec<f64>> {
    v?.as_array()?.iter().map(Value::as_f64).collect()
}

/// Stability region of a model's predictor: the box from `data` (its range), else the
/// model's recorded training range (`fit.scheduling`), then `ranges` overrides; the other
/// signals held at the data's mean, else the recorded training mean.
pub fn stability_report(
    model: &LpvSs,
    names: &[String],
    fit: &Value,
    data: Option<&Signals>,
    ranges: &[String],
) -> Result<StabilityReport, ObserverError> {
    model.validate().map_err(ObserverError::Shape)?;
    let s = model.m() - 1;
    if names.len() != s {
        return Err(ObserverError::SchedulingNames {
            signals: s,
            names: names.len(),
        });
    }
    let rec = fit.get("scheduling");
    let (mut sbox, reference, reference_source) = match data {
        Some(sig) => (
            SchedBox::from_signals(names, sig),
            (0..s).map(|j| sig.p.column(j).mean()).collect::<Vec<_>>(),
            "data mean".to_string(),
        ),
        None => {
            let lo = f64_list(rec.and_then(|r| r.get("min")));
            let hi = f64_list(rec.and_then(|r| r.get("max")));
            let mean = f64_list(rec.and_then(|r| r.get("mean")));
            let have = |v: &Option<Vec<f64>>| v.as_ref().is_some_and(|v| v.len() == s);
            let (lo, hi, src) = if have(&lo) && have(&hi) {
                (lo.unwrap_or_default(), hi.unwrap_or_default(), "data")
            } else {
                (vec![f64::NAN; s], vec![f64::NAN; s], "unknown")
            };
            let (reference, rs) = if have(&mean) {
                (mean.unwrap_or_default(), "training mean (model fit record)")
            } else {
                (
                    (0..s)
                        .map(|j| {
                            if lo[j].is_finite() {
                                0.5 * (lo[j] + hi[j])
                            } else {
                                0.0
                            }
                        })
                        .collect(),
                    "box centre",
                )
            };
            (
                SchedBox {
                    names: names.to_vec(),
                    lo,
                    hi,
                    source: vec![src.into(); s],
                },
                reference,
                rs.to_string(),
            )
        }
    };
    sbox.apply_ranges(ranges)?;
    if let Some(j) = (0..s).find(|&j| !(sbox.lo[j].is_finite() && sbox.hi[j].is_finite())) {
        return Err(ObserverError::NoOperatingRange(names[j].clone()));
    }
    let mut reference = reference;
    for (j, r) in reference.iter_mut().enumerate() {
        if !r.is_finite() {
            *r = 0.5 * (sbox.lo[j] + sbox.hi[j]);
        }
    }
    let regions = stability_regions(model, &sbox, &reference, REGION_WIDEN);
    let max_rho = max_predictor_radius(model, &sbox, REPORT_GRID);
    Ok(StabilityReport {
        sbox,
        reference,
        reference_source,
        regions,
        max_rho,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fine-step march (1/200 of the operating width, no growth) the adaptive one of
    /// [`stability_regions`] replaced: the first unstable fine step, bisected.
    fn fine_march_edge(
        model: &LpvSs,
        reference: &[f64],
        j: usize,
        dir: f64,
        step: f64,
        limit: f64,
    ) -> f64 {
        let s = reference.len();
        let mut fam = PredictorFamily::new(model);
        let mut stable = |v: f64| {
            let mut mu = vec![1.0; s + 1];
            for i in 0..s {
                mu[i + 1] = if i == j { v } else { reference[i] };
            }
            fam.rho(&mu) < 1.0
        };
        let mut inside = reference[j];
        let (mut good, mut bad) = loop {
            let next = inside + dir * step;
            if (dir > 0.0 && next > limit) || (dir < 0.0 && next < limit) {
                if stable(limit) {
                    return limit;
                }
                break (inside, limit);
            }
            if !stable(next) {
                break (inside, next);
            }
            inside = next;
        };
        while (good - bad).abs() > 1e-6 * (1.0 + good.abs()) {
            let mid = 0.5 * (good + bad);
            if stable(mid) {
                good = mid;
            } else {
                bad = mid;
            }
        }
        good
    }

    #[test]
    fn fast_stability_report_equals_the_dense_one_on_fitted_models() {
        use crate::pbsid::{fit, PbsidOptions};
        use crate::systems;
        let mut cases = 0;
        for seed in 0..6u64 {
            for (exp, p) in [
                (systems::b1(600, 0.05, 7100 + seed), 2),
                (systems::b2(200, 25.0, 7200 + seed), 4),
                (systems::b3(250, 7300 + seed), 3),
            ] {
                let Ok(f) = fit(&exp.train, &PbsidOptions::new(p)) else {
                    continue;
                };
                let names: Vec<String> = (0..exp.train.p.ncols())
                    .map(|j| format!("p{}", j + 1))
                    .collect();
                let sbox = SchedBox::from_signals(&names, &exp.train);
                let reference: Vec<f64> = (0..exp.train.p.ncols())
                    .map(|j| exp.train.p.column(j).mean())
                    .collect();
                for per_dim in [REPORT_GRID, 31] {
                    let fast = max_predictor_radius(&f.model, &sbox, per_dim);
                    let dense = max_predictor_radius_dense(&f.model, &sbox, per_dim);
                    assert!(
                        (fast - dense).abs() <= 1e-12 * dense.max(1.0),
                        "{} seed {seed}: {fast} vs {dense}",
                        exp.name
                    );
                    // and the old per-point nalgebra evaluation on the lattice agrees
                    if per_dim == 31 {
                        let slow = sbox
                            .grid(per_dim)
                            .iter()
                            .map(|mu| schur_spectral_radius(&predictor_matrix(&f.model, mu)))
                            .fold(0.0, f64::max);
                        assert!(
                            (slow - dense).abs() <= 1e-10 * slow.max(1.0),
                            "{slow} {dense}"
                        );
                    }
                }
                for r in stability_regions(&f.model, &sbox, &reference, REGION_WIDEN) {
                    let j = r.index;
                    let w = (sbox.hi[j] - sbox.lo[j]).abs().max(1e-3);
                    let wlo = sbox.lo[j].min(reference[j]) - REGION_WIDEN * w;
                    let whi = sbox.hi[j].max(reference[j]) + REGION_WIDEN * w;
                    let Some((a, b)) = r.interval else { continue };
                    let a0 = fine_march_edge(&f.model, &reference, j, -1.0, w / 200.0, wlo);
                    let b0 = fine_march_edge(&f.model, &reference, j, 1.0, w / 200.0, whi);
                    let tol = 4e-6 * (1.0 + a0.abs().max(b0.abs()));
                    assert!(
                        (a - a0).abs() <= tol && (b - b0).abs() <= tol,
                        "{} seed {seed} p{}: [{a}, {b}] vs fine march [{a0}, {b0}]",
                        exp.name,
                        j + 1
                    );
                    cases += 1;
                }
            }
        }
        assert!(cases >= 30, "{cases}");
    }

    fn two() -> SchedBox {
        SchedBox {
            names: vec!["p1".into(), "p2".into()],
            lo: vec![0.0, -1.0],
            hi: vec![1.0, 2.0],
            source: vec!["data".into(); 2],
        }
    }

    #[test]
    fn box_vertices_grid_and_ranges() {
        let b = two();
        let v = b.vertices();
        assert_eq!(v.len(), 4);
        for corner in [[0.0, -1.0], [1.0, -1.0], [0.0, 2.0], [1.0, 2.0]] {
            assert!(v
                .iter()
                .any(|m| m[0] == 1.0 && m[1] == corner[0] && m[2] == corner[1]));
        }
        let g = b.grid(5);
        assert_eq!(g.len(), 25);
        assert!(g
            .iter()
            .all(|m| (0.0..=1.0).contains(&m[1]) && (-1.0..=2.0).contains(&m[2])));
        // a degenerate interval halves the vertices
        let mut d = two();
        d.lo[1] = 0.5;
        d.hi[1] = 0.5;
        assert_eq!(d.vertices().len(), 2);
        // overrides
        let mut b = two();
        b.apply_ranges(&["p2=-0.8:1.2,p1=3:4".into()]).unwrap();
        assert_eq!(
            (b.lo.clone(), b.hi.clone()),
            (vec![3.0, -0.8], vec![4.0, 1.2])
        );
        assert_eq!(b.source, vec!["--scheduling-range", "--scheduling-range"]);
        for bad in ["p3=0:1", "p1=1:0", "p1=0", "p1", "p1=x:1", "p1=0:inf"] {
            assert!(two().apply_ranges(&[bad.into()]).is_err(), "{bad}");
        }
        assert!(matches!(
            two().apply_ranges(&["p3=0:1".into()]),
            Err(ObserverError::RangeSignal { name, .. }) if name == "p3"
        ));
        assert_eq!(
            two().apply_ranges(&["p1=1:0".into()]),
            Err(ObserverError::RangeOrder("p1=1:0".into()))
        );
        assert!(matches!(
            two().apply_ranges(&["p1".into()]),
            Err(ObserverError::RangeSyntax(_))
        ));
        // LTI: one vertex, the constant
        let e = SchedBox {
            names: vec![],
            lo: vec![],
            hi: vec![],
            source: vec![],
        };
        assert_eq!(e.vertices(), vec![DVector::from_element(1, 1.0)]);
    }

    #[test]
    fn triangle_variable_order_is_clarabels() {
        // upper triangle, column-major: (0,0), (0,1), (1,1), (0,2), (1,2), (2,2)
        let order: Vec<(usize, usize)> =
            (0..3).flat_map(|j| (0..=j).map(move |i| (i, j))).collect();
        for (k, (i, j)) in order.into_iter().enumerate() {
            assert_eq!(pvar(i, j), k);
            assert_eq!(pvar(j, i), k);
        }
    }

    #[test]
    fn lti_design_is_certified_and_regions_follow_the_predictor() {
        // x+ = 1.1 x + u + w, y = x + v: unstable plant, stabilising observer gain needed
        let m = LpvSs {
            a: vec![DMatrix::from_element(1, 1, 1.1)],
            b: vec![DMatrix::from_element(1, 1, 1.0)],
            k: vec![DMatrix::zeros(1, 1)],
            c: vec![DMatrix::from_element(1, 1, 1.0)],
            d: vec![DMatrix::zeros(1, 1)],
        };
        let nc = NoiseCov {
            q: DMatrix::from_element(1, 1, 0.5),
            s: DMatrix::zeros(1, 1),
            r: DMatrix::from_element(1, 1, 1.0),
            columns: 0,
        };
        let b = SchedBox {
            names: vec![],
            lo: vec![],
            hi: vec![],
            source: vec![],
        };
        let d = design_hinf(&m, &nc, &b, &HinfOptions::default()).unwrap();
        assert!(d.certificate.ok());
        let mut mk = m.clone();
        mk.k = d.k.clone();
        assert!(max_predictor_radius(&mk, &b, 3) < 1.0);
        assert!(max_predictor_radius(&m, &b, 3) > 1.0);
        // scaling the noise leaves P and K unchanged and scales gamma^2 (the normalisation)
        let nc2 = NoiseCov {
            q: &nc.q * 1e-6,
            s: &nc.s * 1e-6,
            r: &nc.r * 1e-6,
            columns: 0,
        };
        let d2 = design_hinf(&m, &nc2, &b, &HinfOptions::default()).unwrap();
        assert!((d2.k[0][(0, 0)] - d.k[0][(0, 0)]).abs() < 1e-9);
        assert!((d2.gamma / d.gamma - 1e-3).abs() < 1e-9);
        // a scheduled A: the region shrinks where the predictor's pole leaves the circle
        let ms = LpvSs {
            a: vec![
                DMatrix::from_element(1, 1, 0.2),
                DMatrix::from_element(1, 1, 0.5),
            ],
            b: vec![DMatrix::zeros(1, 1); 2],
            k: vec![DMatrix::zeros(1, 1); 2],
            c: vec![DMatrix::from_element(1, 1, 1.0)],
            d: vec![DMatrix::zeros(1, 1)],
        };
        let sb = SchedBox {
            names: vec!["p1".into()],
            lo: vec![-1.0],
            hi: vec![1.0],
            source: vec!["data".into()],
        };
        // |0.2 + 0.5 p| < 1  <=>  p in (-2.4, 1.6)
        let r = &stability_regions(&ms, &sb, &[0.0], 10.0)[0];
        let (lo, hi) = r.interval.unwrap();
        assert!(
            (lo + 2.4).abs() < 1e-5 && (hi - 1.6).abs() < 1e-5,
            "{lo} {hi}"
        );
        assert!(r.covers_operating && r.open == (false, false));
    }
}
