//! Streaming kernel method: a fixed-capacity dictionary of windows selected by the kernel
//! selection of Algorithm 3 (kernel paper section 6.2) in its streaming form, and the
//! dictionary-projected normal equations of the dual problem (19), accumulated per sample.
//!
//! **Feature vectors and kernel.** Window k holds samples k..k+p; its feature vector is
//! phi_k = [z_k^p; u_{k+p}] (the column k of [Z; U], eq. (10), (12)), or z_k^p without the
//! feedthrough D. The kernel k(a, b) = phi_a^T phi_b = [Z^T Z + U^T U]_{ab} is evaluated by
//! Theorem 10 ([`dual_kernel`]): Z is never formed. A dictionary window is a [`Samples`]
//! source of its own p + 1 samples.
//!
//! **Admission (Algorithm 3, streaming).** Algorithm 3 keeps row j of the kernel matrix when
//! its squared distance to the span of the rows already kept exceeds epsilon. Row j of
//! Z^T Z + U^T U is phi_j^T [Z; U], so row j depends linearly on rows D exactly when phi_j
//! depends on {phi_a, a in D} (phi_j lies in the column space of [Z; U]): at exact dependence
//! both tests keep the same rows, in the same (data) order. The streaming form (approximate
//! linear dependence) needs only kernels with the dictionary:
//!
//! delta = k(w, w) - k_D(w)^T K_D^{-1} k_D(w),  k_D(w) = [k(d_1, w), ..., k(d_M, w)],
//!
//! the squared residual of phi_w projected on span{phi_d}. The window is admitted when
//! `delta > epsilon` and `delta > rel_floor * k(w, w)` (the second condition keeps round-off
//! from admitting exactly dependent windows). The Cholesky factor L of K_D is extended by one
//! row per admission, [L^{-1} k_D(w), sqrt(delta)], so a test costs one forward solve,
//! O(M^2), plus M kernels of O(p (m + r + l)) each. `epsilon` is absolute (kernel units, as in
//! Algorithm 3); with periodic scheduling of period P and generic inputs the exact number of
//! admitted windows at epsilon = 0 is (r + l) sum_{j=1}^p min(P, m^{p-j+1}) (+ r with
//! feedthrough), at most the P (r + l) p of section 6.1.
//!
//! **Two phases** (kernel vectors of earlier windows lack the entries of rows admitted
//! later, so accumulating while the dictionary grows would not be the batch problem):
//! 1. *Building*: each full window is tested and possibly admitted (nothing accumulated).
//! 2. [`KernelDictionary::freeze`], then *Accumulating*: for each full window k the kernel
//!    vector k_k = k_D(w_k) and the target y_{k+p} are added to a [`Gram`] of
//!    [k_k; y_{k+p}], which holds sum k k^T (M x M), sum k y^T (M x l) and sum y y^T.
//!
//! The accumulated problem is exactly the batch restricted dual problem of Algorithm 3
//! ("solve min ||Y - alpha~ Z||", Z = the rows D of Z^T Z + U^T U) over the accumulated
//! windows C: min_alpha ||Y_C - alpha K_{D,C}||_F^2 + lambda ||alpha||_F^2, solved by
//! [`KernelDictionary::solve`]. On the host, run the data twice (build, freeze,
//! [`KernelDictionary::break_window`], accumulate): C is every window, as in the paper. On a
//! device, freeze after a leading segment: D comes from that segment and C is every window
//! completed after the freeze.
//!
//! **Eq. (25) restricted to D.** Row block i (i = 1..f) of Gamma^p K^p Z, column b, is
//! alpha~ kappa_i(b), kappa_i(b)_a = [sum_{j >= i} (Z^{i,j})^T Z^{1,j}]_{a,b} =
//! [`shifted_kernel`]`(d_a, 0, src, b, i, p)` (kernel paper eq. (25)): the shifted kernel touches samples 0..p-i of the
//! dictionary window and b..b+p-1 of the data, so every dictionary row has what it needs.
//! [`KernelDictionary::shifted_kernels`] gives kappa, [`KernelDictionary::state_candidate`]
//! the column g_b = Gamma^p K^p z_b (f l values). The realization (section 4.3) is linear in
//! g: with alpha known (frozen after the solve) a further pass accumulates the second moments
//! of [`KernelDictionary::write_realization_vector`],
//! v_k = [mu_{k+p} (x) [g_k; u_{k+p}; y_{k+p}]; g_{k+1}], both g from one window of p + 1
//! samples; the SVD of sum g_k g_k^T (eq. (15)) and both regressions of section 4.3 are
//! linear maps of those moments (see `realize_from_stats` in the host for the same idea with
//! z_k^p in place of g_k).
//!
//! **Forgetting, windows and merging** (issue 18). Only the normal equations accumulate;
//! the dictionary D is fixed at the freeze and never aged. [`KernelDictionary::set_forgetting`]
//! makes them S <- lambda S + [k; y][k; y]^T per window ([`Gram::set_forgetting`]), so
//! [`KernelDictionary::solve`] becomes the ridge problem with rows weighted by
//! sqrt(lambda^age); a sliding window of N windows is [`crate::sliding::Sliding`] over the
//! frozen dictionary (the [`crate::sliding::Rebase`] impl: the last N/2 ..= N - 1 windows).
//! They are alternatives. Merging normal equations ([`KernelDictionary::normal_equations_mut`],
//! [`Gram::merge`]) is only meaningful with the same dictionary D (the kernel vectors are
//! columns of K_{D,:}): then plain sums merge into the concatenated record, forgetting sums
//! (equal lambda required) only between records that ran at the same time, and two windows
//! into the sum of both.
//!
//! **State size** (values of `T`): window (p + 2)(r + l + s + 1), dictionary
//! M (p + 1)(r + l + s + 1) + M (M + 1)/2 + M + l, normal equations (M + l)(M + l + 1)
//! (compensated sums: two packed triangles). The closed-loop blade example (B5: r = 1,
//! l = 2, s = 1, p = 10) with M = 100: 60 + 10 652 + 10 506 = 21 218 values, 83 KiB in f32 (the primal Gram of its q = 6 138
//! regressors would need 18.9 M values); realization moments with f = 10: dimension
//! m (f l + r + l) + f l = 66, 2 211 values.

use crate::error::{Error, Field};
use crate::kernel::{dual_kernel, shifted_kernel};
use crate::real::{dot, Real};
use crate::stats::{gram_storage_len, packed_len, Gram};
use crate::window::{window_storage_len, PbsidDims, Samples, Slab, Window};

/// Values the dictionary storage needs for `capacity` windows of these dimensions: the
/// windows M (p + 1)(r + l + s + 1), the packed Cholesky factor M (M + 1)/2 and a scratch
/// vector M + l. `const` for firmware arrays; 0 on overflow.
pub const fn dictionary_storage_len(
    r: usize,
    l: usize,
    s: usize,
    p: usize,
    capacity: usize,
) -> usize {
    match dictionary_storage_checked(r, l, s, p, capacity) {
        Some(v) => v,
        None => 0,
    }
}

const fn dictionary_storage_checked(
    r: usize,
    l: usize,
    s: usize,
    p: usize,
    capacity: usize,
) -> Option<usize> {
    let per = match (p + 1).checked_mul(r + l + s + 1) {
        Some(v) => v,
        None => return None,
    };
    let wins = match capacity.checked_mul(per) {
        Some(v) => v,
        None => return None,
    };
    let chol = match capacity.checked_mul(capacity + 1) {
        Some(v) => v / 2,
        None => return None,
    };
    match wins.checked_add(chol) {
        Some(v) => v.checked_add(capacity + l),
        None => None,
    }
}

/// Values the normal-equation storage needs: the [`Gram`] of [k; y], dimension
/// capacity + l, with compensated sums (two packed triangles, [`gram_storage_len`]: see
/// [`crate::stats`]). `const` for firmware arrays.
pub const fn dictionary_gram_len(l: usize, capacity: usize) -> usize {
    gram_storage_len(capacity + l)
}

/// Length of the realization vector v_k of [`KernelDictionary::write_realization_vector`]
/// for future window `f`: m (f l + r + l) + f l.
pub const fn realization_vector_len(r: usize, l: usize, s: usize, f: usize) -> usize {
    (s + 1) * (f * l + r + l) + f * l
}

/// Tuning of a [`KernelDictionary`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DictionaryConfig<T> {
    /// Maximum number of dictionary windows M (the selected rows of Algorithm 3).
    pub capacity: usize,
    /// Absolute admission tolerance epsilon of Algorithm 3 on the squared residual delta
    /// (kernel units: scale it with the data). 0 admits every independent window.
    pub epsilon: T,
    /// Round-off guard: admission also needs delta > rel_floor k(w, w). Default sqrt(eps)
    /// of `T` (1.5e-8 in f64, 3.5e-4 in f32). The computed delta of an exactly dependent
    /// window is round-off of order eps cond(L) k(w, w); with every admitted delta above
    /// rel_floor k, cond(L) stays below about sqrt(M / rel_floor), so sqrt(eps) keeps the two
    /// apart for any practical M (a fixed 1e4 eps let dependent windows in at M = 28).
    pub rel_floor: T,
    /// Include the feedthrough term u_{k+p}^T u_{k+p}' in the kernel (D estimated).
    pub feedthrough: bool,
}

