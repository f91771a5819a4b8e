//! A sliding window of about N vectors over [`Gram`] statistics (issue 18): two
//! half-window accumulators, the older one dropped whole when the newer one is full. Where
//! the papers' statistics are sums over a record (kernel paper problem (13)), this is the
//! same sum over the last N/2 to N vectors; no sample is ever subtracted, so nothing
//! cancels catastrophically in f32.
//!
//! Two forms: [`SlidingGram`] (two Gram storages, each `packed_len(dim)`, or
//! [`crate::gram_storage_len`] for compensated sums) and windows by rebasing ([`HalfWindow`],
//! [`Rebase`], [`Sliding`]: one accumulator plus one snapshot of its sums), implemented for
//! every accumulator of the core: [`Gram`], [`crate::PbsidStats`],
//! [`crate::bciv::BcivStats`] and [`crate::dictionary::KernelDictionary`] (normal
//! equations). The device keeps its window this way, the snapshot in the Gram's spare
//! storage.
//!
//! **Merge semantics.** A windowed accumulator holds plain sums over its last N/2 ..= N - 1
//! vectors, so merging two adds their windows: the window of the union only when both hold
//! the same time span (two sensors of one plant, counted by the same clock). Windows and
//! forgetting are alternatives ([`Rebase::check_rebase`] refuses lambda < 1); forgetting
//! statistics merge only with the same lambda and as they are (see [`crate::stats`]).

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

// ---------------------------------------------------------------------------------------
// Windows by rebasing: one accumulator and a snapshot of its previous half

/// Bookkeeping of a sliding window of N statistic vectors kept as *totals plus a snapshot*:
/// the accumulator sums every vector; when the current half holds N/2 vectors the totals
/// are rebased ([`rebase_gram`], [`Rebase::rebase`]): totals <- totals - snapshot (the
/// older half leaves: what remains is the newest N/2 vectors) and snapshot <- the new
/// totals. The window then holds the last N/2 ..= N - 1 vectors, and the accumulator
/// always holds the windowed sums, so solvers and pulls read it as they read plain sums.
///
/// Accuracy: the subtraction once per N/2 vectors rounds like one more addition, and since
/// the snapshot is the bitwise copy of the totals it is later subtracted from, that rounding
/// leaves with the half it belongs to: the error stays that of summing N vectors, never
/// grows with the stream. Compared with [`SlidingGram`] (two accumulators, nothing
/// subtracted) it needs one snapshot (packed values only, no low parts) instead of a second
/// accumulator, and the sums need no merging before a solve.
///
/// Forgetting and a window are alternatives (the snapshot would have to age with the
/// totals): [`rebase_gram`] refuses an accumulator with lambda < 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HalfWindow {
    half: u64,
    in_half: u64,
}

impl HalfWindow {
    /// A window of `window` vectors (>= 2; an odd length is rounded down to even).
    pub fn new(window: u64) -> Result<Self, Error> {
        if window < 2 {
            return Err(Error::InvalidConfig(
                "sliding window must hold at least 2 vectors",
            ));
        }
        Ok(HalfWindow {
            half: window / 2,
            in_half: 0,
        })
    }

    /// Vectors per half (N/2).
    pub fn half(&self) -> u64 {
        self.half
    }

    /// Count one accumulated vector; true when the half is full and the caller must rebase
    /// now (with `count` = [`HalfWindow::half`]).
    pub fn added(&mut self) -> bool {
        self.in_half += 1;
        if self.in_half >= self.half {
            self.in_half = 0;
            true
        } else {
            false
        }
    }

    /// Start over (the accumulator and snapshot were emptied).
    pub fn clear(&mut self) {
        self.in_half = 0;
    }
}

/// totals <- totals (+ low parts) - snapshot, snapshot <- totals; the low parts restart at 0
/// (`lo` empty: plain totals). Shared by every [`Rebase`] implementation.
pub(crate) fn rebase_values<T: Real>(hi: &mut [T], lo: &mut [T], snapshot: &mut [T]) {
    let comp = !lo.is_empty();
    for (k, (h, s)) in hi.iter_mut().zip(snapshot.iter_mut()).enumerate() {
        let mut v = *h - *s;
        if comp {
            v += lo[k];
            lo[k] = T::ZERO;
        }
        *h = v;
        *s = v;
    }
}

