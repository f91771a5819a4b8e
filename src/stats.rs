//! Sufficient statistics: streaming second moments, mergeable.
//!
//! [`Gram`] accumulates sum_k w_k w_k^T (packed upper triangle) for any vector w; it is the
//! one second-moment accumulator of the project (the host's least-squares steps use it too).
//! [`PbsidStats`] feeds it with w_k = [z_k^p; u_{k+p}; y_{k+p}], the statistics from which
//! problem (13) of the kernel paper (and its regularised forms) is solved without the data.

use crate::error::{check_vec, Error, Field};
use crate::real::{first_non_finite, Real};
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
    _t: core::marker::PhantomData<T>,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Gram<T, S> {
    /// An empty accumulator for vectors of length `dim` over `storage` (zeroed here).
    pub fn new(dim: usize, mut storage: S) -> Result<Self, Error> {
        let needed = packed_len(dim);
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
            _t: core::marker::PhantomData,
        })
    }

    /// Vector length.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of vectors accumulated.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The packed upper triangle (row-major: (0,0), (0,1), ..., (0,d-1), (1,1), ...).
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

    /// Add w w^T. Rejects a wrong length or a non-finite entry without changing anything.
    pub fn update(&mut self, w: &[T]) -> Result<(), Error> {
        check_vec(Field::Regressor, w, self.dim)?;
        check_products(w)?;
        self.rank_k(w, 1);
        Ok(())
    }

    /// Add the outer products of `n` vectors stored row-major in `rows` (n x dim). The
    /// packed matrix is streamed once per batch instead of once per vector, which is what
    /// makes a host-side batch fast; the result equals n single updates. All rows are
    /// checked first: on error nothing changes.
    pub fn update_batch(&mut self, rows: &[T], n: usize) -> Result<(), Error> {
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
        check_products(rows)?;
        self.rank_k(rows, n);
        Ok(())
    }

    /// The rank-n update proper (inputs already validated).
    fn rank_k(&mut self, rows: &[T], n: usize) {
        let dim = self.dim;
        let data = self.data.as_mut();
        let mut off = 0;
        for i in 0..dim {
            let row = &mut data[off..off + dim - i];
            for b in 0..n {
                let w = &rows[b * dim..(b + 1) * dim];
                let wi = w[i];
                if wi == T::ZERO {
                    continue;
                }
                for (acc, x) in row.iter_mut().zip(&w[i..]) {
                    *acc += wi * *x;
                }
            }
            off += dim - i;
        }
        self.count += n as u64;
    }

    /// Add another accumulator of the same dimension: the result equals accumulating the
    /// concatenated data (how experiments or devices combine).
    pub fn merge<S2: AsRef<[T]> + AsMut<[T]>>(&mut self, other: &Gram<T, S2>) -> Result<(), Error> {
        if other.dim != self.dim {
            return Err(Error::Mismatch);
        }
        let n = packed_len(self.dim);
        for (a, b) in self.data.as_mut()[..n].iter_mut().zip(other.packed()) {
            *a += *b;
        }
        self.count += other.count;
        Ok(())
    }

    /// Forget everything accumulated.
    pub fn reset(&mut self) {
        let n = packed_len(self.dim);
        for v in self.data.as_mut()[..n].iter_mut() {
            *v = T::ZERO;
        }
        self.count = 0;
    }

    /// Overwrite the contents (e.g. statistics pulled from a device). `packed` must have
    /// `packed_len(dim)` finite values.
    pub fn load(&mut self, packed: &[T], count: u64) -> Result<(), Error> {
        check_vec(Field::Regressor, packed, packed_len(self.dim))?;
        self.data.as_mut()[..packed.len()].copy_from_slice(packed);
        self.count = count;
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

/// Streaming sufficient statistics of LPV-PBSID_opt: a [`Window`] feeding a [`Gram`] of
/// w_k = [z_k^p; u_{k+p}; y_{k+p}] (problem (13) of the kernel paper), plus the regressor
/// scratch. Storage is caller-provided: see [`PbsidStatsArrays`] for the static form.
#[derive(Debug, Clone)]
pub struct PbsidStats<T, SW, SG, SR> {
    window: Window<T, SW>,
    gram: Gram<T, SG>,
    scratch: SR,
    stat_len: usize,
}

impl<T, SW, SG, SR> PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
{
    /// Build over the three storages: window (`window_storage_len`), Gram
    /// (`packed_len(stat_len)`) and regressor scratch (`stat_len`).
    pub fn with_storage(dims: PbsidDims, window: SW, gram: SG, scratch: SR) -> Result<Self, Error> {
        let stat_len = dims.stat_len()?;
        if scratch.as_ref().len() < stat_len {
            return Err(Error::Capacity {
                needed: stat_len,
                capacity: scratch.as_ref().len(),
            });
        }
        Ok(PbsidStats {
            window: Window::new(dims, window)?,
            gram: Gram::new(stat_len, gram)?,
            scratch,
            stat_len,
        })
    }

    /// The dimensions.
    pub fn dims(&self) -> PbsidDims {
        self.window.dims()
    }

    /// The accumulated second moments of w_k.
    pub fn gram(&self) -> &Gram<T, SG> {
        &self.gram
    }

    /// Mutable access (merging statistics from another source).
    pub fn gram_mut(&mut self) -> &mut Gram<T, SG> {
        &mut self.gram
    }

    /// Feed one sample. Returns `Ok(true)` when a full window produced a regressor that was
    /// accumulated. A rejected sample (wrong length, NaN/inf, overflow in the regressor)
    /// leaves the statistics and the window exactly as they were.
    pub fn update(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<bool, Error> {
        let was_len = self.window.len();
        self.window.push(u, y, p)?;
        if !self.window.is_full() {
            return Ok(false);
        }
        let w = &mut self.scratch.as_mut()[..self.stat_len];
        if let Err(e) = self.window.regressor(w) {
            self.window.unpush(was_len);
            return Err(e);
        }
        if let Err(e) = self.gram.update(w) {
            self.window.unpush(was_len);
            return Err(e);
        }
        Ok(true)
    }

    /// Start a new experiment: the next regressor needs p + 1 fresh samples; the
    /// statistics are kept.
    pub fn break_window(&mut self) {
        self.window.clear();
    }
}

/// Statically sized storage for [`PbsidStats`] (firmware): `W` window values, `G` Gram
/// values, `R` regressor values; compute them with [`window_storage_len`], [`packed_len`]
/// and [`PbsidDims::stat_len`] in `const` items.
pub type PbsidStatsArrays<T, const W: usize, const G: usize, const R: usize> =
    PbsidStats<T, [T; W], [T; G], [T; R]>;

impl<T: Real, const W: usize, const G: usize, const R: usize> PbsidStatsArrays<T, W, G, R> {
    /// Static-storage statistics for `dims`; fails if the capacities are too small.
    pub fn new(dims: PbsidDims) -> Result<Self, Error> {
        if W < window_storage_len(dims.r, dims.l, dims.s, dims.p) {
            return Err(Error::Capacity {
                needed: window_storage_len(dims.r, dims.l, dims.s, dims.p),
                capacity: W,
            });
        }
        Self::with_storage(dims, [T::ZERO; W], [T::ZERO; G], [T::ZERO; R])
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
        assert!(batch.update_batch(&[1.0, 2.0, 3.0, f64::NAN, 0.0, 0.0], 2).is_err());
        assert_eq!(batch.packed(), &before[..]);
        assert_eq!(batch.count(), 7);
    }

    #[test]
    fn static_storage_stats() {
        const R: usize = 1;
        const L: usize = 1;
        const S: usize = 1;
        const P: usize = 2;
        const D: usize = match crate::window::regressor_len(R, L, S, P) {
            Some(q) => q + R + L,
            None => 0,
        };
        const W: usize = window_storage_len(R, L, S, P);
        let dims = PbsidDims::new(R, L, S, P).unwrap();
        let mut st = PbsidStatsArrays::<f32, W, { packed_len(D) }, D>::new(dims).unwrap();
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
    }
}
