//! Regressor windows: a ring buffer of the last p+1 samples (u_k, y_k, mu_k) and the
//! LPV-PBSID regressor z_k^p of the kernel paper (Definitions 5-6, the columns of Z in
//! eq. (12)): block j (j = 1..p) is mu_{k+p-1} (x) ... (x) mu_{k+j-1} (x) z_{k+j-1} with
//! z = [u; y] and mu = [1, p1, ..., ps].

use crate::error::{check_vec, Error, Field};
use crate::real::Real;
use crate::ring::Ring;

/// Dimensions of an LPV-PBSID problem: `r` inputs, `l` outputs, `s` scheduling signals
/// (m = s + 1 local models, the affine 1 is implicit) and past window `p`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PbsidDims {
    /// Number of inputs r.
    pub r: usize,
    /// Number of outputs l.
    pub l: usize,
    /// Number of measured scheduling signals s (m = s + 1).
    pub s: usize,
    /// Past window p.
    pub p: usize,
}

/// m^e with overflow check, usable in `const` items.
const fn pow_checked(m: usize, e: usize) -> Option<usize> {
    let mut acc: usize = 1;
    let mut i = 0;
    while i < e {
        acc = match acc.checked_mul(m) {
            Some(v) => v,
            None => return None,
        };
        i += 1;
    }
    Some(acc)
}

/// Length of z_k^p: q = (r + l) sum_{j=1}^p m^j (kernel paper section 4.4), or `None` on
/// overflow. `const` so firmware can size static storage at compile time.
pub const fn regressor_len(r: usize, l: usize, s: usize, p: usize) -> Option<usize> {
    let m = s + 1;
    let mut sum: usize = 0;
    let mut j = 1;
    while j <= p {
        let mj = match pow_checked(m, j) {
            Some(v) => v,
            None => return None,
        };
        sum = match sum.checked_add(mj) {
            Some(v) => v,
            None => return None,
        };
        j += 1;
    }
    sum.checked_mul(r + l)
}

/// Values a ring of `slots` samples of these dimensions needs (see [`Window`]).
pub const fn window_storage_len(r: usize, l: usize, s: usize, p: usize) -> usize {
    (p + 2) * (r + l + s + 1)
}

impl PbsidDims {
    /// Validate and build.
    pub fn new(r: usize, l: usize, s: usize, p: usize) -> Result<Self, Error> {
        if p == 0 {
            return Err(Error::InvalidConfig("past window p must be at least 1"));
        }
        if l == 0 {
            return Err(Error::InvalidConfig("at least one output is needed"));
        }
        let d = PbsidDims { r, l, s, p };
        d.stat_len()?;
        Ok(d)
    }
    /// Number of local models m = s + 1.
    pub const fn m(&self) -> usize {
        self.s + 1
    }
    /// Length of z_k = [u_k; y_k].
    pub const fn nz(&self) -> usize {
        self.r + self.l
    }
    /// Values stored per sample in a window: [u, y, mu].
    pub const fn sample_len(&self) -> usize {
        self.r + self.l + self.s + 1
    }
    /// Regressor length q (rows of Z).
    pub fn q(&self) -> Result<usize, Error> {
        regressor_len(self.r, self.l, self.s, self.p).ok_or(Error::Overflow)
    }
    /// Length of the accumulated vector w_k = [z_k^p; u_{k+p}; y_{k+p}].
    pub fn stat_len(&self) -> Result<usize, Error> {
        self.q()?
            .checked_add(self.r + self.l)
            .ok_or(Error::Overflow)
    }
    /// Length of block j (1-based) of z_k^p: m^{p-j+1} (r + l).
    pub fn block_len(&self, j: usize) -> usize {
        pow_checked(self.m(), self.p + 1 - j).unwrap_or(usize::MAX) * self.nz()
    }
    /// Offset of block j (1-based) inside z_k^p.
    pub fn block_offset(&self, j: usize) -> usize {
        (1..j).map(|jj| self.block_len(jj)).sum()
    }
}

/// Split a block row [u (r), y (l), p (s)] (the sample layout of [`crate::Streaming`]
/// blocks and of the wire) into (u, y, p). A short row gives short slices (which the
/// update then rejects), never a panic.
pub(crate) fn split_sample<'a, T>(d: &PbsidDims, row: &'a [T]) -> (&'a [T], &'a [T], &'a [T]) {
    let (u, rest) = row.split_at(d.r.min(row.len()));
    let (y, p) = rest.split_at(d.l.min(rest.len()));
    (u, y, p)
}

/// A source of consecutive samples, indexed from 0 (oldest): the ring buffer on the device,
/// a data slab on the host. Kernel evaluations (Theorem 10) are written against this.
pub trait Samples<T: Real> {
    /// z_t = [u_t; y_t].
    fn z(&self, t: usize) -> &[T];
    /// u_t.
    fn u(&self, t: usize) -> &[T];
    /// y_t.
    fn y(&self, t: usize) -> &[T];
    /// mu_t = [1, p1_t, ..., ps_t].
    fn mu(&self, t: usize) -> &[T];
    /// Number of samples available.
    fn len(&self) -> usize;
    /// True when no sample is available.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Samples laid out contiguously, one row [u, y, mu] per sample (the host's data slab).
#[derive(Debug, Clone, Copy)]
pub struct Slab<'a, T> {
    data: &'a [T],
    r: usize,
    l: usize,
    m: usize,
}

