//! Sufficient statistics: streaming second moments, mergeable (kernel paper section 4:
//! problem (13), and with the extended layout the realization of section 4.3; sparse paper
//! problem (33) is solved from the same statistics by [`crate::lasso`]).
//!
//! [`Gram`] accumulates sum_k w_k w_k^T (packed upper triangle) for any vector w; it is the
//! one second-moment accumulator of the project (the host's least-squares steps use it too).
//! [`PbsidStats`] feeds it with w_k = [z_k^p; u_{k+p}; y_{k+p}], the statistics from which
//! problem (13) of the kernel paper (and its regularised forms) is solved without the data.
//!
//! ## Long accumulation (issue 18)
//!
//! A plain running sum in f32 stops counting: 2^24 + 1 = 2^24, and a sum of 10^7 values of
//! mean 1 is 1.6 % low. [`Summation::Compensated`] keeps, next to every packed total, its low
//! part (Kahan: 4 additions instead of 1 per entry, [`kahan_add`]); the total in
//! [`Gram::packed`] is then the compensated sum rounded to within an ulp, however many samples
//! went in. Options measured (`host-tools/tests/f32_long_run.rs`, B2-like plant,
//! r = l = s = 1, p = 2, extended layout, f32 statistics against compensated f64 statistics
//! of the same f32 samples, largest per-entry relative error):
//!
//! | samples | plain f32 | compensated f32 | VAF of the model: f64 / compensated / plain |
//! |---|---|---|---|
//! | 10^7 | 1.9e-2 | 6.5e-8 | 94.1216 / 94.1216 / 93.51 |
//! | 10^8 | 0.83 (counts stuck at 2^24) | 5.5e-8 | 94.1218 / 94.1218 / no fit (scheduling looks constant) |
//!
//! The test `f32_long_run` runs 10^7 samples in `make test` (12 s here) and 10^8 in
//! `make test-long` (87-126 s of CPU, one core); the example `f32_long_run` runs 10^9
//! (about 15 minutes of CPU by the same rate; not run in this round).
//!
//! - Blocked summation (a block of B vectors summed plainly, then flushed into the total):
//!   with a block in registers it is free, and [`Gram::update_batch`] does exactly that (the
//!   register tile is the block, flushed compensated). A block kept in memory for single
//!   updates needs a third triangle and makes `packed()` lag the last B - 1 samples (it is
//!   `&self` and cannot fold them in), so single updates add compensated at once instead.
//! - Blocked without compensation (two levels) still grows like (B + N/B) eps: at N = 10^9
//!   no B keeps f32 within 1e-5. Pairwise summation needs log2 N partial triangles.
//! - Compensated (the choice): storage two packed triangles, [`gram_storage_len`]; cost per
//!   entry and sample 4 additions and one more load/store (`benches/summation.rs` in the host
//!   measures it against plain summation, both in one process; docs/bench-device.md has the
//!   Cortex-M4F count).
//!
//! Sizing: a caller that gives [`Gram::new`] `gram_storage_len(dim)` values gets compensated
//! sums, `packed_len(dim)` plain ones (the old behaviour, bit for bit);
//! [`Gram::with_summation`] chooses explicitly. The device engine, [`crate::bciv::BcivStats`]
//! and the kernel dictionary's normal equations always compensate (their storage functions
//! include the low parts). [`Gram::merge`] adds the other's totals and low parts
//! compensated.
//!
//! ## Forgetting and windows
//!
//! [`Gram::set_forgetting`] (and [`PbsidStats::set_forgetting`],
//! `BcivStats::set_forgetting`): S <- lambda S + w w^T per vector, lambda in (0, 1], the
//! effective count in [`Gram::weight`] (and in the constant entry of a statistic vector).
//! Merging two forgetting statistics adds them as they are, which is only meaningful for
//! records that ran at the same time (two sensors of one plant, both weighted by the same
//! clock): [`Gram::merge`] therefore requires equal lambdas (`Error::Mismatch` otherwise)
//! and does not re-age either side. A record that ended earlier must be aged by the caller
//! first. Sliding windows: [`crate::sliding`] (rebasing, [`crate::sliding::Rebase`] for
//! Gram, PbsidStats, BcivStats and the kernel dictionary's normal equations) and
//! [`crate::SlidingGram`] (two half-window Grams taking turns).

use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;

use crate::error::{check_vec, Error, Field};
use crate::real::{first_non_finite, Real};
#[cfg(test)]
use crate::window::Samples;
use crate::window::{window_storage_len, PbsidDims, Window};

/// Number of values in the packed upper triangle of a `dim` x `dim` symmetric matrix.
pub const fn packed_len(dim: usize) -> usize {
    dim * (dim + 1) / 2
}

/// Reject vectors whose outer product would overflow to infinity.
fn check_products<T: Real>(w: &[T]) -> Result<(), Error> {
    let big = w.iter().fold(T::ZERO, |a, x| a.max(x.abs()));
    if (big * big).is_finite() {
        Ok(())
    } else {
        Err(Error::Overflow)
    }
}

/// Streaming sum of outer products sum_k w_k w_k^T, packed upper triangle, row-major, in
/// caller-provided storage (`[T; packed_len(dim)]` on the device, `Vec<T>` on the host).
///
/// Size: dim(dim+1)/2 values; B1 with p = 3 (dim 425) needs 90 525 values.
#[derive(Debug, Clone)]
pub struct Gram<T, S> {
    dim: usize,
    count: u64,
    data: S,
    summation: Summation,
    /// The summation follows the storage (built by [`Gram::new`]): re-chosen by
    /// [`Gram::reset_dim`].
    auto: bool,
    /// Forgetting factor lambda in (0, 1]: S <- lambda S + w w^T per vector.
    lambda: T,
    /// Effective count sum_k lambda^(age of vector k) (= count with lambda = 1).
    weight: f64,
    _t: core::marker::PhantomData<T>,
}

/// How a [`Gram`] adds into its running totals (see the module doc for the measurements).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Summation {
    /// Plain sequential addition: `packed_len(dim)` values of storage; the relative error
    /// grows like n eps (f32: 1.6 % low after 10^7 additions of 1).
    Plain,
    /// Compensated (Kahan) addition of every flushed block: a second packed triangle holds
    /// the low parts, `2 packed_len(dim)` values ([`gram_storage_len`]); the error stays a
    /// few eps whatever the number of samples.
    Compensated,
}

/// Storage a compensated [`Gram`] of vectors of length `dim` needs: two packed triangles
/// (the totals, then their low parts). A [`Gram::new`] over at least this much storage
/// sums with [`Summation::Compensated`].
pub const fn gram_storage_len(dim: usize) -> usize {
    2 * packed_len(dim)
}

