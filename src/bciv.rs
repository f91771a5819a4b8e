//! Streaming bias-corrected instrumental-variable statistics (BC-IV paper, section 5).
//!
//! With the scheduling measured as p(k) = p_o(k) + eta(k), eta ~ N(0, sigma^2) (eq. (3)),
//! the IV cross moment sum z(k) phi(k)^T is biased. Section 5.1 replaces
//! Omega_k = z(k) [chi(k) (x) pbasis(p_o(k))]^T by a matrix Psi_k of the *measured* data whose
//! expectation is the same (eq. (12)), built with the Hermite substitution (11). Psi_k is a
//! polynomial in sigma^2, so we accumulate one matrix per power of sigma^2:
//! Psi(sigma^2) = sum_t sigma^(2t) M_t, and any sigma can be evaluated after the data has gone
//! (the grid search of section 5.3 becomes a streaming operation).
//!
//! **Instruments.** z(k) = zeta(k) (x) pbasis_z(p(k)): `zeta(k)` is given by the caller (the
//! paper's choice, section 4, is zeta(k) = [-yhat(k-1) .. -yhat(k-na), u(k) .. u(k-nb)] with
//! yhat the simulated output of the current model: [`crate::arx::ArxWindow::simulate_step`]
//! and [`crate::arx::ArxWindow::write_chi`] build it), pbasis_z is the polynomial basis of
//! degree `ngz` (the paper: ngz = ng). Because z(k) contains the *noisy* p(k), the
//! correction accounts for the shared eta(k): for instrument monomial P_i and regressor
//! monomial P_j of one signal,
//!
//! E[(p_o + eta)^i] p_o^j = sum_l K(i, l) sigma^(2l) p_o^(i+j-2l),
//!
//! and each p_o^n is replaced by the term inside the expectation of eq. (11),
//! h_n(p) = sum_m (-1)^m K(n, m) sigma^(2m) p^(n-2m), with K(n, m) = n! / (m! (n-2m)! 2^m).
//! For j = 0 this reduces to P_i(p) itself (no correction where p_o does not appear). A
//! caller who wants a z(k) that does not depend on p(k) at all sets `ngz = 0` and passes the
//! whole instrument as `zeta`.
//!
//! **Several scheduling signals** with independent noise: the factors of the signals
//! multiply (monomials are products of powers). Signal s has variance
//! sigma_s^2 = rho_s sigma^2 with fixed ratios rho_s (default 1: a common sigma; rho_s = 0
//! for a noise-free signal), so Psi stays a polynomial in the one scalar sigma^2.
//!
//! Requirements of the paper (section 5): zeta(k) and chi(k) must not depend on eta(k) (true
//! for the simulated-output instruments and for ARX regressors: they use p only through
//! past samples), and eta is white and Gaussian.
//!
//! **Forgetting, windows and merging** (issue 18). [`BcivStats::set_forgetting`]: every
//! accumulated sample first scales the statistics and their low parts by lambda, so
//! Psi = sum_k lambda^(n-1-k) Psi_k and z^T y likewise (eq. (10) with weighted rows; the
//! constant N of eq. (10) becomes the effective count sum lambda^age, which the caller takes
//! as 1/(1 - lambda) once the record is long). A sliding window of N samples:
//! [`crate::sliding::Sliding`] over a `BcivStats` (the [`crate::sliding::Rebase`] impl
//! below) keeps the statistics of the last N/2 ..= N - 1 samples by rebasing the sums and
//! their low parts every N/2 samples; the two are alternatives (a window refuses
//! lambda < 1). Merging ([`BcivStats::merge`]) adds the other's sums as they are: exact
//! for plain sums (the concatenated record); for forgetting statistics only between
//! records that ran at the same time (same lambda required, neither side re-aged); two
//! windows merge into the sum of both windows (one window of the union only if their
//! halves cover the same samples of two sensors).

use crate::arx::{arx_window_len, basis_len, for_each_monomial, write_basis, ArxDims, ArxWindow};
use crate::error::{check_vec, Error, Field};
use crate::real::{first_non_finite, Real};
use crate::stats::kahan_add;

/// Highest ng + ngz supported (the Hermite coefficients are exact integers in u64 up to 20!).
pub const MAX_TOTAL_DEGREE: usize = 20;

/// Dimensions of the BC-IV statistics: the LPV-ARX model, the length `nzeta` of the
/// instrument part zeta(k) and the degree `ngz` of the instrument basis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BcivDims {
    /// The model whose regressor phi(k) = chi(k) (x) pbasis(p(k)) is corrected.
    pub arx: ArxDims,
    /// Length of zeta(k).
    pub nzeta: usize,
    /// Degree of the instrument basis pbasis_z (same signals, same ordering as the model's).
    pub ngz: usize,
}

/// The sizes derived from [`BcivDims`] (all validated against overflow).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Sizes {
    chi: usize,
    nbas: usize,
    nbz: usize,
    ntheta: usize,
    nz: usize,
    npow: usize,
    dmax: usize,
    // offsets into the storage
    stats: usize,
    ratios: usize,
    exps_r: usize,
    exps_z: usize,
    chi_buf: usize,
    zbasis: usize,
    ftab: usize,
    powers: usize,
    poly: usize,
    /// the low parts of the compensated statistics (`stats` values)
    comp: usize,
    total: usize,
}

