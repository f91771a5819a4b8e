//! LPV-ARX regressors (BC-IV paper, section 3.3): the polynomial scheduling basis
//! pbasis(k), the extended regressor chi(k) and phi(k) = chi(k) (x) pbasis(k) (eq. (6)),
//! over a ring buffer of past samples in caller-provided storage.
//!
//! Conventions (the `lpv-arx` model file of DESIGN.md section 5):
//! - model: y(k) = -sum_{i=1}^{na} a_i(p(k)) y(k-i) + sum_{j=0}^{nb} b_j(p(k)) u(k-j), one output,
//!   `r` inputs; the paper's eq. (4) for r = 1. (The paper's *example*, section 6.1, writes
//!   +a_i y(k-i); its a_{1,2} = -0.8 is +0.8 here: BENCHMARKS.md B6.)
//! - chi(k) = [-y(k-1) .. -y(k-na), u_1(k) .. u_1(k-nb), .., u_r(k) .. u_r(k-nb)]
//!   (section 3.3; several inputs follow one another, all lags of an input together).
//! - phi(k) = chi(k) (x) pbasis(k): entry `c * n_basis + m` is chi_c(k) * pbasis_m(k), the
//!   basis index runs fastest, so theta = [a_1; ..; a_na; b_{1,0}; ..; b_{1,nb}; b_{2,0}; ..]
//!   with each block the coefficients of one lag on the basis (eq. (5)-(6)).
//! - pbasis(k) for s scheduling signals and degree n_g: every monomial of total degree <= n_g
//!   in graded lexicographic order: 1; p1 .. ps; p1^2, p1 p2, .., p1 ps, p2^2, .., ps^2;
//!   p1^3, ... For one signal this is [1, p, .., p^ng] of eq. (5). Monomial d > 0 is
//!   `pbasis[parent] * p[var]` (see [`for_each_monomial`]), which is how it is computed.

use crate::error::{check_vec, Error, Field};
use crate::real::{first_non_finite, Real};
use crate::ring::Ring;

/// Binomial coefficient C(n, k), `None` on overflow. `const` so firmware can size storage.
pub const fn binom(n: usize, k: usize) -> Option<usize> {
    if k > n {
        return Some(0);
    }
    let k = if k > n - k { n - k } else { k };
    let mut acc: usize = 1;
    let mut i = 0;
    while i < k {
        // acc * (n - i) / (i + 1) stays an integer at every step
        acc = match acc.checked_mul(n - i) {
            Some(v) => v / (i + 1),
            None => return None,
        };
        i += 1;
    }
    Some(acc)
}

/// Number of basis functions: monomials of total degree <= `ng` in `s` signals,
/// C(s + ng, ng) (1 for s = 0: the constant only).
pub const fn basis_len(s: usize, ng: usize) -> Option<usize> {
    match s.checked_add(ng) {
        Some(n) => binom(n, ng),
        None => None,
    }
}

/// Length of chi(k): na + r (nb + 1).
pub const fn chi_len(r: usize, na: usize, nb: usize) -> usize {
    na + r * (nb + 1)
}

/// Values an [`ArxWindow`] needs: (max(na, nb) + 2) samples of [u, y, p] plus one basis
/// vector of scratch. `const` so firmware can size a static array; 0 on overflow.
pub const fn arx_window_len(r: usize, s: usize, na: usize, nb: usize, ng: usize) -> usize {
    let depth = if na > nb { na } else { nb };
    let nbas = match basis_len(s, ng) {
        Some(v) => v,
        None => return 0,
    };
    (depth + 2) * (r + 1 + s) + nbas
}