impl<T: Real> DictionaryConfig<T> {
    /// Capacity M, tolerance epsilon, feedthrough; the default round-off guard.
    pub fn new(capacity: usize, epsilon: T, feedthrough: bool) -> Self {
        DictionaryConfig {
            capacity,
            epsilon,
            rel_floor: T::EPSILON.sqrt(),
            feedthrough,
        }
    }

    fn check(&self) -> Result<(), Error> {
        if self.capacity == 0 {
            return Err(Error::InvalidConfig(
                "dictionary capacity must be at least 1",
            ));
        }
        if !self.epsilon.is_finite() || self.epsilon < T::ZERO {
            return Err(Error::InvalidConfig(
                "kernel tolerance epsilon must be finite and >= 0",
            ));
        }
        if !self.rel_floor.is_finite() || self.rel_floor < T::ZERO {
            return Err(Error::InvalidConfig(
                "relative floor must be finite and >= 0",
            ));
        }
        Ok(())
    }
}

/// Which phase a [`KernelDictionary`] is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Windows are tested for admission; nothing is accumulated.
    Building,
    /// The dictionary is frozen; windows feed the normal equations.
    Accumulating,
}

/// What one sample did. Window indices count full windows since the start of the phase
/// (construction or [`KernelDictionary::freeze`]); a break does not reset them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Step<T> {
    /// Fewer than p + 1 samples since the start or the last break: no window yet.
    Filling,
    /// Building: delta exceeded the tolerance; the window is now dictionary row `slot`.
    Admitted {
        /// Window index in this phase.
        window: u64,
        /// Dictionary row (admission order).
        slot: usize,
        /// Squared residual delta of the projection on the previous dictionary.
        residual: T,
    },
    /// Building: within tolerance of the dictionary's span; not admitted.
    Dependent {
        /// Window index in this phase.
        window: u64,
        /// Squared residual delta.
        residual: T,
    },
    /// Building: independent, but the dictionary holds `capacity` windows: rejected, and
    /// counted in [`KernelDictionary::rejected_full`] (a larger M or epsilon would keep it).
    Full {
        /// Window index in this phase.
        window: u64,
        /// Squared residual delta.
        residual: T,
    },
    /// Accumulating: k_D(w_k) and y_{k+p} were added to the normal equations.
    Accumulated {
        /// Window index in this phase.
        window: u64,
    },
}

/// Dictionary window `a` in storage: its p + 1 rows [u, y, mu] as a [`Slab`].
#[inline(always)]
fn stored<'a, T: Real>(wins: &'a [T], dims: &PbsidDims, a: usize) -> Slab<'a, T> {
    let per = (dims.p + 1) * dims.sample_len();
    Slab::from_rows(&wins[a * per..(a + 1) * per], dims.r, dims.l, dims.m())
}

/// The normal equations: storage until the freeze fixes their dimension M + l.
#[derive(Debug, Clone)]
enum Normal<T, S> {
    Building(S),
    Frozen(Gram<T, S>),
    /// Only while `freeze` moves the storage.
    Moving,
}

/// Streaming kernel dictionary (Algorithm 3, Theorem 10) with the dictionary-projected
/// normal equations of the dual problem (19); see the module documentation for the exact
/// semantics. Storage is caller-provided: `SW` the window ([`window_storage_len`]), `SD` the
/// dictionary ([`dictionary_storage_len`]), `SG` the normal equations
/// ([`dictionary_gram_len`]); [`KernelDictionaryArrays`] is the static form.
///
/// Size: see the module documentation (B5 with M = 100: 15 965 values).
#[derive(Debug, Clone)]
pub struct KernelDictionary<T, SW, SD, SG> {
    dims: PbsidDims,
    config: DictionaryConfig<T>,
    window: Window<T, SW>,
    store: SD,
    normal: Normal<T, SG>,
    len: usize,
    windows: u64,
    dependent: u64,
    full: u64,
    max_full_residual: T,
    /// Forgetting factor of the normal equations (applied at the freeze).
    lambda: T,
}

impl<T, SW, SD, SG> KernelDictionary<T, SW, SD, SG>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SD: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
{
    /// An empty dictionary in the building phase over the three storages; each is checked
    /// against the capacity.
    pub fn with_storage(
        dims: PbsidDims,
        config: DictionaryConfig<T>,
        window: SW,
        store: SD,
        gram: SG,
    ) -> Result<Self, Error> {
        config.check()?;
        let cap = config.capacity;
        let needed = dictionary_storage_checked(dims.r, dims.l, dims.s, dims.p, cap)
            .ok_or(Error::Overflow)?;
        if store.as_ref().len() < needed {
            return Err(Error::Capacity {
                needed,
                capacity: store.as_ref().len(),
            });
        }
        let gdim = cap.checked_add(dims.l).ok_or(Error::Overflow)?;
        // compensated sums: two packed triangles (dictionary_gram_len)
        let gneeded = gdim.checked_mul(gdim + 1).ok_or(Error::Overflow)?;
        if gram.as_ref().len() < gneeded {
            return Err(Error::Capacity {
                needed: gneeded,
                capacity: gram.as_ref().len(),
            });
        }
        Ok(KernelDictionary {
            dims,
            config,
            window: Window::new(dims, window)?,
            store,
            normal: Normal::Building(gram),
            len: 0,
            windows: 0,
            dependent: 0,
            full: 0,
            max_full_residual: T::ZERO,
            lambda: T::ONE,
        })
    }

    /// The dimensions.
    pub fn dims(&self) -> PbsidDims {
        self.dims
    }

    /// The configuration.
    pub fn config(&self) -> DictionaryConfig<T> {
        self.config
    }

    /// The current phase.
    pub fn phase(&self) -> Phase {
        match self.normal {
            Normal::Building(_) => Phase::Building,
            _ => Phase::Accumulating,
        }
    }

    /// Number of dictionary windows M.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when no window has been admitted.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Maximum number of dictionary windows.
    pub fn capacity(&self) -> usize {
        self.config.capacity
    }

    /// True when the dictionary holds `capacity` windows.
    pub fn is_full(&self) -> bool {
        self.len == self.config.capacity
    }

    /// Full windows seen in the current phase.
    pub fn windows(&self) -> u64 {
        self.windows
    }

    /// Windows found dependent (within tolerance) while building.
    pub fn rejected_dependent(&self) -> u64 {
        self.dependent
    }

    /// Independent windows rejected because the dictionary was full.
    pub fn rejected_full(&self) -> u64 {
        self.full
    }

    /// Largest residual delta among the windows rejected because the dictionary was full
    /// (0 when none): how far from the span the dictionary leaves the data.
    pub fn max_rejected_residual(&self) -> T {
        self.max_full_residual
    }

    /// The sample window (the last p + 1 samples, oldest first).
    pub fn window(&self) -> &Window<T, SW> {
        &self.window
    }

