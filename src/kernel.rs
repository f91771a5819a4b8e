//! Kernels of the LPV-PBSID kernel method (kernel paper section 5.2), evaluated without
//! forming Z: Lemma 9 turns inner products of Kronecker products into products of inner
//! products, so every entry costs O(p (m + r + l)) instead of O(q).
//!
//! One function per result of the kernel paper:
//! - [`theorem10`]: Theorem 10 (kernels LPV), the one evaluation every kernel here calls.
//! - [`dual_kernel`]: the kernel matrix Z^T Z + U^T U of the dual problem (19).
//! - [`shifted_kernel`]: the row-block kernels sum_{j >= i} (Z^{i,j})^T Z^{1,j} of eq. (25)
//!   (kernel paper; "eq. (25)" of the sparse paper is the noise covariance, not this), from
//!   which Gamma^p K^p Z = [alpha kappa_1; ...; alpha kappa_f] is built
//!   ([`crate::dictionary::KernelDictionary::state_candidate`] on the device, the host's
//!   dual realization).

use crate::real::{dot, Real};
use crate::window::Samples;

/// Kernel paper, Theorem 10, generalised to the shifted windows of eq. (23)-(25):
///
/// sum_{t0 = t_start}^{p-1} ( prod_{t = t0}^{p-1} mu_{a+t}^T mu'_{b+t} ) z_{a+t0}^T z'_{b+t0}
///
/// where `a` indexes samples of `x` and `b` samples of `y` (the same sequence for a batch
/// kernel, a dictionary window and a new window when streaming). With `t_start = 0` this is
/// the entry (a, b) of Z^T Z; with `t_start = i - 1` and `a` shifted back by i - 1 it is
/// entry (a + i - 1, b) of sum_{j >= i} (Z^{i,j})^T Z^{1,j}, the kernel of row block i of
/// eq. (25). `a` may be negative as long as a + t_start >= 0.
#[inline]
pub fn theorem10<T: Real, X: Samples<T> + ?Sized, Y: Samples<T> + ?Sized>(
    x: &X,
    a: isize,
    y: &Y,
    b: usize,
    t_start: usize,
    p: usize,
) -> T {
    let mut acc = T::ZERO;
    let mut prod = T::ONE;
    for t in (t_start..p).rev() {
        let ta = (a + t as isize) as usize;
        prod *= dot(x.mu(ta), y.mu(b + t));
        acc += prod * dot(x.z(ta), y.z(b + t));
    }
    acc
}

/// Kernel paper, eq. (25): entry (a, b) of sum_{j=i}^{p} (Z^{i,j})^T Z^{1,j} (Z^{i,j} of
/// eq. (23)), the kernel of row block `i` (1-based, 1..=p) of Gamma^p K^p Z: row block i,
/// column b of eq. (25) is alpha times the vector of these entries over a. Column a of
/// Z^{i,j} is built from samples a..a+p-i of `x` and column b of Z^{1,j} from samples
/// b..b+p-1 of `y`; `a` indexes `x` as in [`theorem10`] (a dictionary window that starts at
/// its own sample 0 passes a = 0). Row block 1 is the plain Z^T Z entry. `i` = 0 is taken
/// as 1.
#[inline]
pub fn shifted_kernel<T: Real, X: Samples<T> + ?Sized, Y: Samples<T> + ?Sized>(
    x: &X,
    a: usize,
    y: &Y,
    b: usize,
    i: usize,
    p: usize,
) -> T {
    let shift = i.saturating_sub(1);
    theorem10(x, a as isize - shift as isize, y, b, shift, p)
}

/// Kernel entry (a, b) of the dual problem (19): [Z^T Z + U^T U]_{ab}, the U^T U term only
/// when the feedthrough D is estimated.
#[inline]
pub fn dual_kernel<T: Real, X: Samples<T> + ?Sized, Y: Samples<T> + ?Sized>(
    x: &X,
    a: usize,
    y: &Y,
    b: usize,
    p: usize,
    feedthrough: bool,
) -> T {
    let mut k = theorem10(x, a as isize, y, b, 0, p);
    if feedthrough {
        k += dot(x.u(a + p), y.u(b + p));
    }
    k
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::window::{write_pbsid_regressor, PbsidDims, Slab};

    #[test]
    fn theorem10_equals_explicit_inner_product() {
        let d = PbsidDims::new(1, 2, 2, 3).unwrap();
        let n = 12;
        let mut data = Vec::new();
        for k in 0..n {
            let f = k as f64;
            data.extend([
                (0.7 * f).sin(),
                (1.3 * f).cos(),
                0.2 * f - 1.0,
                1.0,
                (0.4 * f).sin(),
                0.1 * f,
            ]);
        }
        let slab = Slab::new(&data, 1, 2, 3).unwrap();
        let q = d.q().unwrap();
        let z = |k: usize| {
            let mut v = vec![0.0; q];
            write_pbsid_regressor(&d, &slab, k, &mut v);
            v
        };
        for a in 0..5 {
            for b in 0..5 {
                let e: f64 = z(a).iter().zip(z(b)).map(|(x, y)| x * y).sum();
                let k = theorem10(&slab, a as isize, &slab, b, 0, d.p);
                assert!((e - k).abs() < 1e-9 * (1.0 + e.abs()), "{a} {b} {e} {k}");
            }
        }
        // shifted kernel of eq. (25), row block i = 2: sum_{j >= i} (Z^{i,j})^T Z^{1,j}.
        let i = 2;
        for a in 1..5usize {
            for b in 0..5 {
                let zb = z(b);
                let mut e = 0.0;
                for j in i..=d.p {
                    // column a of Z^{i,j} (eq. 23), built from its definition:
                    // P_{p-j+1 | a+j-i} z_{a+j-i}, 0-based.
                    let mut col = slab.z(a + j - i).to_vec();
                    for t in 0..=(d.p - j) {
                        let mu = slab.mu(a + j - i + t);
                        let mut v = Vec::new();
                        for m in mu {
                            for c in &col {
                                v.push(m * c);
                            }
                        }
                        col = v;
                    }
                    let off = d.block_offset(j);
                    let len = d.block_len(j);
                    e += col
                        .iter()
                        .zip(&zb[off..off + len])
                        .map(|(x, y)| x * y)
                        .sum::<f64>();
                }
                let k = theorem10(&slab, a as isize - (i as isize - 1), &slab, b, i - 1, d.p);
                assert!((e - k).abs() < 1e-9 * (1.0 + e.abs()), "{a} {b} {e} {k}");
                assert_eq!(shifted_kernel(&slab, a, &slab, b, i, d.p), k);
            }
        }
    }
}
