//! Link the system OpenBLAS (Debian `libopenblas-dev`): clarabel's SDP support names the
//! `blas-src` / `lapack-src` crates without a provider; the provider is this link line.
//! Nothing is downloaded or compiled here.
fn main() {
    println!("cargo:rustc-link-lib=dylib=openblas");
    println!("cargo:rerun-if-changed=build.rs");
}
