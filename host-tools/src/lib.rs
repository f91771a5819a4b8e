//! lpvid-host: the std companion of the `lpvid` core — files, fits, validation and the
//! `lpvid` command line. Every statistic comes from the core; this crate solves, realises,
//! simulates and reports.
//!
//! Where each idea lives: [`data`] (CSV), [`model`] (model JSON, signal factors),
//! [`lpvss`] (the state-space model, simulation, predictor), [`simulate`] (any model on a
//! data file), [`metrics`] (VAF, BFR), [`linalg`] (eigen, least squares), [`pbsid`]
//! (LPV-PBSID_opt, kernel paper Algorithms 1-2), [`arx`] (LPV-ARX: LS, refined IV, BC-IV,
//! BC-IV-LASSO), [`bpdn`] (sparse estimation, section 4.2 of
//! the sparse paper), [`systems`] (benchmark generators),
//! [`link`] (the device link over a serial port),
//! [`diagnose`] (residual tests, missing effects, the fix),
//! [`pipeline`] (settings + data -> the identified model every front end gets), [`record`]
//! (the model file's `fit` record), [`error`] (the typed errors).
//!
//! Layers: the core `lpvid` <- this library (no argument parsing, no printing) <- the front
//! ends: the `lpvid` command line (the `cli` module, compiled only with the `cli` feature,
//! never imported by the library), the device link's host side, the Python package.

pub mod arx;
pub mod blas;
pub use pbsid::bpdn;
#[cfg(feature = "cli")]
pub mod cli;
pub mod data;
pub mod diagnose;
pub mod error;
pub mod kernel_sweep;
pub mod linalg;
pub mod link;
pub mod lpvss;
pub mod metrics;
pub mod model;
pub mod observer;
pub mod pbsid;
pub mod pipeline;
pub mod record;
pub mod refine;
pub mod sensitivity;
pub mod significance;
pub mod simulate;
pub mod statistics;
pub mod stream;
pub mod systems;

pub use error::Error;