/// One compensated (Kahan) addition of `v` into the pair (`hi`, `lo`), true sum
/// ~ hi + lo: `hi` stays the correctly rounded total to within an ulp, `lo` the part of
/// the total that f32/f64 cannot hold in `hi`. 4 additions instead of 1.
#[inline(always)]
pub(crate) fn kahan_add<T: Real>(hi: &mut T, lo: &mut T, v: T) {
    let y = v + *lo;
    let t = *hi + y;
    *lo = y - (t - *hi);
    *hi = t;
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Gram<T, S> {
    /// An empty accumulator for vectors of length `dim` over `storage` (zeroed here):
    /// [`Summation::Compensated`] if the storage holds [`gram_storage_len`] values,
    /// [`Summation::Plain`] if it holds only `packed_len(dim)`.
    pub fn new(dim: usize, storage: S) -> Result<Self, Error> {
        let summation = if storage.as_ref().len() >= gram_storage_len(dim) {
            Summation::Compensated
        } else {
            Summation::Plain
        };
        let mut g = Self::with_summation(dim, storage, summation)?;
        g.auto = true;
        Ok(g)
    }

    /// An empty accumulator with an explicit [`Summation`]; fails if `storage` is smaller
    /// than that summation needs (`packed_len(dim)` or [`gram_storage_len`]).
    pub fn with_summation(dim: usize, mut storage: S, summation: Summation) -> Result<Self, Error> {
        let needed = Self::storage_needed(dim, summation);
        let cap = storage.as_ref().len();
        if cap < needed {
            return Err(Error::Capacity {
                needed,
                capacity: cap,
            });
        }
        for v in storage.as_mut()[..needed].iter_mut() {
            *v = T::ZERO;
        }
        Ok(Gram {
            dim,
            count: 0,
            data: storage,
            summation,
            auto: false,
            lambda: T::ONE,
            weight: 0.0,
            _t: core::marker::PhantomData,
        })
    }

    fn storage_needed(dim: usize, summation: Summation) -> usize {
        match summation {
            Summation::Plain => packed_len(dim),
            Summation::Compensated => gram_storage_len(dim),
        }
    }

    /// How this accumulator sums.
    pub fn summation(&self) -> Summation {
        self.summation
    }

    /// Exponential forgetting from now on: every new vector first scales the accumulated
    /// matrix (and its low parts) by `lambda`, S <- lambda S + w w^T, so S weights a vector
    /// of age a by lambda^a (effective memory 1/(1 - lambda) vectors). `lambda` must be in
    /// (0, 1]; 1 is the plain sum. The statistics so far are kept. The scaling's own
    /// rounding (eps/2 per vector, decaying with lambda) is not compensated: the relative
    /// error it leaves is below eps / (2 (1 - lambda)) in the worst case.
    pub fn set_forgetting(&mut self, lambda: T) -> Result<(), Error> {
        if !(lambda.is_finite() && lambda > T::ZERO && lambda <= T::ONE) {
            return Err(Error::InvalidConfig("forgetting factor must be in (0, 1]"));
        }
        self.lambda = lambda;
        Ok(())
    }

    /// The forgetting factor (1: none).
    pub fn forgetting(&self) -> T {
        self.lambda
    }

    /// Effective number of vectors: sum over the vectors of lambda^age (the weight of the
    /// constant entry of a statistic vector); equals [`Gram::count`] without forgetting.
    pub fn weight(&self) -> f64 {
        self.weight
    }

    /// The low parts of the compensated totals (same packing as [`Gram::packed`]; the
    /// exact-ish total is `packed()[i] + compensation()[i]`), empty for
    /// [`Summation::Plain`].
    pub fn compensation(&self) -> &[T] {
        let n = packed_len(self.dim);
        match self.summation {
            Summation::Plain => &[],
            Summation::Compensated => &self.data.as_ref()[n..2 * n],
        }
    }

    /// The storage split for a sliding window kept beside the sums in the same array
    /// ([`crate::sliding`], the device's window): totals, their low parts (empty for
    /// [`Summation::Plain`]) and the spare values after what the summation uses.
    pub(crate) fn storage_parts(&mut self) -> (&mut [T], &mut [T], &mut [T]) {
        let n = packed_len(self.dim);
        let used = Self::storage_needed(self.dim, self.summation);
        let (sums, spare) = self.data.as_mut().split_at_mut(used);
        let (hi, lo) = sums.split_at_mut(n);
        (hi, lo, spare)
    }

    /// Set the vector count (and the weight: no forgetting) after the sums were rebased by
    /// [`crate::sliding`].
    pub(crate) fn set_count(&mut self, count: u64) {
        self.count = count;
        self.weight = count as f64;
    }

    /// Vector length.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of vectors accumulated.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The packed upper triangle (row-major: (0,0), (0,1), ..., (0,d-1), (1,1), ...). With
    /// [`Summation::Compensated`] every value is the compensated total rounded to within an
    /// ulp (the low parts are in [`Gram::compensation`]).
    pub fn packed(&self) -> &[T] {
        &self.data.as_ref()[..packed_len(self.dim)]
    }

    #[inline(always)]
    fn row_offset(&self, i: usize) -> usize {
        // sum_{r<i} (dim - r)
        i * self.dim - i * i.saturating_sub(1) / 2
    }

    /// Entry (i, j) of the accumulated symmetric matrix.
    pub fn get(&self, i: usize, j: usize) -> T {
        let (a, b) = if i <= j { (i, j) } else { (j, i) };
        self.data.as_ref()[self.row_offset(a) + (b - a)]
    }

    /// What [`Gram::update`] checks: length, finiteness, no overflow in the products.
    pub(crate) fn check(&self, w: &[T]) -> Result<(), Error> {
        check_vec(Field::Regressor, w, self.dim)?;
        check_products(w)
    }

    /// Add w w^T. Rejects a wrong length or a non-finite entry without changing anything.
    pub fn update(&mut self, w: &[T]) -> Result<(), Error> {
        self.check(w)?;
        self.rank_k(w, 1);
        Ok(())
    }

    /// Add the outer products of `n` vectors stored row-major in `rows` (n x dim). The
    /// packed matrix is read and written once per batch instead of once per vector, which is
    /// what makes a host-side batch fast; the result equals n single updates up to the order
    /// of the additions. All rows are checked first: on error nothing changes.
    pub fn update_batch(&mut self, rows: &[T], n: usize) -> Result<(), Error> {
        self.check_batch(rows, n)?;
        self.rank_k(rows, n);
        Ok(())
    }

    /// What [`Gram::update_batch`] checks before anything changes: `n` rows of length
    /// [`Gram::dim`], finite, with products that do not overflow (a host that computes a
    /// block's products itself says with this which row was bad, see [`Gram::add_packed`]).
    pub fn check_batch(&self, rows: &[T], n: usize) -> Result<(), Error> {
        let expected = n.checked_mul(self.dim).ok_or(Error::Overflow)?;
        if rows.len() != expected {
            return Err(Error::Dimension {
                field: Field::Regressor,
                expected,
                got: rows.len(),
            });
        }
        if let Some(index) = first_non_finite(rows) {
            return Err(Error::NonFinite {
                field: Field::Regressor,
                index,
            });
        }
        check_products(rows)
    }

    /// The rank-n update proper (inputs already validated), with tiles that fit the 16
    /// vector registers of SSE2 in f64 and the 32 single registers of a Cortex-M4F.
    fn rank_k(&mut self, rows: &[T], n: usize) {
        if self.lambda != T::ONE && n > 1 {
            // every vector is weighted differently: one at a time
            for w in rows.chunks_exact(self.dim).take(n) {
                self.rank_k_tiled(w, 1);
            }
            return;
        }
        self.rank_k_tiled(rows, n);
    }

    /// C += sum_b w_b w_b^T on the packed upper triangle, register-blocked: a tile of four
    /// triangle rows by `CB` = 4 columns is summed over all n vectors in registers and added to
    /// C once, so C is streamed once per batch and each loaded value feeds 4 or `CB`
    /// multiply-adds. With n = 1 (or a zero C) the result is bit-identical to sequential
    /// single updates.
    #[inline(always)]
    fn rank_k_tiled(&mut self, rows: &[T], n: usize) {
        const CB: usize = 4;
        let dim = self.dim;
        if n == 0 {
            return;
        }
        self.count += n as u64;
        let lambda = self.lambda;
        // n > 1 only without forgetting (see rank_k)
        self.weight = self.weight * lambda.to_f64() + n as f64;
        if dim == 0 {
            return;
        }
        let p = packed_len(dim);
        let comp = self.summation == Summation::Compensated;
        let (hi, lo): (&mut [T], &mut [T]) = if comp {
            self.data.as_mut()[..2 * p].split_at_mut(p)
        } else {
            (&mut self.data.as_mut()[..p], &mut [])
        };
        if n == 1 {
            // one vector (the device's per-sample path): row by row, each entry independent
            // (vectorises); bit-identical to the tiled code with n = 1
            let w = &rows[..dim];
            let mut off = 0;
            for (i, &wi) in w.iter().enumerate() {
                let row = off..off + dim - i;
                if lambda != T::ONE {
                    if comp {
                        for ((h, l), x) in hi[row.clone()].iter_mut().zip(&mut lo[row]).zip(&w[i..])
                        {
                            *h *= lambda;
                            *l *= lambda;
                            kahan_add(h, l, wi * *x);
                        }
                    } else {
                        for (h, x) in hi[row].iter_mut().zip(&w[i..]) {
                            *h = lambda * *h + wi * *x;
                        }
                    }
                } else if comp {
                    for ((h, l), x) in hi[row.clone()].iter_mut().zip(&mut lo[row]).zip(&w[i..]) {
                        kahan_add(h, l, wi * *x);
                    }
                } else {
                    for (h, x) in hi[row].iter_mut().zip(&w[i..]) {
                        *h += wi * *x;
                    }
                }
                off += dim - i;
            }
            return;
        }
        // the flush of a block sum `v` (the n vectors summed in registers) into entry `idx`
        let mut put = |idx: usize, v: T| {
            if comp {
                kahan_add(&mut hi[idx], &mut lo[idx], v);
            } else {
                hi[idx] += v;
            }
        };
        let vectors = || rows.chunks_exact(dim).take(n);
        let mut off = 0;
        let mut i = 0;
        while i + 4 <= dim {
            let o1 = off + dim - i;
            let o2 = o1 + dim - i - 1;
            let o3 = o2 + dim - i - 2;
            // the head: columns i..i+2 of rows i..i+2 (column i+3 is in the tiles)
            let mut h = [T::ZERO; 6];
            for w in vectors() {
                let (a0, a1, a2) = (w[i], w[i + 1], w[i + 2]);
                h[0] += a0 * a0;
                h[1] += a0 * a1;
                h[2] += a0 * a2;
                h[3] += a1 * a1;
                h[4] += a1 * a2;
                h[5] += a2 * a2;
            }
            for (idx, v) in [off, off + 1, off + 2, o1, o1 + 1, o2].into_iter().zip(h) {
                put(idx, v);
            }
            // columns i+3.. of the four rows, aligned: where column i+3 starts in each row
            let base = [off + 3, o1 + 2, o2 + 1, o3];
            let len = dim - i - 3;
            let mut j = 0;
            while j + CB <= len {
                let mut acc = [[T::ZERO; CB]; 4];
                for w in vectors() {
                    let a = [w[i], w[i + 1], w[i + 2], w[i + 3]];
                    let x = &w[i + 3 + j..i + 3 + j + CB];
                    for (row, &ar) in acc.iter_mut().zip(&a) {
                        for (s, &xv) in row.iter_mut().zip(x) {
                            *s += ar * xv;
                        }
                    }
                }
                for (b, row) in base.iter().zip(&acc) {
                    for (t, &v) in row.iter().enumerate() {
                        put(b + j + t, v);
                    }
                }
                j += CB;
            }
            for jj in j..len {
                let mut acc = [T::ZERO; 4];
                for w in vectors() {
                    let xv = w[i + 3 + jj];
                    for (s, &ar) in acc.iter_mut().zip(&w[i..i + 4]) {
                        *s += ar * xv;
                    }
                }
                for (b, &v) in base.iter().zip(&acc) {
                    put(b + jj, v);
                }
            }
            off += 4 * (dim - i) - 6;
            i += 4;
        }
        while i < dim {
            if n == 1 || !comp {
                // one vector (or plain sums): add straight into the totals
                for w in vectors() {
                    let wi = w[i];
                    for (t, x) in w[i..].iter().enumerate() {
                        put(off + t, wi * *x);
                    }
                }
            } else {
                // a block of vectors: sum each entry over the block, then one compensated add
                for t in 0..dim - i {
                    let mut v = T::ZERO;
                    for w in vectors() {
                        v += w[i] * w[i + t];
                    }
                    put(off + t, v);
                }
            }
            off += dim - i;
            i += 1;
        }
    }

    /// Add another accumulator of the same dimension: the result equals accumulating the
    /// concatenated data (how experiments or devices combine). A compensated accumulator
    /// adds the other's totals and low parts with compensation (a plain one adds the
    /// other's total rounded), so merging keeps the accuracy of both.
    pub fn merge<S2: AsRef<[T]> + AsMut<[T]>>(&mut self, other: &Gram<T, S2>) -> Result<(), Error> {
        if other.dim != self.dim || other.lambda != self.lambda {
            return Err(Error::Mismatch);
        }
        let n = packed_len(self.dim);
        let olo = other.compensation();
        let ohi = other.packed();
        match self.summation {
            Summation::Plain => {
                for (k, a) in self.data.as_mut()[..n].iter_mut().enumerate() {
                    *a += match olo.get(k) {
                        Some(l) => ohi[k] + *l,
                        None => ohi[k],
                    };
                }
            }
            Summation::Compensated => {
                let (hi, lo) = self.data.as_mut()[..2 * n].split_at_mut(n);
                for k in 0..n {
                    kahan_add(&mut hi[k], &mut lo[k], ohi[k]);
                    if let Some(l) = olo.get(k) {
                        kahan_add(&mut hi[k], &mut lo[k], *l);
                    }
                }
            }
        }
        self.count += other.count;
        self.weight += other.weight;
        Ok(())
    }

    /// Add a block computed elsewhere: `packed`, the packed upper triangle of the sum of the
    /// outer products of `n` vectors (a host's BLAS syrk of a batch). The result equals
    /// [`Gram::update_batch`] of those vectors up to the order of the additions, compensated
    /// or not as this accumulator is. Needs `packed_len(dim)` finite values and no
    /// forgetting (each vector would weigh differently: `Error::Mismatch`); on error
    /// nothing changes.
    pub fn add_packed(&mut self, packed: &[T], n: u64) -> Result<(), Error> {
        if self.lambda != T::ONE {
            return Err(Error::Mismatch);
        }
        let p = packed_len(self.dim);
        check_vec(Field::Regressor, packed, p)?;
        match self.summation {
            Summation::Plain => {
                for (a, v) in self.data.as_mut()[..p].iter_mut().zip(packed) {
                    *a += *v;
                }
            }
            Summation::Compensated => {
                let (hi, lo) = self.data.as_mut()[..2 * p].split_at_mut(p);
                for ((h, l), v) in hi.iter_mut().zip(lo.iter_mut()).zip(packed) {
                    kahan_add(h, l, *v);
                }
            }
        }
        self.count += n;
        self.weight += n as f64;
        Ok(())
    }

    /// Forget everything accumulated (the forgetting factor is kept).
    pub fn reset(&mut self) {
        let n = Self::storage_needed(self.dim, self.summation);
        for v in self.data.as_mut()[..n].iter_mut() {
            *v = T::ZERO;
        }
        self.count = 0;
        self.weight = 0.0;
    }

    /// Start over for vectors of length `dim` in the same storage (an empty accumulator, as
    /// [`Gram::new`] would give, without moving the storage). The summation is chosen again
    /// from the storage if the accumulator came from [`Gram::new`], kept otherwise. Fails,
    /// changing nothing, if the storage is too small.
    pub fn reset_dim(&mut self, dim: usize) -> Result<(), Error> {
        let cap = self.data.as_ref().len();
        let summation = if self.auto {
            if cap >= gram_storage_len(dim) {
                Summation::Compensated
            } else {
                Summation::Plain
            }
        } else {
            self.summation
        };
        let needed = Self::storage_needed(dim, summation);
        if cap < needed {
            return Err(Error::Capacity {
                needed,
                capacity: cap,
            });
        }
        self.dim = dim;
        self.summation = summation;
        self.reset();
        Ok(())
    }

    /// Overwrite the contents (e.g. statistics pulled from a device). `packed` must have
    /// `packed_len(dim)` finite values.
    pub fn load(&mut self, packed: &[T], count: u64) -> Result<(), Error> {
        check_vec(Field::Regressor, packed, packed_len(self.dim))?;
        let n = packed.len();
        let data = self.data.as_mut();
        data[..n].copy_from_slice(packed);
        if self.summation == Summation::Compensated {
            for v in data[n..2 * n].iter_mut() {
                *v = T::ZERO;
            }
        }
        self.count = count;
        self.weight = count as f64;
        Ok(())
    }

    /// Write the full symmetric matrix, row-major, into `out` (dim x dim).
    pub fn write_dense(&self, out: &mut [T]) -> Result<(), Error> {
        let dim = self.dim;
        if out.len() != dim * dim {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: dim * dim,
                got: out.len(),
            });
        }
        let data = self.packed();
        let mut off = 0;
        for i in 0..dim {
            for j in i..dim {
                let v = data[off + j - i];
                out[i * dim + j] = v;
                out[j * dim + i] = v;
            }
            off += dim - i;
        }
        Ok(())
    }
}

