//! Sparse estimation on statistics: ONE covariance-update coordinate-descent engine
//! (glmnet style) with two penalties, allocation-free.
//!
//! Problem (Theta is l x q, row-major; G = sum phi phi^T is q x q, C = sum y phi^T is l x q):
//!
//! minimise 1/2 tr(Theta G Theta^T) - tr(Theta C^T) + lambda sum_j w_j pen(Theta[:, j])
//!
//! - [`Penalty::L1`]: pen = sum_o |Theta[o, j]| — the BC-IV-LASSO cost (10) of the BC-IV
//!   paper with (G, C) = (H, g^T) of [`crate::bciv::BcivStats::normal_equations`]
//!   (objective = (10)/2 + const, so the paper's lambda is 2 lambda here);
//! - [`Penalty::Group`]: pen = ||Theta[:, j]||_2 — the l2,1 norm of [C K^p, D] of problem (33)
//!   of the sparse-PBSID paper in its Lagrangian form (one group = one regressor column shared
//!   by the l outputs), with (G, C) the [z; u] block and the y-row of the PBSID statistics.
//!   The block Hessian of a group is G_jj I_l, so each block step is an exact group
//!   soft-threshold: no inner iterations.
//!
//! For l = 1 the two penalties coincide. Weights w_j >= 0 (adaptive Lasso; w_j = 0:
//! unpenalised, w_j = +inf: excluded, fixed at 0); to penalise standardised coefficients use
//! w_j = sqrt(G_jj / N).
//!
//! **Algorithm.** Covariance updates: the gradient residual R = C - Theta G (l x q) is kept
//! up to date after each coordinate move (O(l q) per move), so the data are never touched.
//! Sweeps run over the active set (columns that are non-zero or unpenalised); when they
//! settle a full sweep over all columns follows (the KKT pass); it either leaves the active
//! set unchanged (done) or adds the violators and the active sweeps resume.
//!
//! **Stopping rule** (max-change, as glmnet): a sweep has settled when
//! max_j G_jj ||Delta Theta[:, j]||^2 <= tol * s0, with s0 = max_j ||C[:, j]||^2 / G_jj the
//! largest decrease of the objective one column can achieve from zero (so `tol` is relative
//! and scale-free; default 1e-14 in f64, 1.4e-9 in f32). The KKT violation of the final
//! point, relative to max_j ||C[:, j]||, is reported in [`Fit::kkt`] as a certificate.
//!
//! **Indefinite G.** The BC-IV cost (10) is a least-squares cost in Psi, so its G = Psi^T Psi
//! is positive semidefinite by construction; a "bias-corrected Gram" Phi^T Phi - Psi_LS of a
//! least-squares correction may be indefinite. The coordinate step needs G_jj > 0: a column
//! with |G_jj| <= q eps max_k G_kk is *flat* and fixed at zero (for a PSD G its whole row is
//! zero, so this is exact); G_jj < 0 makes the objective unbounded below along that axis and
//! is rejected with [`Error::Singular`]. With positive diagonals but an indefinite G, every
//! coordinate step still decreases the objective; if it runs away to infinity the solve
//! stops with [`Error::NoConvergence`] and Theta is reset to zero.

use core::ops::ControlFlow;

use crate::error::{check_vec, Error, Field};
use crate::real::{first_non_finite, Real};
use crate::stats::Gram;

/// G_jj, or [`Error::NonFinite`] (index j q + j of the dense G) when it is NaN or infinite.
fn finite_diagonal<T: Real, M: SymMatrix<T> + ?Sized>(g: &M, j: usize) -> Result<T, Error> {
    let v = g.get(j, j);
    if v.is_finite() {
        Ok(v)
    } else {
        Err(Error::NonFinite {
            field: Field::Regressor,
            index: j * g.dim() + j,
        })
    }
}

/// A symmetric q x q matrix the engine reads entry by entry.
pub trait SymMatrix<T> {
    /// Dimension q.
    fn dim(&self) -> usize;
    /// Entry (i, j), i, j < dim.
    fn get(&self, i: usize, j: usize) -> T;
    /// `out[k] += alpha * G[j, k]` for k < dim: the update a coordinate step makes. The
    /// default reads entries one by one; a lazily evaluated G overrides it to fetch column
    /// j once and run a vectorised loop.
    fn add_scaled_column(&self, j: usize, alpha: T, out: &mut [T])
    where
        T: Real,
    {
        for (k, o) in out.iter_mut().enumerate() {
            *o += alpha * self.get(j, k);
        }
    }
}