fn sizes(d: &BcivDims) -> Result<Sizes, Error> {
    let a = d.arx;
    let chi = a.chi_len();
    let nbas = a.n_basis()?;
    let nbz = basis_len(a.s, d.ngz).ok_or(Error::Overflow)?;
    let ntheta = a.n_theta()?;
    let nz = d.nzeta.checked_mul(nbz).ok_or(Error::Overflow)?;
    let dmax = a.ng + d.ngz;
    let npow = dmax / 2 + 1;
    let m = nz
        .checked_mul(ntheta)
        .and_then(|v| v.checked_mul(npow))
        .ok_or(Error::Overflow)?;
    let add = |x: usize, y: usize| x.checked_add(y).ok_or(Error::Overflow);
    let mul = |x: usize, y: usize| x.checked_mul(y).ok_or(Error::Overflow);
    let stats = add(nz, m)?;
    let ratios = stats;
    let exps_r = add(ratios, a.s)?;
    let exps_z = add(exps_r, mul(nbas, a.s)?)?;
    let chi_buf = add(exps_z, mul(nbz, a.s)?)?;
    let zbasis = add(chi_buf, chi)?;
    let ftab = add(zbasis, nbz)?;
    let powers = add(ftab, mul(mul(nbz, nbas)?, npow)?)?;
    let poly = add(powers, mul(a.s, dmax + 1)?)?;
    let comp = add(poly, 2 * npow)?;
    let total = add(comp, stats)?;
    Ok(Sizes {
        chi,
        nbas,
        nbz,
        ntheta,
        nz,
        npow,
        dmax,
        stats,
        ratios,
        exps_r,
        exps_z,
        chi_buf,
        zbasis,
        ftab,
        powers,
        poly,
        comp,
        total,
    })
}

impl BcivDims {
    /// Validate and build. `nzeta` must be >= 1; ng + ngz <= [`MAX_TOTAL_DEGREE`].
    pub fn new(arx: ArxDims, nzeta: usize, ngz: usize) -> Result<Self, Error> {
        if nzeta == 0 {
            return Err(Error::InvalidConfig("instrument length nzeta must be >= 1"));
        }
        if arx.ng + ngz > MAX_TOTAL_DEGREE {
            return Err(Error::InvalidConfig(
                "ng + ngz exceeds 20 (Hermite coefficients)",
            ));
        }
        let d = BcivDims { arx, nzeta, ngz };
        sizes(&d)?;
        Ok(d)
    }
    /// The paper's instruments (section 4): zeta(k) has the layout of chi(k) (simulated
    /// outputs in place of measured ones) and the instrument basis is the model's, so
    /// n_z = n_theta and Psi is square.
    pub fn paper(arx: ArxDims) -> Result<Self, Error> {
        Self::new(arx, arx.chi_len(), arx.ng)
    }
    /// Number of parameters n_theta (columns of Psi).
    pub fn n_theta(&self) -> usize {
        sizes(self).map(|s| s.ntheta).unwrap_or(0)
    }
    /// Instrument length n_z = nzeta * C(s + ngz, ngz) (rows of Psi).
    pub fn n_z(&self) -> usize {
        sizes(self).map(|s| s.nz).unwrap_or(0)
    }
    /// Number of powers of sigma^2 accumulated: floor((ng + ngz) / 2) + 1.
    pub fn n_pow(&self) -> usize {
        (self.arx.ng + self.ngz) / 2 + 1
    }
    /// Length of the statistic values [sum z y; M_0; ..; M_T] (what a device sends).
    pub fn stats_len(&self) -> usize {
        sizes(self).map(|s| s.stats).unwrap_or(0)
    }
    /// Storage [`BcivStats`] needs (statistics, configuration and per-sample scratch).
    pub fn storage_len(&self) -> usize {
        sizes(self).map(|s| s.total).unwrap_or(0)
    }
    /// Storage of the internal ARX window.
    pub fn window_len(&self) -> usize {
        self.arx.window_len()
    }
}

/// Storage [`BcivStats`] needs, as a `const fn` for static arrays on the device (0 on
/// overflow); same value as [`BcivDims::storage_len`].
#[allow(clippy::too_many_arguments)]
pub const fn bciv_storage_len(
    r: usize,
    s: usize,
    na: usize,
    nb: usize,
    ng: usize,
    nzeta: usize,
    ngz: usize,
) -> usize {
    let chi = na + r * (nb + 1);
    let (nbas, nbz) = match (basis_len(s, ng), basis_len(s, ngz)) {
        (Some(a), Some(b)) => (a, b),
        _ => return 0,
    };
    let ntheta = chi * nbas;
    let nz = nzeta * nbz;
    let npow = (ng + ngz) / 2 + 1;
    2 * (nz + npow * nz * ntheta)
        + s
        + (nbas + nbz) * s
        + chi
        + nbz
        + npow * nbz * nbas
        + s * (ng + ngz + 1)
        + 2 * npow
}

/// Storage of the window of [`BcivStats`] as a `const fn` (see [`arx_window_len`]).
pub const fn bciv_window_len(r: usize, s: usize, na: usize, nb: usize, ng: usize) -> usize {
    arx_window_len(r, s, na, nb, ng)
}

/// n! for n <= 20.
fn fact(n: usize) -> u64 {
    (1..=n as u64).product()
}

/// K(n, m) = n! / (m! (n - 2m)! 2^m): the number of ways to pick m disjoint pairs among n
/// items; the coefficient of eq. (11) and of the Gaussian moments E[eta^(2m)] C(n, 2m).
fn k_coef(n: usize, m: usize) -> u64 {
    (fact(n) / (fact(m) * fact(n - 2 * m))) >> m
}

/// Coefficients (powers of sigma^2, t = 0..) of the corrected product for one signal:
/// f(p) with E[f(p_o + eta)] = E[(p_o + eta)^i] p_o^j (section 5.1, steps 1-3, with eq. (11)),
/// scaled by rho^t (sigma_s^2 = rho sigma^2). `pw[e]` = p^e. Adds nothing beyond `out.len()`.
fn hermite_factor<T: Real>(i: usize, j: usize, rho: T, pw: &[T], out: &mut [T]) {
    for v in out.iter_mut() {
        *v = T::ZERO;
    }
    let mut rho_t = T::ONE;
    for (t, o) in out.iter_mut().enumerate() {
        if 2 * t > i + j {
            break;
        }
        let mut acc = T::ZERO;
        for l in 0..=(i / 2).min(t) {
            let n = i + j - 2 * l;
            let m = t - l;
            if 2 * m > n {
                continue;
            }
            let c = k_coef(i, l) as f64 * k_coef(n, m) as f64;
            let term = T::of(c) * pw[n - 2 * m];
            if m % 2 == 0 {
                acc += term;
            } else {
                acc -= term;
            }
        }
        *o = acc * rho_t;
        rho_t *= rho;
    }
}