/// Rebase a [`Gram`] for a [`HalfWindow`]: the sums keep only the newest half (`count`
/// vectors). `snapshot`: `packed_len(dim)` values, or `None` for the spare storage after
/// the Gram's own sums (the device keeps its window in the one static array: a plain Gram
/// over `2 packed_len` values, or a compensated one over `3 packed_len`). Fails, changing
/// nothing, with forgetting (lambda < 1) or a snapshot too small.
pub fn rebase_gram<T: Real, S: AsRef<[T]> + AsMut<[T]>>(
    g: &mut Gram<T, S>,
    snapshot: Option<&mut [T]>,
    count: u64,
) -> Result<(), Error> {
    if g.forgetting() != T::ONE {
        return Err(WINDOW_AND_FORGETTING);
    }
    let n = crate::stats::packed_len(g.dim());
    let (hi, lo, spare) = g.storage_parts();
    let snap = match snapshot {
        Some(s) => s,
        None => spare,
    };
    if snap.len() < n {
        return Err(Error::Capacity {
            needed: n,
            capacity: snap.len(),
        });
    }
    rebase_values(hi, lo, &mut snap[..n]);
    g.set_count(count);
    Ok(())
}

/// Values a [`Gram`] of dimension `dim` needs to keep its window's snapshot in its own
/// storage ([`rebase_gram`] with `None`): the sums ([`crate::Summation`]) plus one packed
/// triangle.
pub const fn inline_window_len(dim: usize, compensated: bool) -> usize {
    let p = crate::stats::packed_len(dim);
    if compensated {
        3 * p
    } else {
        2 * p
    }
}

/// An accumulator whose sums can be rebased for a sliding window ([`HalfWindow`]).
///
/// Implemented for [`Gram`], [`crate::PbsidStats`], [`crate::bciv::BcivStats`] (its
/// statistics sum z y and M_t and their low parts) and
/// [`crate::dictionary::KernelDictionary`] (its normal equations, once frozen).
pub trait Rebase<T> {
    /// Values of the sums (the snapshot's length).
    fn sums_len(&self) -> usize;
    /// sums <- sums - snapshot, snapshot <- the new sums, count <- `count`.
    fn rebase(&mut self, snapshot: &mut [T], count: u64) -> Result<(), Error>;
    /// Empty the sums (configuration kept).
    fn clear_sums(&mut self);
    /// Whether the sums can be rebased at all: `Err` with forgetting (lambda < 1: the
    /// snapshot would have to age with the sums), or while a dictionary is still building.
    /// [`Sliding::new`] checks it, so a rebase inside an update does not fail.
    fn check_rebase(&self) -> Result<(), Error> {
        Ok(())
    }
}

/// The error of a window over forgetting statistics.
pub(crate) const WINDOW_AND_FORGETTING: Error =
    Error::InvalidConfig("a sliding window and forgetting are alternatives");

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Rebase<T> for Gram<T, S> {
    fn sums_len(&self) -> usize {
        crate::stats::packed_len(self.dim())
    }
    fn rebase(&mut self, snapshot: &mut [T], count: u64) -> Result<(), Error> {
        rebase_gram(self, Some(snapshot), count)
    }
    fn clear_sums(&mut self) {
        self.reset();
    }
    fn check_rebase(&self) -> Result<(), Error> {
        if self.forgetting() != T::ONE {
            return Err(WINDOW_AND_FORGETTING);
        }
        Ok(())
    }
}

impl<T, SW, SG, SR> Rebase<T> for crate::stats::PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
{
    fn sums_len(&self) -> usize {
        crate::stats::packed_len(self.gram().dim())
    }
    fn rebase(&mut self, snapshot: &mut [T], count: u64) -> Result<(), Error> {
        rebase_gram(self.gram_mut(), Some(snapshot), count)
    }
    fn clear_sums(&mut self) {
        self.gram_mut().reset();
    }
    fn check_rebase(&self) -> Result<(), Error> {
        self.gram().check_rebase()
    }
}