/// A dense symmetric matrix, row-major n x n (e.g. the H of the BC-IV normal equations).
#[derive(Debug, Clone, Copy)]
pub struct Dense<'a, T> {
    data: &'a [T],
    n: usize,
}

impl<'a, T: Real> Dense<'a, T> {
    /// Wrap `data` (n x n, row-major; only symmetry of use is assumed, not checked).
    pub fn new(data: &'a [T], n: usize) -> Result<Self, Error> {
        let need = n.checked_mul(n).ok_or(Error::Overflow)?;
        if data.len() != need {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: need,
                got: data.len(),
            });
        }
        Ok(Dense { data, n })
    }
}

impl<T: Real> SymMatrix<T> for Dense<'_, T> {
    fn dim(&self) -> usize {
        self.n
    }
    #[inline(always)]
    fn get(&self, i: usize, j: usize) -> T {
        self.data[i * self.n + j]
    }
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> SymMatrix<T> for Gram<T, S> {
    fn dim(&self) -> usize {
        Gram::dim(self)
    }
    #[inline(always)]
    fn get(&self, i: usize, j: usize) -> T {
        Gram::get(self, i, j)
    }
}

/// The leading n x n block of a symmetric matrix: the regressor block of the second moments
/// of w = [phi; y] (e.g. the [z; u] block of [`crate::stats::PbsidStats`]).
#[derive(Debug, Clone, Copy)]
pub struct Leading<'a, M: ?Sized> {
    inner: &'a M,
    n: usize,
}

impl<'a, M: ?Sized> Leading<'a, M> {
    /// The leading `n` x `n` block of `inner`.
    pub fn new<T>(inner: &'a M, n: usize) -> Result<Self, Error>
    where
        M: SymMatrix<T>,
    {
        if n > inner.dim() {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: inner.dim(),
                got: n,
            });
        }
        Ok(Leading { inner, n })
    }
}

impl<T, M: SymMatrix<T> + ?Sized> SymMatrix<T> for Leading<'_, M> {
    fn dim(&self) -> usize {
        self.n
    }
    #[inline(always)]
    fn get(&self, i: usize, j: usize) -> T {
        self.inner.get(i, j)
    }
}

/// Copy the cross term C (l x q, row-major) out of second moments of w = [phi (q); y (l); ..]:
/// C[o, j] = sum y_o phi_j = entry (q + o, j).
pub fn cross_from<T: Real, M: SymMatrix<T> + ?Sized>(
    m: &M,
    q: usize,
    l: usize,
    out: &mut [T],
) -> Result<(), Error> {
    let need = q.checked_mul(l).ok_or(Error::Overflow)?;
    if out.len() != need {
        return Err(Error::Dimension {
            field: Field::Storage,
            expected: need,
            got: out.len(),
        });
    }
    if q + l > m.dim() {
        return Err(Error::Dimension {
            field: Field::Regressor,
            expected: m.dim(),
            got: q + l,
        });
    }
    for o in 0..l {
        for j in 0..q {
            out[o * q + j] = m.get(q + o, j);
        }
    }
    Ok(())
}

/// Which penalty: per entry (l1) or per column shared by the outputs (l2,1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Penalty {
    /// sum_{o,j} w_j |Theta[o, j]|: BC-IV-LASSO, cost (10) of the BC-IV paper.
    L1,
    /// sum_j w_j ||Theta[:, j]||_2: the l2,1 norm of problem (33) of the sparse-PBSID paper.
    Group,
}

/// A problem instance: the statistics (G, C), the number of outputs l, the penalty and the
/// optional weights. Nothing is copied.
#[derive(Debug, Clone, Copy)]
pub struct Problem<'a, T, M: ?Sized> {
    gram: &'a M,
    cross: &'a [T],
    l: usize,
    q: usize,
    weights: Option<&'a [T]>,
    penalty: Penalty,
}

impl<'a, T: Real, M: SymMatrix<T> + ?Sized> Problem<'a, T, M> {
    /// G (q x q), C (l x q row-major, finite), l outputs, the penalty; unit weights.
    pub fn new(gram: &'a M, cross: &'a [T], l: usize, penalty: Penalty) -> Result<Self, Error> {
        if l == 0 {
            return Err(Error::InvalidConfig("at least one output is needed"));
        }
        let q = gram.dim();
        check_vec(
            Field::Regressor,
            cross,
            q.checked_mul(l).ok_or(Error::Overflow)?,
        )?;
        Ok(Problem {
            gram,
            cross,
            l,
            q,
            weights: None,
            penalty,
        })
    }