/// Streaming BC-IV statistics (section 5.1): sum z(k) y(k) and M_t with
/// Psi(sigma^2) = sum_t sigma^(2t) M_t = sum_k Psi_k; M_0 = sum z(k) phi(k)^T is the plain IV
/// moment. Holds an [`ArxWindow`] (storage `W`) that builds chi(k) from the measured data;
/// all other storage is `S` (statistics first, then configuration and per-sample scratch).
///
/// Size: `storage_len` + `window_len` values, of which n_z (1 + n_pow n_theta) are the
/// statistics. B6 with the paper's instruments (n_theta = n_z = 21, 3 powers of sigma^2):
/// 2 743 + 21 values (1 344 of them statistics, 1 344 their compensation: the sums are
/// compensated as in [`crate::stats`]), 11 KB in f32.
#[derive(Debug, Clone)]
pub struct BcivStats<T, S, W> {
    dims: BcivDims,
    sz: Sizes,
    window: ArxWindow<T, W>,
    data: S,
    count: u64,
    /// Forgetting factor in (0, 1] (1: plain sums).
    lambda: T,
}

impl<T, S, W> BcivStats<T, S, W>
where
    T: Real,
    S: AsRef<[T]> + AsMut<[T]>,
    W: AsRef<[T]> + AsMut<[T]>,
{
    /// Empty statistics over `storage` (`dims.storage_len()`) and `window`
    /// (`dims.window_len()`), all noise ratios 1 (a common sigma).
    pub fn new(dims: BcivDims, mut storage: S, window: W) -> Result<Self, Error> {
        let sz = sizes(&dims)?;
        let cap = storage.as_ref().len();
        if cap < sz.total {
            return Err(Error::Capacity {
                needed: sz.total,
                capacity: cap,
            });
        }
        let window = ArxWindow::new(dims.arx, window)?;
        let s = dims.arx.s;
        {
            let buf = storage.as_mut();
            buf[..sz.stats].fill(T::ZERO);
            buf[sz.comp..sz.comp + sz.stats].fill(T::ZERO);
            for v in buf[sz.ratios..sz.ratios + s].iter_mut() {
                *v = T::ONE;
            }
        }
        let mut st = BcivStats {
            dims,
            sz,
            window,
            data: storage,
            count: 0,
            lambda: T::ONE,
        };
        st.fill_exponents()?;
        Ok(st)
    }

    /// Exponent tables of both bases, stored as small integers in T.
    fn fill_exponents(&mut self) -> Result<(), Error> {
        let s = self.dims.arx.s;
        if s == 0 {
            return Ok(());
        }
        let sz = self.sz;
        let buf = self.data.as_mut();
        // the table of arx::write_exponents, kept as small integers in T: no extra storage type
        for (ng, off, n) in [
            (self.dims.arx.ng, sz.exps_r, sz.nbas),
            (self.dims.ngz, sz.exps_z, sz.nbz),
        ] {
            // reproduce write_exponents row by row via the parent recursion
            for v in buf[off..off + n * s].iter_mut() {
                *v = T::ZERO;
            }
            for_each_monomial(s, ng, |i, parent, var| {
                for k in 0..s {
                    buf[off + i * s + k] = buf[off + parent * s + k];
                }
                buf[off + i * s + var] += T::ONE;
            });
        }
        Ok(())
    }

    /// The dimensions.
    pub fn dims(&self) -> BcivDims {
        self.dims
    }

    /// Number of samples accumulated (N of eq. (10)).
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Noise-variance ratios rho_s (sigma_s^2 = rho_s sigma^2).
    pub fn noise_ratios(&self) -> &[T] {
        let s = self.dims.arx.s;
        &self.data.as_ref()[self.sz.ratios..self.sz.ratios + s]
    }

    /// Set the ratios rho_s >= 0 (e.g. 0 for a noise-free signal, 4 for a sensor with twice
    /// the standard deviation). Only before the first sample: the accumulated M_t depend
    /// on them.
    pub fn set_noise_ratios(&mut self, rho: &[T]) -> Result<(), Error> {
        check_vec(Field::Scheduling, rho, self.dims.arx.s)?;
        if self.count != 0 {
            return Err(Error::InvalidConfig(
                "noise ratios can only be set before accumulating",
            ));
        }
        if rho.iter().any(|r| *r < T::ZERO) {
            return Err(Error::InvalidConfig("noise ratios must be >= 0"));
        }
        let o = self.sz.ratios;
        self.data.as_mut()[o..o + rho.len()].copy_from_slice(rho);
        Ok(())
    }

    /// sum_k z(k) y(k) (the Z^T Y of eq. (10)), length n_z.
    pub fn zy(&self) -> &[T] {
        &self.data.as_ref()[..self.sz.nz]
    }

    /// M_t (n_z x n_theta, row-major), the coefficient of sigma^(2t) in Psi. M_0 = Z^T Phi.
    pub fn moment(&self, t: usize) -> Option<&[T]> {
        if t >= self.sz.npow {
            return None;
        }
        let len = self.sz.nz * self.sz.ntheta;
        let off = self.sz.nz + t * len;
        Some(&self.data.as_ref()[off..off + len])
    }

    /// All statistic values [sum z y; M_0; ..; M_T] (what a device sends to the host).
    pub fn values(&self) -> &[T] {
        &self.data.as_ref()[..self.sz.stats]
    }

    /// Overwrite the statistic values and count (statistics pulled from a device with the
    /// same dimensions and ratios). Checked for length and finiteness first.
    pub fn load(&mut self, values: &[T], count: u64) -> Result<(), Error> {
        check_vec(Field::Regressor, values, self.sz.stats)?;
        let sz = self.sz;
        let buf = self.data.as_mut();
        buf[..sz.stats].copy_from_slice(values);
        for v in buf[sz.comp..sz.comp + sz.stats].iter_mut() {
            *v = T::ZERO;
        }
        self.count = count;
        Ok(())
    }

    /// Forget the statistics (the window and ratios are kept).
    pub fn reset(&mut self) {
        let sz = self.sz;
        let buf = self.data.as_mut();
        buf[..sz.stats].fill(T::ZERO);
        buf[sz.comp..sz.comp + sz.stats].fill(T::ZERO);
        self.count = 0;
    }

    /// Exponential forgetting of the statistics from now on: Psi <- lambda Psi + Psi_k per
    /// accumulated sample, lambda in (0, 1] (1: plain sums). Merging then needs the same
    /// lambda (see [`crate::stats`] for what a merge of forgetting statistics means).
    pub fn set_forgetting(&mut self, lambda: T) -> Result<(), Error> {
        if !(lambda.is_finite() && lambda > T::ZERO && lambda <= T::ONE) {
            return Err(Error::InvalidConfig("forgetting factor must be in (0, 1]"));
        }
        self.lambda = lambda;
        Ok(())
    }

    /// Start a new experiment: the next regressor needs max(na, nb) + 1 fresh samples.
    pub fn break_window(&mut self) {
        self.window.clear();
    }

    /// Add another accumulator of the same dimensions and noise ratios: the result equals
    /// accumulating the concatenated data (experiments, devices, cross-validation folds).
    pub fn merge<S2, W2>(&mut self, other: &BcivStats<T, S2, W2>) -> Result<(), Error>
    where
        S2: AsRef<[T]> + AsMut<[T]>,
        W2: AsRef<[T]> + AsMut<[T]>,
    {
        if other.dims != self.dims
            || other.noise_ratios() != self.noise_ratios()
            || other.lambda != self.lambda
        {
            return Err(Error::Mismatch);
        }
        let sz = self.sz;
        let ob = other.data.as_ref();
        let (ohi, olo) = (&ob[..sz.stats], &ob[sz.comp..sz.comp + sz.stats]);
        let (hi, rest) = self.data.as_mut().split_at_mut(sz.stats);
        let lo = &mut rest[sz.comp - sz.stats..sz.comp];
        for (((h, l), oh), ol) in hi.iter_mut().zip(lo.iter_mut()).zip(ohi).zip(olo) {
            kahan_add(h, l, *oh);
            kahan_add(h, l, *ol);
        }
        self.count += other.count;
        Ok(())
    }

    /// Feed sample k: the instrument part zeta(k) (length nzeta), u(k), the measured y(k)
    /// and the measured (noisy) p(k). Returns `Ok(true)` when the window was full and the
    /// sample was accumulated. Non-finite or wrongly sized data, or values whose products
    /// overflow, are rejected with the statistics and the window left exactly as they were.
    pub fn update(&mut self, zeta: &[T], u: &[T], y: T, p: &[T]) -> Result<bool, Error> {
        check_vec(Field::Regressor, zeta, self.dims.nzeta)?;
        let was = self.window.len();
        self.window.push(u, y, p)?;
        if !self.window.is_ready() {
            return Ok(false);
        }
        let sz = self.sz;
        let r = {
            let chi = &mut self.data.as_mut()[sz.chi_buf..sz.chi_buf + sz.chi];
            self.window.write_chi(chi)
        };
        let r = r.and_then(|_| self.accumulate_checked(zeta, None, y, p));
        match r {
            Ok(()) => Ok(true),
            Err(e) => {
                self.window.unpush(was);
                Err(e)
            }
        }
    }

    /// Accumulate one sample whose chi(k) the caller built (host batch path; the internal
    /// window is not used): zeta(k), chi(k) (length na + r(nb+1)), y(k), p(k). On error
    /// nothing changes.
    pub fn accumulate(&mut self, zeta: &[T], chi: &[T], y: T, p: &[T]) -> Result<(), Error> {
        check_vec(Field::Regressor, zeta, self.dims.nzeta)?;
        check_vec(Field::Regressor, chi, self.sz.chi)?;
        self.accumulate_checked(zeta, Some(chi), y, p)
    }

    /// The per-sample update Psi_k (section 5.1 steps 1-3) for every power of sigma^2.
    /// `chi` is `None` when it is already in the scratch.
    fn accumulate_checked(
        &mut self,
        zeta: &[T],
        chi: Option<&[T]>,
        y: T,
        p: &[T],
    ) -> Result<(), Error> {
        let d = self.dims;
        let sz = self.sz;
        let s = d.arx.s;
        check_vec(Field::Output, core::slice::from_ref(&y), 1)?;
        check_vec(Field::Scheduling, p, s)?;
        let buf = self.data.as_mut();
        if let Some(c) = chi {
            buf[sz.chi_buf..sz.chi_buf + sz.chi].copy_from_slice(c);
        }
        // powers p_s^e, e = 0..=dmax
        let w = sz.dmax + 1;
        for (si, pv) in p.iter().enumerate() {
            let row = &mut buf[sz.powers + si * w..sz.powers + (si + 1) * w];
            let mut acc = T::ONE;
            for v in row.iter_mut() {
                *v = acc;
                acc *= *pv;
            }
        }
        if first_non_finite(&buf[sz.powers..sz.powers + s * w]).is_some() {
            return Err(Error::Overflow);
        }
        write_basis(s, d.ngz, p, &mut buf[sz.zbasis..sz.zbasis + sz.nbz])?;
        // F[t][iz][jb]: product over signals of the univariate corrected factors
        let npow = sz.npow;
        let (head, tail) = buf.split_at_mut(sz.ftab);
        let (ftab, rest) = tail.split_at_mut(sz.powers - sz.ftab);
        let (powers, poly) = rest.split_at_mut(sz.poly - sz.powers);
        let (poly, comp) = poly.split_at_mut(2 * npow);
        let (acc_poly, factor) = poly.split_at_mut(npow);
        let ratios = &head[sz.ratios..sz.ratios + s];
        let exps_r = &head[sz.exps_r..sz.exps_r + sz.nbas * s];
        let exps_z = &head[sz.exps_z..sz.exps_z + sz.nbz * s];
        for iz in 0..sz.nbz {
            for jb in 0..sz.nbas {
                for v in acc_poly.iter_mut() {
                    *v = T::ZERO;
                }
                acc_poly[0] = T::ONE;
                for si in 0..s {
                    let ei = exps_z[iz * s + si].to_f64() as usize;
                    let ej = exps_r[jb * s + si].to_f64() as usize;
                    if ei == 0 && ej == 0 {
                        continue;
                    }
                    hermite_factor(ei, ej, ratios[si], &powers[si * w..(si + 1) * w], factor);
                    // acc_poly *= factor (truncated: degrees beyond npow - 1 cannot occur)
                    for t in (0..npow).rev() {
                        let mut v = T::ZERO;
                        for u in 0..=t {
                            v += acc_poly[u] * factor[t - u];
                        }
                        acc_poly[t] = v;
                    }
                }
                for t in 0..npow {
                    ftab[(t * sz.nbz + iz) * sz.nbas + jb] = acc_poly[t];
                }
            }
        }
        // overflow guard before touching the statistics
        let amax = |v: &[T]| v.iter().fold(T::ZERO, |a, x| a.max(x.abs()));
        let fmax = amax(ftab);
        let zmax = amax(zeta);
        let chi_v = &head[sz.chi_buf..sz.chi_buf + sz.chi];
        let zb = &head[sz.zbasis..sz.zbasis + sz.nbz];
        let cmax = amax(chi_v);
        let bmax = amax(zb);
        if !fmax.is_finite()
            || !bmax.is_finite()
            || !(zmax * cmax * fmax).is_finite()
            || !(zmax * bmax * y.abs()).is_finite()
        {
            return Err(Error::Overflow);
        }
        // sum z y
        let (stats, cfg) = head.split_at_mut(sz.stats);
        let chi_v = &cfg[sz.chi_buf - sz.stats..sz.chi_buf - sz.stats + sz.chi];
        let zb = &cfg[sz.zbasis - sz.stats..sz.zbasis - sz.stats + sz.nbz];
        if self.lambda != T::ONE {
            // Psi <- lambda Psi + Psi_k (statistics and their low parts)
            for v in stats.iter_mut().chain(comp[..sz.stats].iter_mut()) {
                *v *= self.lambda;
            }
        }
        let (zy, m) = stats.split_at_mut(sz.nz);
        // compensated sums (see `crate::stats`): the low parts, same layout
        let (czy, cm) = comp[..sz.stats].split_at_mut(sz.nz);
        for (a, za) in zeta.iter().enumerate() {
            let zay = *za * y;
            for (iz, b) in zb.iter().enumerate() {
                let k = a * sz.nbz + iz;
                kahan_add(&mut zy[k], &mut czy[k], zay * *b);
            }
        }
        // M_t += sum over (alpha, iz), (beta, jb): zeta_alpha chi_beta F_t[iz][jb]
        let blk = sz.nz * sz.ntheta;
        for t in 0..npow {
            let mt = &mut m[t * blk..(t + 1) * blk];
            let ct = &mut cm[t * blk..(t + 1) * blk];
            let ft = &ftab[t * sz.nbz * sz.nbas..(t + 1) * sz.nbz * sz.nbas];
            for (a, za) in zeta.iter().enumerate() {
                if *za == T::ZERO {
                    continue;
                }
                for iz in 0..sz.nbz {
                    let span = (a * sz.nbz + iz) * sz.ntheta..(a * sz.nbz + iz + 1) * sz.ntheta;
                    let row = &mut mt[span.clone()];
                    let crow = &mut ct[span];
                    let frow = &ft[iz * sz.nbas..(iz + 1) * sz.nbas];
                    for (b, cb) in chi_v.iter().enumerate() {
                        let zc = *za * *cb;
                        if zc == T::ZERO {
                            continue;
                        }
                        let cols = b * sz.nbas..(b + 1) * sz.nbas;
                        for ((dst, lo), f) in row[cols.clone()]
                            .iter_mut()
                            .zip(crow[cols].iter_mut())
                            .zip(frow)
                        {
                            kahan_add(dst, lo, zc * *f);
                        }
                    }
                }
            }
        }
        self.count += 1;
        Ok(())
    }

    fn check_sigma2(sigma2: T) -> Result<(), Error> {
        if !sigma2.is_finite() || sigma2 < T::ZERO {
            return Err(Error::InvalidConfig("sigma^2 must be finite and >= 0"));
        }
        Ok(())
    }

    /// Psi(sigma^2) = sum_t sigma^(2t) M_t (= sum_k Psi_k of section 5.1) into `out`
    /// (n_z x n_theta, row-major), by Horner's rule.
    pub fn eval_psi(&self, sigma2: T, out: &mut [T]) -> Result<(), Error> {
        Self::check_sigma2(sigma2)?;
        let len = self.sz.nz * self.sz.ntheta;
        if out.len() != len {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: len,
                got: out.len(),
            });
        }
        for v in out.iter_mut() {
            *v = T::ZERO;
        }
        for t in (0..self.sz.npow).rev() {
            let mt = self.moment(t).unwrap_or(&[]);
            for (o, m) in out.iter_mut().zip(mt) {
                *o = *o * sigma2 + *m;
            }
        }
        Ok(())
    }

    /// Normal equations of the bias-corrected cost (10) for a given sigma^2:
    /// H = Psi^T Psi / N^2 (n_theta x n_theta, row-major, positive semidefinite) and
    /// g = Psi^T (Z^T Y) / N^2, so J_CIV(theta, 0, N) = theta^T H theta - 2 g^T theta + const.
    /// Feed (H, g) to [`crate::lasso`]: its objective 1/2 theta^T H theta - g^T theta +
    /// lambda_e ||theta||_1 is (10) / 2, i.e. the paper's lambda = 2 lambda_e.
    /// `psi` is scratch of n_z x n_theta values (left holding Psi(sigma^2)).
    pub fn normal_equations(
        &self,
        sigma2: T,
        psi: &mut [T],
        h: &mut [T],
        g: &mut [T],
    ) -> Result<(), Error> {
        let nt = self.sz.ntheta;
        let nz = self.sz.nz;
        if h.len() != nt * nt {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: nt * nt,
                got: h.len(),
            });
        }
        if g.len() != nt {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: nt,
                got: g.len(),
            });
        }
        if self.count == 0 {
            return Err(Error::InvalidConfig("no samples accumulated"));
        }
        self.eval_psi(sigma2, psi)?;
        let n = T::of(self.count as f64);
        let inv = T::ONE / (n * n);
        for v in h.iter_mut() {
            *v = T::ZERO;
        }
        for v in g.iter_mut() {
            *v = T::ZERO;
        }
        let zy = self.zy();
        for rrow in 0..nz {
            let row = &psi[rrow * nt..(rrow + 1) * nt];
            let zyr = zy[rrow];
            for a in 0..nt {
                let pa = row[a];
                if pa == T::ZERO {
                    continue;
                }
                g[a] += pa * zyr;
                let hrow = &mut h[a * nt..(a + 1) * nt];
                for (hb, pb) in hrow[a..].iter_mut().zip(&row[a..]) {
                    *hb += pa * *pb;
                }
            }
        }
        for a in 0..nt {
            g[a] *= inv;
            for b in a..nt {
                let v = h[a * nt + b] * inv;
                h[a * nt + b] = v;
                h[b * nt + a] = v;
            }
        }
        if first_non_finite(h).is_some() || first_non_finite(g).is_some() {
            return Err(Error::Overflow);
        }
        Ok(())
    }

    /// The non-regularised bias-corrected cost J_CIV(theta, 0, N) = ||(Z^T Y - Psi theta)/N||^2
    /// of eq. (10) with lambda = 0, from the statistics alone (no scratch): the criterion of
    /// the sigma search and of the lambda cross-validation on calibration data (sections 5.2,
    /// 5.3). With sigma^2 = 0 it is the IV cost J_IV(theta, 0, N) of eq. (8).
    pub fn civ_cost(&self, sigma2: T, theta: &[T]) -> Result<T, Error> {
        Self::check_sigma2(sigma2)?;
        check_vec(Field::Regressor, theta, self.sz.ntheta)?;
        if self.count == 0 {
            return Err(Error::InvalidConfig("no samples accumulated"));
        }
        let nt = self.sz.ntheta;
        let inv_n = T::ONE / T::of(self.count as f64);
        let zy = self.zy();
        let mut cost = T::ZERO;
        for (rrow, zyr) in zy.iter().enumerate() {
            let mut psi_theta = T::ZERO;
            for t in (0..self.sz.npow).rev() {
                let mt = self.moment(t).unwrap_or(&[]);
                let row = &mt[rrow * nt..(rrow + 1) * nt];
                let mut dotv = T::ZERO;
                for (a, b) in row.iter().zip(theta) {
                    dotv += *a * *b;
                }
                psi_theta = psi_theta * sigma2 + dotv;
            }
            let e = (*zyr - psi_theta) * inv_n;
            cost += e * e;
        }
        if cost.is_finite() {
            Ok(cost)
        } else {
            Err(Error::Overflow)
        }
    }
}