/// What [`PbsidStats`] accumulates.
///
/// - `Plain`: the second moments of s_k = [w_k; 1; p_{k+p}] with
///   w_k = [z_k^p; u_{k+p}; y_{k+p}]: everything problem (13) needs, plus the count and the
///   first and second moments of every channel (for scaling after the fact).
/// - `Extended`: the second moments of s_k = [mu_{k+p} (x) w_k; 1; p_{k+p}]. Because
///   mu^(1) = 1, w_k is its leading part, and because z_{k+1}^p is a selection of
///   mu_{k+p} (x) [z_k^p; z_{k+p}], every moment of the realization step (section 4.3:
///   states x_{k+p} = T z_k^p and x_{k+p+1} = T z_{k+1}^p) is a linear function of these
///   statistics: a device can ship them and the host finishes the whole fit without data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatsLayout {
    /// Statistics of problem (13) only.
    Plain,
    /// Statistics of (13) and of the realization (m times longer vector).
    Extended,
}

/// Length of the statistic vector s_k of `layout` for `dims`.
pub fn stat_vector_len(dims: &PbsidDims, layout: StatsLayout) -> Result<usize, Error> {
    let d = dims.stat_len()?;
    let core = match layout {
        StatsLayout::Plain => d,
        StatsLayout::Extended => d.checked_mul(dims.m()).ok_or(Error::Overflow)?,
    };
    core.checked_add(1 + dims.s).ok_or(Error::Overflow)
}