/// Visit the monomials of the basis in order: `f(index, parent, var)` for index = 1..n_basis
/// says `pbasis[index] = pbasis[parent] * p[var]` (`pbasis[0] = 1`). Degree-d monomials are
/// p_var times the degree-(d-1) monomials that use only signals var..s-1 (a suffix of the
/// degree-(d-1) block), which gives graded lexicographic order with no storage.
pub fn for_each_monomial(s: usize, ng: usize, mut f: impl FnMut(usize, usize, usize)) {
    let mut prev_off = 0;
    let mut prev_len = 1;
    let mut next = 1;
    for d in 1..=ng {
        if s == 0 {
            break;
        }
        for var in 0..s {
            // monomials of degree d - 1 in the s - var signals var..s-1
            let suffix = binom(s - var + d - 2, d - 1).unwrap_or(0);
            let start = prev_off + prev_len - suffix;
            for parent in start..prev_off + prev_len {
                f(next, parent, var);
                next += 1;
            }
        }
        prev_off += prev_len;
        prev_len = next - prev_off;
    }
}

/// Write pbasis(p) (section 3.3, eq. (5); graded lexicographic for several signals) into
/// `out` (length `basis_len(s, ng)`).
pub fn write_basis<T: Real>(s: usize, ng: usize, p: &[T], out: &mut [T]) -> Result<(), Error> {
    let n = basis_len(s, ng).ok_or(Error::Overflow)?;
    if p.len() != s {
        return Err(Error::Dimension {
            field: Field::Scheduling,
            expected: s,
            got: p.len(),
        });
    }
    if out.len() != n {
        return Err(Error::Dimension {
            field: Field::Regressor,
            expected: n,
            got: out.len(),
        });
    }
    out[0] = T::ONE;
    for_each_monomial(s, ng, |i, parent, var| out[i] = out[parent] * p[var]);
    Ok(())
}

/// Write the exponent table of the basis: row `m` (length s) holds the power of each signal
/// in monomial m. `out` has `basis_len(s, ng) * s` entries, row-major. Used to name the
/// basis functions in a model file and by the Hermite correction (BC-IV paper eq. (11)).
pub fn write_exponents(s: usize, ng: usize, out: &mut [u16]) -> Result<(), Error> {
    let n = basis_len(s, ng).ok_or(Error::Overflow)?;
    let len = n.checked_mul(s).ok_or(Error::Overflow)?;
    if out.len() != len {
        return Err(Error::Dimension {
            field: Field::Storage,
            expected: len,
            got: out.len(),
        });
    }
    if ng > u16::MAX as usize {
        return Err(Error::InvalidConfig("polynomial degree too large"));
    }
    for v in out[..s.min(len)].iter_mut() {
        *v = 0;
    }
    for_each_monomial(s, ng, |i, parent, var| {
        for k in 0..s {
            out[i * s + k] = out[parent * s + k];
        }
        out[i * s + var] += 1;
    });
    Ok(())
}

/// Dimensions of an LPV-ARX model: `r` inputs, one output, `s` scheduling signals,
/// `na` output lags, `nb` input lags (0..=nb), basis degree `ng` (eq. (4)-(5)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ArxDims {
    /// Number of inputs r.
    pub r: usize,
    /// Number of scheduling signals s (the basis has the constant 1 on top).
    pub s: usize,
    /// Output lags n_a.
    pub na: usize,
    /// Input lags n_b (lags 0..=nb).
    pub nb: usize,
    /// Polynomial degree n_g.
    pub ng: usize,
}

