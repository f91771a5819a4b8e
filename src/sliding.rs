//! A sliding window of about N vectors over [`Gram`] statistics (issue 18): two
//! half-window accumulators, the older one dropped whole when the newer one is full. Where
//! the papers' statistics are sums over a record (kernel paper problem (13)), this is the
//! same sum over the last N/2 to N vectors; no sample is ever subtracted, so nothing
//! cancels catastrophically in f32.
//!
//! Size: two Gram storages (each `packed_len(dim)`, or [`crate::gram_storage_len`] for
//! compensated sums).

use crate::error::Error;
use crate::real::Real;
use crate::stats::Gram;

/// Second moments of the last `half + 1 ..= 2 half` vectors: two [`Gram`]s taking turns.
#[derive(Debug, Clone)]
pub struct SlidingGram<T, S> {
    halves: [Gram<T, S>; 2],
    cur: usize,
    half: u64,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> SlidingGram<T, S> {
    /// A window of `window` vectors (>= 2; an odd length is rounded down to even) of length
    /// `dim` over two storages, summed as [`Gram::new`] chooses for each.
    pub fn new(dim: usize, window: u64, a: S, b: S) -> Result<Self, Error> {
        if window < 2 {
            return Err(Error::InvalidConfig(
                "sliding window must hold at least 2 vectors",
            ));
        }
        Ok(SlidingGram {
            halves: [Gram::new(dim, a)?, Gram::new(dim, b)?],
            cur: 0,
            half: window / 2,
        })
    }

    /// Add w w^T; when the current half is full, the older half is emptied and takes over.
    /// A rejected vector changes nothing.
    pub fn update(&mut self, w: &[T]) -> Result<(), Error> {
        if self.halves[self.cur].count() == self.half {
            // check first, so a bad vector does not drop the old half
            self.halves[self.cur].check(w)?;
            self.cur = 1 - self.cur;
            self.halves[self.cur].reset();
        }
        self.halves[self.cur].update(w)
    }

    /// Vectors in the window now.
    pub fn count(&self) -> u64 {
        self.halves[0].count() + self.halves[1].count()
    }

    /// Entry (i, j) of the windowed sum.
    pub fn get(&self, i: usize, j: usize) -> T {
        self.halves[0].get(i, j) + self.halves[1].get(i, j)
    }

    /// The windowed sum into `out` (emptied first; same dimension and forgetting factor 1),
    /// for a solver that reads a [`Gram`].
    pub fn write_total<S2: AsRef<[T]> + AsMut<[T]>>(
        &self,
        out: &mut Gram<T, S2>,
    ) -> Result<(), Error> {
        if out.dim() != self.halves[0].dim() {
            return Err(Error::Mismatch);
        }
        out.reset();
        out.merge(&self.halves[0])?;
        out.merge(&self.halves[1])
    }
}
