//! The one streaming interface of the core ([`Streaming`]) and the merge of accumulators
//! ([`Merge`]) (DESIGN.md section 3; the statistics they stream are those of the kernel paper
//! problem (13) and the BC-IV paper section 5, see each implementor).
//!
//! Every accumulator of the core implements [`Streaming`]: one sample in
//! ([`Streaming::update`]), or a block of samples ([`Streaming::update_block`], a default
//! method that loops over the samples; [`Gram`] overrides it with its register-blocked batch
//! update). Samples differ in shape, so each implementor names its own
//! [`Streaming::Sample`] and [`Streaming::Output`]:
//!
//! | implementor | `Sample<'a>` | block row | `Output` |
//! |---|---|---|---|
//! | [`PbsidStats`] | `(u, y, p)`: `(&[T], &[T], &[T])` | `[u (r), y (l), p (s)]` | `bool`: a vector was accumulated |
//! | [`KernelDictionary`] | `(u, y, p)` | `[u, y, p]` | [`Step`] |
//! | [`ArxWindow`] | `(u, y, p)`: `(&[T], T, &[T])` | `[u (r), y, p (s)]` | `()` |
//! | [`BcivStats`] | `(zeta, u, y, p)`: `(&[T], &[T], T, &[T])` | `[zeta (nzeta), u, y, p]` | `bool` |
//! | [`Gram`] | the vector w: `&[T]` | `w (dim)` | `()` |
//!
//! A block is row-major: [`Streaming::row_len`] values per sample, in the order of the table
//! (for the statistics this is the sample layout of the wire, `docs/wire.md`). The inherent
//! methods (`PbsidStats::update(u, y, p)`, `ArxWindow::push`, `BcivStats::update`,
//! `Gram::update`, `Gram::update_batch`, `KernelDictionary::update`) are the same operations
//! with the sample unpacked; method-call syntax picks the inherent one, generic code the trait.
//!
//! [`Merge`] is implemented by the accumulators whose sum is the accumulator of the
//! concatenated data: [`Gram`], [`PbsidStats`], [`BcivStats`].
//!
//! [`PbsidStats`]: crate::stats::PbsidStats
//! [`Gram`]: crate::stats::Gram
//! [`KernelDictionary`]: crate::dictionary::KernelDictionary
//! [`Step`]: crate::dictionary::Step
//! [`ArxWindow`]: crate::arx::ArxWindow
//! [`BcivStats`]: crate::bciv::BcivStats

use crate::error::{Error, Field};
use crate::real::Real;

/// An accumulator fed one sample at a time: `update(&mut self, x) -> Result<y, Error>`.
///
/// Every update is atomic: a rejected sample (wrong length, NaN/inf, overflow) returns an
/// error and leaves the state exactly as it was.
pub trait Streaming<T: Real> {
    /// One sample, borrowed from the caller (see the module table).
    type Sample<'a>;
    /// What one update reports.
    type Output;

    /// Feed one sample.
    fn update(&mut self, x: Self::Sample<'_>) -> Result<Self::Output, Error>;

    /// Values one sample takes in a block row (see the module table).
    fn row_len(&self) -> usize;

    /// One block row (`row_len()` values) as a sample.
    fn sample<'a>(&self, row: &'a [T]) -> Self::Sample<'a>;

    /// Feed the samples of `rows` (row-major, [`Streaming::row_len`] values each) in order.
    /// A length that is not a whole number of rows is rejected before anything changes.
    /// Otherwise it stops at the first rejected sample and returns its error: the samples
    /// before it stay applied (each update is atomic). An implementation may apply the whole
    /// block atomically instead ([`crate::Gram`] does: on error nothing changes).
    fn update_block(&mut self, rows: &[T]) -> Result<(), Error> {
        let w = check_block(rows.len(), self.row_len())?;
        for row in rows.chunks_exact(w) {
            let x = self.sample(row);
            self.update(x)?;
        }
        Ok(())
    }
}

/// Check that `len` values are a whole number of rows of `w` values (`w` > 0); returns `w`.
pub(crate) fn check_block(len: usize, w: usize) -> Result<usize, Error> {
    if w == 0 || len % w != 0 {
        return Err(Error::Dimension {
            field: Field::Regressor,
            expected: w,
            got: len,
        });
    }
    Ok(w)
}

/// Accumulators that add up: after `a.merge(&b)`, `a` equals the accumulator of a's data
/// followed by b's (how experiments, devices or cross-validation folds combine). Shapes must
/// agree ([`Error::Mismatch`] otherwise, and nothing changes).
pub trait Merge<Rhs: ?Sized = Self> {
    /// Add `other` into `self`.
    fn merge(&mut self, other: &Rhs) -> Result<(), Error>;
}