impl ArxDims {
    /// Validate and build: the regressor must be non-empty and its length must not overflow.
    pub fn new(r: usize, s: usize, na: usize, nb: usize, ng: usize) -> Result<Self, Error> {
        let d = ArxDims { r, s, na, nb, ng };
        if d.chi_len() == 0 {
            return Err(Error::InvalidConfig(
                "LPV-ARX regressor is empty (na = 0 and no input)",
            ));
        }
        d.n_theta()?;
        // ring storage must be addressable too
        (d.depth() + 2)
            .checked_mul(r + 1 + s)
            .ok_or(Error::Overflow)?;
        Ok(d)
    }
    /// Past samples a regressor needs: max(na, nb).
    pub const fn depth(&self) -> usize {
        if self.na > self.nb {
            self.na
        } else {
            self.nb
        }
    }
    /// Length of chi(k): na + r (nb + 1).
    pub const fn chi_len(&self) -> usize {
        chi_len(self.r, self.na, self.nb)
    }
    /// Number of basis functions C(s + ng, ng).
    pub fn n_basis(&self) -> Result<usize, Error> {
        basis_len(self.s, self.ng).ok_or(Error::Overflow)
    }
    /// Number of parameters n_theta = chi_len * n_basis (length of phi(k)).
    pub fn n_theta(&self) -> Result<usize, Error> {
        self.chi_len()
            .checked_mul(self.n_basis()?)
            .ok_or(Error::Overflow)
    }
    /// Values one stored sample takes: [u, y, p].
    pub const fn sample_len(&self) -> usize {
        self.r + 1 + self.s
    }
    /// Storage an [`ArxWindow`] needs (see [`arx_window_len`]).
    pub fn window_len(&self) -> usize {
        arx_window_len(self.r, self.s, self.na, self.nb, self.ng)
    }
    /// Index in theta of coefficient `m` (basis function) of a_i, i in 1..=na.
    pub fn index_a(&self, i: usize, m: usize) -> Option<usize> {
        let nbas = self.n_basis().ok()?;
        (i >= 1 && i <= self.na && m < nbas).then(|| (i - 1) * nbas + m)
    }
    /// Index in theta of coefficient `m` of b_j of input `input` (0-based), lag j in 0..=nb.
    pub fn index_b(&self, input: usize, j: usize, m: usize) -> Option<usize> {
        let nbas = self.n_basis().ok()?;
        (input < self.r && j <= self.nb && m < nbas)
            .then(|| (self.na + input * (self.nb + 1) + j) * nbas + m)
    }
}

