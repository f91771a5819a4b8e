//! The system OpenBLAS, loaded on first use.
//!
//! clarabel's PSD cones (the H-infinity observer's LMI (30) of the sparse paper) call a
//! handful of BLAS/LAPACK routines through the `blas-sys`/`lapack-sys` declarations, which
//! name no provider. Linking `libopenblas` into the binary made every `lpvid` process pay for
//! it at start (symbol binding of the whole library, its thread pool spun up: about 1.8 ms of
//! the 3 ms CPU of `lpvid --version`, measured with `perf stat`), although only the observer
//! uses it. Here each routine clarabel links is defined as a forwarder that opens the library
//! on its first call (`libloading`), so a process that never solves an SDP never loads it, and
//! a machine without OpenBLAS still runs everything else. [`load`] is the checked entry: the
//! observer calls it before the solver and turns a missing library into an error value.

use std::os::raw::{c_char, c_int};
use std::sync::OnceLock;

/// Names tried, in order: Debian's runtime name (package `libopenblas0`), then the
/// development symlink.
const LIBRARY_NAMES: [&str; 2] = ["libopenblas.so.0", "libopenblas.so"];

/// Why the BLAS library is not available.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the system OpenBLAS could not be loaded ({0}); install it (Debian: libopenblas0)")]
pub struct BlasUnavailable(pub String);

/// The library, opened once per process (or the reason it could not be).
fn library() -> &'static Result<libloading::Library, BlasUnavailable> {
    static LIB: OnceLock<Result<libloading::Library, BlasUnavailable>> = OnceLock::new();
    LIB.get_or_init(|| {
        let mut reasons = Vec::new();
        for name in LIBRARY_NAMES {
            // SAFETY: OpenBLAS's initialisers only set up its own state (thread pool, CPU
            // dispatch); nothing of ours runs during the load.
            match unsafe { libloading::Library::new(name) } {
                Ok(lib) => {
                    single_thread(&lib);
                    return Ok(lib);
                }
                Err(e) => reasons.push(format!("{name}: {e}")),
            }
        }
        Err(BlasUnavailable(reasons.join("; ")))
    })
}

/// The SDP's blocks are at most 4n x 4n: BLAS threads only add synchronisation (measured on
/// the 2-core machine: the n = 4, 4-vertex solve took 26-29 ms with two OpenBLAS threads,
/// 11-16 ms with one). Use one thread unless the user set OPENBLAS_NUM_THREADS.
fn single_thread(lib: &libloading::Library) {
    if std::env::var_os("OPENBLAS_NUM_THREADS").is_some() {
        return;
    }
    // SAFETY: `openblas_set_num_threads(int)` is OpenBLAS's plain setter of its global thread
    // count; the signature is the library's. Absent in another BLAS: nothing to set.
    unsafe {
        if let Ok(set) = lib.get::<unsafe extern "C" fn(c_int)>(b"openblas_set_num_threads\0") {
            set(1);
        }
    }
}

/// Open the library now (first call) and say whether it is there. Call before any solver
/// that uses BLAS: the forwarders below cannot return an error through the Fortran API.
pub fn load() -> Result<(), BlasUnavailable> {
    library().as_ref().map(|_| ()).map_err(Clone::clone)
}

/// The address of `name` (NUL-terminated) in the loaded library.
///
/// # Panics
/// When the library or the symbol is missing: only reachable when a caller skipped [`load`]
/// (a panic in an `extern "C"` forwarder aborts the process with this message).
fn symbol<F: Copy>(name: &'static [u8]) -> F {
    let lib = match library() {
        Ok(lib) => lib,
        Err(e) => panic!("{e} (a BLAS routine was called without blas::load)"),
    };
    // SAFETY: F is the routine's C signature as declared by blas-sys/lapack-sys (the
    // forwarder's own signature); the library stays loaded for the whole process.
    match unsafe { lib.get::<F>(name) } {
        Ok(f) => *f,
        Err(e) => panic!("OpenBLAS has no {}: {e}", String::from_utf8_lossy(name)),
    }
}

