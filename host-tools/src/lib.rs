//! lpvid-host: the std companion of the `lpvid` core — files, fits, validation and the
//! `lpvid` command line. Every statistic comes from the core; this crate solves, realises,
//! simulates and reports.

pub mod lpvss;
pub mod metrics;
pub mod systems;
