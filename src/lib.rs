//! # lpvid — the core
//!
//! Identification of Linear Parameter-Varying systems, the streaming part: `#![no_std]`,
//! no `alloc`, no panics on data (errors are values), generic over `f32`/`f64`.
//!
//! Where each idea lives (papers in `../shared/papers/`):
//! - [`window`]: regressor windows, z_k^p of the kernel paper (Definitions 5-6, eq. (12)).
//! - [`stats`]: second-moment statistics of problem (13), mergeable.
//! - [`kernel`]: the kernels of Theorem 10 and the row blocks of eq. (25), never forming Z.
//! - [`dictionary`]: streaming kernel dictionary (Algorithm 3 selection) and its projected normal equations.
//! - [`arx`]: LPV-ARX regressors phi(k) = chi(k) (x) pbasis(k) (BC-IV paper, eq. (6)).
//! - [`bciv`]: bias-corrected IV statistics, one matrix per power of sigma^2 (BC-IV paper, section 5).
//! - [`lasso`]: coordinate-descent Lasso on statistics, l1 (BC-IV cost (10)) and l2,1 (sparse paper (33)).
//! - [`protocol`]: the device-host wire frames (COBS, CRC-32, postcard messages), shared by both.
//! - [`device`]: the transport-agnostic device engine (bytes in, bytes out, owns the statistics).
//!
//! Storage is always caller-provided (`AsRef<[T]> + AsMut<[T]>`): arrays sized by `const`
//! functions on the device, `Vec`s on the host; one implementation, two ways to own it.
#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]

pub mod arx;
pub mod bciv;
pub mod device;
pub mod dictionary;
pub mod error;
pub mod kernel;
pub mod lasso;
pub mod protocol;
pub mod real;
pub mod stats;
pub mod window;

pub use error::{Error, Field};
pub use real::Real;
pub use stats::{packed_len, stat_vector_len, write_stat_vector, Gram, PbsidStats, StatsLayout};
pub use window::{regressor_len, window_storage_len, PbsidDims, Samples, Slab, Window};

/// The one streaming interface: feed a sample (u_k, y_k, p_k) to an accumulator. Returns
/// whether the sample completed a regressor that was accumulated. On error the state is
/// unchanged.
pub trait Streaming<T: Real> {
    /// Feed one sample.
    fn update(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<bool, Error>;
}

impl<T, SW, SG, SR> Streaming<T> for PbsidStats<T, SW, SG, SR>
where
    T: Real,
    SW: AsRef<[T]> + AsMut<[T]>,
    SG: AsRef<[T]> + AsMut<[T]>,
    SR: AsRef<[T]> + AsMut<[T]>,
{
    fn update(&mut self, u: &[T], y: &[T], p: &[T]) -> Result<bool, Error> {
        PbsidStats::update(self, u, y, p)
    }
}