impl<'a, T: Real> Slab<'a, T> {
    /// Wrap `data` (row-major, rows of length r + l + m).
    pub fn new(data: &'a [T], r: usize, l: usize, m: usize) -> Result<Self, Error> {
        let w = r + l + m;
        if w == 0 || data.len() % w != 0 {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: w,
                got: data.len(),
            });
        }
        Ok(Slab { data, r, l, m })
    }
    /// Wrap whole rows known to have the right length (the core's own storage).
    #[inline(always)]
    pub(crate) fn from_rows(data: &'a [T], r: usize, l: usize, m: usize) -> Self {
        Slab { data, r, l, m }
    }

    #[inline(always)]
    fn row(&self, t: usize) -> &'a [T] {
        let w = self.r + self.l + self.m;
        &self.data[t * w..(t + 1) * w]
    }
}

impl<T: Real> Samples<T> for Slab<'_, T> {
    #[inline(always)]
    fn z(&self, t: usize) -> &[T] {
        &self.row(t)[..self.r + self.l]
    }
    #[inline(always)]
    fn u(&self, t: usize) -> &[T] {
        &self.row(t)[..self.r]
    }
    #[inline(always)]
    fn y(&self, t: usize) -> &[T] {
        &self.row(t)[self.r..self.r + self.l]
    }
    #[inline(always)]
    fn mu(&self, t: usize) -> &[T] {
        &self.row(t)[self.r + self.l..]
    }
    fn len(&self) -> usize {
        self.data.len() / (self.r + self.l + self.m)
    }
}

