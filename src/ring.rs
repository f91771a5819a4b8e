//! The one sample ring buffer of the core: the last `depth` samples of `width` values each,
//! in caller-provided storage, with one spare slot so the newest push can be undone. Both
//! regressor windows sit on it: [`crate::window::Window`] (the p + 1 samples of z_k^p, kernel
//! paper Definitions 5-6) and [`crate::arx::ArxWindow`] (the max(na, nb) + 1 samples of chi(k),
//! BC-IV paper section 3.3). No paper equation lives here.

use crate::error::Error;
use crate::real::Real;

/// Values a [`Ring`] of `depth` samples of `width` values needs: (depth + 1) width (one
/// spare slot). `const` for firmware arrays; 0 on overflow.
pub const fn ring_len(width: usize, depth: usize) -> usize {
    match (depth + 1).checked_mul(width) {
        Some(v) => v,
        None => 0,
    }
}

/// Ring buffer of the last `depth` samples (rows of `width` values) over storage `S`
/// (`[T; N]` on the device, `Vec<T>` on the host). Storage beyond the ring's
/// [`ring_len`] values is left to the owner ([`Ring::tail`]). The spare slot keeps the sample
/// that dropped out at the last push, which is what makes [`Ring::unpush`] exact.
#[derive(Debug, Clone)]
pub struct Ring<T, S> {
    buf: S,
    width: usize,
    depth: usize,
    /// Slot the next sample is written to.
    head: usize,
    /// Number of valid samples, at most `depth`.
    len: usize,
    _t: core::marker::PhantomData<T>,
}

impl<T: Real, S: AsRef<[T]> + AsMut<[T]>> Ring<T, S> {
    /// An empty ring of `depth` samples of `width` values over `buf`, which must hold at
    /// least [`ring_len`]`(width, depth)` values.
    pub fn new(width: usize, depth: usize, buf: S) -> Result<Self, Error> {
        let needed = depth
            .checked_add(1)
            .and_then(|s| s.checked_mul(width))
            .ok_or(Error::Overflow)?;
        if buf.as_ref().len() < needed {
            return Err(Error::Capacity {
                needed,
                capacity: buf.as_ref().len(),
            });
        }
        Ok(Ring {
            buf,
            width,
            depth,
            head: 0,
            len: 0,
            _t: core::marker::PhantomData,
        })
    }

    #[inline(always)]
    fn slots(&self) -> usize {
        self.depth + 1
    }

    /// Values per sample.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Samples held at most.
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// Append a sample written by `fill` into its row (`width` values; the row holds stale
    /// values, `fill` must write all of them). The oldest drops out once `depth` are held.
    /// The caller validates the sample first: a push cannot fail.
    pub fn push_with(&mut self, fill: impl FnOnce(&mut [T])) {
        let w = self.width;
        let off = self.head * w;
        fill(&mut self.buf.as_mut()[off..off + w]);
        self.head = (self.head + 1) % self.slots();
        if self.len < self.depth {
            self.len += 1;
        }
    }

    /// Undo the most recent push (the spare slot still holds the sample that dropped out).
    /// `was_len` is [`Ring::len`] before that push.
    pub fn unpush(&mut self, was_len: usize) {
        self.head = (self.head + self.slots() - 1) % self.slots();
        self.len = was_len;
    }

    /// Number of samples held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when no sample is held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// True once `depth` samples are held.
    pub fn is_full(&self) -> bool {
        self.len == self.depth
    }

    /// Forget all samples.
    pub fn clear(&mut self) {
        self.len = 0;
        self.head = 0;
    }

    #[inline(always)]
    fn slot_row(&self, slot: usize) -> core::ops::Range<usize> {
        slot * self.width..(slot + 1) * self.width
    }

    /// Row of sample `t` counted from the oldest held (t = 0); `t < len()`.
    #[inline(always)]
    pub fn oldest(&self, t: usize) -> &[T] {
        let slots = self.slots();
        let slot = (self.head + slots - self.len + t) % slots;
        &self.buf.as_ref()[self.slot_row(slot)]
    }

    #[inline(always)]
    fn newest_slot(&self, lag: usize) -> usize {
        let slots = self.slots();
        (self.head + 2 * slots - 1 - lag) % slots
    }

    /// Row of the sample `lag` steps before the newest (lag = 0: the newest); `lag < len()`.
    #[inline(always)]
    pub fn newest(&self, lag: usize) -> &[T] {
        &self.buf.as_ref()[self.slot_row(self.newest_slot(lag))]
    }

    /// Mutable row of the sample `lag` steps before the newest.
    #[inline(always)]
    pub fn newest_mut(&mut self, lag: usize) -> &mut [T] {
        let r = self.slot_row(self.newest_slot(lag));
        &mut self.buf.as_mut()[r]
    }

    /// The storage behind the ring (beyond [`ring_len`] values), the owner's scratch.
    pub fn tail(&self) -> &[T] {
        &self.buf.as_ref()[self.slots() * self.width..]
    }

    /// The newest-but-`lag` row and the mutable storage behind the ring, together.
    pub fn newest_and_tail_mut(&mut self, lag: usize) -> (&[T], &mut [T]) {
        let r = self.slot_row(self.newest_slot(lag));
        let ring = self.slots() * self.width;
        let (ring_part, tail) = self.buf.as_mut().split_at_mut(ring);
        (&ring_part[r], tail)
    }

    /// Slot the next sample goes to (tests compare states with it).
    #[cfg(test)]
    pub(crate) fn head(&self) -> usize {
        self.head
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn push_unpush_and_order() {
        let mut r = Ring::new(2, 3, [0.0f64; 8]).unwrap();
        assert!(Ring::<f64, _>::new(2, 3, [0.0f64; 7]).is_err());
        for k in 0..5 {
            let was = r.len();
            r.push_with(|row| row.copy_from_slice(&[k as f64, -(k as f64)]));
            assert_eq!(r.len(), (was + 1).min(3));
        }
        assert!(r.is_full());
        assert_eq!(r.oldest(0), &[2.0, -2.0]);
        assert_eq!(r.newest(0), &[4.0, -4.0]);
        assert_eq!(r.newest(2), r.oldest(0));
        r.unpush(3);
        assert_eq!(r.newest(0), &[3.0, -3.0]);
        assert_eq!(r.oldest(0), &[1.0, -1.0]);
        r.newest_mut(0)[1] = 9.0;
        assert_eq!(r.oldest(2), &[3.0, 9.0]);
        r.clear();
        assert!(r.is_empty());
        assert_eq!(ring_len(2, 3), 8);
    }
}