    /// Per-column weights w_j (length q): >= 0, +inf excludes the column; NaN or negative
    /// values are rejected.
    pub fn with_weights(mut self, w: &'a [T]) -> Result<Self, Error> {
        if w.len() != self.q {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: self.q,
                got: w.len(),
            });
        }
        for (index, v) in w.iter().enumerate() {
            // +inf is allowed (excluded column), NaN is not
            match v.partial_cmp(&T::ZERO) {
                None => {
                    return Err(Error::NonFinite {
                        field: Field::Regressor,
                        index,
                    })
                }
                Some(core::cmp::Ordering::Less) => {
                    return Err(Error::InvalidConfig("weights must be >= 0"))
                }
                _ => {}
            }
        }
        self.weights = Some(w);
        Ok(self)
    }

    /// Number of regressor columns q.
    pub fn q(&self) -> usize {
        self.q
    }

    /// Number of outputs l.
    pub fn l(&self) -> usize {
        self.l
    }

    /// The penalty.
    pub fn penalty(&self) -> Penalty {
        self.penalty
    }

    #[inline(always)]
    fn w(&self, j: usize) -> T {
        match self.weights {
            Some(w) => w[j],
            None => T::ONE,
        }
    }
}

/// Solver settings (in the spirit of Clarabel's settings struct).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings<T> {
    /// Maximum number of sweeps (active or full) per lambda.
    pub max_iter: usize,
    /// Relative max-change tolerance (see the module documentation).
    pub tol: T,
    /// Number of points of the automatic lambda path.
    pub n_lambda: usize,
    /// lambda_min / lambda_max of the automatic path (geometric spacing).
    pub lambda_min_ratio: T,
}

impl<T: Real> Default for Settings<T> {
    fn default() -> Self {
        let eps2 = T::EPSILON * T::EPSILON;
        Settings {
            max_iter: 10_000,
            tol: T::of(1e-14).max(eps2 * T::of(1e5)),
            n_lambda: 100,
            lambda_min_ratio: T::of(1e-4),
        }
    }
}

/// Result of one path point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit<T> {
    /// Position on the path (0 for a single solve).
    pub index: usize,
    /// lambda of this point (the engine's scaling, see the module documentation).
    pub lambda: T,
    /// Sweeps used.
    pub iterations: usize,
    /// Whether the stopping rule was met within `max_iter` sweeps.
    pub converged: bool,
    /// Number of non-zero columns of Theta.
    pub active: usize,
    /// Largest violation of the optimality (KKT) conditions, relative to max_j ||C[:, j]||.
    pub kkt: T,
    /// Objective value 1/2 tr(Theta G Theta^T) - tr(Theta C^T) + lambda * penalty.
    pub objective: T,
}

/// Work values [`CoordinateDescent`] needs: (l + 1) q (the residual R and the active flags).
pub const fn work_len(l: usize, q: usize) -> usize {
    (l + 1) * q
}

/// Work values [`refit`] needs: q^2 + 2q.
pub const fn refit_work_len(q: usize) -> usize {
    q * q + 2 * q
}

/// Column classes fixed by the problem.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Class {
    Free,
    /// w_j = 0: always active.
    Unpenalised,
    /// w_j = +inf or a flat diagonal: fixed at zero.
    Fixed,
}

/// Scale information computed once per solve.
#[derive(Clone, Copy)]
struct Scale<T> {
    /// Tolerance threshold on max_j G_jj ||delta_j||^2.
    thresh: T,
    /// max_j ||C[:, j]|| (KKT normalisation).
    cmax: T,
    /// Flat-diagonal threshold.
    flat: T,
}