/// `const` form of [`stat_vector_len`] for sizing firmware storage (0 on overflow).
pub const fn stat_vector_len_const(
    r: usize,
    l: usize,
    s: usize,
    p: usize,
    extended: bool,
) -> usize {
    match crate::window::regressor_len(r, l, s, p) {
        Some(q) => {
            let d = q + r + l;
            (if extended { d * (s + 1) } else { d }) + 1 + s
        }
        None => 0,
    }
}

/// Write the statistic vector s_k of `layout` for the window starting at sample `k` of
/// `src` (samples k..k+p) into `out` (length [`stat_vector_len`]). The one place that
/// defines the layout; the device and the host both call it.
pub fn write_stat_vector<T: Real, X: crate::window::Samples<T> + ?Sized>(
    dims: &PbsidDims,
    layout: StatsLayout,
    src: &X,
    k: usize,
    out: &mut [T],
) {
    let q = crate::window::regressor_len(dims.r, dims.l, dims.s, dims.p).unwrap_or(0);
    let d = q + dims.r + dims.l;
    let p = dims.p;
    {
        let w = &mut out[..d];
        crate::window::write_pbsid_regressor(dims, src, k, &mut w[..q]);
        w[q..q + dims.r].copy_from_slice(src.u(k + p));
        w[q + dims.r..].copy_from_slice(src.y(k + p));
    }
    let mu = src.mu(k + p);
    let core = match layout {
        StatsLayout::Plain => d,
        StatsLayout::Extended => {
            // mu (x) w, filled from the top so w (block 0, mu^(1) = 1) survives until last
            let (head, tail) = out.split_at_mut(d);
            for i in (1..dims.m()).rev() {
                let mi = mu[i];
                for (dst, v) in tail[(i - 1) * d..i * d].iter_mut().zip(head.iter()) {
                    *dst = mi * *v;
                }
            }
            d * dims.m()
        }
    };
    out[core] = T::ONE;
    out[core + 1..core + 1 + dims.s].copy_from_slice(&mu[1..]);
}

/// Streaming sufficient statistics of LPV-PBSID_opt: a [`Window`] feeding a [`Gram`] of
/// the statistic vector of a [`StatsLayout`] (problem (13) of the kernel paper, and with
/// `Extended` the realization too). Storage is caller-provided: see [`PbsidStatsArrays`]
/// for the static form.
///
/// Size: window (p+2)(r+l+s+1) + Gram L(L+1)/2 + scratch L values with
/// L = [`stat_vector_len`]; the B2 blade model (r = l = s = 1) with p = 3 and `Extended`
/// needs L = 65, 2 145 Gram values, about 8.9 KiB in f32.
#[derive(Debug, Clone)]
pub struct PbsidStats<T, SW, SG, SR> {
    window: Window<T, SW>,
    gram: Gram<T, SG>,
    scratch: SR,
    layout: StatsLayout,
    len: usize,
}

impl<T, SW, SG, SR> PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
{
    /// Build over the three storages: window (`window_storage_len`), Gram
    /// (`packed_len(L)`) and scratch (`L`), L = [`stat_vector_len`].
    pub fn with_storage(
        dims: PbsidDims,
        layout: StatsLayout,
        window: SW,
        gram: SG,
        scratch: SR,
    ) -> Result<Self, Error> {
        let len = stat_vector_len(&dims, layout)?;
        if scratch.as_ref().len() < len {
            return Err(Error::Capacity {
                needed: len,
                capacity: scratch.as_ref().len(),
            });
        }
        Ok(PbsidStats {
            window: Window::new(dims, window)?,
            gram: Gram::new(len, gram)?,
            scratch,
            layout,
            len,
        })
    }