/// A sliding window over the BC-IV statistics ([`crate::sliding::Sliding`]): the sums
/// [sum z y; M_0; ..; M_T] and their low parts are rebased together, so the window holds
/// the statistics of the last N/2 ..= N - 1 accumulated samples, still compensated.
impl<T, S, W> crate::sliding::Rebase<T> for BcivStats<T, S, W>
where
    T: Real,
    S: AsRef<[T]> + AsMut<[T]>,
    W: AsRef<[T]> + AsMut<[T]>,
{
    fn sums_len(&self) -> usize {
        self.sz.stats
    }

    fn rebase(&mut self, snapshot: &mut [T], count: u64) -> Result<(), Error> {
        self.check_rebase()?;
        let sz = self.sz;
        if snapshot.len() < sz.stats {
            return Err(Error::Capacity {
                needed: sz.stats,
                capacity: snapshot.len(),
            });
        }
        // the low parts live after the configuration (comp >= stats)
        let (head, rest) = self.data.as_mut().split_at_mut(sz.comp);
        crate::sliding::rebase_values(
            &mut head[..sz.stats],
            &mut rest[..sz.stats],
            &mut snapshot[..sz.stats],
        );
        self.count = count;
        Ok(())
    }

    fn clear_sums(&mut self) {
        self.reset();
    }

    fn check_rebase(&self) -> Result<(), Error> {
        if self.lambda != T::ONE {
            return Err(crate::sliding::WINDOW_AND_FORGETTING);
        }
        Ok(())
    }
}

