//! # lpvid — the core
//!
//! Identification of Linear Parameter-Varying systems, the streaming part: `#![no_std]`,
//! no `alloc`, no panics on data (errors are values), generic over `f32`/`f64`.
//!
//! Where each idea lives (papers in `../shared/papers/`; "kernel paper" is
//! lpv-pbsid-kernel-automatica2009, "sparse paper" lpv-pbsid-sparse-bpdn-hinf-observer,
//! "BC-IV paper" lpv-bias-corrected-iv-lasso):
//! - [`streaming`]: the one [`Streaming`] trait (one sample, a block) and [`Merge`].
//! - [`ring`]: the one sample ring buffer under both regressor windows.
//! - [`window`]: regressor windows, z_k^p of the kernel paper (Definitions 5-6, eq. (12)).
//! - [`stats`]: second-moment statistics of problem (13) of the kernel paper, mergeable.
//! - [`kernel`]: Theorem 10 and the row-block kernels of eq. (25) of the kernel paper, never forming Z.
//! - [`dictionary`]: streaming kernel dictionary (kernel paper Algorithm 3) and its projected normal equations.
//! - [`arx`]: LPV-ARX regressors phi(k) = chi(k) (x) pbasis(k) (BC-IV paper, eq. (6)).
//! - [`bciv`]: bias-corrected IV statistics, one matrix per power of sigma^2 (BC-IV paper, section 5).
//! - [`lasso`]: coordinate-descent Lasso on statistics, l1 (BC-IV cost (10)) and l2,1 (sparse paper (33)).
//! - [`model`]: the `[A|B|K|C|D]` value layout of an LPV state-space model and its one-step
//!   predictor (kernel paper eq. (1)-(2), innovation form), shared by the device and the host.
//! - `protocol` (feature `device`): the device-host wire frames (COBS, CRC-32, postcard
//!   messages), shared by both; written down in `docs/wire.md`.
//! - `device` (feature `device`): the transport-agnostic device engine (bytes in, bytes
//!   out, owns the statistics).
//!
//! Cargo feature `device` (default on) adds serde + postcard and the two wire modules;
//! `default-features = false` gives the statistics with nalgebra + libm only.
//!
//! Storage is always caller-provided (`AsRef<[T]> + AsMut<[T]>`): arrays sized by `const`
//! functions on the device, `Vec`s on the host; one implementation, two ways to own it.
#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]

pub mod arx;
pub mod bciv;
#[cfg(feature = "device")]
pub mod device;
pub mod dictionary;
pub mod error;
pub mod kernel;
pub mod lasso;
pub mod model;
#[cfg(feature = "device")]
pub mod protocol;
pub mod real;
pub mod ring;
pub mod sliding;
pub mod stats;
pub mod streaming;
pub mod window;

pub use error::{Error, Field};
pub use model::{ModelDims, ModelView};
pub use real::Real;
pub use sliding::SlidingGram;
pub use stats::{
    gram_storage_len, packed_len, stat_vector_len, write_stat_vector, Gram, PbsidStats,
    StatsLayout, Summation,
};
pub use streaming::{Merge, Streaming};
pub use window::{regressor_len, window_storage_len, PbsidDims, Samples, Slab, Window};