/// The covariance-update coordinate-descent engine over caller-provided work storage
/// (`[T; work_len(l, q)]` on the device, a `Vec` on the host). Never allocates.
///
/// Size: (l + 1) q values; B6 (q = 21, l = 1) 42 values.
#[derive(Debug, Clone)]
pub struct CoordinateDescent<T, S> {
    work: S,
    l: usize,
    q: usize,
    _t: core::marker::PhantomData<T>,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> CoordinateDescent<T, S> {
    /// An engine for l outputs and q columns over `work` (at least `work_len(l, q)` values).
    pub fn new(l: usize, q: usize, work: S) -> Result<Self, Error> {
        let need = (l.checked_add(1).ok_or(Error::Overflow)?)
            .checked_mul(q)
            .ok_or(Error::Overflow)?;
        if work.as_ref().len() < need {
            return Err(Error::Capacity {
                needed: need,
                capacity: work.as_ref().len(),
            });
        }
        if l == 0 {
            return Err(Error::InvalidConfig("at least one output is needed"));
        }
        Ok(CoordinateDescent {
            work,
            l,
            q,
            _t: core::marker::PhantomData,
        })
    }

    fn check<M: SymMatrix<T> + ?Sized>(
        &self,
        prob: &Problem<'_, T, M>,
        settings: &Settings<T>,
    ) -> Result<Scale<T>, Error> {
        if prob.l != self.l || prob.q != self.q {
            return Err(Error::Mismatch);
        }
        if settings.tol < T::ZERO || !settings.tol.is_finite() {
            return Err(Error::InvalidConfig("tol must be finite and >= 0"));
        }
        let q = self.q;
        let g = prob.gram;
        let mut dmax = T::ZERO;
        // O(q): only the diagonal is checked here, so a lazily evaluated G (large q, few
        // active columns) is never expanded; a non-finite off-diagonal entry makes Theta or
        // R non-finite and is reported as `NoConvergence` by the sweep that meets it.
        for i in 0..q {
            dmax = dmax.max(finite_diagonal(g, i)?.abs());
        }
        let flat = dmax * T::EPSILON * T::of(q as f64);
        let mut s0 = T::ZERO;
        let mut cmax = T::ZERO;
        for j in 0..q {
            let gjj = g.get(j, j);
            if gjj < -flat {
                return Err(Error::Singular);
            }
            let mut n2 = T::ZERO;
            for o in 0..self.l {
                let c = prob.cross[o * q + j];
                n2 += c * c;
            }
            cmax = cmax.max(n2.sqrt());
            if gjj > flat {
                s0 = s0.max(n2 / gjj);
            }
        }
        if !s0.is_finite() {
            return Err(Error::Overflow);
        }
        Ok(Scale {
            thresh: settings.tol * s0,
            cmax,
            flat,
        })
    }

    #[inline(always)]
    fn class<M: SymMatrix<T> + ?Sized>(prob: &Problem<'_, T, M>, sc: &Scale<T>, j: usize) -> Class {
        let w = prob.w(j);
        if !w.is_finite() || prob.gram.get(j, j) <= sc.flat {
            Class::Fixed
        } else if w == T::ZERO {
            Class::Unpenalised
        } else {
            Class::Free
        }
    }

    /// R = C - Theta G, with fixed columns of Theta zeroed first.
    fn init_residual<M: SymMatrix<T> + ?Sized>(
        &mut self,
        prob: &Problem<'_, T, M>,
        sc: &Scale<T>,
        theta: &mut [T],
    ) {
        let (l, q) = (self.l, self.q);
        for j in 0..q {
            if Self::class(prob, sc, j) == Class::Fixed {
                for o in 0..l {
                    theta[o * q + j] = T::ZERO;
                }
            }
        }
        let r = &mut self.work.as_mut()[..l * q];
        r.copy_from_slice(prob.cross);
        for o in 0..l {
            for j in 0..q {
                let t = theta[o * q + j];
                if t == T::ZERO {
                    continue;
                }
                prob.gram
                    .add_scaled_column(j, -t, &mut r[o * q..(o + 1) * q]);
            }
        }
    }

    /// Exact block step on column j; returns G_jj ||delta||^2. `thr` = lambda w_j.
    #[inline]
    fn step<M: SymMatrix<T> + ?Sized>(
        &mut self,
        prob: &Problem<'_, T, M>,
        j: usize,
        thr: T,
        theta: &mut [T],
    ) -> T {
        let (l, q) = (self.l, self.q);
        let g = prob.gram;
        let gjj = g.get(j, j);
        let r = &mut self.work.as_mut()[..l * q];
        let mut change = T::ZERO;
        let group_factor = match prob.penalty {
            Penalty::Group if l > 1 => {
                let mut n2 = T::ZERO;
                for o in 0..l {
                    let rho = r[o * q + j] + gjj * theta[o * q + j];
                    n2 += rho * rho;
                }
                let norm = n2.sqrt();
                Some(if norm > thr {
                    (T::ONE - thr / norm) / gjj
                } else {
                    T::ZERO
                })
            }
            _ => None,
        };
        for o in 0..l {
            let idx = o * q + j;
            let rho = r[idx] + gjj * theta[idx];
            let new = match group_factor {
                Some(f) => f * rho,
                None => {
                    if rho > thr {
                        (rho - thr) / gjj
                    } else if rho < -thr {
                        (rho + thr) / gjj
                    } else {
                        T::ZERO
                    }
                }
            };
            let delta = new - theta[idx];
            if delta != T::ZERO {
                theta[idx] = new;
                g.add_scaled_column(j, -delta, &mut r[o * q..(o + 1) * q]);
                change += gjj * delta * delta;
            }
        }
        change
    }

    /// Coordinate descent at `lam` (None: infinity, only unpenalised columns move) from the
    /// current theta/R. Returns (sweeps, converged).
    fn run<M: SymMatrix<T> + ?Sized>(
        &mut self,
        prob: &Problem<'_, T, M>,
        sc: &Scale<T>,
        lam: Option<T>,
        theta: &mut [T],
        settings: &Settings<T>,
    ) -> Result<(usize, bool), Error> {
        let (l, q) = (self.l, self.q);
        // active flags
        for j in 0..q {
            let cls = Self::class(prob, sc, j);
            let nz = (0..l).any(|o| theta[o * q + j] != T::ZERO);
            let movable = match (cls, lam) {
                (Class::Fixed, _) => false,
                (Class::Unpenalised, _) => true,
                (Class::Free, None) => false,
                (Class::Free, Some(_)) => nz,
            };
            self.work.as_mut()[l * q + j] = if movable { T::ONE } else { T::ZERO };
        }
        let mut sweeps = 0;
        loop {
            // active sweeps
            loop {
                if sweeps >= settings.max_iter {
                    return Ok((sweeps, false));
                }
                sweeps += 1;
                let mut dmax = T::ZERO;
                for j in 0..q {
                    if self.work.as_ref()[l * q + j] == T::ZERO {
                        continue;
                    }
                    let thr = match Self::class(prob, sc, j) {
                        Class::Unpenalised => T::ZERO,
                        _ => lam.unwrap_or(T::MAX) * prob.w(j),
                    };
                    dmax = dmax.max(self.step(prob, j, thr, theta));
                }
                if !dmax.is_finite() || first_non_finite(theta).is_some() {
                    for v in theta.iter_mut() {
                        *v = T::ZERO;
                    }
                    return Err(Error::NoConvergence);
                }
                if dmax <= sc.thresh {
                    break;
                }
            }
            // full (KKT) sweep over every column that may move at this lambda
            if sweeps >= settings.max_iter {
                return Ok((sweeps, false));
            }
            sweeps += 1;
            let mut dmax = T::ZERO;
            let mut added = 0usize;
            for j in 0..q {
                let cls = Self::class(prob, sc, j);
                let thr = match (cls, lam) {
                    (Class::Fixed, _) | (Class::Free, None) => continue,
                    (Class::Unpenalised, _) => T::ZERO,
                    (Class::Free, Some(lm)) => lm * prob.w(j),
                };
                dmax = dmax.max(self.step(prob, j, thr, theta));
                let nz = (0..l).any(|o| theta[o * q + j] != T::ZERO);
                if nz && self.work.as_ref()[l * q + j] == T::ZERO {
                    self.work.as_mut()[l * q + j] = T::ONE;
                    added += 1;
                }
            }
            if !dmax.is_finite()
                || first_non_finite(theta).is_some()
                || first_non_finite(&self.work.as_ref()[..l * q]).is_some()
            {
                for v in theta.iter_mut() {
                    *v = T::ZERO;
                }
                return Err(Error::NoConvergence);
            }
            if added == 0 && dmax <= sc.thresh {
                return Ok((sweeps, true));
            }
        }
    }

    /// KKT violation (relative) and objective at `lam` for the current theta/R.
    fn certificate<M: SymMatrix<T> + ?Sized>(
        &self,
        prob: &Problem<'_, T, M>,
        sc: &Scale<T>,
        lam: T,
        theta: &[T],
    ) -> (T, T, usize) {
        let (l, q) = (self.l, self.q);
        let r = &self.work.as_ref()[..l * q];
        let mut viol = T::ZERO;
        let mut pen = T::ZERO;
        let mut active = 0;
        let mut quad = T::ZERO;
        for (i, t) in theta.iter().enumerate() {
            quad += *t * (prob.cross[i] + r[i]);
        }
        for j in 0..q {
            let cls = Self::class(prob, sc, j);
            let thr = match cls {
                Class::Fixed => continue,
                Class::Unpenalised => T::ZERO,
                Class::Free => lam * prob.w(j),
            };
            let mut n2t = T::ZERO;
            for o in 0..l {
                let t = theta[o * q + j];
                n2t += t * t;
            }
            let nt = n2t.sqrt();
            if nt > T::ZERO {
                active += 1;
            }
            match prob.penalty {
                Penalty::Group => {
                    pen += prob.w(j) * nt;
                    let mut v2 = T::ZERO;
                    if nt > T::ZERO {
                        for o in 0..l {
                            let d = r[o * q + j] - thr * theta[o * q + j] / nt;
                            v2 += d * d;
                        }
                        viol = viol.max(v2.sqrt());
                    } else {
                        for o in 0..l {
                            v2 += r[o * q + j] * r[o * q + j];
                        }
                        viol = viol.max(v2.sqrt() - thr);
                    }
                }
                Penalty::L1 => {
                    for o in 0..l {
                        let t = theta[o * q + j];
                        let ro = r[o * q + j];
                        pen += prob.w(j) * t.abs();
                        let v = if t > T::ZERO {
                            (ro - thr).abs()
                        } else if t < T::ZERO {
                            (ro + thr).abs()
                        } else {
                            ro.abs() - thr
                        };
                        viol = viol.max(v);
                    }
                }
            }
        }
        let denom = if sc.cmax > T::ZERO { sc.cmax } else { T::ONE };
        let objective = -quad / T::of(2.0) + if lam > T::ZERO { lam * pen } else { T::ZERO };
        (viol / denom, objective, active)
    }

    /// lambda_max: the smallest lambda for which every penalised column is zero (computed
    /// from the statistics: unpenalised columns are fitted first, then
    /// max_j ||R[:, j]|| / w_j for the group penalty, max_{o,j} |R[o, j]| / w_j for l1).
    /// `theta` is set to the solution at lambda_max.
    pub fn lambda_max<M: SymMatrix<T> + ?Sized>(
        &mut self,
        prob: &Problem<'_, T, M>,
        theta: &mut [T],
        settings: &Settings<T>,
    ) -> Result<T, Error> {
        if theta.len() != self.l * self.q {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: self.l * self.q,
                got: theta.len(),
            });
        }
        let sc = self.check(prob, settings)?;
        for v in theta.iter_mut() {
            *v = T::ZERO;
        }
        self.init_residual(prob, &sc, theta);
        let (l, q) = (self.l, self.q);
        if (0..q).any(|j| Self::class(prob, &sc, j) == Class::Unpenalised) {
            self.run(prob, &sc, None, theta, settings)?;
        }
        let r = &self.work.as_ref()[..l * q];
        let mut lmax = T::ZERO;
        for j in 0..q {
            if Self::class(prob, &sc, j) != Class::Free {
                continue;
            }
            let w = prob.w(j);
            let v = match prob.penalty {
                Penalty::Group => {
                    let mut n2 = T::ZERO;
                    for o in 0..l {
                        n2 += r[o * q + j] * r[o * q + j];
                    }
                    n2.sqrt()
                }
                Penalty::L1 => (0..l).fold(T::ZERO, |a, o| a.max(r[o * q + j].abs())),
            };
            lmax = lmax.max(v / w);
        }
        if lmax.is_finite() {
            Ok(lmax)
        } else {
            Err(Error::Overflow)
        }
    }

    /// Solve at one `lambda` >= 0, warm-started from `theta` (l x q, row-major; zeros for a
    /// cold start), which receives the solution. Not converging within `max_iter` sweeps is
    /// reported in [`Fit::converged`], not as an error.
    pub fn solve<M: SymMatrix<T> + ?Sized>(
        &mut self,
        prob: &Problem<'_, T, M>,
        lambda: T,
        theta: &mut [T],
        settings: &Settings<T>,
    ) -> Result<Fit<T>, Error> {
        if !lambda.is_finite() || lambda < T::ZERO {
            return Err(Error::InvalidConfig("lambda must be finite and >= 0"));
        }
        check_vec(Field::Regressor, theta, self.l * self.q)?;
        let sc = self.check(prob, settings)?;
        self.init_residual(prob, &sc, theta);
        let (iterations, converged) = self.run(prob, &sc, Some(lambda), theta, settings)?;
        let (kkt, objective, active) = self.certificate(prob, &sc, lambda, theta);
        Ok(Fit {
            index: 0,
            lambda,
            iterations,
            converged,
            active,
            kkt,
            objective,
        })
    }

    /// The automatic path: lambda_k = lambda_max * ratio^(k / (n - 1)), k = 0..n_lambda,
    /// warm-started from one point to the next. `f(&fit, theta)` sees every point (theta is
    /// the solution, only valid during the call) and may stop the path with
    /// `ControlFlow::Break(())`. Returns the number of points visited; `theta` is left at
    /// the last one. If lambda_max = 0 (nothing to select) a single point is produced.
    pub fn path<M, F>(
        &mut self,
        prob: &Problem<'_, T, M>,
        settings: &Settings<T>,
        theta: &mut [T],
        mut f: F,
    ) -> Result<usize, Error>
    where
        M: SymMatrix<T> + ?Sized,
        F: FnMut(&Fit<T>, &[T]) -> ControlFlow<()>,
    {
        if settings.n_lambda == 0 {
            return Err(Error::InvalidConfig("n_lambda must be >= 1"));
        }
        let r = settings.lambda_min_ratio;
        if !(r > T::ZERO && r <= T::ONE) {
            return Err(Error::InvalidConfig("lambda_min_ratio must be in (0, 1]"));
        }
        let lmax = self.lambda_max(prob, theta, settings)?;
        let n = if lmax > T::ZERO { settings.n_lambda } else { 1 };
        let lr = libm::log(r.to_f64());
        for k in 0..n {
            let lambda = if k == 0 {
                lmax
            } else {
                lmax * T::of(libm::exp(lr * k as f64 / (n - 1) as f64))
            };
            let mut fit = self.solve(prob, lambda, theta, settings)?;
            fit.index = k;
            if f(&fit, theta).is_break() {
                return Ok(k + 1);
            }
        }
        Ok(n)
    }

    /// A path over given lambdas (e.g. the common grid of a cross-validation, computed from
    /// the full training statistics), warm-started in the given order (decreasing is the
    /// efficient order). Starts from `theta` as given. Same callback as [`Self::path`].
    pub fn path_with<M, F>(
        &mut self,
        prob: &Problem<'_, T, M>,
        lambdas: &[T],
        settings: &Settings<T>,
        theta: &mut [T],
        mut f: F,
    ) -> Result<usize, Error>
    where
        M: SymMatrix<T> + ?Sized,
        F: FnMut(&Fit<T>, &[T]) -> ControlFlow<()>,
    {
        if lambdas.iter().any(|v| !v.is_finite() || *v < T::ZERO) {
            return Err(Error::InvalidConfig("lambdas must be finite and >= 0"));
        }
        for (k, lambda) in lambdas.iter().enumerate() {
            let mut fit = self.solve(prob, *lambda, theta, settings)?;
            fit.index = k;
            if f(&fit, theta).is_break() {
                return Ok(k + 1);
            }
        }
        Ok(lambdas.len())
    }
}