/// The last p + 1 samples [u, y, mu] on a [`Ring`] in caller-provided storage `S` (an
/// array `[T; window_storage_len(..)]` on the device, a `Vec` on the host). The ring's spare
/// slot makes [`Window::unpush`] possible, so a caller can undo a push when a later step fails.
///
/// Size: (p + 2)(r + l + s + 1) values; B1 with p = 3 needs 50 values (200 bytes in f32).
#[derive(Debug, Clone)]
pub struct Window<T, S> {
    dims: PbsidDims,
    ring: Ring<T, S>,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Window<T, S> {
    /// A window over `buf`, which must hold at least `window_storage_len` values.
    pub fn new(dims: PbsidDims, buf: S) -> Result<Self, Error> {
        let needed = window_storage_len(dims.r, dims.l, dims.s, dims.p);
        if buf.as_ref().len() < needed {
            return Err(Error::Capacity {
                needed,
                capacity: buf.as_ref().len(),
            });
        }
        Ok(Window {
            dims,
            ring: Ring::new(dims.sample_len(), dims.p + 1, buf)?,
        })
    }

    /// The dimensions.
    pub fn dims(&self) -> PbsidDims {
        self.dims
    }

    /// Append sample (u, y, p); the oldest drops out once p + 1 are held. Checks lengths
    /// and finiteness first: on error nothing changes.
    pub fn push(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<(), Error> {
        let d = self.dims;
        check_vec(Field::Input, u, d.r)?;
        check_vec(Field::Output, y, d.l)?;
        check_vec(Field::Scheduling, p, d.s)?;
        self.ring.push_with(|row| {
            row[..d.r].copy_from_slice(u);
            row[d.r..d.r + d.l].copy_from_slice(y);
            row[d.r + d.l] = T::ONE;
            row[d.r + d.l + 1..].copy_from_slice(p);
        });
        Ok(())
    }

    /// Undo the most recent push (the spare slot still holds the sample that dropped out).
    /// `was_len` is `len()` before that push.
    pub fn unpush(&mut self, was_len: usize) {
        self.ring.unpush(was_len);
    }

    /// Number of samples held (at most p + 1).
    pub fn len(&self) -> usize {
        self.ring.len()
    }

    /// True when no sample is held.
    pub fn is_empty(&self) -> bool {
        self.ring.is_empty()
    }

    /// True once p + 1 samples are held and a regressor can be formed.
    pub fn is_full(&self) -> bool {
        self.ring.is_full()
    }

    /// Forget all samples (e.g. between experiments: windows never straddle a gap).
    pub fn clear(&mut self) {
        self.ring.clear();
    }

    #[inline(always)]
    fn row(&self, t: usize) -> &[T] {
        // t = 0 is the oldest held sample.
        self.ring.oldest(t)
    }

    /// Write w_k = [z_k^p; u_{k+p}; y_{k+p}] into `out` (length `dims.stat_len()`), the
    /// vector whose second moments are the sufficient statistics of problem (13).
    pub fn regressor(&self, out: &mut [T]) -> Result<(), Error> {
        let d = self.dims;
        let q = d.q()?;
        if out.len() != q + d.r + d.l {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected: q + d.r + d.l,
                got: out.len(),
            });
        }
        if !self.is_full() {
            return Err(Error::InvalidConfig("window not full yet"));
        }
        write_pbsid_regressor(&d, self, 0, &mut out[..q]);
        out[q..q + d.r].copy_from_slice(self.u(d.p));
        out[q + d.r..].copy_from_slice(self.y(d.p));
        Ok(())
    }
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Samples<T> for Window<T, S> {
    fn z(&self, t: usize) -> &[T] {
        let d = self.dims;
        &self.row(t)[..d.r + d.l]
    }
    fn u(&self, t: usize) -> &[T] {
        &self.row(t)[..self.dims.r]
    }
    fn y(&self, t: usize) -> &[T] {
        let d = self.dims;
        &self.row(t)[d.r..d.r + d.l]
    }
    fn mu(&self, t: usize) -> &[T] {
        let d = self.dims;
        &self.row(t)[d.r + d.l..]
    }
    fn len(&self) -> usize {
        self.ring.len()
    }
}

/// Write z_k^p (the column N_k^p zbar_k^p of Z, eq. (12), Definitions 5-6) for the window
/// starting at sample `k` of `src` into `out` (length q). Each block is built in place by
/// repeated Kronecker expansion with the next-newer mu, so the cost is O(q) and no scratch
/// is needed.
pub fn write_pbsid_regressor<T: Real, X: Samples<T> + ?Sized>(
    d: &PbsidDims,
    src: &X,
    k: usize,
    out: &mut [T],
) {
    let nz = d.nz();
    let m = d.m();
    let mut off = 0;
    for j in 1..=d.p {
        let blen = d.block_len(j);
        let block = &mut out[off..off + blen];
        // innermost factor z_{k+j-1}
        block[..nz].copy_from_slice(src.z(k + j - 1));
        let mut len = nz;
        for t in (j - 1)..d.p {
            let mu = src.mu(k + t);
            // block[..m*len] = mu (x) block[..len], filled from the top so the source survives.
            for i in (1..m).rev() {
                let mi = mu[i];
                let (head, tail) = block.split_at_mut(i * len);
                for (dst, src) in tail[..len].iter_mut().zip(head[..len].iter()) {
                    *dst = mi * *src;
                }
            }
            let m0 = mu[0];
            for v in block[..len].iter_mut() {
                *v *= m0;
            }
            len *= m;
        }
        off += blen;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference Kronecker product.
    fn kron(a: &[f64], b: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        for x in a {
            for y in b {
                out.push(x * y);
            }
        }
        out
    }

    #[test]
    fn regressor_matches_definition_5_6() {
        let d = PbsidDims::new(1, 2, 1, 3).unwrap();
        let mut w = Window::new(d, vec![0.0; window_storage_len(1, 2, 1, 3)]).unwrap();
        let samples: Vec<(f64, [f64; 2], f64)> = (0..6)
            .map(|k| {
                (
                    k as f64 + 0.5,
                    [k as f64 * 2.0 - 1.0, 0.3 * k as f64],
                    0.1 * k as f64 - 0.2,
                )
            })
            .collect();
        for (u, y, p) in &samples[..4] {
            w.push(&[*u], y, &[*p]).unwrap();
        }
        // window holds samples 0..=3 (k = 0, p = 3)
        let z = |k: usize| vec![samples[k].0, samples[k].1[0], samples[k].1[1]];
        let mu = |k: usize| vec![1.0, samples[k].2];
        let mut expect = Vec::new();
        for j in 1..=3usize {
            let mut v = z(j - 1);
            for t in (j - 1)..3 {
                v = kron(&mu(t), &v);
            }
            expect.extend(v);
        }
        expect.extend([samples[3].0, samples[3].1[0], samples[3].1[1]]);
        let mut out = vec![0.0; d.stat_len().unwrap()];
        w.regressor(&mut out).unwrap();
        assert_eq!(out.len(), 3 * (2 + 4 + 8) + 3);
        for (a, b) in out.iter().zip(&expect) {
            assert!((a - b).abs() < 1e-12);
        }
    }

    #[test]
    fn push_rejects_nan_and_leaves_state() {
        let d = PbsidDims::new(1, 1, 1, 2).unwrap();
        let mut w = Window::new(d, [0.0f32; 16]).unwrap();
        w.push(&[1.0], &[2.0], &[0.5]).unwrap();
        let before = w.clone();
        assert_eq!(
            w.push(&[1.0], &[f32::NAN], &[0.5]),
            Err(Error::NonFinite {
                field: Field::Output,
                index: 0
            })
        );
        assert_eq!(w.len(), before.len());
        assert_eq!(w.ring.head(), before.ring.head());
        assert!(w.push(&[1.0, 2.0], &[1.0], &[0.5]).is_err());
    }

    #[test]
    fn sizes_and_overflow() {
        assert_eq!(regressor_len(2, 3, 3, 3), Some(5 * (4 + 16 + 64)));
        assert_eq!(regressor_len(2, 3, 3, 5), Some(6820));
        assert_eq!(regressor_len(1, 1, 3, 200), None);
        assert_eq!(PbsidDims::new(1, 1, 3, 200), Err(Error::Overflow));
        assert!(PbsidDims::new(1, 1, 0, 0).is_err());
    }
}
