//! Theorem 10 of the kernel paper against the definition: the N x N kernel matrix Z^T Z built
//! from the explicit regressors z_k^p of eq. (12) (what the `kernel` benchmark times) equals
//! the one evaluated without Z, to rounding, on B2 (s = 1) and B3 (r = l = 2).

#[path = "../benches/kernel/explicit.rs"]
mod explicit;

use lpvid::{PbsidDims, Slab};
use lpvid_host::systems;

fn check(name: &str, sig: &lpvid_host::lpvss::Signals, p: usize, q_expected: usize) {
    let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
    let dims = PbsidDims::new(r, l, s, p).unwrap();
    assert_eq!(dims.q().unwrap(), q_expected, "{name} p={p}");
    let rows = explicit::slab_rows(sig);
    let slab = Slab::new(&rows, r, l, s + 1).unwrap();
    let nb = sig.len() - p;
    let (k10, kz) = explicit::both(&dims, &slab, nb);
    assert_eq!((k10.nrows(), k10.ncols()), (nb, nb));
    let d = explicit::rel_diff(&k10, &kz);
    assert!(d < 1e-13, "{name} p={p}: relative difference {d:e}");
    // symmetric, positive diagonal, and not a trivial matrix
    for a in 0..nb {
        assert!(k10[(a, a)] > 0.0);
        for b in 0..nb {
            assert_eq!(k10[(a, b)], k10[(b, a)]);
        }
    }
    // one entry against the plain definition sum_i z_0[i] z_1[i]
    let q = q_expected;
    let mut z0 = vec![0.0; q];
    let mut z1 = vec![0.0; q];
    lpvid::window::write_pbsid_regressor(&dims, &slab, 0, &mut z0);
    lpvid::window::write_pbsid_regressor(&dims, &slab, 1, &mut z1);
    let e: f64 = z0.iter().zip(&z1).map(|(a, b)| a * b).sum();
    assert!(
        (k10[(0, 1)] - e).abs() <= 1e-12 * e.abs().max(1.0),
        "{e} {}",
        k10[(0, 1)]
    );
}

#[test]
fn theorem10_equals_explicit_z_on_b2() {
    let exp = systems::b2(75, 25.0, 1);
    // q = (r + l) sum_{j=1}^p m^j with r = l = 1, m = 2
    for (p, q) in [(3, 28), (5, 124), (8, 1020)] {
        check("B2", &exp.train, p, q);
    }
}

#[test]
fn theorem10_equals_explicit_z_on_b3() {
    let exp = systems::b3(250, 1);
    // r = l = 2, m = 2
    for (p, q) in [(3, 56), (6, 504)] {
        check("B3", &exp.train, p, q);
    }
}