/// The de-biased refit (section 5.2 of the BC-IV paper; the unpenalised re-estimate after
/// structure selection): minimise 1/2 tr(Theta G Theta^T) - tr(Theta C^T) over the support
/// = columns non-zero in `theta` on entry, plus unpenalised (w_j = 0) columns, minus excluded
/// (w_j = +inf) ones, by a Cholesky factorisation of G restricted to the support. `theta`
/// receives the refit (zero off the support). `work`: `refit_work_len(q)` values. Returns
/// the support size. A singular restricted G gives [`Error::Singular`] with theta unchanged.
pub fn refit<T: Real, M: SymMatrix<T> + ?Sized>(
    prob: &Problem<'_, T, M>,
    theta: &mut [T],
    work: &mut [T],
) -> Result<usize, Error> {
    let (l, q) = (prob.l, prob.q);
    check_vec(Field::Regressor, theta, l * q)?;
    let need = q
        .checked_mul(q)
        .and_then(|v| v.checked_add(2 * q))
        .ok_or(Error::Overflow)?;
    if work.len() < need {
        return Err(Error::Capacity {
            needed: need,
            capacity: work.len(),
        });
    }
    let g = prob.gram;
    let (mat, rest) = work.split_at_mut(q * q);
    let (flags, rhs) = rest.split_at_mut(q);
    let mut k = 0;
    let mut dmax = T::ZERO;
    for j in 0..q {
        let w = prob.w(j);
        let nz = (0..l).any(|o| theta[o * q + j] != T::ZERO);
        let inside = w.is_finite() && (nz || w == T::ZERO);
        flags[j] = if inside { T::ONE } else { T::ZERO };
        if inside {
            k += 1;
            dmax = dmax.max(finite_diagonal(g, j)?.abs());
        }
    }
    // G_SS, dense k x k
    let mut a = 0;
    for (i, fi) in flags.iter().enumerate() {
        if *fi == T::ZERO {
            continue;
        }
        let mut b = 0;
        for (j, fj) in flags.iter().enumerate() {
            if *fj == T::ZERO {
                continue;
            }
            let v = g.get(i, j);
            if !v.is_finite() {
                return Err(Error::NonFinite {
                    field: Field::Regressor,
                    index: i * q + j,
                });
            }
            mat[a * k + b] = v;
            b += 1;
        }
        a += 1;
    }
    // Cholesky, lower triangle in place
    let tiny = dmax * T::EPSILON * T::of(k.max(1) as f64);
    for c in 0..k {
        let mut d = mat[c * k + c];
        for p in 0..c {
            d -= mat[c * k + p] * mat[c * k + p];
        }
        if d <= tiny || !d.is_finite() {
            return Err(Error::Singular);
        }
        let d = d.sqrt();
        mat[c * k + c] = d;
        for r in c + 1..k {
            let mut v = mat[r * k + c];
            for p in 0..c {
                v -= mat[r * k + p] * mat[c * k + p];
            }
            mat[r * k + c] = v / d;
        }
    }
    for o in 0..l {
        // gather C[o, S]
        let mut a = 0;
        for (j, fj) in flags.iter().enumerate() {
            if *fj != T::ZERO {
                rhs[a] = prob.cross[o * q + j];
                a += 1;
            }
        }
        // L y = c, L^T x = y
        for r in 0..k {
            let mut v = rhs[r];
            for p in 0..r {
                v -= mat[r * k + p] * rhs[p];
            }
            rhs[r] = v / mat[r * k + r];
        }
        for r in (0..k).rev() {
            let mut v = rhs[r];
            for p in r + 1..k {
                v -= mat[p * k + r] * rhs[p];
            }
            rhs[r] = v / mat[r * k + r];
        }
        let mut a = 0;
        for j in 0..q {
            if flags[j] != T::ZERO {
                theta[o * q + j] = rhs[a];
                a += 1;
            } else {
                theta[o * q + j] = T::ZERO;
            }
        }
    }
    Ok(k)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_coordinate_closed_form() {
        // 1/2 g t^2 - c t + lam |t|  ->  t = soft(c, lam) / g
        let g = [4.0f64];
        let gm = Dense::new(&g, 1).unwrap();
        let c = [3.0];
        let prob = Problem::new(&gm, &c, 1, Penalty::L1).unwrap();
        let mut cd = CoordinateDescent::new(1, 1, [0.0; 2]).unwrap();
        let mut th = [0.0];
        let fit = cd.solve(&prob, 1.0, &mut th, &Settings::default()).unwrap();
        assert!((th[0] - 0.5).abs() < 1e-15);
        assert!(fit.converged);
        assert!(fit.kkt < 1e-12);
        let lmax = cd.lambda_max(&prob, &mut th, &Settings::default()).unwrap();
        assert_eq!(lmax, 3.0);
    }

    #[test]
    fn indefinite_and_flat_diagonals() {
        let g = [1.0f64, 0.0, 0.0, -1.0];
        let gm = Dense::new(&g, 2).unwrap();
        let c = [1.0, 1.0];
        let prob = Problem::new(&gm, &c, 1, Penalty::L1).unwrap();
        let mut cd = CoordinateDescent::new(1, 2, vec![0.0; 4]).unwrap();
        let mut th = [0.0, 0.0];
        assert_eq!(
            cd.solve(&prob, 0.1, &mut th, &Settings::default()),
            Err(Error::Singular)
        );
        let g = [1.0f64, 0.0, 0.0, 0.0];
        let gm = Dense::new(&g, 2).unwrap();
        let c = [1.0, 0.0];
        let prob = Problem::new(&gm, &c, 1, Penalty::L1).unwrap();
        let mut th = [0.0, 5.0];
        let fit = cd.solve(&prob, 0.0, &mut th, &Settings::default()).unwrap();
        assert_eq!(th, [1.0, 0.0]);
        assert!(fit.converged);
    }
}
