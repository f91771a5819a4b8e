//! Errors of the core, as values: the core never panics on data (DESIGN.md section 3;
//! no paper equation lives here).

use core::fmt;

/// Which part of a sample or statistic an error refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Field {
    /// Input vector u.
    Input,
    /// Output vector y.
    Output,
    /// Scheduling signals p (without the implicit leading 1 of mu).
    Scheduling,
    /// A regressor or statistic vector built from the above.
    Regressor,
    /// Storage handed to a constructor.
    Storage,
}

impl fmt::Display for Field {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Field::Input => "input u",
            Field::Output => "output y",
            Field::Scheduling => "scheduling p",
            Field::Regressor => "regressor",
            Field::Storage => "storage",
        })
    }
}

/// Everything that can go wrong in the core. Every fallible operation leaves its
/// state exactly as it was before the call when it returns an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Error {
    /// A NaN or infinity at `index` of `field`.
    NonFinite {
        /// Which vector.
        field: Field,
        /// Position in that vector.
        index: usize,
    },
    /// A vector of the wrong length.
    Dimension {
        /// Which vector.
        field: Field,
        /// Length required.
        expected: usize,
        /// Length given.
        got: usize,
    },
    /// Storage too small for the configured dimensions.
    Capacity {
        /// Values required.
        needed: usize,
        /// Values available.
        capacity: usize,
    },
    /// The configured dimensions overflow `usize` (regressor grows as m^p).
    Overflow,
    /// Two statistics of different shapes cannot be merged.
    Mismatch,
    /// A configuration value outside its valid range (e.g. past window 0).
    InvalidConfig(&'static str),
    /// A linear system was singular or not positive definite.
    Singular,
    /// An iterative solver did not converge.
    NoConvergence,
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::NonFinite { field, index } => {
                write!(f, "non-finite value (NaN or inf) in {field} at index {index}")
            }
            Error::Dimension {
                field,
                expected,
                got,
            } => write!(f, "{field} has length {got}, expected {expected}"),
            Error::Capacity { needed, capacity } => write!(
                f,
                "storage holds {capacity} values but the dimensions need {needed}"
            ),
            Error::Overflow => f.write_str(
                "overflow: the dimensions (the regressor grows as m^p) or a product of values exceed the range",
            ),
            Error::Mismatch => f.write_str("statistics have different shapes"),
            Error::InvalidConfig(what) => write!(f, "invalid configuration: {what}"),
            Error::Singular => f.write_str("singular or indefinite matrix"),
            Error::NoConvergence => f.write_str("iteration did not converge"),
        }
    }
}

/// The core's errors are ordinary Rust errors (`core::error::Error`, stable since 1.81): a
/// host wraps them with `?` into its own error types (thiserror's `#[from]`/`#[source]`).
impl core::error::Error for Error {}

/// Check a vector's length and finiteness before it touches any state.
pub fn check_vec<T: crate::Real>(field: Field, v: &[T], expected: usize) -> Result<(), Error> {
    if v.len() != expected {
        return Err(Error::Dimension {
            field,
            expected,
            got: v.len(),
        });
    }
    match crate::real::first_non_finite(v) {
        Some(index) => Err(Error::NonFinite { field, index }),
        None => Ok(()),
    }
}
