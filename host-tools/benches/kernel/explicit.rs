//! The two ways of building the N x N kernel matrix Z^T Z of the dual problem (19), shared by
//! the `kernel` benchmark and its test (`host-tools/tests/kernel_explicit.rs`): Theorem 10
//! (never forming Z) and the explicit regressor matrix Z of eq. (12) times its transpose.

use faer::linalg::matmul::triangular::{matmul, BlockStructure};
use faer::{Accum, Mat, MatRef, Par};
use lpvid::kernel::theorem10;
use lpvid::window::write_pbsid_regressor;
use lpvid::{PbsidDims, Slab};
use lpvid_host::lpvss::Signals;

/// Rows [u_k, y_k, 1, p_k] of a data set, the slab layout of the core.
pub fn slab_rows(sig: &Signals) -> Vec<f64> {
    let mut rows =
        Vec::with_capacity(sig.len() * (sig.u.ncols() + sig.y.ncols() + sig.p.ncols() + 1));
    for k in 0..sig.len() {
        rows.extend(sig.u.row(k).iter());
        rows.extend(sig.y.row(k).iter());
        rows.push(1.0);
        rows.extend(sig.p.row(k).iter());
    }
    rows
}

/// Kernel matrix by Theorem 10: entry (a, b) = z_a^T z_b for the `nb` windows, the upper
/// triangle evaluated and mirrored, as the dual path of `pbsid` does.
pub fn by_theorem10(dims: &PbsidDims, slab: &Slab<'_, f64>, nb: usize) -> Mat<f64> {
    let mut g = Mat::<f64>::zeros(nb, nb);
    for a in 0..nb {
        for b in a..nb {
            let v = theorem10(slab, a as isize, slab, b, 0, dims.p);
            g[(a, b)] = v;
            g[(b, a)] = v;
        }
    }
    g
}

/// Z (q x nb, column k = z_k^p of eq. (12)) written into `z` (length q nb, column-major).
pub fn form_z(dims: &PbsidDims, slab: &Slab<'_, f64>, nb: usize, z: &mut [f64]) {
    let q = dims.q().expect("q fits in usize");
    assert_eq!(z.len(), q * nb);
    for (k, col) in z.chunks_exact_mut(q).enumerate() {
        write_pbsid_regressor(dims, slab, k, col);
    }
}

/// Z^T Z from an explicit Z (q x nb, column-major) by faer's blocked SIMD product: the lower
/// triangle only (half the flops, like the symmetric rank-k update of BLAS), then mirrored.
/// `par` chooses the threads (the benchmark uses one, as Theorem 10 does).
pub fn gram_of_z(z: &[f64], q: usize, nb: usize, par: Par) -> Mat<f64> {
    let zm = MatRef::from_column_major_slice(z, q, nb);
    let mut g = Mat::<f64>::zeros(nb, nb);
    matmul(
        g.as_mut(),
        BlockStructure::TriangularLower,
        Accum::Replace,
        zm.transpose(),
        BlockStructure::Rectangular,
        zm,
        BlockStructure::Rectangular,
        1.0,
        par,
    );
    for a in 0..nb {
        for b in a + 1..nb {
            g[(a, b)] = g[(b, a)];
        }
    }
    g
}

/// Both ways at once (for the test): (Theorem 10, explicit).
pub fn both(dims: &PbsidDims, slab: &Slab<'_, f64>, nb: usize) -> (Mat<f64>, Mat<f64>) {
    let q = dims.q().expect("q fits in usize");
    let mut z = vec![0.0; q * nb];
    form_z(dims, slab, nb, &mut z);
    (by_theorem10(dims, slab, nb), gram_of_z(&z, q, nb, Par::Seq))
}

/// Largest |K1 - K2| relative to the largest |K2| entry.
pub fn rel_diff(k1: &Mat<f64>, k2: &Mat<f64>) -> f64 {
    let mut num = 0.0f64;
    let mut den = 0.0f64;
    for j in 0..k1.ncols() {
        for i in 0..k1.nrows() {
            num = num.max((k1[(i, j)] - k2[(i, j)]).abs());
            den = den.max(k2[(i, j)].abs());
        }
    }
    num / den
}