    /// Dictionary window `slot` (admission order): its p + 1 samples [u, y, mu] as a slab.
    pub fn dictionary_window(&self, slot: usize) -> Option<Slab<'_, T>> {
        if slot >= self.len {
            return None;
        }
        let d = self.dims;
        let per = (d.p + 1) * d.sample_len();
        Slab::new(
            &self.store.as_ref()[slot * per..(slot + 1) * per],
            d.r,
            d.l,
            d.m(),
        )
        .ok()
    }

    /// The Cholesky factor of K_D, packed lower triangle by rows (row i holds i + 1 values
    /// from offset i (i + 1)/2): K_D = L L^T.
    pub fn cholesky(&self) -> &[T] {
        let off = self.windows_len();
        &self.store.as_ref()[off..off + packed_len(self.len)]
    }

    /// The accumulated normal equations (a [`Gram`] of [k_D(w_k); y_{k+p}], dimension M + l:
    /// entries (a, b) < M are sum k k^T, (a, M + j) sum k y^T, (M + i, M + j) sum y y^T;
    /// `count()` is the number of windows). `None` while building.
    pub fn normal_equations(&self) -> Option<&Gram<T, SG>> {
        match &self.normal {
            Normal::Frozen(g) => Some(g),
            _ => None,
        }
    }

    /// Mutable normal equations (merge statistics of another source with the same
    /// dictionary, reset, load). `None` while building.
    pub fn normal_equations_mut(&mut self) -> Option<&mut Gram<T, SG>> {
        match &mut self.normal {
            Normal::Frozen(g) => Some(g),
            _ => None,
        }
    }

    fn windows_len(&self) -> usize {
        let d = self.dims;
        self.config.capacity * (d.p + 1) * d.sample_len()
    }

    /// End the building phase: the dictionary is fixed at its current M windows and the
    /// normal equations (dimension M + l) start empty. The sample window is kept (a device
    /// continues its stream); a host replaying the data calls [`Self::break_window`] first.
    pub fn freeze(&mut self) -> Result<(), Error> {
        let storage = match core::mem::replace(&mut self.normal, Normal::Moving) {
            Normal::Building(s) => s,
            other => {
                self.normal = other;
                return Err(Error::InvalidConfig("dictionary already frozen"));
            }
        };
        // capacity checked at construction for M = capacity, so this cannot fail
        let gram = Gram::with_summation(
            self.len + self.dims.l,
            storage,
            crate::stats::Summation::Compensated,
        )?;
        let mut gram = gram;
        gram.set_forgetting(self.lambda)?;
        self.normal = Normal::Frozen(gram);
        self.windows = 0;
        Ok(())
    }

    /// Exponential forgetting of the normal equations, lambda in (0, 1] per accumulated
    /// window (1: plain sums): S <- lambda S + [k; y][k; y]^T ([`Gram::set_forgetting`]),
    /// so window k of n weighs lambda^(n - 1 - k) and the ridge solve follows the recent
    /// windows (memory about 1/(1 - lambda)). Before the freeze it is kept for the normal
    /// equations the freeze creates; after it, it applies from the next window on. The
    /// dictionary itself (which windows span the kernel rows) is not aged: it is fixed at
    /// the freeze. See the module documentation for merging.
    pub fn set_forgetting(&mut self, lambda: T) -> Result<(), Error> {
        if !(lambda.is_finite() && lambda > T::ZERO && lambda <= T::ONE) {
            return Err(Error::InvalidConfig("forgetting factor must be in (0, 1]"));
        }
        if let Normal::Frozen(g) = &mut self.normal {
            g.set_forgetting(lambda)?;
        }
        self.lambda = lambda;
        Ok(())
    }

    /// The forgetting factor (1: none).
    pub fn forgetting(&self) -> T {
        self.lambda
    }

    /// Start a new experiment: the next window needs p + 1 fresh samples (windows never
    /// straddle a gap). Dictionary and normal equations are kept.
    pub fn break_window(&mut self) {
        self.window.clear();
    }

    /// Feed one sample (u_k, y_k, p_k). Building: test the completed window for admission.
    /// Accumulating: add its kernel vector and target to the normal equations. A rejected
    /// sample (wrong length, NaN/inf, overflow) leaves every state exactly as it was.
    pub fn update(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<Step<T>, Error> {
        if matches!(self.normal, Normal::Moving) {
            return Err(Error::InvalidConfig("dictionary state lost in freeze"));
        }
        let was_len = self.window.len();
        self.window.push(u, y, p)?;
        if !self.window.is_full() {
            return Ok(Step::Filling);
        }
        let res = if matches!(self.normal, Normal::Building(_)) {
            self.admit()
        } else {
            self.accumulate()
        };
        if res.is_err() {
            self.window.unpush(was_len);
        }
        res
    }

    /// The admission test of Algorithm 3 (streaming form) for the current full window.
    fn admit(&mut self) -> Result<Step<T>, Error> {
        let d = self.dims;
        let (p, m, ft) = (d.p, self.len, self.config.feedthrough);
        let wlen = self.windows_len();
        let cap = self.config.capacity;
        let (wins, rest) = self.store.as_mut().split_at_mut(wlen);
        let (chol, scratch) = rest.split_at_mut(packed_len(cap));
        let c = &mut scratch[..m];
        for (a, ca) in c.iter_mut().enumerate() {
            *ca = dual_kernel(&stored(wins, &d, a), 0, &self.window, 0, p, ft);
        }
        let ktt = dual_kernel(&self.window, 0, &self.window, 0, p, ft);
        // forward solve L c = k_D(w) in place
        for i in 0..m {
            let row = &chol[packed_len(i)..packed_len(i) + i + 1];
            c[i] = (c[i] - dot(&row[..i], &c[..i])) / row[i];
        }
        let delta = ktt - dot(c, c);
        if !ktt.is_finite() || !delta.is_finite() || c.iter().any(|v| !v.is_finite()) {
            return Err(Error::Overflow);
        }
        let window = self.windows;
        let independent = delta > self.config.epsilon && delta > self.config.rel_floor * ktt;
        if !independent {
            self.windows += 1;
            self.dependent += 1;
            return Ok(Step::Dependent {
                window,
                residual: delta,
            });
        }
        if m == cap {
            self.windows += 1;
            self.full += 1;
            self.max_full_residual = self.max_full_residual.max(delta);
            return Ok(Step::Full {
                window,
                residual: delta,
            });
        }
        // L row m = [L^{-1} k_D(w), sqrt(delta)]
        let off = packed_len(m);
        chol[off..off + m].copy_from_slice(c);
        chol[off + m] = delta.sqrt();
        let w = d.sample_len();
        let nz = d.nz();
        let per = (p + 1) * w;
        let dst = &mut wins[m * per..(m + 1) * per];
        for (t, row) in dst.chunks_exact_mut(w).enumerate() {
            row[..nz].copy_from_slice(self.window.z(t));
            row[nz..].copy_from_slice(self.window.mu(t));
        }
        self.len += 1;
        self.windows += 1;
        Ok(Step::Admitted {
            window,
            slot: m,
            residual: delta,
        })
    }

    /// Add [k_D(w_k); y_{k+p}] of the current full window to the normal equations.
    fn accumulate(&mut self) -> Result<Step<T>, Error> {
        let d = self.dims;
        let (p, m, ft) = (d.p, self.len, self.config.feedthrough);
        let wlen = self.windows_len();
        let cap = self.config.capacity;
        let (wins, rest) = self.store.as_mut().split_at_mut(wlen);
        let v = &mut rest[packed_len(cap)..packed_len(cap) + m + d.l];
        for (a, va) in v[..m].iter_mut().enumerate() {
            *va = dual_kernel(&stored(wins, &d, a), 0, &self.window, 0, p, ft);
        }
        v[m..].copy_from_slice(self.window.y(p));
        let gram = match &mut self.normal {
            Normal::Frozen(g) => g,
            _ => return Err(Error::InvalidConfig("dictionary not frozen")),
        };
        if let Err(e) = gram.update(v) {
            // the samples were finite: a non-finite kernel or product is an overflow
            return Err(match e {
                Error::NonFinite { .. } => Error::Overflow,
                other => other,
            });
        }
        let window = self.windows;
        self.windows += 1;
        Ok(Step::Accumulated { window })
    }

    /// The kernel vector k_D(w) = [k(d_1, w), ..., k(d_M, w)] of the window starting at
    /// sample `b` of `src` (samples b..b+p) into `out` (length M): column b of the rows D of
    /// Z^T Z + U^T U (Theorem 10), for a host computing K_{D,:} itself.
    pub fn kernel_vector<X: Samples<T> + ?Sized>(
        &self,
        src: &X,
        b: usize,
        out: &mut [T],
    ) -> Result<(), Error> {
        let d = self.dims;
        check_len(out.len(), self.len)?;
        check_source(src.len(), b, d.p + 1)?;
        let wins = &self.store.as_ref()[..self.windows_len()];
        for (a, o) in out.iter_mut().enumerate() {
            *o = dual_kernel(
                &stored(wins, &d, a),
                0,
                src,
                b,
                d.p,
                self.config.feedthrough,
            );
        }
        Ok(())
    }

    /// Work values [`Self::solve`] needs: M (M + 1)/2.
    pub fn solve_work_len(&self) -> usize {
        packed_len(self.len)
    }

    /// Solve the restricted dual problem of Algorithm 3 from the normal equations:
    /// alpha~ = argmin ||Y - alpha K_{D,C}||_F^2 + lambda ||alpha||_F^2, i.e.
    /// alpha~ (S_kk + lambda I) = S_yk, by Cholesky in `work` ([`Self::solve_work_len`]).
    /// `alpha` is l x M, row-major (alpha[j M + a]). [`Error::Singular`] when
    /// S_kk + lambda I is not numerically positive definite (raise lambda).
    pub fn solve(&self, lambda: T, work: &mut [T], alpha: &mut [T]) -> Result<(), Error> {
        let g = self
            .normal_equations()
            .ok_or(Error::InvalidConfig("dictionary not frozen"))?;
        let (m, l) = (self.len, self.dims.l);
        if !lambda.is_finite() || lambda < T::ZERO {
            return Err(Error::InvalidConfig(
                "regularisation lambda must be finite and >= 0",
            ));
        }
        if work.len() < packed_len(m) {
            return Err(Error::Capacity {
                needed: packed_len(m),
                capacity: work.len(),
            });
        }
        check_len(alpha.len(), l * m)?;
        // Cholesky S_kk + lambda I = L L^T, packed lower by rows
        for i in 0..m {
            let oi = packed_len(i);
            for j in 0..=i {
                let oj = packed_len(j);
                let mut s = g.get(i, j);
                if i == j {
                    s += lambda;
                }
                s -= dot(&work[oi..oi + j], &work[oj..oj + j]);
                if i == j {
                    let scale = g.get(i, i) + lambda;
                    if !s.is_finite() || s <= T::EPSILON * scale || s <= T::ZERO {
                        return Err(Error::Singular);
                    }
                    work[oi + i] = s.sqrt();
                } else {
                    work[oi + j] = s / work[oj + j];
                }
            }
        }
        for j in 0..l {
            let x = &mut alpha[j * m..(j + 1) * m];
            for (a, xa) in x.iter_mut().enumerate() {
                *xa = g.get(a, m + j);
            }
            for i in 0..m {
                let oi = packed_len(i);
                x[i] = (x[i] - dot(&work[oi..oi + i], &x[..i])) / work[oi + i];
            }
            for i in (0..m).rev() {
                let mut s = x[i];
                for (k, xk) in x.iter().enumerate().skip(i + 1) {
                    s -= work[packed_len(k) + i] * *xk;
                }
                x[i] = s / work[packed_len(i) + i];
            }
        }
        if let Some(index) = crate::real::first_non_finite(alpha) {
            return Err(Error::NonFinite {
                field: Field::Regressor,
                index,
            });
        }
        Ok(())
    }

    /// Residual sum of squares ||Y - alpha K_{D,C}||_F^2 from the normal equations:
    /// tr S_yy - 2 tr(alpha S_ky) + tr(alpha S_kk alpha^T) (for GCV on the host).
    pub fn residual_sum_of_squares(&self, alpha: &[T]) -> Result<T, Error> {
        let g = self
            .normal_equations()
            .ok_or(Error::InvalidConfig("dictionary not frozen"))?;
        let (m, l) = (self.len, self.dims.l);
        check_len(alpha.len(), l * m)?;
        let mut rss = T::ZERO;
        for j in 0..l {
            let x = &alpha[j * m..(j + 1) * m];
            rss += g.get(m + j, m + j);
            for a in 0..m {
                let mut sa = T::ZERO;
                for (b, xb) in x.iter().enumerate() {
                    sa += g.get(a, b) * *xb;
                }
                rss += x[a] * (sa - (T::ONE + T::ONE) * g.get(a, m + j));
            }
        }
        Ok(rss)
    }

    /// Shifted kernels of eq. (25) of the kernel paper ([`shifted_kernel`]) between the dictionary and the window starting at sample
    /// `b` of `src` (needs samples b..b+p-1): out[(i-1) M + a] =
    /// [sum_{j >= i} (Z^{i,j})^T Z^{1,j}]_{d_a, b} for row blocks i = 1..f (`f` <= p).
    pub fn shifted_kernels<X: Samples<T> + ?Sized>(
        &self,
        src: &X,
        b: usize,
        f: usize,
        out: &mut [T],
    ) -> Result<(), Error> {
        let d = self.dims;
        check_future(f, d.p)?;
        check_len(out.len(), f * self.len)?;
        check_source(src.len(), b, d.p)?;
        let wins = &self.store.as_ref()[..self.windows_len()];
        for i in 1..=f {
            for a in 0..self.len {
                out[(i - 1) * self.len + a] =
                    shifted_kernel(&stored(wins, &d, a), 0, src, b, i, d.p);
            }
        }
        Ok(())
    }

    /// Column b of Gamma^p K^p Z restricted to D (eq. (25), Algorithm 3):
    /// out[(i-1) l + j] = sum_a alpha[j M + a] kappa_i(b)_a, the state candidate
    /// g_b = Gamma^p K^p z_b of the window starting at sample `b` of `src` (samples
    /// b..b+p-1). The state is x_{b+p} = T g_b with T from the SVD (15) of sum g g^T.
    pub fn state_candidate<X: Samples<T> + ?Sized>(
        &self,
        src: &X,
        b: usize,
        f: usize,
        alpha: &[T],
        out: &mut [T],
    ) -> Result<(), Error> {
        let d = self.dims;
        let (m, l) = (self.len, d.l);
        check_future(f, d.p)?;
        check_len(alpha.len(), l * m)?;
        check_len(out.len(), f * l)?;
        check_source(src.len(), b, d.p)?;
        let wins = &self.store.as_ref()[..self.windows_len()];
        for v in out.iter_mut() {
            *v = T::ZERO;
        }
        for a in 0..m {
            let da = stored(wins, &d, a);
            for i in 1..=f {
                let k = shifted_kernel(&da, 0, src, b, i, d.p);
                for j in 0..l {
                    out[(i - 1) * l + j] += alpha[j * m + a] * k;
                }
            }
        }
        Ok(())
    }

    /// The realization vector of window k (samples k..k+p of `src`) for a frozen alpha:
    /// v_k = [mu_{k+p} (x) [g_k; u_{k+p}; y_{k+p}]; g_{k+1}] (block i of the Kronecker
    /// product is mu_{k+p}(i) [g_k; u; y]), length [`realization_vector_len`]. The second
    /// moments of v_k over the regression windows give the SVD (15) (block of g_k) and both
    /// least-squares problems of section 4.3 (x = T g, e = y - C x - D u are linear in v).
    pub fn write_realization_vector<X: Samples<T> + ?Sized>(
        &self,
        src: &X,
        k: usize,
        f: usize,
        alpha: &[T],
        out: &mut [T],
    ) -> Result<(), Error> {
        let d = self.dims;
        let (r, l, p) = (d.r, d.l, d.p);
        check_future(f, p)?;
        check_len(out.len(), realization_vector_len(r, l, d.s, f))?;
        check_source(src.len(), k, p + 1)?;
        let fl = f * l;
        let nxi = fl + r + l;
        let m = d.m();
        {
            let (head, tail) = out.split_at_mut(m * nxi);
            self.state_candidate(src, k + 1, f, alpha, tail)?;
            self.state_candidate(src, k, f, alpha, &mut head[..fl])?;
            head[fl..fl + r].copy_from_slice(src.u(k + p));
            head[fl + r..nxi].copy_from_slice(src.y(k + p));
            let mu = src.mu(k + p);
            let (b0, rest) = head.split_at_mut(nxi);
            for i in 1..m {
                for (dst, v) in rest[(i - 1) * nxi..i * nxi].iter_mut().zip(b0.iter()) {
                    *dst = mu[i] * *v;
                }
            }
            for v in b0.iter_mut() {
                *v *= mu[0];
            }
        }
        Ok(())
    }
}