/// Define each routine as a forwarder to the library's, resolved once.
macro_rules! forward {
    ($($(#[$doc:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?);)*) => {$(
        $(#[$doc])*
        ///
        /// # Safety
        /// The Fortran routine's contract: every pointer valid for what it describes.
        #[no_mangle]
        pub unsafe extern "C" fn $name($($arg: $ty),*) {
            type F = unsafe extern "C" fn($($ty),*);
            static ADDRESS: OnceLock<F> = OnceLock::new();
            let f = *ADDRESS.get_or_init(|| symbol::<F>(concat!(stringify!($name), "\0").as_bytes()));
            // SAFETY: forwarded unchanged to the routine of the same signature.
            unsafe { f($($arg),*) }
        }
    )*};
}

forward! {
    /// BLAS dgemm: C <- alpha op(A) op(B) + beta C.
    fn dgemm_(transa: *const c_char, transb: *const c_char, m: *const c_int, n: *const c_int,
        k: *const c_int, alpha: *const f64, a: *const f64, lda: *const c_int, b: *const f64,
        ldb: *const c_int, beta: *const f64, c: *mut f64, ldc: *const c_int);
    /// BLAS dsyrk: C <- alpha A A^T + beta C (one triangle).
    fn dsyrk_(uplo: *const c_char, trans: *const c_char, n: *const c_int, k: *const c_int,
        alpha: *const f64, a: *const f64, lda: *const c_int, beta: *const f64, c: *mut f64,
        ldc: *const c_int);
    /// BLAS dsyr2k: C <- alpha (A B^T + B A^T) + beta C (one triangle).
    fn dsyr2k_(uplo: *const c_char, trans: *const c_char, n: *const c_int, k: *const c_int,
        alpha: *const f64, a: *const f64, lda: *const c_int, b: *const f64, ldb: *const c_int,
        beta: *const f64, c: *mut f64, ldc: *const c_int);
    /// LAPACK dgesdd: SVD by divide and conquer.
    fn dgesdd_(jobz: *const c_char, m: *const c_int, n: *const c_int, a: *mut f64,
        lda: *const c_int, s: *mut f64, u: *mut f64, ldu: *const c_int, vt: *mut f64,
        ldvt: *const c_int, work: *mut f64, lwork: *const c_int, iwork: *mut c_int,
        info: *mut c_int);
    /// LAPACK dgesvd: SVD by QR iteration.
    fn dgesvd_(jobu: *const c_char, jobvt: *const c_char, m: *const c_int, n: *const c_int,
        a: *mut f64, lda: *const c_int, s: *mut f64, u: *mut f64, ldu: *const c_int,
        vt: *mut f64, ldvt: *const c_int, work: *mut f64, lwork: *const c_int,
        info: *mut c_int);
    /// LAPACK dpotrf: Cholesky factor.
    fn dpotrf_(uplo: *const c_char, n: *const c_int, a: *mut f64, lda: *const c_int,
        info: *mut c_int);
    /// LAPACK dpotrs: solve with a Cholesky factor.
    fn dpotrs_(uplo: *const c_char, n: *const c_int, nrhs: *const c_int, a: *const f64,
        lda: *const c_int, b: *mut f64, ldb: *const c_int, info: *mut c_int);
    /// LAPACK dsyevr: symmetric eigenvalues (the PSD cone's projection).
    fn dsyevr_(jobz: *const c_char, range: *const c_char, uplo: *const c_char,
        n: *const c_int, a: *mut f64, lda: *const c_int, vl: *const f64, vu: *const f64,
        il: *const c_int, iu: *const c_int, abstol: *const f64, m: *mut c_int, w: *mut f64,
        z: *mut f64, ldz: *const c_int, isuppz: *mut c_int, work: *mut f64,
        lwork: *const c_int, iwork: *mut c_int, liwork: *const c_int, info: *mut c_int);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loads_and_forwards_a_product() {
        load().expect("libopenblas is installed by make setup");
        // [1 2; 3 4] (column-major) times [5; 6] through dgemm: [17; 39]
        let a = [1.0, 3.0, 2.0, 4.0];
        let b = [5.0, 6.0];
        let mut c = [0.0; 2];
        let (m, n, k, one, zero) = (2, 1, 2, 1.0, 0.0);
        // SAFETY: column-major arrays of the stated sizes and leading dimensions.
        unsafe {
            dgemm_(
                c"N".as_ptr(),
                c"N".as_ptr(),
                &m,
                &n,
                &k,
                &one,
                a.as_ptr(),
                &m,
                b.as_ptr(),
                &k,
                &zero,
                c.as_mut_ptr(),
                &m,
            )
        };
        assert_eq!(c, [17.0, 39.0]);
    }
}