/// A sliding window of N vectors over any [`Rebase`] accumulator, with the snapshot in
/// storage `S` ([`Rebase::sums_len`] values): the accumulator always holds the sums of the
/// last N/2 ..= N - 1 vectors (see [`HalfWindow`]).
#[derive(Debug, Clone)]
pub struct Sliding<T, A, S> {
    inner: A,
    snapshot: S,
    win: HalfWindow,
    _t: core::marker::PhantomData<T>,
}

impl<T, A, S> Sliding<T, A, S> {
    /// The accumulator (read it as usual: its sums are the window's).
    pub fn inner(&self) -> &A {
        &self.inner
    }

    /// Vectors per half.
    pub fn half(&self) -> u64 {
        self.win.half()
    }
}

impl<T: Real, A: Rebase<T>, S: AsRef<[T]> + AsMut<[T]>> Sliding<T, A, S> {
    /// A window of `window` vectors (>= 2) over `inner`, which is emptied; `snapshot` must
    /// hold `inner.sums_len()` values. Fails if `inner` cannot be rebased
    /// ([`Rebase::check_rebase`]: forgetting, or a dictionary still building).
    pub fn new(mut inner: A, window: u64, mut snapshot: S) -> Result<Self, Error> {
        let win = HalfWindow::new(window)?;
        inner.check_rebase()?;
        let n = inner.sums_len();
        let cap = snapshot.as_ref().len();
        if cap < n {
            return Err(Error::Capacity {
                needed: n,
                capacity: cap,
            });
        }
        snapshot.as_mut()[..n].fill(T::ZERO);
        inner.clear_sums();
        Ok(Sliding {
            inner,
            snapshot,
            win,
            _t: core::marker::PhantomData,
        })
    }

    /// Run one update of the accumulator (`f` returns whether it accumulated a vector, as
    /// `PbsidStats::update` and `BcivStats::update` do) and rebase when a half is full. A
    /// rejected sample changes nothing.
    pub fn update_with<R>(
        &mut self,
        f: impl FnOnce(&mut A) -> Result<R, Error>,
        accumulated: impl FnOnce(&R) -> bool,
    ) -> Result<R, Error> {
        let r = f(&mut self.inner)?;
        if accumulated(&r) && self.win.added() {
            let n = self.inner.sums_len();
            self.inner
                .rebase(&mut self.snapshot.as_mut()[..n], self.win.half())?;
        }
        Ok(r)
    }