/// The last max(na, nb) + 1 samples (u, y, p) of an LPV-ARX model on a [`Ring`] in
/// caller-provided storage `S` (`[T; arx_window_len(..)]` on the device, `Vec` on the host),
/// followed by one basis vector of scratch. The ring's spare slot makes
/// [`ArxWindow::unpush`] possible.
///
/// Size: (max(na, nb) + 2)(r + 1 + s) + C(s + ng, ng) values; B6 (na = 4, nb = 2, r = s = 1,
/// ng = 2) needs 21 values (84 bytes in f32).
#[derive(Debug, Clone)]
pub struct ArxWindow<T, S> {
    dims: ArxDims,
    ring: Ring<T, S>,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> ArxWindow<T, S> {
    /// A window over `buf` (at least `dims.window_len()` values).
    pub fn new(dims: ArxDims, buf: S) -> Result<Self, Error> {
        let needed = dims.window_len();
        if needed == 0 {
            return Err(Error::Overflow);
        }
        if buf.as_ref().len() < needed {
            return Err(Error::Capacity {
                needed,
                capacity: buf.as_ref().len(),
            });
        }
        Ok(ArxWindow {
            dims,
            ring: Ring::new(dims.sample_len(), dims.depth() + 1, buf)?,
        })
    }

    /// The dimensions.
    pub fn dims(&self) -> ArxDims {
        self.dims
    }

    /// Append sample k: u(k) (length r), y(k), p(k) (length s). Lengths and finiteness are
    /// checked first: on error nothing changes.
    pub fn push(&mut self, u: &[T], y: T, p: &[T]) -> Result<(), Error> {
        let d = self.dims;
        check_vec(Field::Input, u, d.r)?;
        check_vec(Field::Output, core::slice::from_ref(&y), 1)?;
        check_vec(Field::Scheduling, p, d.s)?;
        self.ring.push_with(|row| {
            row[..d.r].copy_from_slice(u);
            row[d.r] = y;
            row[d.r + 1..].copy_from_slice(p);
        });
        Ok(())
    }

    /// Undo the most recent push; `was_len` is [`ArxWindow::len`] before it.
    pub fn unpush(&mut self, was_len: usize) {
        self.ring.unpush(was_len);
    }

    /// Number of samples held (at most max(na, nb) + 1).
    pub fn len(&self) -> usize {
        self.ring.len()
    }

    /// True when nothing is held.
    pub fn is_empty(&self) -> bool {
        self.ring.is_empty()
    }

    /// True once max(na, nb) + 1 samples are held: chi(k) of the newest sample exists.
    pub fn is_ready(&self) -> bool {
        self.ring.is_full()
    }

    /// Forget all samples (a new experiment: regressors never straddle a gap).
    pub fn clear(&mut self) {
        self.ring.clear();
    }

    /// Row of the sample `lag` steps before the newest (lag < len).
    #[inline(always)]
    fn row(&self, lag: usize) -> &[T] {
        self.ring.newest(lag)
    }

    /// Newest sample's scheduling p(k).
    pub fn p_now(&self) -> Option<&[T]> {
        if self.ring.is_empty() {
            return None;
        }
        Some(&self.row(0)[self.dims.r + 1..])
    }

    /// Write chi(k) of the newest sample k (section 3.3): [-y(k-1)..-y(k-na), u(k)..u(k-nb)
    /// per input]. y(k) itself is not used, so this is also the instrument part
    /// [-yhat(k-1).., u(k)..] of section 4 when the window holds simulated outputs.
    pub fn write_chi(&self, out: &mut [T]) -> Result<(), Error> {
        let d = self.dims;
        if out.len() != d.chi_len() {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: d.chi_len(),
                got: out.len(),
            });
        }
        if !self.is_ready() {
            return Err(Error::InvalidConfig(
                "ARX window not ready: needs max(na, nb) + 1 samples",
            ));
        }
        for i in 1..=d.na {
            out[i - 1] = -self.row(i)[d.r];
        }
        for input in 0..d.r {
            for j in 0..=d.nb {
                out[d.na + input * (d.nb + 1) + j] = self.row(j)[input];
            }
        }
        Ok(())
    }

    /// Write phi(k) = chi(k) (x) pbasis(p(k)) of the newest sample (eq. (6)), built in place:
    /// the basis goes to the front, then each block is scaled from the top down.
    pub fn write_regressor(&self, out: &mut [T]) -> Result<(), Error> {
        let d = self.dims;
        let nbas = d.n_basis()?;
        let nt = d.n_theta()?;
        if out.len() != nt {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: nt,
                got: out.len(),
            });
        }
        if !self.is_ready() {
            return Err(Error::InvalidConfig(
                "ARX window not ready: needs max(na, nb) + 1 samples",
            ));
        }
        let p = &self.row(0)[d.r + 1..];
        write_basis(d.s, d.ng, p, &mut out[..nbas])?;
        for c in (1..d.chi_len()).rev() {
            let x = self.chi_entry(c);
            let (head, tail) = out.split_at_mut(c * nbas);
            for (o, b) in tail[..nbas].iter_mut().zip(&head[..nbas]) {
                *o = x * *b;
            }
        }
        let x0 = self.chi_entry(0);
        for o in out[..nbas].iter_mut() {
            *o *= x0;
        }
        match first_non_finite(out) {
            Some(_) => Err(Error::Overflow),
            None => Ok(()),
        }
    }

    /// Entry c of chi(k) (window ready).
    #[inline(always)]
    fn chi_entry(&self, c: usize) -> T {
        let d = self.dims;
        if c < d.na {
            -self.row(c + 1)[d.r]
        } else {
            let k = c - d.na;
            let input = k / (d.nb + 1);
            let j = k % (d.nb + 1);
            self.row(j)[input]
        }
    }

    /// One-step prediction phi(k)^T theta for the newest sample (eq. (6) without the
    /// residual). Uses the basis scratch inside the storage.
    pub fn predict(&mut self, theta: &[T]) -> Result<T, Error> {
        let d = self.dims;
        let nbas = d.n_basis()?;
        let nt = d.n_theta()?;
        if theta.len() != nt {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: nt,
                got: theta.len(),
            });
        }
        if !self.is_ready() {
            return Err(Error::InvalidConfig(
                "ARX window not ready: needs max(na, nb) + 1 samples",
            ));
        }
        // basis of p(k) into the scratch behind the ring
        {
            let (newest, scratch) = self.ring.newest_and_tail_mut(0);
            write_basis(d.s, d.ng, &newest[d.r + 1..], &mut scratch[..nbas])?;
        }
        let basis = &self.ring.tail()[..nbas];
        let mut acc = T::ZERO;
        for c in 0..d.chi_len() {
            let x = self.chi_entry(c);
            let mut coef = T::ZERO;
            for (b, t) in basis.iter().zip(&theta[c * nbas..(c + 1) * nbas]) {
                coef += *b * *t;
            }
            acc += x * coef;
        }
        if acc.is_finite() {
            Ok(acc)
        } else {
            Err(Error::Overflow)
        }
    }

    /// Simulation step of the model theta (free run, the noise-free output estimate yhat of
    /// section 4 used to build instruments): with the window holding past *simulated*
    /// outputs, push (u(k), p(k)), return yhat(k) = phi(k)^T theta and store it as y(k).
    /// The window must already hold max(na, nb) samples (seed it with [`ArxWindow::push`]:
    /// measured outputs or zeros, the initial condition). On error nothing changes.
    pub fn simulate_step(&mut self, theta: &[T], u: &[T], p: &[T]) -> Result<T, Error> {
        let d = self.dims;
        if self.ring.len() < d.depth() {
            return Err(Error::InvalidConfig(
                "ARX simulation needs max(na, nb) seeded samples",
            ));
        }
        let was = self.ring.len();
        self.push(u, T::ZERO, p)?;
        match self.predict(theta) {
            Ok(yhat) => {
                self.ring.newest_mut(0)[d.r] = yhat;
                Ok(yhat)
            }
            Err(e) => {
                self.unpush(was);
                Err(e)
            }
        }
    }
}