    /// Configure again for `dims` and `layout` in place: the Gram and scratch storage stay
    /// where they are (no copy of the Gram through the stack, unlike building a new value
    /// with [`PbsidStats::with_storage`]); only the window gets the new storage `window`
    /// (small: `window_storage_len` values). The statistics start empty (summation as in
    /// [`Gram::reset_dim`]). Fails, changing
    /// nothing, if a storage is too small.
    pub fn reconfigure(
        &mut self,
        dims: PbsidDims,
        layout: StatsLayout,
        window: SW,
    ) -> Result<(), Error> {
        let len = stat_vector_len(&dims, layout)?;
        if self.scratch.as_ref().len() < len {
            return Err(Error::Capacity {
                needed: len,
                capacity: self.scratch.as_ref().len(),
            });
        }
        let cap = self.gram.data.as_ref().len();
        let needed = if self.gram.auto {
            packed_len(len)
        } else {
            Gram::<T, SG>::storage_needed(len, self.gram.summation)
        };
        if cap < needed {
            return Err(Error::Capacity {
                needed,
                capacity: cap,
            });
        }
        self.window = Window::new(dims, window)?;
        self.gram.reset_dim(len)?;
        self.layout = layout;
        self.len = len;
        Ok(())
    }

    /// The dimensions.
    pub fn dims(&self) -> PbsidDims {
        self.window.dims()
    }

    /// The layout.
    pub fn layout(&self) -> StatsLayout {
        self.layout
    }

    /// The accumulated second moments of the statistic vector.
    pub fn gram(&self) -> &Gram<T, SG> {
        &self.gram
    }

    /// Mutable access (merging statistics from another source).
    pub fn gram_mut(&mut self) -> &mut Gram<T, SG> {
        &mut self.gram
    }

    /// The statistic vector s_k of the last window accumulated ([`write_stat_vector`]; its
    /// head is [z_k^p; u_{k+p}; y_{k+p}]): what a recursive estimate predicts from.
    pub fn last_vector(&self) -> &[T] {
        &self.scratch.as_ref()[..self.len]
    }

    /// Exponential forgetting of the statistics ([`Gram::set_forgetting`]): lambda in
    /// (0, 1]. The constant entry of the statistic vector then holds the effective count.
    pub fn set_forgetting(&mut self, lambda: T) -> Result<(), Error> {
        self.gram.set_forgetting(lambda)
    }

    /// Feed one sample. Returns `Ok(true)` when a full window produced a vector that was
    /// accumulated. A rejected sample (wrong length, NaN/inf, overflow in the products)
    /// leaves the statistics and the window exactly as they were.
    pub fn update(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<bool, Error> {
        let was_len = self.window.len();
        self.window.push(u, y, p)?;
        if !self.window.is_full() {
            return Ok(false);
        }
        let dims = self.window.dims();
        let v = &mut self.scratch.as_mut()[..self.len];
        write_stat_vector(&dims, self.layout, &self.window, 0, v);
        if let Err(e) = self.gram.update(v) {
            self.window.unpush(was_len);
            // the inputs were finite: a non-finite product is an overflow
            return Err(match e {
                Error::NonFinite { .. } => Error::Overflow,
                other => other,
            });
        }
        Ok(true)
    }

    /// Start a new experiment: the next vector needs p + 1 fresh samples; the statistics
    /// are kept.
    pub fn break_window(&mut self) {
        self.window.clear();
    }
}

/// One sample (u, y, p) of problem (13)'s data; a block row is [u (r), y (l), p (s)]. The
/// output says whether the sample completed a window whose vector was accumulated.
impl<T, SW, SG, SR> crate::Streaming<T> for PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
{
    type Sample<'a> = (&'a [T], &'a [T], &'a [T]);
    type Output = bool;

    fn update(&mut self, (u, y, p): Self::Sample<'_>) -> Result<bool, Error> {
        PbsidStats::update(self, u, y, p)
    }

    fn row_len(&self) -> usize {
        let d = self.dims();
        d.r + d.l + d.s
    }

    fn sample<'a>(&self, row: &'a [T]) -> Self::Sample<'a> {
        crate::window::split_sample(&self.window.dims(), row)
    }
}

/// Merging statistics sums their Grams; dimensions and layout must agree. The windows are
/// not merged (each source keeps its own partial window).
impl<T, SW, SG, SR, SW2, SG2, SR2> crate::Merge<PbsidStats<T, SW2, SG2, SR2>>
    for PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
    SW2: AsRef<[T]> + AsMut<[T]>,
    SG2: AsRef<[T]> + AsMut<[T]>,
    SR2: AsRef<[T]> + AsMut<[T]>,
{
    fn merge(&mut self, other: &PbsidStats<T, SW2, SG2, SR2>) -> Result<(), Error> {
        if self.dims() != other.dims() || self.layout != other.layout {
            return Err(Error::Mismatch);
        }
        self.gram.merge(&other.gram)
    }
}

/// One vector w (a block row is w, `dim` values). The block update is
/// [`Gram::update_batch`]: register-blocked, and atomic (on error nothing changes).
impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> crate::Streaming<T> for Gram<T, S> {
    type Sample<'a> = &'a [T];
    type Output = ();

    fn update(&mut self, w: &[T]) -> Result<(), Error> {
        Gram::update(self, w)
    }

    fn row_len(&self) -> usize {
        self.dim
    }

    fn sample<'a>(&self, row: &'a [T]) -> &'a [T] {
        row
    }

    fn update_block(&mut self, rows: &[T]) -> Result<(), Error> {
        let w = crate::streaming::check_block(rows.len(), self.dim)?;
        self.update_batch(rows, rows.len() / w)
    }
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>, S2: AsRef<[T]> + AsMut<[T]>> crate::Merge<Gram<T, S2>>
    for Gram<T, S>
{
    fn merge(&mut self, other: &Gram<T, S2>) -> Result<(), Error> {
        Gram::merge(self, other)
    }
}

/// Statically sized storage for [`PbsidStats`] (firmware): `W` window values, `G` Gram
/// values, `R` vector values; compute them with [`window_storage_len`], [`packed_len`]
/// and [`stat_vector_len_const`] in `const` items.
pub type PbsidStatsArrays<T, const W: usize, const G: usize, const R: usize> =
    PbsidStats<T, [T; W], [T; G], [T; R]>;

impl<T: Real, const W: usize, const G: usize, const R: usize> PbsidStatsArrays<T, W, G, R> {
    /// Static-storage statistics for `dims`; fails if the capacities are too small.
    pub fn new(dims: PbsidDims, layout: StatsLayout) -> Result<Self, Error> {
        if W < window_storage_len(dims.r, dims.l, dims.s, dims.p) {
            return Err(Error::Capacity {
                needed: window_storage_len(dims.r, dims.l, dims.s, dims.p),
                capacity: W,
            });
        }
        Self::with_storage(dims, layout, [T::ZERO; W], [T::ZERO; G], [T::ZERO; R])
    }