fn check_len(got: usize, expected: usize) -> Result<(), Error> {
    if got != expected {
        return Err(Error::Dimension {
            field: Field::Storage,
            expected,
            got,
        });
    }
    Ok(())
}

fn check_future(f: usize, p: usize) -> Result<(), Error> {
    if f == 0 || f > p {
        return Err(Error::InvalidConfig(
            "future window f must be between 1 and p",
        ));
    }
    Ok(())
}

fn check_source(len: usize, start: usize, need: usize) -> Result<(), Error> {
    match start.checked_add(need) {
        Some(end) if end <= len => Ok(()),
        _ => Err(Error::Dimension {
            field: Field::Regressor,
            expected: start.saturating_add(need),
            got: len,
        }),
    }
}

/// Statically sized [`KernelDictionary`] (firmware): `W` window values, `D` dictionary
/// values, `G` normal-equation values; size them with [`window_storage_len`],
/// [`dictionary_storage_len`] and [`dictionary_gram_len`] in `const` items.
pub type KernelDictionaryArrays<T, const W: usize, const D: usize, const G: usize> =
    KernelDictionary<T, [T; W], [T; D], [T; G]>;

impl<T: Real, const W: usize, const D: usize, const G: usize> KernelDictionaryArrays<T, W, D, G> {
    /// Static-storage dictionary; fails if the capacities are too small.
    pub fn new(dims: PbsidDims, config: DictionaryConfig<T>) -> Result<Self, Error> {
        let need = window_storage_len(dims.r, dims.l, dims.s, dims.p);
        if W < need {
            return Err(Error::Capacity {
                needed: need,
                capacity: W,
            });
        }
        Self::with_storage(dims, config, [T::ZERO; W], [T::ZERO; D], [T::ZERO; G])
    }
}

/// One sample (u, y, p); a block row is [u (r), y (l), p (s)]. The output is the [`Step`].
/// A sliding window over the normal equations ([`crate::sliding::Sliding`]), for a frozen
/// dictionary: wrap it after [`KernelDictionary::freeze`] (the window counts accumulated
/// windows; [`Step::Accumulated`] is what `update_with` counts). The sums are the Gram of
/// [k; y], dimension M + l, rebased with its low parts.
impl<T, SW, SD, SG> crate::sliding::Rebase<T> for KernelDictionary<T, SW, SD, SG>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SD: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
{
    fn sums_len(&self) -> usize {
        packed_len(self.len + self.dims.l)
    }

    fn rebase(&mut self, snapshot: &mut [T], count: u64) -> Result<(), Error> {
        match &mut self.normal {
            Normal::Frozen(g) => crate::sliding::rebase_gram(g, Some(snapshot), count),
            _ => Err(Error::InvalidConfig(
                "a dictionary window starts after the freeze",
            )),
        }
    }

    fn clear_sums(&mut self) {
        if let Normal::Frozen(g) = &mut self.normal {
            g.reset();
        }
    }

    fn check_rebase(&self) -> Result<(), Error> {
        match &self.normal {
            Normal::Frozen(g) => crate::sliding::Rebase::check_rebase(g),
            _ => Err(Error::InvalidConfig(
                "a dictionary window starts after the freeze",
            )),
        }
    }
}