/// One sample (u, y, p) with a scalar y; a block row is [u (r), y, p (s)]. Pushing reports
/// nothing ([`ArxWindow::is_ready`] says when chi(k) exists).
impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> crate::Streaming<T> for ArxWindow<T, S> {
    type Sample<'a> = (&'a [T], T, &'a [T]);
    type Output = ();

    fn update(&mut self, (u, y, p): Self::Sample<'_>) -> Result<(), Error> {
        self.push(u, y, p)
    }

    fn row_len(&self) -> usize {
        self.dims.sample_len()
    }

    fn sample<'a>(&self, row: &'a [T]) -> Self::Sample<'a> {
        split_arx_sample(self.dims.r, row)
    }
}

/// Split a row [u (r), y, p] into (u, y, p); a short row gives short slices and a NaN y
/// (rejected by the update), never a panic.
pub(crate) fn split_arx_sample<T: Real>(r: usize, row: &[T]) -> (&[T], T, &[T]) {
    let (u, rest) = row.split_at(r.min(row.len()));
    match rest.split_first() {
        Some((y, p)) => (u, *y, p),
        None => (u, T::of(f64::NAN), rest),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_order_and_sizes() {
        assert_eq!(basis_len(1, 2), Some(3));
        assert_eq!(basis_len(2, 2), Some(6));
        assert_eq!(basis_len(3, 3), Some(20));
        assert_eq!(basis_len(0, 5), Some(1));
        let mut out = [0.0f64; 10];
        write_basis(3, 2, &[2.0, 3.0, 5.0], &mut out).unwrap();
        // 1; p1 p2 p3; p1^2 p1p2 p1p3 p2^2 p2p3 p3^2
        assert_eq!(out, [1.0, 2.0, 3.0, 5.0, 4.0, 6.0, 10.0, 9.0, 15.0, 25.0]);
        let mut e = [0u16; 20];
        write_exponents(2, 3, &mut e).unwrap();
        assert_eq!(
            e,
            [0, 0, 1, 0, 0, 1, 2, 0, 1, 1, 0, 2, 3, 0, 2, 1, 1, 2, 0, 3]
        );
        let mut one = [0.0f32; 4];
        write_basis(1, 3, &[0.5], &mut one).unwrap();
        assert_eq!(one, [1.0, 0.5, 0.25, 0.125]);
        assert!(write_basis(1, 3, &[0.5, 1.0], &mut one).is_err());
    }

    /// Hand-written reference: r = 2 inputs, s = 2 signals, na = 2, nb = 1, ng = 2.
    #[test]
    fn regressor_matches_hand_reference() {
        let d = ArxDims::new(2, 2, 2, 1, 2).unwrap();
        let mut w = ArxWindow::new(d, vec![0.0f64; d.window_len()]).unwrap();
        let u = |k: usize| [1.0 + k as f64, -0.5 * k as f64];
        let y = |k: usize| 0.3 * (k * k) as f64 - 1.0;
        let p = |k: usize| [0.1 * k as f64 + 0.2, 1.0 - 0.2 * k as f64];
        let mut out = vec![0.0; d.n_theta().unwrap()];
        for k in 0..5 {
            w.push(&u(k), y(k), &p(k)).unwrap();
            assert_eq!(w.is_ready(), k >= 2);
        }
        let k = 4;
        let chi = [
            -y(k - 1),
            -y(k - 2),
            u(k)[0],
            u(k - 1)[0],
            u(k)[1],
            u(k - 1)[1],
        ];
        let [p1, p2] = p(k);
        let basis = [1.0, p1, p2, p1 * p1, p1 * p2, p2 * p2];
        let mut expect = Vec::new();
        for c in chi {
            for b in basis {
                expect.push(c * b);
            }
        }
        w.write_regressor(&mut out).unwrap();
        assert_eq!(out, expect);
        let mut c = [0.0; 6];
        w.write_chi(&mut c).unwrap();
        assert_eq!(c, chi);
        // prediction = phi^T theta; theta index helpers agree with the layout
        let theta: Vec<f64> = (0..36).map(|i| 0.01 * i as f64 - 0.1).collect();
        let pred = w.predict(&theta).unwrap();
        let e: f64 = expect.iter().zip(&theta).map(|(a, b)| a * b).sum();
        assert!((pred - e).abs() < 1e-12);
        assert_eq!(expect[d.index_a(2, 4).unwrap()], -y(k - 2) * p1 * p2);
        assert_eq!(expect[d.index_b(1, 1, 5).unwrap()], u(k - 1)[1] * p2 * p2);
        // simulate_step replaces y(k) by the prediction of the new sample
        let before = w.clone();
        let yhat = w.simulate_step(&theta, &u(5), &p(5)).unwrap();
        let mut check = before.clone();
        check.push(&u(5), 123.0, &p(5)).unwrap();
        assert!((check.predict(&theta).unwrap() - yhat).abs() < 1e-12);
        let mut c2 = [0.0; 6];
        // after one more push the newest y is -chi[0]
        w.push(&u(6), 0.0, &p(6)).unwrap();
        w.write_chi(&mut c2).unwrap();
        assert_eq!(c2[0], -yhat);
        // bad data leaves the window alone
        let snap = (w.len(), w.ring.head());
        assert!(w.push(&[f64::NAN, 0.0], 0.0, &[0.0, 0.0]).is_err());
        assert!(w.push(&[0.0, 0.0], f64::INFINITY, &[0.0, 0.0]).is_err());
        assert!(w.simulate_step(&theta[..3], &u(7), &p(7)).is_err());
        assert_eq!((w.len(), w.ring.head()), snap);
    }

    #[test]
    fn window_readiness_and_f32() {
        let d = ArxDims::new(1, 1, 1, 0, 2).unwrap();
        let mut w = ArxWindow::new(d, [0.0f32; arx_window_len(1, 1, 1, 0, 2)]).unwrap();
        let mut out = [0.0f32; 6];
        w.push(&[1.0], 2.0, &[0.5]).unwrap();
        assert!(w.write_regressor(&mut out).is_err());
        assert!(w.simulate_step(&[0.0; 6], &[1.0], &[0.5]).is_ok());
        w.write_regressor(&mut out).unwrap();
        assert_eq!(out, [-2.0, -1.0, -0.5, 1.0, 0.5, 0.25]);
    }

    #[test]
    fn index_helpers() {
        let d = ArxDims::new(2, 1, 2, 1, 2).unwrap();
        assert_eq!(d.chi_len(), 2 + 2 * 2);
        assert_eq!(d.n_theta().unwrap(), 18);
        assert_eq!(d.index_a(1, 2), Some(2));
        assert_eq!(d.index_b(1, 1, 0), Some((2 + 2 + 1) * 3));
        assert_eq!(d.index_a(0, 0), None);
        assert!(ArxDims::new(0, 1, 0, 3, 2).is_err());
    }
}