    /// Build the statistics for `dims` directly in `slot` (a `static` of the firmware, or a
    /// field of a larger struct) and return them: the Gram (`G` values, tens of KiB on a
    /// device) is zeroed where it lives and never passes through the stack, whereas
    /// [`PbsidStatsArrays::new`] returns the arrays by value. Only the window (`W` values)
    /// is built on the stack. `slot` may already hold statistics: they are overwritten (the
    /// type has no destructor). On error (a capacity too small, bad dimensions) `slot` is
    /// left untouched. The Gram sums [`Summation::Compensated`] when `G` holds
    /// [`gram_storage_len`] values for this configuration, else plainly (as [`Gram::new`]).
    pub fn init_in_place(
        slot: &mut MaybeUninit<Self>,
        dims: PbsidDims,
        layout: StatsLayout,
    ) -> Result<&mut Self, Error> {
        let len = stat_vector_len(&dims, layout)?;
        let summation = if G >= gram_storage_len(len) {
            Summation::Compensated
        } else {
            Summation::Plain
        };
        let st = Self::init_in_place_with(slot, dims, layout, summation)?;
        st.gram.auto = true;
        Ok(st)
    }

    /// [`PbsidStatsArrays::init_in_place`] with an explicit [`Summation`] (fails if `G` is
    /// smaller than it needs).
    pub fn init_in_place_with(
        slot: &mut MaybeUninit<Self>,
        dims: PbsidDims,
        layout: StatsLayout,
        summation: Summation,
    ) -> Result<&mut Self, Error> {
        let auto = false;
        let len = stat_vector_len(&dims, layout)?;
        if R < len {
            return Err(Error::Capacity {
                needed: len,
                capacity: R,
            });
        }
        let needed = Gram::<T, [T; G]>::storage_needed(len, summation);
        if G < needed {
            return Err(Error::Capacity {
                needed,
                capacity: G,
            });
        }
        let window = Window::new(dims, [T::ZERO; W])?;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` points to writable, suitably aligned memory for one `Self`. Every field
        // (and every element of the two large arrays) is written exactly once through raw
        // field pointers, without creating a reference to uninitialised memory, before the
        // slot is assumed initialised. Overwriting a previous value leaks nothing: `Self`
        // holds plain arrays and `Copy` fields only and has no `Drop`.
        unsafe {
            addr_of_mut!((*p).window).write(window);
            let g = addr_of_mut!((*p).gram);
            addr_of_mut!((*g).dim).write(len);
            addr_of_mut!((*g).count).write(0);
            addr_of_mut!((*g).summation).write(summation);
            addr_of_mut!((*g).auto).write(auto);
            addr_of_mut!((*g).lambda).write(T::ONE);
            addr_of_mut!((*g).weight).write(0.0);
            addr_of_mut!((*g)._t).write(core::marker::PhantomData);
            let data = addr_of_mut!((*g).data) as *mut T;
            for i in 0..G {
                data.add(i).write(T::ZERO);
            }
            let scratch = addr_of_mut!((*p).scratch) as *mut T;
            for i in 0..R {
                scratch.add(i).write(T::ZERO);
            }
            addr_of_mut!((*p).layout).write(layout);
            addr_of_mut!((*p).len).write(len);
            Ok(slot.assume_init_mut())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gram_matches_dense_and_merges() {
        let rows: Vec<[f64; 3]> = (0..7)
            .map(|k| [k as f64, 1.0 - 0.5 * k as f64, (k * k) as f64 * 0.1])
            .collect();
        let mut all = Gram::new(3, vec![0.0; 6]).unwrap();
        let mut a = Gram::new(3, vec![0.0; 6]).unwrap();
        let mut b = Gram::new(3, [0.0; 6]).unwrap();
        for (k, r) in rows.iter().enumerate() {
            all.update(r).unwrap();
            if k < 3 {
                a.update(r).unwrap();
            } else {
                b.update(r).unwrap();
            }
        }
        a.merge(&b).unwrap();
        assert_eq!(a.count(), 7);
        for i in 0..3 {
            for j in 0..3 {
                let e: f64 = rows.iter().map(|r| r[i] * r[j]).sum();
                assert!((all.get(i, j) - e).abs() < 1e-12);
                assert!((a.get(i, j) - e).abs() < 1e-12);
            }
        }
        let flat: Vec<f64> = rows.iter().flatten().copied().collect();
        let mut batch = Gram::new(3, vec![0.0; 6]).unwrap();
        batch.update_batch(&flat, 7).unwrap();
        assert_eq!(batch.packed(), all.packed());
        let before = batch.packed().to_vec();
        assert!(batch.update(&[1.0, f64::INFINITY, 0.0]).is_err());
        assert!(batch
            .update_batch(&[1.0, 2.0, 3.0, f64::NAN, 0.0, 0.0], 2)
            .is_err());
        assert_eq!(batch.packed(), &before[..]);
        assert_eq!(batch.count(), 7);
    }

    #[test]
    fn a_block_added_packed_equals_the_batch_update() {
        let (dim, n) = (6usize, 9usize);
        let rows: Vec<f64> = (0..n * dim)
            .map(|t| ((t * 37 % 23) as f64 - 11.0) * 0.13)
            .collect();
        let mut block = Gram::new(dim, vec![0.0; packed_len(dim)]).unwrap();
        block.update_batch(&rows, n).unwrap();
        for storage in [packed_len(dim), gram_storage_len(dim)] {
            let mut a = Gram::new(dim, vec![0.0; storage]).unwrap();
            let mut b = Gram::new(dim, vec![0.0; storage]).unwrap();
            a.update_batch(&rows, n).unwrap();
            b.add_packed(block.packed(), n as u64).unwrap();
            assert_eq!((a.count(), a.weight()), (b.count(), b.weight()));
            for (x, y) in a.packed().iter().zip(b.packed()) {
                assert!((x - y).abs() <= 1e-12 * (1.0 + x.abs()));
            }
            // a bad block, or one on an accumulator with forgetting, changes nothing
            let before = b.packed().to_vec();
            let mut bad = block.packed().to_vec();
            bad[4] = f64::INFINITY;
            assert_eq!(
                b.add_packed(&bad, 1),
                Err(Error::NonFinite {
                    field: Field::Regressor,
                    index: 4
                })
            );
            assert!(b.add_packed(&bad[1..], 1).is_err());
            b.set_forgetting(0.5).unwrap();
            assert_eq!(b.add_packed(block.packed(), 1), Err(Error::Mismatch));
            assert_eq!((b.packed(), b.count()), (&before[..], n as u64));
        }
    }

    #[test]
    fn blocked_update_equals_naive() {
        for dim in [1usize, 3, 4, 5, 9, 13, 21] {
            for n in [1usize, 2, 3, 7] {
                let rows: Vec<f64> = (0..n * dim)
                    .map(|t| ((t * 37 % 11) as f64 - 5.0) * 0.3)
                    .collect();
                let mut g = Gram::new(dim, vec![0.0; packed_len(dim)]).unwrap();
                g.update_batch(&rows, n).unwrap();
                for i in 0..dim {
                    for j in 0..dim {
                        let e: f64 = (0..n).map(|b| rows[b * dim + i] * rows[b * dim + j]).sum();
                        assert!((g.get(i, j) - e).abs() < 1e-12, "dim {dim} n {n} ({i},{j})");
                    }
                }
            }
        }
    }

    #[test]
    fn static_storage_stats() {
        const R: usize = 1;
        const L: usize = 1;
        const S: usize = 1;
        const P: usize = 2;
        const D: usize = stat_vector_len_const(R, L, S, P, true);
        const W: usize = window_storage_len(R, L, S, P);
        let dims = PbsidDims::new(R, L, S, P).unwrap();
        let mut st =
            PbsidStatsArrays::<f32, W, { packed_len(D) }, D>::new(dims, StatsLayout::Extended)
                .unwrap();
        let mut n = 0;
        for k in 0..10 {
            let x = k as f32;
            if st.update(&[x], &[0.5 * x], &[0.1 * x]).unwrap() {
                n += 1;
            }
        }
        assert_eq!(n, 8);
        assert_eq!(st.gram().count(), 8);
        let before = st.gram().packed().to_vec();
        assert!(st.update(&[f32::NAN], &[0.0], &[0.0]).is_err());
        // overflow: finite input, infinite outer product
        assert_eq!(st.update(&[1e30], &[1e30], &[1e30]), Err(Error::Overflow));
        assert_eq!(st.gram().packed(), &before[..]);
        // the window was restored: the next good sample behaves as if nothing happened
        assert!(st.update(&[10.0], &[5.0], &[1.0]).unwrap());
        // channel block: count and sum of p_{k+p} sit at the end of the vector
        let n = st.gram().dim();
        assert_eq!(st.gram().get(n - 2, n - 2), 9.0);
        let sum_p: f32 = (2..10).map(|k| 0.1 * k as f32).sum::<f32>() + 1.0;
        assert!((st.gram().get(n - 2, n - 1) - sum_p).abs() < 1e-5);
    }

    #[test]
    fn in_place_configuration_equals_by_value() {
        // capacities of B1-like dims at p = 2, used for smaller configurations too
        const W: usize = window_storage_len(2, 1, 1, 2);
        const D: usize = stat_vector_len_const(2, 1, 1, 2, true);
        const G: usize = packed_len(D);
        type St = PbsidStatsArrays<f64, W, G, D>;
        let dims_a = PbsidDims::new(2, 1, 1, 2).unwrap();
        let dims_b = PbsidDims::new(1, 1, 1, 2).unwrap();
        let mut by_value = St::new(dims_a, StatsLayout::Extended).unwrap();
        feed(&mut by_value, 20);
        // in place, on garbage first: everything is (re)initialised
        let mut slot = MaybeUninit::<St>::uninit();
        // SAFETY: f64 arrays and plain fields: any bit pattern is a valid St after writing
        // every byte, and init_in_place overwrites all of them anyway.
        unsafe { core::ptr::write_bytes(slot.as_mut_ptr() as *mut u8, 0x7f, size_of::<St>()) };
        let st = St::init_in_place(&mut slot, dims_a, StatsLayout::Extended).unwrap();
        assert_eq!(st.gram().count(), 0);
        assert_eq!(st.gram().dim(), D);
        feed(st, 20);
        assert_eq!(st.gram().packed(), by_value.gram().packed());
        assert_eq!(st.gram().count(), 18);
        // again over the used slot, other dims: the old statistics are gone
        let st = St::init_in_place(&mut slot, dims_b, StatsLayout::Plain).unwrap();
        let mut fresh_b = St::new(dims_b, StatsLayout::Plain).unwrap();
        feed(st, 12);
        feed(&mut fresh_b, 12);
        assert_eq!(
            st.gram().dim(),
            stat_vector_len(&dims_b, StatsLayout::Plain).unwrap()
        );
        assert_eq!(st.gram().packed(), fresh_b.gram().packed());
        // too small a capacity: error, and the slot keeps what it had
        let big = PbsidDims::new(2, 1, 1, 3).unwrap();
        assert!(matches!(
            St::init_in_place(&mut slot, big, StatsLayout::Extended),
            Err(Error::Capacity { .. })
        ));
        // SAFETY: initialised above, and the failed call wrote nothing.
        let st = unsafe { slot.assume_init_mut() };
        assert_eq!(st.gram().packed(), fresh_b.gram().packed());
        assert_eq!(st.dims(), dims_b);

        // reconfigure (any storage): same as a fresh value, storage kept, errors change nothing
        let mut v = PbsidStats::with_storage(
            dims_b,
            StatsLayout::Plain,
            vec![0.0; W],
            vec![0.0; G],
            vec![0.0; D],
        )
        .unwrap();
        feed(&mut v, 7);
        let gram_ptr = v.gram().packed().as_ptr();
        v.reconfigure(dims_a, StatsLayout::Extended, vec![0.0; W])
            .unwrap();
        assert_eq!(v.gram().count(), 0);
        assert_eq!(v.gram().packed().as_ptr(), gram_ptr);
        feed(&mut v, 20);
        assert_eq!(v.gram().packed(), by_value.gram().packed());
        assert_eq!(v.layout(), StatsLayout::Extended);
        let before = v.gram().packed().to_vec();
        assert!(v
            .reconfigure(big, StatsLayout::Extended, vec![0.0; 4 * W])
            .is_err());
        assert_eq!(v.gram().packed(), &before[..]);
        assert_eq!(v.dims(), dims_a);
        // Gram alone
        let mut g = Gram::new(2, [1.0f32; 6]).unwrap();
        g.update(&[1.0, 2.0]).unwrap();
        g.reset_dim(3).unwrap();
        assert_eq!((g.dim(), g.count()), (3, 0));
        assert_eq!(g.packed(), &[0.0; 6]);
        assert!(g.reset_dim(4).is_err());
        assert_eq!(g.dim(), 3);
    }

    /// Feed n samples of a fixed signal (r <= 2, s <= 1), whatever the storage.
    fn feed<SW, SG, SR>(st: &mut PbsidStats<f64, SW, SG, SR>, n: usize)
    where
        SW: AsRef<[f64]> + AsMut<[f64]>,
        SG: AsRef<[f64]> + AsMut<[f64]>,
        SR: AsRef<[f64]> + AsMut<[f64]>,
    {
        let (r, s) = (st.dims().r, st.dims().s);
        for k in 0..n {
            let x = k as f64;
            let u = [0.3 * x - 1.0, (0.7 * x).sin()];
            st.update(&u[..r], &[(1.1 * x).cos()], &[0.05 * x][..s])
                .unwrap();
        }
    }

    #[test]
    fn extended_vector_contains_plain_and_shift() {
        use crate::window::{write_pbsid_regressor, Slab};
        let dims = PbsidDims::new(1, 1, 1, 2).unwrap();
        let data: Vec<f64> = (0..8)
            .flat_map(|k| {
                let f = k as f64;
                [f.sin(), (0.3 * f).cos(), 1.0, 0.5 + 0.1 * f]
            })
            .collect();
        let slab = Slab::new(&data, 1, 1, 2).unwrap();
        let lp = stat_vector_len(&dims, StatsLayout::Plain).unwrap();
        let le = stat_vector_len(&dims, StatsLayout::Extended).unwrap();
        let (mut vp, mut ve) = (vec![0.0; lp], vec![0.0; le]);
        write_stat_vector(&dims, StatsLayout::Plain, &slab, 1, &mut vp);
        write_stat_vector(&dims, StatsLayout::Extended, &slab, 1, &mut ve);
        let d = dims.stat_len().unwrap();
        assert_eq!(&vp[..d], &ve[..d]);
        assert_eq!(&vp[d..], &ve[2 * d..]);
        let mu2 = slab.mu(1 + 2)[1];
        for i in 0..d {
            assert!((ve[d + i] - mu2 * vp[i]).abs() < 1e-15);
        }
        // z_{k+1}^p block 1 = mu_{k+p} (x) block 2 of z_k^p: a selection of the extended vector
        let q = dims.q().unwrap();
        let mut z1 = vec![0.0; q];
        write_pbsid_regressor(&dims, &slab, 2, &mut z1);
        let b2 = dims.block_offset(2);
        let l2 = dims.block_len(2);
        for (t, zt) in z1[..2 * l2].iter().enumerate() {
            let (i, j) = (t / l2, t % l2);
            assert!((zt - ve[i * d + b2 + j]).abs() < 1e-15);
        }
    }
}

#[cfg(test)]
mod summation_tests {
    use super::*;

    /// A deterministic pseudo-random stream in [-1, 1) (xorshift), for sums with mixed signs.
    fn stream(seed: u64) -> impl FnMut() -> f64 {
        let mut x = seed | 1;
        move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    #[test]
    fn compensated_f32_counts_past_2_pow_24() {
        // 2^24 + 10^6 additions of 1: plain f32 stops at 2^24, compensated counts on
        let n = (1u64 << 24) + 1_000_000;
        let mut plain = Gram::new(1, [0.0f32; 1]).unwrap();
        let mut comp = Gram::new(1, [0.0f32; 2]).unwrap();
        assert_eq!(plain.summation(), Summation::Plain);
        assert_eq!(comp.summation(), Summation::Compensated);
        for _ in 0..n {
            plain.update(&[1.0]).unwrap();
            comp.update(&[1.0]).unwrap();
        }
        assert_eq!(plain.get(0, 0), 16_777_216.0);
        assert_eq!(
            comp.get(0, 0) as f64 + comp.compensation()[0] as f64,
            n as f64
        );
        assert!((comp.get(0, 0) as f64 - n as f64).abs() <= 2.0);
    }

    #[test]
    fn compensated_single_batch_and_merge_agree_with_f64() {
        let dim = 7;
        let mut next = stream(7);
        let n = 20_000;
        let rows: Vec<f32> = (0..n * dim).map(|_| (next() + 0.3) as f32).collect();
        let mut exact = vec![0.0f64; packed_len(dim)];
        let mut single = Gram::new(dim, vec![0.0f32; gram_storage_len(dim)]).unwrap();
        let mut batch = Gram::new(dim, vec![0.0f32; gram_storage_len(dim)]).unwrap();
        let mut a = Gram::new(dim, vec![0.0f32; gram_storage_len(dim)]).unwrap();
        let mut b = Gram::new(dim, vec![0.0f32; gram_storage_len(dim)]).unwrap();
        let mut plain = Gram::new(dim, vec![0.0f32; packed_len(dim)]).unwrap();
        for (k, w) in rows.chunks_exact(dim).enumerate() {
            single.update(w).unwrap();
            plain.update(w).unwrap();
            if k < n / 3 {
                a.update(w).unwrap();
            } else {
                b.update(w).unwrap();
            }
            let mut off = 0;
            for i in 0..dim {
                for j in i..dim {
                    // f32 x f32 is exact in f64
                    exact[off + j - i] += w[i] as f64 * w[j] as f64;
                }
                off += dim - i;
            }
        }
        for chunk in rows.chunks(dim * 64) {
            batch.update_batch(chunk, chunk.len() / dim).unwrap();
        }
        a.merge(&b).unwrap();
        assert_eq!(a.count(), n as u64);
        let scale = exact.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = |g: &Gram<f32, Vec<f32>>| {
            g.packed()
                .iter()
                .zip(&exact)
                .map(|(x, e)| (*x as f64 - e).abs() / scale)
                .fold(0.0, f64::max)
        };
        // within a couple of f32 ulps of the largest entry
        for g in [&single, &batch, &a] {
            assert!(worst(g) < 2.0 * f32::EPSILON as f64, "{}", worst(g));
        }
        // plain summation is measurably worse on the same data
        assert!(worst(&plain) > 10.0 * worst(&single));
        // load keeps the summation and clears the low parts
        let mut l = Gram::new(dim, vec![0.0f32; gram_storage_len(dim)]).unwrap();
        l.load(single.packed(), 3).unwrap();
        assert!(l.compensation().iter().all(|v| *v == 0.0));
        assert_eq!(l.packed(), single.packed());
        // explicit summation needs its storage
        assert!(
            Gram::with_summation(dim, vec![0.0f32; packed_len(dim)], Summation::Compensated)
                .is_err()
        );
    }
}

#[cfg(test)]
mod forgetting_tests {
    use super::*;

    #[test]
    fn forgetting_weights_by_age_and_merges_only_alike() {
        let lambda = 0.9f64;
        let rows: Vec<[f64; 2]> = (0..50).map(|k| [1.0, (k as f64 * 0.37).sin()]).collect();
        for storage in [packed_len(2), gram_storage_len(2)] {
            let mut g = Gram::new(2, vec![0.0; storage]).unwrap();
            g.set_forgetting(lambda).unwrap();
            let flat: Vec<f64> = rows.iter().flatten().copied().collect();
            // a batch is applied vector by vector under forgetting
            g.update_batch(&flat[..20], 10).unwrap();
            for r in &rows[10..] {
                g.update(r).unwrap();
            }
            let n = rows.len();
            let e = |i: usize, j: usize| -> f64 {
                rows.iter()
                    .enumerate()
                    .map(|(k, r)| lambda.powi((n - 1 - k) as i32) * r[i] * r[j])
                    .sum()
            };
            for (i, j) in [(0, 0), (0, 1), (1, 1)] {
                assert!((g.get(i, j) - e(i, j)).abs() < 1e-12, "{i}{j}");
            }
            assert_eq!(g.count(), 50);
            assert!((g.weight() - e(0, 0)).abs() < 1e-12);
            // merge: only statistics with the same forgetting factor
            let plain = Gram::new(2, vec![0.0; storage]).unwrap();
            assert_eq!(g.merge(&plain), Err(Error::Mismatch));
            assert!(g.set_forgetting(0.0).is_err());
            assert!(g.set_forgetting(1.5).is_err());
            assert!(g.set_forgetting(f64::NAN).is_err());
            assert_eq!(g.forgetting(), lambda);
        }
    }
}

#[cfg(test)]
mod sliding_tests {
    use super::*;
    use crate::SlidingGram;

    #[test]
    fn sliding_window_holds_the_last_half_to_full_window() {
        let n = 8u64;
        let mut sl = SlidingGram::new(
            1,
            n,
            vec![0.0f64; gram_storage_len(1)],
            vec![0.0; gram_storage_len(1)],
        )
        .unwrap();
        for k in 1..=37u64 {
            sl.update(&[k as f64]).unwrap();
            let c = sl.count();
            assert!(c <= n && (c == k || c > n / 2), "k {k} count {c}");
            // the window is the last c vectors: sum of squares of k-c+1..=k
            let e: f64 = (k + 1 - c..=k).map(|j| (j * j) as f64).sum();
            assert_eq!(sl.get(0, 0), e);
        }
        let before = (sl.count(), sl.get(0, 0));
        assert!(sl.update(&[f64::NAN]).is_err());
        assert_eq!((sl.count(), sl.get(0, 0)), before);
        let mut out = Gram::new(1, vec![0.0; 1]).unwrap();
        sl.write_total(&mut out).unwrap();
        assert_eq!(out.get(0, 0), before.1);
        assert!(SlidingGram::new(1, 1, vec![0.0f64; 1], vec![0.0; 1]).is_err());
    }
}