    /// Empty the window.
    pub fn clear(&mut self) {
        let n = self.inner.sums_len();
        self.snapshot.as_mut()[..n].fill(T::ZERO);
        self.inner.clear_sums();
        self.win.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::{gram_storage_len, packed_len, Summation};

    fn vectors(n: usize, dim: usize) -> std::vec::Vec<f64> {
        (0..n * dim)
            .map(|i| ((i as f64) * 0.731).sin() + 0.1 * (i % 7) as f64)
            .collect()
    }

    /// The rebased window equals a fresh sum over the vectors it claims to hold, in every
    /// summation, with the snapshot outside or inside the Gram's storage.
    #[test]
    fn rebased_window_is_the_sum_of_the_last_vectors() {
        let dim = 4;
        let rows = vectors(101, dim);
        for (window, storage, inline) in [
            (10u64, packed_len(dim), false),
            (10, gram_storage_len(dim), false),
            (7, inline_window_len(dim, false), true),
            (12, inline_window_len(dim, true), true),
        ] {
            let mut g = Gram::<f64, _>::new(dim, std::vec![0.0; storage]).unwrap();
            if inline && storage == inline_window_len(dim, false) {
                g = Gram::with_summation(dim, std::vec![0.0; storage], Summation::Plain).unwrap();
            } else if inline {
                g = Gram::with_summation(dim, std::vec![0.0; storage], Summation::Compensated)
                    .unwrap();
            }
            let mut snap = std::vec![0.0; packed_len(dim)];
            let mut win = HalfWindow::new(window).unwrap();
            let half = win.half() as usize;
            for (k, w) in rows.chunks_exact(dim).enumerate() {
                g.update(w).unwrap();
                if win.added() {
                    if inline {
                        rebase_gram(&mut g, None, half as u64).unwrap();
                    } else {
                        rebase_gram(&mut g, Some(&mut snap), half as u64).unwrap();
                    }
                }
                // vectors held: the newest half and whatever the current half has
                let seen = k + 1;
                let held = if seen < half {
                    seen
                } else {
                    half + seen % half
                };
                assert_eq!(g.count() as usize, held, "window {window} at {seen}");
                assert!(held >= half.min(seen) && held < 2 * half);
                let mut fresh = Gram::<f64, _>::new(dim, std::vec![0.0; packed_len(dim)]).unwrap();
                for v in rows[(seen - held) * dim..seen * dim].chunks_exact(dim) {
                    fresh.update(v).unwrap();
                }
                for (a, b) in g.packed().iter().zip(fresh.packed()) {
                    assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} vs {b}");
                }
            }
        }
        let mut g = Gram::<f64, _>::new(2, std::vec![0.0; 3]).unwrap();
        g.set_forgetting(0.9).unwrap();
        assert!(rebase_gram(&mut g, Some(&mut [0.0; 3]), 1).is_err());
        assert!(rebase_gram(
            &mut Gram::<f64, _>::new(2, std::vec![0.0; 3]).unwrap(),
            None,
            1
        )
        .is_err());
        assert!(HalfWindow::new(1).is_err());
    }

    /// f32 over a long stream: the window's error stays that of N vectors (no drift from
    /// the rebases), measured against f64.
    #[test]
    fn rebased_window_does_not_drift_in_f32() {
        let dim = 3;
        let window = 200u64;
        let mut g = Gram::<f32, _>::with_summation(
            dim,
            std::vec![0.0f32; inline_window_len(dim, false)],
            Summation::Plain,
        )
        .unwrap();
        let mut win = HalfWindow::new(window).unwrap();
        let n = 200_000;
        let mut hist: std::vec::Vec<[f64; 3]> = std::vec::Vec::with_capacity(n);
        let mut worst: f64 = 0.0;
        let mut early: f64 = 0.0;
        for k in 0..n {
            let x = [
                1.0 + ((k as f64) * 0.37).sin(),
                ((k as f64) * 0.011).cos(),
                0.5,
            ];
            hist.push(x);
            g.update(&x.map(|v| v as f32)).unwrap();
            if win.added() {
                rebase_gram(&mut g, None, win.half()).unwrap();
                let held = g.count() as usize;
                let mut exact = [0.0f64; 6];
                for v in &hist[hist.len() - held..] {
                    let v32 = v.map(|a| a as f32 as f64);
                    let mut o = 0;
                    for i in 0..dim {
                        for j in i..dim {
                            exact[o] += v32[i] * v32[j];
                            o += 1;
                        }
                    }
                }
                // relative to sqrt(G_ii G_jj), the scale of the rounding of a sum of products
                let diag = [exact[0], exact[3], exact[5]];
                let mut o = 0;
                for i in 0..dim {
                    for j in i..dim {
                        let e =
                            (g.packed()[o] as f64 - exact[o]).abs() / (diag[i] * diag[j]).sqrt();
                        if k < n / 10 {
                            early = early.max(e);
                        }
                        worst = worst.max(e);
                        o += 1;
                    }
                }
            }
        }
        std::println!("window error: first tenth {early:e}, whole run {worst:e}");
        // 100 to 199 vectors summed in f32 (plain): well under 200 eps, and no growth after
        // 1 000 rebases beyond the spread of the first 100
        assert!(worst < 200.0 * f32::EPSILON as f64, "worst {worst:e}");
        assert!(worst < 2.0 * early, "early {early:e}, whole {worst:e}");
    }
}
