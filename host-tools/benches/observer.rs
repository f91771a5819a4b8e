//! Observer LMI benchmark (placeholder until observer.rs lands).
fn main() {}