/// One sample (zeta, u, y, p) with a scalar y; a block row is [zeta (nzeta), u (r), y,
/// p (s)]. The output says whether the sample was accumulated (window full).
impl<T, S, W> crate::Streaming<T> for BcivStats<T, S, W>
where
    T: Real,
    S: AsRef<[T]> + AsMut<[T]>,
    W: AsRef<[T]> + AsMut<[T]>,
{
    type Sample<'a> = (&'a [T], &'a [T], T, &'a [T]);
    type Output = bool;

    fn update(&mut self, (zeta, u, y, p): Self::Sample<'_>) -> Result<bool, Error> {
        BcivStats::update(self, zeta, u, y, p)
    }

    fn row_len(&self) -> usize {
        self.dims.nzeta + self.dims.arx.sample_len()
    }

    fn sample<'a>(&self, row: &'a [T]) -> Self::Sample<'a> {
        let (zeta, rest) = row.split_at(self.dims.nzeta.min(row.len()));
        let (u, y, p) = crate::arx::split_arx_sample(self.dims.arx.r, rest);
        (zeta, u, y, p)
    }
}

impl<T, S, W, S2, W2> crate::Merge<BcivStats<T, S2, W2>> for BcivStats<T, S, W>
where
    T: Real,
    S: AsRef<[T]> + AsMut<[T]>,
    W: AsRef<[T]> + AsMut<[T]>,
    S2: AsRef<[T]> + AsMut<[T]>,
    W2: AsRef<[T]> + AsMut<[T]>,
{
    fn merge(&mut self, other: &BcivStats<T, S2, W2>) -> Result<(), Error> {
        BcivStats::merge(self, other)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// E[(p_o + eta)^n] for eta ~ N(0, s2): sum_k K(n, k) s2^k p_o^(n-2k).
    fn gauss_moment(n: usize, po: f64, s2: f64) -> f64 {
        (0..=n / 2)
            .map(|k| k_coef(n, k) as f64 * s2.powi(k as i32) * po.powi((n - 2 * k) as i32))
            .sum()
    }

    #[test]
    fn hermite_factor_is_exactly_unbiased() {
        // f(p) = sum_t c_t(p) sigma^(2t) is a polynomial in p; take its expectation with the
        // exact Gaussian moments and compare with E[(p_o + eta)^i] p_o^j.
        let s2 = 0.37;
        let po = 0.8;
        for i in 0..=4usize {
            for j in 0..=4usize {
                let npow = (i + j) / 2 + 1;
                // expectation, linear in the monomials p^e: evaluate f with p^e -> E[p^e]
                let pw: Vec<f64> = (0..=i + j).map(|e| gauss_moment(e, po, s2)).collect();
                let mut c = vec![0.0; npow];
                hermite_factor(i, j, 1.0, &pw, &mut c);
                let ef: f64 = c
                    .iter()
                    .enumerate()
                    .map(|(t, v)| v * s2.powi(t as i32))
                    .sum();
                let expect = gauss_moment(i, po, s2) * po.powi(j as i32);
                assert!((ef - expect).abs() < 1e-10, "i={i} j={j} {ef} {expect}");
                // j = 0: no correction, f(p) = p^i identically
                if j == 0 {
                    let p = 1.7f64;
                    let pw: Vec<f64> = (0..=i).map(|e| p.powi(e as i32)).collect();
                    hermite_factor(i, 0, 1.0, &pw, &mut c);
                    assert!((c[0] - p.powi(i as i32)).abs() < 1e-12);
                    for v in &c[1..] {
                        assert!(v.abs() < 1e-12);
                    }
                }
            }
        }
        // eq. (11) itself (i = 0): h_2(p) = p^2 - sigma^2, h_3 = p^3 - 3 sigma^2 p
        let p = 2.0f64;
        let pw: Vec<f64> = (0..=3).map(|e| p.powi(e)).collect();
        let mut c = vec![0.0; 2];
        hermite_factor(0, 3, 1.0, &pw, &mut c);
        assert_eq!(c, vec![8.0, -6.0]);
        hermite_factor(0, 2, 0.5, &pw, &mut c);
        assert_eq!(c, vec![4.0, -0.5]);
    }

    #[test]
    fn static_storage_f32() {
        const N: usize = bciv_storage_len(1, 1, 1, 0, 2, 2, 2);
        const W: usize = bciv_window_len(1, 1, 1, 0, 2);
        let arx = ArxDims::new(1, 1, 1, 0, 2).unwrap();
        let d = BcivDims::paper(arx).unwrap();
        let mut st = BcivStats::new(d, [0.0f32; N], [0.0f32; W]).unwrap();
        let mut n = 0;
        for k in 0..20 {
            let x = 0.1 * k as f32;
            if st.update(&[0.5 - x, x], &[x], 1.0 - x, &[x * x]).unwrap() {
                n += 1;
            }
        }
        assert_eq!(n, 19);
        assert_eq!(st.count(), 19);
        let mut psi = [0.0f32; 36];
        st.eval_psi(0.01, &mut psi).unwrap();
        assert!(psi.iter().all(|v| v.is_finite()));
        assert!(st.civ_cost(0.01, &[0.1; 6]).unwrap() >= 0.0);
    }

    #[test]
    fn forgetting_scales_the_past() {
        let arx = ArxDims::new(1, 1, 2, 1, 2).unwrap();
        let d = BcivDims::paper(arx).unwrap();
        let st =
            || BcivStats::new(d, vec![0.0f64; d.storage_len()], vec![0.0; d.window_len()]).unwrap();
        let chi_len = 2 + 2;
        let sample = |k: usize| {
            let f = k as f64;
            let zeta: Vec<f64> = (0..d.nzeta).map(|i| (0.3 * f + i as f64).sin()).collect();
            let chi: Vec<f64> = (0..chi_len).map(|i| (0.7 * f - i as f64).cos()).collect();
            (zeta, chi, 0.1 * f - 0.4, [0.2 + 0.05 * f])
        };
        let (mut a, mut b, mut fg) = (st(), st(), st());
        fg.set_forgetting(0.5).unwrap();
        let (z, c, y, p) = sample(1);
        a.accumulate(&z, &c, y, &p).unwrap();
        fg.accumulate(&z, &c, y, &p).unwrap();
        let (z, c, y, p) = sample(2);
        b.accumulate(&z, &c, y, &p).unwrap();
        fg.accumulate(&z, &c, y, &p).unwrap();
        for ((f, x), y) in fg.values().iter().zip(a.values()).zip(b.values()) {
            assert!((f - (0.5 * x + y)).abs() < 1e-12);
        }
        assert_eq!(a.merge(&fg), Err(Error::Mismatch));
        assert!(fg.set_forgetting(0.0).is_err());
    }

    fn bciv_dims() -> BcivDims {
        BcivDims::paper(ArxDims::new(1, 1, 2, 1, 2).unwrap()).unwrap()
    }

    fn bciv_new<T: Real>(d: BcivDims) -> BcivStats<T, Vec<T>, Vec<T>> {
        BcivStats::new(
            d,
            vec![T::ZERO; d.storage_len()],
            vec![T::ZERO; d.window_len()],
        )
        .unwrap()
    }

    /// Sample k as (zeta, chi, y, p) in `T` (chi of length na + nb + 1 = 4).
    fn bciv_sample<T: Real>(d: BcivDims, k: usize) -> (Vec<T>, Vec<T>, T, [T; 1]) {
        let f = k as f64;
        let zeta = (0..d.nzeta)
            .map(|i| T::of((0.3 * f + i as f64).sin()))
            .collect();
        let chi = (0..4).map(|i| T::of((0.7 * f - i as f64).cos())).collect();
        (
            zeta,
            chi,
            T::of((0.05 * f).sin() - 0.4),
            [T::of(0.2 + 0.5 * (0.11 * f).cos())],
        )
    }

    /// Largest |a - b| over the statistic values, relative to the largest |b|.
    fn rel_diff<T: Real>(a: &[T], b: &[T]) -> f64 {
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.to_f64().abs()));
        a.iter()
            .zip(b)
            .map(|(x, y)| (x.to_f64() - y.to_f64()).abs())
            .fold(0.0, f64::max)
            / scale.max(1e-300)
    }

    /// A sliding window of N samples over the BC-IV statistics holds exactly the sums of
    /// the last N/2 ..= N - 1 samples (the rebase subtracts the older half, low parts
    /// included): checked against fresh statistics of those samples after every sample.
    fn window_is_the_sum_of_the_last_samples<T: Real>(tol: f64) -> f64 {
        use crate::sliding::{Rebase, Sliding};
        let d = bciv_dims();
        let window = 10u64;
        let half = 5usize;
        let mut sl = Sliding::new(bciv_new::<T>(d), window, vec![T::ZERO; d.stats_len()]).unwrap();
        assert_eq!(sl.inner().sums_len(), d.stats_len());
        let mut worst: f64 = 0.0;
        for k in 0..57 {
            let (z, c, y, p) = bciv_sample::<T>(d, k);
            sl.update_with(|s| s.accumulate(&z, &c, y, &p).map(|_| true), |a| *a)
                .unwrap();
            let seen = k + 1;
            let held = if seen < half {
                seen
            } else {
                half + seen % half
            };
            assert_eq!(sl.inner().count() as usize, held, "after {seen}");
            let mut fresh = bciv_new::<T>(d);
            for j in seen - held..seen {
                let (z, c, y, p) = bciv_sample::<T>(d, j);
                fresh.accumulate(&z, &c, y, &p).unwrap();
            }
            let e = rel_diff(sl.inner().values(), fresh.values());
            assert!(e <= tol, "after {seen}: {e:e}");
            worst = worst.max(e);
        }
        // forgetting and a window are alternatives
        let mut fg = bciv_new::<T>(d);
        fg.set_forgetting(T::of(0.9)).unwrap();
        assert!(Sliding::new(fg, window, vec![T::ZERO; d.stats_len()]).is_err());
        assert!(Sliding::new(bciv_new::<T>(d), window, vec![T::ZERO; 3]).is_err());
        worst
    }

    #[test]
    fn bciv_window_is_the_sum_of_the_last_samples_f64_f32() {
        let e64 = window_is_the_sum_of_the_last_samples::<f64>(1e-14);
        // f32: a few roundings of values of the window's size (compensated sums, one
        // subtraction per rebase)
        let e32 = window_is_the_sum_of_the_last_samples::<f32>(4.0 * f32::EPSILON as f64);
        std::println!("bciv window: worst relative difference f64 {e64:e}, f32 {e32:e}");
    }

    /// Forgetting weights sample k by lambda^(n - 1 - k): the forgetting statistics equal
    /// the weighted sum of single-sample statistics, in f64 and f32.
    fn forgetting_weights_by_age<T: Real>(tol: f64) -> f64 {
        let d = bciv_dims();
        let (lambda, n) = (0.8f64, 40usize);
        let mut fg = bciv_new::<T>(d);
        fg.set_forgetting(T::of(lambda)).unwrap();
        let mut want = vec![0.0f64; d.stats_len()];
        for k in 0..n {
            let (z, c, y, p) = bciv_sample::<T>(d, k);
            fg.accumulate(&z, &c, y, &p).unwrap();
            let mut one = bciv_new::<T>(d);
            one.accumulate(&z, &c, y, &p).unwrap();
            let w = lambda.powi((n - 1 - k) as i32);
            for (a, v) in want.iter_mut().zip(one.values()) {
                *a += w * v.to_f64();
            }
        }
        let want: Vec<T> = want.iter().map(|v| T::of(*v)).collect();
        let e = rel_diff(fg.values(), &want);
        assert!(e <= tol, "{e:e}");
        e
    }

    #[test]
    fn bciv_forgetting_weights_by_age_f64_f32() {
        let e64 = forgetting_weights_by_age::<f64>(1e-14);
        let e32 = forgetting_weights_by_age::<f32>(1e-5);
        std::println!("bciv forgetting: relative difference f64 {e64:e}, f32 {e32:e}");
    }

    #[test]
    fn sizes_are_consistent() {
        let arx = ArxDims::new(1, 1, 4, 2, 2).unwrap();
        let d = BcivDims::paper(arx).unwrap();
        assert_eq!(d.n_theta(), 21);
        assert_eq!(d.n_z(), 21);
        assert_eq!(d.n_pow(), 3);
        assert_eq!(d.stats_len(), 21 + 3 * 21 * 21);
        assert_eq!(d.storage_len(), bciv_storage_len(1, 1, 4, 2, 2, 7, 2));
        assert_eq!(d.window_len(), bciv_window_len(1, 1, 4, 2, 2));
        // the sizes quoted in the documentation of BcivStats
        assert_eq!(d.storage_len(), 1399 + 1344);
        assert_eq!(d.window_len(), 21);
        assert!(BcivDims::new(arx, 0, 2).is_err());
        assert!(BcivDims::new(ArxDims::new(1, 1, 1, 0, 15).unwrap(), 2, 15).is_err());
    }
}