impl<T, SW, SD, SG> crate::Streaming<T> for KernelDictionary<T, SW, SD, SG>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SD: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
{
    type Sample<'a> = (&'a [T], &'a [T], &'a [T]);
    type Output = Step<T>;

    fn update(&mut self, (u, y, p): Self::Sample<'_>) -> Result<Step<T>, Error> {
        KernelDictionary::update(self, u, y, p)
    }

    fn row_len(&self) -> usize {
        self.dims.r + self.dims.l + self.dims.s
    }

    fn sample<'a>(&self, row: &'a [T]) -> Self::Sample<'a> {
        crate::window::split_sample(&self.dims, row)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::theorem10;
    use crate::window::window_storage_len;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    type Dict<T> = KernelDictionary<T, Vec<T>, Vec<T>, Vec<T>>;

    fn dict<T: Real>(dims: PbsidDims, cfg: DictionaryConfig<T>) -> Dict<T> {
        let (r, l, s, p) = (dims.r, dims.l, dims.s, dims.p);
        KernelDictionary::with_storage(
            dims,
            cfg,
            vec![T::ZERO; window_storage_len(r, l, s, p)],
            vec![T::ZERO; dictionary_storage_len(r, l, s, p, cfg.capacity)],
            vec![T::ZERO; dictionary_gram_len(l, cfg.capacity)],
        )
        .unwrap()
    }

    fn normal(rng: &mut StdRng) -> f64 {
        let u1: f64 = rng.gen::<f64>().max(1e-300);
        let u2: f64 = rng.gen();
        (-2.0 * u1.ln()).sqrt() * (2.0 * core::f64::consts::PI * u2).cos()
    }

    /// Rows [u, y, 1, rho] of a two-state LPV system in closed form (r inputs, l outputs,
    /// s = 1), with process noise.
    fn lpv_data(n: usize, r: usize, l: usize, seed: u64) -> Vec<f64> {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut x = [0.0f64; 2];
        let mut out = Vec::new();
        for k in 0..n {
            let rho = 0.5 * (0.3 * k as f64).sin() + 0.2 * normal(&mut rng);
            let u: Vec<f64> = (0..r).map(|_| normal(&mut rng)).collect();
            let y: Vec<f64> = (0..l)
                .map(|j| x[0] + (j as f64 + 0.5) * x[1] + 0.1 * normal(&mut rng))
                .collect();
            out.extend(&u);
            out.extend(&y);
            out.extend([1.0, rho]);
            let us: f64 = u.iter().sum();
            x = [
                (0.5 + 0.3 * rho) * x[0] + 0.2 * x[1] + us,
                -0.3 * x[0] + (0.4 - 0.2 * rho) * x[1] + 0.5 * us,
            ];
        }
        out
    }

    /// Feed samples `from..to` of `data` (rows [u, y, 1, p]) and collect the steps.
    fn feed<T: Real>(
        dct: &mut Dict<T>,
        data: &[f64],
        dims: PbsidDims,
        from: usize,
        to: usize,
    ) -> Vec<Step<T>> {
        let (r, l) = (dims.r, dims.l);
        let w = dims.sample_len();
        (from..to)
            .map(|k| {
                let row = &data[k * w..(k + 1) * w];
                let cv = |s: &[f64]| s.iter().map(|v| T::of(*v)).collect::<Vec<T>>();
                dct.update(&cv(&row[..r]), &cv(&row[r..r + l]), &cv(&row[r + l + 1..]))
                    .unwrap()
            })
            .collect()
    }

    fn admitted<T>(steps: &[Step<T>]) -> Vec<usize> {
        steps
            .iter()
            .filter_map(|s| match s {
                Step::Admitted { window, .. } => Some(*window as usize),
                _ => None,
            })
            .collect()
    }

    /// Plain Gaussian elimination with partial pivoting: solve A X = B (A n x n, B n x c,
    /// row-major), the test's independent dense solve.
    fn dense_solve(mut a: Vec<f64>, mut b: Vec<f64>, n: usize, c: usize) -> Vec<f64> {
        for col in 0..n {
            let piv = (col..n)
                .max_by(|&i, &j| a[i * n + col].abs().total_cmp(&a[j * n + col].abs()))
                .unwrap();
            for k in 0..n {
                a.swap(col * n + k, piv * n + k);
            }
            for k in 0..c {
                b.swap(col * c + k, piv * c + k);
            }
            for i in col + 1..n {
                let f = a[i * n + col] / a[col * n + col];
                for k in col..n {
                    a[i * n + k] -= f * a[col * n + k];
                }
                for k in 0..c {
                    b[i * c + k] -= f * b[col * c + k];
                }
            }
        }
        for col in (0..n).rev() {
            for k in 0..c {
                let mut s = b[col * c + k];
                for j in col + 1..n {
                    s -= a[col * n + j] * b[j * c + k];
                }
                b[col * c + k] = s / a[col * n + col];
            }
        }
        b
    }

    /// Batch reference: K_{D,C} by `dual_kernel` over the slab and the restricted dual
    /// problem of Algorithm 3 solved densely: returns (S_kk, S_ky, alpha (l x M)).
    fn batch(
        slab: &Slab<'_, f64>,
        dims: PbsidDims,
        d: &[usize],
        cols: core::ops::Range<usize>,
        ft: bool,
        lambda: f64,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (m, l, p) = (d.len(), dims.l, dims.p);
        let kd: Vec<Vec<f64>> = d
            .iter()
            .map(|&a| {
                cols.clone()
                    .map(|b| dual_kernel(slab, a, slab, b, p, ft))
                    .collect()
            })
            .collect();
        let ys: Vec<&[f64]> = cols.clone().map(|b| slab.y(b + p)).collect();
        let mut skk = vec![0.0; m * m];
        let mut sky = vec![0.0; m * l];
        for a in 0..m {
            for b in 0..m {
                skk[a * m + b] = kd[a].iter().zip(&kd[b]).map(|(x, y)| x * y).sum();
            }
            for j in 0..l {
                sky[a * l + j] = kd[a].iter().zip(&ys).map(|(x, y)| x * y[j]).sum();
            }
        }
        let mut reg = skk.clone();
        for a in 0..m {
            reg[a * m + a] += lambda;
        }
        let x = dense_solve(reg, sky.clone(), m, l); // M x l
        let mut alpha = vec![0.0; l * m];
        for a in 0..m {
            for j in 0..l {
                alpha[j * m + a] = x[a * l + j];
            }
        }
        (skk, sky, alpha)
    }

    fn rel_close(a: &[f64], b: &[f64], tol: f64) {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(0.0f64, |s, v| s.max(v.abs())).max(1e-300);
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= tol * scale,
                "entry {i}: {x} vs {y} (scale {scale})"
            );
        }
    }

    /// A frozen dictionary over `data` (rows [u, y, 1, p], r = 1, l = 2, p = 3) in `T`, the
    /// window broken for a second pass, and the data in `T`.
    fn frozen_dictionary<T: Real>(n: usize) -> (Dict<T>, PbsidDims, Vec<T>) {
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let data = lpv_data(n, 1, 2, 11);
        let slab = Slab::new(&data, 1, 2, 2).unwrap();
        let k00 = dual_kernel(&slab, 0, &slab, 0, dims.p, true);
        let mut dct = dict::<T>(dims, DictionaryConfig::new(12, T::of(0.05 * k00), true));
        feed(&mut dct, &data, dims, 0, n);
        assert!(dct.len() >= 4, "{}", dct.len());
        dct.freeze().unwrap();
        dct.break_window();
        let dt = data.iter().map(|v| T::of(*v)).collect();
        (dct, dims, dt)
    }

    /// The vectors [k_D(w_b); y_{b+p}] of every window b of `data`, in `T`, as the
    /// accumulation computes them (`kernel_vector` over the same stored windows).
    fn window_vectors<T: Real>(dct: &Dict<T>, dims: PbsidDims, data: &[T]) -> Vec<Vec<T>> {
        let slab = Slab::new(data, dims.r, dims.l, dims.m()).unwrap();
        let m = dct.len();
        (0..slab.len() - dims.p)
            .map(|b| {
                let mut v = vec![T::ZERO; m + dims.l];
                dct.kernel_vector(&slab, b, &mut v[..m]).unwrap();
                v[m..].copy_from_slice(slab.y(b + dims.p));
                v
            })
            .collect()
    }

    /// Largest difference of a Gram's entries from `want` (packed, f64), each relative to
    /// sqrt(want_ii want_jj).
    fn gram_rel_diff<T: Real>(g: &Gram<T, Vec<T>>, want: &[f64]) -> f64 {
        let dim = g.dim();
        let diag = |i: usize| want[packed_len(dim) - packed_len(dim - i)];
        let mut worst: f64 = 0.0;
        let mut o = 0;
        for i in 0..dim {
            for j in i..dim {
                let scale = (diag(i) * diag(j)).sqrt().max(1e-300);
                worst = worst.max((g.packed()[o].to_f64() - want[o]).abs() / scale);
                o += 1;
            }
        }
        worst
    }

    /// sum over `vecs` of weight(k) v v^T, packed, in f64.
    fn weighted_gram<T: Real>(vecs: &[Vec<T>], weight: impl Fn(usize) -> f64) -> Vec<f64> {
        let dim = vecs[0].len();
        let mut out = vec![0.0f64; packed_len(dim)];
        for (k, v) in vecs.iter().enumerate() {
            let w = weight(k);
            let mut o = 0;
            for i in 0..dim {
                for j in i..dim {
                    out[o] += w * v[i].to_f64() * v[j].to_f64();
                    o += 1;
                }
            }
        }
        out
    }

    /// Forgetting on the dictionary's normal equations weights window k of n by
    /// lambda^(n - 1 - k), set before or after the freeze; a sliding window of N holds
    /// exactly the last N/2 ..= N - 1 windows (checked after every window). f64 and f32.
    fn forgetting_and_window<T: Real>(tol: f64) -> (f64, f64) {
        use crate::sliding::{Rebase, Sliding};
        let n = 160;
        let (dct, dims, data) = frozen_dictionary::<T>(n);
        let vecs = window_vectors(&dct, dims, &data);
        let nbar = vecs.len();
        let w = dims.sample_len();
        let row = |k: usize| &data[k * w..(k + 1) * w];
        let (r, l) = (dims.r, dims.l);
        // forgetting
        let lambda = 0.95f64;
        let mut fg = dct.clone();
        fg.set_forgetting(T::of(lambda)).unwrap();
        assert_eq!(fg.forgetting(), T::of(lambda));
        for k in 0..n {
            let x = row(k);
            fg.update(&x[..r], &x[r..r + l], &x[r + l + 1..]).unwrap();
        }
        let g = fg.normal_equations().unwrap();
        assert_eq!(g.count(), nbar as u64);
        let lam = T::of(lambda).to_f64();
        let want = weighted_gram(&vecs, |k| lam.powi((nbar - 1 - k) as i32));
        let ef = gram_rel_diff(g, &want);
        assert!(ef <= tol, "forgetting {ef:e}");
        assert!(fg.set_forgetting(T::ZERO).is_err());
        // sliding window of 20 windows (half 10)
        let half = 10usize;
        let mut sl = Sliding::new(dct.clone(), 20, vec![T::ZERO; packed_len(12 + l)]).unwrap();
        assert_eq!(sl.inner().sums_len(), packed_len(dct.len() + l));
        let mut ew: f64 = 0.0;
        let mut seen = 0usize;
        for k in 0..n {
            let x = row(k);
            let step = sl
                .update_with(
                    |d| d.update(&x[..r], &x[r..r + l], &x[r + l + 1..]),
                    |s| matches!(s, Step::Accumulated { .. }),
                )
                .unwrap();
            if !matches!(step, Step::Accumulated { .. }) {
                continue;
            }
            seen += 1;
            let held = if seen < half {
                seen
            } else {
                half + seen % half
            };
            let g = sl.inner().normal_equations().unwrap();
            assert_eq!(g.count() as usize, held, "after {seen}");
            let want = weighted_gram(&vecs, |j| {
                if j + held >= seen && j < seen {
                    1.0
                } else {
                    0.0
                }
            });
            let e = gram_rel_diff(g, &want);
            assert!(e <= tol, "window after {seen}: {e:e}");
            ew = ew.max(e);
        }
        assert_eq!(seen, nbar);
        // forgetting and a window are alternatives; a window needs the freeze
        assert!(Sliding::new(fg, 20, vec![T::ZERO; packed_len(12 + l)]).is_err());
        let building = dict::<T>(dims, DictionaryConfig::new(12, T::ONE, true));
        assert!(Sliding::new(building, 20, vec![T::ZERO; packed_len(12 + l)]).is_err());
        (ef, ew)
    }

    #[test]
    fn dictionary_forgetting_and_window_f64_f32() {
        let e64 = forgetting_and_window::<f64>(1e-13);
        let e32 = forgetting_and_window::<f32>(2e-6);
        std::println!(
            "dictionary (forgetting, window) worst relative difference: f64 {e64:?}, f32 {e32:?}"
        );
    }

    /// Setting forgetting before the freeze carries it into the normal equations.
    #[test]
    fn dictionary_forgetting_set_before_the_freeze() {
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let mut dct = dict::<f64>(dims, DictionaryConfig::new(4, 0.0, true));
        dct.set_forgetting(0.5).unwrap();
        dct.freeze().unwrap();
        assert_eq!(dct.normal_equations().unwrap().forgetting(), 0.5);
    }

    #[test]
    fn two_pass_equals_batch_restricted_dual() {
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let n = 240;
        let data = lpv_data(n, 1, 2, 7);
        let slab = Slab::new(&data, 1, 2, 2).unwrap();
        let nbar = n - dims.p;
        for ft in [true, false] {
            let k00 = dual_kernel(&slab, 0, &slab, 0, dims.p, ft);
            let cfg = DictionaryConfig::new(30, 0.05 * k00, ft);
            let mut dct = dict::<f64>(dims, cfg);
            let steps = feed(&mut dct, &data, dims, 0, n);
            let d = admitted(&steps);
            assert_eq!(d.len(), dct.len());
            assert!(dct.len() > 5 && dct.len() <= 30, "{}", dct.len());
            assert_eq!(
                steps.iter().filter(|s| **s == Step::Filling).count(),
                dims.p
            );
            assert_eq!(
                dct.rejected_dependent() + dct.rejected_full() + d.len() as u64,
                (n - dims.p) as u64
            );
            // the dictionary stores exactly the admitted windows, and L L^T = K_D
            let chol = dct.cholesky();
            for (sa, &a) in d.iter().enumerate() {
                let win = dct.dictionary_window(sa).unwrap();
                for t in 0..=dims.p {
                    assert_eq!(win.z(t), slab.z(a + t));
                    assert_eq!(win.mu(t), slab.mu(a + t));
                }
                for (sb, &b) in d.iter().enumerate().take(sa + 1) {
                    let llt: f64 = (0..=sb)
                        .map(|k| chol[packed_len(sa) + k] * chol[packed_len(sb) + k])
                        .sum();
                    let kab = dual_kernel(&slab, a, &slab, b, dims.p, ft);
                    assert!((llt - kab).abs() < 1e-10 * k00, "{llt} {kab}");
                }
            }
            // every window left out is within tolerance of the span, or the dictionary was full
            for s in &steps {
                if let Step::Dependent { window, residual } = s {
                    let w = *window as usize;
                    let ktt = dual_kernel(&slab, w, &slab, w, dims.p, ft);
                    assert!(*residual <= cfg.epsilon || *residual <= cfg.rel_floor * ktt);
                }
            }
            assert!(dct.normal_equations().is_none());
            dct.freeze().unwrap();
            assert_eq!(dct.phase(), Phase::Accumulating);
            assert!(dct.freeze().is_err());
            dct.break_window();
            let steps2 = feed(&mut dct, &data, dims, 0, n);
            assert_eq!(
                steps2
                    .iter()
                    .filter(|s| matches!(s, Step::Accumulated { .. }))
                    .count(),
                nbar
            );
            let m = dct.len();
            let g = dct.normal_equations().unwrap();
            assert_eq!(g.count(), nbar as u64);
            for lambda in [0.0, 1e-3 * k00 * k00] {
                let (skk, sky, alpha_b) = batch(&slab, dims, &d, 0..nbar, ft, lambda);
                let got_kk: Vec<f64> = (0..m * m).map(|i| g.get(i / m, i % m)).collect();
                let got_ky: Vec<f64> = (0..m * 2).map(|i| g.get(i / 2, m + i % 2)).collect();
                rel_close(&got_kk, &skk, 1e-12);
                rel_close(&got_ky, &sky, 1e-12);
                let mut work = vec![0.0; dct.solve_work_len()];
                let mut alpha = vec![0.0; 2 * m];
                dct.solve(lambda, &mut work, &mut alpha).unwrap();
                rel_close(&alpha, &alpha_b, 1e-9);
                // residual from the statistics equals the batch residual
                let mut rss = 0.0;
                for b in 0..nbar {
                    for j in 0..2 {
                        let pred: f64 = (0..m)
                            .map(|a| alpha[j * m + a] * dual_kernel(&slab, d[a], &slab, b, 3, ft))
                            .sum();
                        rss += (slab.y(b + 3)[j] - pred).powi(2);
                    }
                }
                let got = dct.residual_sum_of_squares(&alpha).unwrap();
                assert!((got - rss).abs() < 1e-8 * (1.0 + rss), "{got} {rss}");
            }
            // the kernel vector helper is column b of K_{D,:}
            let mut kv = vec![0.0; m];
            dct.kernel_vector(&slab, 17, &mut kv).unwrap();
            for (a, &da) in d.iter().enumerate() {
                assert_eq!(kv[a], dual_kernel(&slab, da, &slab, 17, 3, ft));
            }
            assert!(dct.kernel_vector(&slab, nbar, &mut kv).is_err());
        }
    }

    #[test]
    fn leading_segment_then_stream() {
        // device mode: build on a leading segment, freeze, keep streaming: the normal
        // equations are the batch problem with rows D and columns = windows after the freeze.
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let n = 200;
        let data = lpv_data(n, 1, 2, 11);
        let slab = Slab::new(&data, 1, 2, 2).unwrap();
        let k00 = dual_kernel(&slab, 0, &slab, 0, 3, true);
        let mut dct = dict::<f64>(dims, DictionaryConfig::new(12, 0.02 * k00, true));
        let lead = 60;
        let d = admitted(&feed(&mut dct, &data, dims, 0, lead));
        assert!(dct.rejected_full() > 0, "capacity should bind here");
        assert!(dct.max_rejected_residual() > 0.02 * k00);
        dct.freeze().unwrap();
        let steps = feed(&mut dct, &data, dims, lead, n);
        assert_eq!(steps[0], Step::Accumulated { window: 0 });
        // the last building window started at lead - 1 - p; the first accumulated at lead - p
        let first = lead - dims.p;
        let (_, _, alpha_b) = batch(&slab, dims, &d, first..n - dims.p, true, 1e-6 * k00 * k00);
        let m = dct.len();
        let mut work = vec![0.0; dct.solve_work_len()];
        let mut alpha = vec![0.0; 2 * m];
        dct.solve(1e-6 * k00 * k00, &mut work, &mut alpha).unwrap();
        rel_close(&alpha, &alpha_b, 1e-9);
    }

    #[test]
    fn eq25_state_candidates_and_realization_vector() {
        let dims = PbsidDims::new(1, 2, 1, 4).unwrap();
        let n = 150;
        let data = lpv_data(n, 1, 2, 3);
        let slab = Slab::new(&data, 1, 2, 2).unwrap();
        let k00 = dual_kernel(&slab, 0, &slab, 0, 4, true);
        let mut dct = dict::<f64>(dims, DictionaryConfig::new(20, 0.05 * k00, true));
        let d = admitted(&feed(&mut dct, &data, dims, 0, n));
        let m = dct.len();
        let mut rng = StdRng::seed_from_u64(5);
        let alpha: Vec<f64> = (0..2 * m).map(|_| normal(&mut rng)).collect();
        let p = dims.p;
        // batch eq. (25) with the rows D: kernel (a, b) of block i is Theorem 10 between the
        // window starting at a - i + 1 and window b, summed from t0 = i - 1 (as the host's
        // dual_gamma_kz_matrix)
        let batch_g = |b: usize, f: usize| -> Vec<f64> {
            let mut g = vec![0.0; f * 2];
            for i in 1..=f {
                for (sa, &a) in d.iter().enumerate() {
                    let k = theorem10(&slab, a as isize - (i as isize - 1), &slab, b, i - 1, p);
                    for j in 0..2 {
                        g[(i - 1) * 2 + j] += alpha[j * m + sa] * k;
                    }
                }
            }
            g
        };
        for f in [1, 2, p] {
            let mut kap = vec![0.0; f * m];
            let mut g = vec![0.0; f * 2];
            for b in [0, 1, 37, n - p] {
                dct.state_candidate(&slab, b, f, &alpha, &mut g).unwrap();
                rel_close(&g, &batch_g(b, f), 1e-12);
                dct.shifted_kernels(&slab, b, f, &mut kap).unwrap();
                // block 1 (i = 1) is the unshifted kernel Z^T Z (Theorem 10)
                for (sa, &a) in d.iter().enumerate() {
                    let k = theorem10(&slab, a as isize, &slab, b, 0, p);
                    assert!((kap[sa] - k).abs() <= 1e-12 * k00);
                }
            }
            // a window needs p samples: b = n - p is the last column, n - p + 1 is refused
            assert!(dct
                .state_candidate(&slab, n - p + 1, f, &alpha, &mut g)
                .is_err());
            // realization vector of window k: [mu (x) [g_k; u; y]; g_{k+1}]
            let len = realization_vector_len(1, 2, 1, f);
            let mut v = vec![0.0; len];
            let k = 20;
            dct.write_realization_vector(&slab, k, f, &alpha, &mut v)
                .unwrap();
            let mut xi = batch_g(k, f);
            xi.extend(slab.u(k + p));
            xi.extend(slab.y(k + p));
            let mu = slab.mu(k + p);
            let mut expect = Vec::new();
            for mi in mu {
                expect.extend(xi.iter().map(|x| mi * x));
            }
            expect.extend(batch_g(k + 1, f));
            rel_close(&v, &expect, 1e-12);
            assert!(dct
                .write_realization_vector(&slab, n - p, f, &alpha, &mut v)
                .is_err());
        }
        assert!(dct
            .state_candidate(&slab, 0, p + 1, &alpha, &mut [0.0; 10])
            .is_err());
    }

    /// Rank of the span of phi_k for periodic scheduling of period P with generic u, y
    /// (section 6.1, made exact): block j of z_k^p is v_c^j (x) z_{k+j-1} with
    /// v_c^j = mu_{k+p-1} (x) ... (x) mu_{k+j-1} depending only on the phase c = k mod P, so
    /// the span is the direct sum over j of span_c{v_c^j} (x) R^{r+l}: dimension
    /// (r + l) sum_j min(P, m^{p-j+1}) for generic mu; the feedthrough adds r.
    fn periodic_rank(r: usize, l: usize, m: usize, p: usize, period: usize, ft: bool) -> usize {
        (r + l)
            * (1..=p)
                .map(|j| period.min(m.pow((p - j + 1) as u32)))
                .sum::<usize>()
            + if ft { r } else { 0 }
    }

    /// Algorithm 3 as printed (batch): keep row j of K when its squared distance to the
    /// span of the kept rows exceeds tol ||row_j||^2 (Gram-Schmidt twice).
    fn algorithm3_rows(k: &[Vec<f64>], tol: f64) -> Vec<usize> {
        let mut basis: Vec<Vec<f64>> = Vec::new();
        let mut kept = Vec::new();
        for (j, row) in k.iter().enumerate() {
            let mut res = row.clone();
            for _ in 0..2 {
                for q in &basis {
                    let c: f64 = q.iter().zip(&res).map(|(a, b)| a * b).sum();
                    for (x, qv) in res.iter_mut().zip(q) {
                        *x -= c * qv;
                    }
                }
            }
            let r2: f64 = res.iter().map(|x| x * x).sum();
            let n2: f64 = row.iter().map(|x| x * x).sum();
            if r2 > tol * n2 {
                let nr = r2.sqrt();
                basis.push(res.iter().map(|x| x / nr).collect());
                kept.push(j);
            }
        }
        kept
    }

    #[test]
    fn periodic_scheduling_admits_the_exact_rank() {
        let mut rng = StdRng::seed_from_u64(21);
        for (p, period, ft) in [
            (3usize, 3usize, true),
            (4, 5, true),
            (3, 2, false),
            (4, 3, false),
        ] {
            let dims = PbsidDims::new(1, 1, 1, p).unwrap();
            let rho: Vec<f64> = (0..period).map(|_| rng.gen::<f64>() * 2.0 - 1.0).collect();
            let n = 400;
            let mut data = Vec::new();
            for k in 0..n {
                data.extend([normal(&mut rng), normal(&mut rng), 1.0, rho[k % period]]);
            }
            let expect = periodic_rank(1, 1, 2, p, period, ft);
            let mut dct = dict::<f64>(dims, DictionaryConfig::new(100, 0.0, ft));
            let d = admitted(&feed(&mut dct, &data, dims, 0, n));
            assert_eq!(dct.len(), expect, "p {p} P {period}");
            assert!(expect <= period * 2 * p + usize::from(ft));
            assert_eq!(dct.rejected_full(), 0);
            // the batch row selection of Algorithm 3 keeps the same rows
            let slab = Slab::new(&data, 1, 1, 2).unwrap();
            let nbar = n - p;
            let kmat: Vec<Vec<f64>> = (0..nbar)
                .map(|a| {
                    (0..nbar)
                        .map(|b| dual_kernel(&slab, a, &slab, b, p, ft))
                        .collect()
                })
                .collect();
            assert_eq!(algorithm3_rows(&kmat, 1e-9), d, "p {p} P {period}");
        }
        // inputs and outputs periodic too: the windows repeat, P of them span everything
        for period in [3usize, 7] {
            let dims = PbsidDims::new(1, 1, 1, 3).unwrap();
            let sig: Vec<[f64; 3]> = (0..period)
                .map(|_| [normal(&mut rng), normal(&mut rng), rng.gen::<f64>()])
                .collect();
            let data: Vec<f64> = (0..200)
                .flat_map(|k| {
                    let s = sig[k % period];
                    [s[0], s[1], 1.0, s[2]]
                })
                .collect();
            let mut dct = dict::<f64>(dims, DictionaryConfig::new(50, 0.0, true));
            let d = admitted(&feed(&mut dct, &data, dims, 0, 200));
            assert_eq!(d, (0..period).collect::<Vec<_>>());
        }
    }

    #[test]
    fn epsilon_zero_admits_independent_windows_up_to_capacity() {
        let dims = PbsidDims::new(1, 1, 1, 3).unwrap();
        let q = dims.q().unwrap();
        assert_eq!(q, 28);
        let mut rng = StdRng::seed_from_u64(4);
        let n = 120;
        let data: Vec<f64> = (0..n)
            .flat_map(|_| [normal(&mut rng), normal(&mut rng), 1.0, normal(&mut rng)])
            .collect();
        for ft in [true, false] {
            let dim = q + usize::from(ft);
            // capacity above the feature dimension: exactly dim windows, the first dim
            let mut dct = dict::<f64>(dims, DictionaryConfig::new(40, 0.0, ft));
            let steps = feed(&mut dct, &data, dims, 0, n);
            assert_eq!(admitted(&steps), (0..dim).collect::<Vec<_>>());
            assert_eq!(dct.rejected_dependent(), (n - 3 - dim) as u64);
            assert_eq!(dct.rejected_full(), 0);
            // capacity below it: the first 10 are admitted, every later window is reported Full
            let mut dct = dict::<f64>(dims, DictionaryConfig::new(10, 0.0, ft));
            let steps = feed(&mut dct, &data, dims, 0, n);
            assert_eq!(admitted(&steps), (0..10).collect::<Vec<_>>());
            assert!(dct.is_full());
            assert_eq!(dct.rejected_full(), (n - 3 - 10) as u64);
            assert!(matches!(
                steps[3 + 10],
                Step::Full { window: 10, residual } if residual > 0.0
            ));
        }
    }

    #[test]
    fn bad_samples_leave_the_state_unchanged() {
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let n = 80;
        let data = lpv_data(n, 1, 2, 9);
        let snapshot = |d: &Dict<f64>| {
            (
                d.store[..d.windows_len()].to_vec(),
                d.cholesky().to_vec(),
                d.len(),
                d.windows(),
                d.rejected_dependent(),
                d.rejected_full(),
                d.window().len(),
                d.normal_equations()
                    .map(|g| (g.packed().to_vec(), g.count())),
            )
        };
        let mut dct = dict::<f64>(dims, DictionaryConfig::new(10, 0.0, true));
        feed(&mut dct, &data, dims, 0, 30);
        for phase in 0..2 {
            if phase == 1 {
                dct.freeze().unwrap();
                feed(&mut dct, &data, dims, 30, 50);
            }
            let before = snapshot(&dct);
            let reference = dct.clone();
            assert_eq!(
                dct.update(&[1.0], &[f64::NAN, 0.0], &[0.1]),
                Err(Error::NonFinite {
                    field: Field::Output,
                    index: 0
                })
            );
            assert!(dct.update(&[f64::INFINITY], &[0.0, 0.0], &[0.1]).is_err());
            assert!(dct.update(&[1.0], &[0.0, 0.0], &[0.1, 0.2]).is_err());
            // finite but the kernels overflow
            assert_eq!(
                dct.update(&[1e200], &[1e200, 1e200], &[1e200]),
                Err(Error::Overflow)
            );
            assert_eq!(snapshot(&dct), before);
            // the next good sample behaves as if nothing had happened
            let mut a = dct.clone();
            let mut b = reference;
            let sa = feed(&mut a, &data, dims, 50, 60);
            let sb = feed(&mut b, &data, dims, 50, 60);
            assert_eq!(sa, sb);
            assert_eq!(snapshot(&a), snapshot(&b));
        }
    }

    #[test]
    fn f32_agrees_with_f64() {
        let dims = PbsidDims::new(1, 2, 1, 3).unwrap();
        let n = 200;
        let data = lpv_data(n, 1, 2, 13);
        let slab = Slab::new(&data, 1, 2, 2).unwrap();
        let k00 = dual_kernel(&slab, 0, &slab, 0, 3, true);
        let mut d64 = dict::<f64>(dims, DictionaryConfig::new(15, 0.1 * k00, true));
        let mut d32 = dict::<f32>(dims, DictionaryConfig::new(15, 0.1 * k00 as f32, true));
        let a64 = admitted(&feed(&mut d64, &data, dims, 0, n));
        let a32 = admitted(&feed(&mut d32, &data, dims, 0, n));
        assert_eq!(a64, a32);
        d64.freeze().unwrap();
        d32.freeze().unwrap();
        d64.break_window();
        d32.break_window();
        feed(&mut d64, &data, dims, 0, n);
        feed(&mut d32, &data, dims, 0, n);
        let m = d64.len();
        let lam = 1e-2 * k00 * k00;
        let mut w64 = vec![0.0; d64.solve_work_len()];
        let mut al64 = vec![0.0; 2 * m];
        d64.solve(lam, &mut w64, &mut al64).unwrap();
        let mut w32 = vec![0.0f32; d32.solve_work_len()];
        let mut al32 = vec![0.0f32; 2 * m];
        d32.solve(lam as f32, &mut w32, &mut al32).unwrap();
        // compare the fitted outputs alpha K_{D,:} (the quantity that matters, eq. (22))
        let (mut e, mut s) = (0.0f64, 0.0f64);
        let mut k64 = vec![0.0; m];
        let mut k32 = vec![0.0f32; m];
        let data32: Vec<f32> = data.iter().map(|v| *v as f32).collect();
        let slab32 = Slab::new(&data32, 1, 2, 2).unwrap();
        for b in 0..n - 3 {
            d64.kernel_vector(&slab, b, &mut k64).unwrap();
            d32.kernel_vector(&slab32, b, &mut k32).unwrap();
            for j in 0..2 {
                let p64: f64 = (0..m).map(|a| al64[j * m + a] * k64[a]).sum();
                let p32: f64 = (0..m).map(|a| (al32[j * m + a] * k32[a]) as f64).sum();
                e += (p64 - p32).powi(2);
                s += p64 * p64;
            }
        }
        assert!(e < 1e-6 * s, "relative error {}", (e / s).sqrt());
    }

    #[test]
    fn static_storage_and_configuration_errors() {
        const R: usize = 1;
        const L: usize = 1;
        const S: usize = 1;
        const P: usize = 2;
        const M: usize = 6;
        const W: usize = window_storage_len(R, L, S, P);
        const D: usize = dictionary_storage_len(R, L, S, P, M);
        const G: usize = dictionary_gram_len(L, M);
        let dims = PbsidDims::new(R, L, S, P).unwrap();
        let mut dct =
            KernelDictionaryArrays::<f32, W, D, G>::new(dims, DictionaryConfig::new(M, 0.0, true))
                .unwrap();
        let mut acc = 0;
        for k in 0..40 {
            let x = k as f32;
            if k == 20 {
                dct.freeze().unwrap();
                dct.break_window();
            }
            let s = dct
                .update(&[(0.7 * x).sin()], &[(1.3 * x).cos()], &[(0.4 * x).sin()])
                .unwrap();
            acc += usize::from(matches!(s, Step::Accumulated { .. }));
        }
        assert_eq!(dct.len(), M);
        assert_eq!(acc, 20 - P);
        let mut work = [0.0f32; packed_len(M)];
        let mut alpha = [0.0f32; L * M];
        dct.solve(1e-3, &mut work, &mut alpha).unwrap();
        // B5 sizes quoted in the module documentation
        assert_eq!(window_storage_len(1, 2, 1, 10), 60);
        assert_eq!(dictionary_storage_len(1, 2, 1, 10, 100), 10_652);
        assert_eq!(dictionary_gram_len(2, 100), 10_506);
        assert_eq!(realization_vector_len(1, 2, 1, 10), 66);
        assert_eq!(PbsidDims::new(1, 2, 1, 10).unwrap().q().unwrap(), 6_138);
        // configuration errors
        let bad = |cfg: DictionaryConfig<f64>, dlen: usize, glen: usize| {
            KernelDictionary::with_storage(
                dims,
                cfg,
                vec![0.0; W],
                vec![0.0; dlen],
                vec![0.0; glen],
            )
            .err()
        };
        assert!(matches!(
            bad(DictionaryConfig::new(0, 0.0, true), D, G),
            Some(Error::InvalidConfig(_))
        ));
        assert!(matches!(
            bad(DictionaryConfig::new(M, -1.0, true), D, G),
            Some(Error::InvalidConfig(_))
        ));
        assert!(matches!(
            bad(DictionaryConfig::new(M, f64::NAN, true), D, G),
            Some(Error::InvalidConfig(_))
        ));
        assert_eq!(
            bad(DictionaryConfig::new(M, 0.0, true), D - 1, G),
            Some(Error::Capacity {
                needed: D,
                capacity: D - 1
            })
        );
        assert!(matches!(
            bad(DictionaryConfig::new(M, 0.0, true), D, G - 1),
            Some(Error::Capacity { .. })
        ));
        assert_eq!(
            bad(DictionaryConfig::new(usize::MAX / 2, 0.0, true), D, G),
            Some(Error::Overflow)
        );
        // solving before the freeze is an error, not a panic
        let d2 = KernelDictionary::with_storage(
            dims,
            DictionaryConfig::new(M, 0.0, true),
            vec![0.0; W],
            vec![0.0; D],
            vec![0.0; G],
        )
        .unwrap();
        assert!(d2.solve(0.0, &mut [], &mut []).is_err());
        // singular normal equations without regularisation are reported
        let mut d3 = d2.clone();
        for k in 0..6 {
            let x = k as f64;
            d3.update(&[x.sin()], &[x.cos()], &[0.3 * x]).unwrap();
        }
        d3.freeze().unwrap();
        let m = d3.len();
        assert!(m > 0);
        let mut work = vec![0.0; d3.solve_work_len()];
        let mut alpha = vec![0.0; m];
        assert_eq!(d3.solve(0.0, &mut work, &mut alpha), Err(Error::Singular));
        assert!(d3.solve(1.0, &mut work, &mut alpha).is_ok());
    }
}
