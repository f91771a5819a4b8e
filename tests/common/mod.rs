//! Helpers shared by the core's integration tests (`mod common;` in a test file).

pub mod counting_alloc;
