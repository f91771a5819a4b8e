//! Theorem 10 of the kernel paper (`papers/lpv-pbsid-kernel-automatica2009.md`, section 5.2)
//! for every pair of windows at once: the batch form of `lpvid::kernel::theorem10` and of
//! `lpvid::kernel::shifted_kernel` (eq. (25)), organised so that the dual kernel
//! Z^T Z + U^T U of (19) and the shifted kernels of eq. (25) cost O(N^2 p) vectorised
//! multiply-adds. This is the host's one evaluation of both: [`crate::pbsid::dual_kernel_matrix`]
//! and [`crate::pbsid::dual_gamma_kz_matrix`] call it.
//!
//! Lemma 9 writes an entry as sums of products of the inner products mu_a^T mu_b and
//! z_a^T z_b. For a fixed window b those products are needed at samples b, ..., b+p-1 only,
//! so the sweep keeps a ring of p columns of the two sample Gram matrices (each computed
//! once, O(N (m + r + l))) and runs the backward recursion of Theorem 10 for all window
//! starts s together, contiguous in memory. The per-entry `theorem10` stays the definition
//! (the streaming dictionary uses it); a test checks the two agree.

use lpvid::{Samples, Slab};

/// Sweeps Theorem 10 over all window starts for one window b at a time.
pub struct KernelSweep {
    p: usize,
    n: usize,
    /// Component j of mu_k at mu[j * n + k] (feature-major, so a Gram column is a sum of
    /// m scaled rows).
    mu: Vec<f64>,
    /// Component j of z_k = [u_k; y_k] at z[j * n + k].
    z: Vec<f64>,
    /// Ring of p columns of the sample Gram matrices: slot c % p holds column c.
    gmu: Vec<Vec<f64>>,
    gz: Vec<Vec<f64>>,
    /// Columns held by the ring: [lo, hi).
    held: (usize, usize),
    prod: Vec<f64>,
    acc: Vec<f64>,
}

impl KernelSweep {
    /// Prepare the sweep over the samples of `slab` for past window `p`.
    pub fn new(slab: &Slab<'_, f64>, p: usize) -> Self {
        let n = slab.len();
        let m = if n > 0 { slab.mu(0).len() } else { 0 };
        let nz = if n > 0 { slab.z(0).len() } else { 0 };
        let mut mu = vec![0.0; n * m];
        let mut z = vec![0.0; n * nz];
        for k in 0..n {
            for (j, &v) in slab.mu(k).iter().enumerate() {
                mu[j * n + k] = v;
            }
            for (j, &v) in slab.z(k).iter().enumerate() {
                z[j * n + k] = v;
            }
        }
        KernelSweep {
            p,
            n,
            mu,
            z,
            gmu: vec![vec![0.0; n]; p.max(1)],
            gz: vec![vec![0.0; n]; p.max(1)],
            held: (0, 0),
            prod: Vec::new(),
            acc: Vec::new(),
        }
    }

    /// Column c of the sample Gram matrices into ring slot c % p.
    fn compute_column(&mut self, c: usize) {
        let slot = c % self.p;
        let n = self.n;
        for (feat, g) in [
            (&self.mu, &mut self.gmu[slot]),
            (&self.z, &mut self.gz[slot]),
        ] {
            g.fill(0.0);
            for row in feat.chunks_exact(n) {
                let w = row[c];
                for (gv, &x) in g.iter_mut().zip(row) {
                    *gv += x * w;
                }
            }
        }
    }

    /// Make columns b..b+p of the sample Gram matrices available.
    fn hold(&mut self, b: usize) {
        let want = (b, b + self.p);
        let (lo, hi) = self.held;
        let start = if lo <= b && b <= hi { hi } else { b };
        for c in start..want.1 {
            self.compute_column(c);
        }
        self.held = want;
    }

    /// Theorem 10 between the windows starting at s = s0, ..., s0 + len - 1 (s may be
    /// negative) and window `b` (kernel paper, Theorem 10 and eq. (25)): after the step for t
    /// (t = p-1 down to 0) `visit(t, ks)` sees ks[s - s0] = theorem10(slab, s, slab, b, t, p)
    /// = shifted_kernel(slab, s + t, slab, b, t + 1, p), the kernel of row block t + 1 of
    /// eq. (25) (t = 0: Z^T Z). Entries whose window reaches before sample 0 at step t
    /// (s + t < 0) are left undefined there; no row block uses them.
    ///
    /// Needs b + p <= number of samples.
    pub fn window(
        &mut self,
        b: usize,
        s0: isize,
        len: usize,
        mut visit: impl FnMut(usize, &[f64]),
    ) {
        let p = self.p;
        assert!(b + p <= self.n, "window {b} needs {p} samples");
        self.hold(b);
        self.prod.clear();
        self.prod.resize(len, 1.0);
        self.acc.clear();
        self.acc.resize(len, 0.0);
        let n = self.n as isize;
        for t in (0..p).rev() {
            let c = b + t;
            let slot = c % p;
            // indices with 0 <= s0 + idx + t < n
            let first = s0 + t as isize;
            let lo = (-first).clamp(0, len as isize) as usize;
            let hi = (n - first).clamp(lo as isize, len as isize) as usize;
            for v in &mut self.prod[..lo] {
                *v = 0.0;
            }
            if hi > lo {
                let row0 = (first + lo as isize) as usize;
                let g = &self.gmu[slot][row0..row0 + (hi - lo)];
                let h = &self.gz[slot][row0..row0 + (hi - lo)];
                for (((pr, ac), &gv), &hv) in self.prod[lo..hi]
                    .iter_mut()
                    .zip(self.acc[lo..hi].iter_mut())
                    .zip(g)
                    .zip(h)
                {
                    *pr *= gv;
                    *ac += *pr * hv;
                }
            }
            visit(t, &self.acc);
        }
    }
}

/// Dot product of two equal-length slices in four independent lanes, so it vectorises
/// (`lpvid::real::dot` sums in order, the device's bit-exact reference, and does not).
pub fn dot4(a: &[f64], b: &[f64]) -> f64 {
    let mut s = [0.0f64; 4];
    let (ca, ra) = a.split_at(a.len() / 4 * 4);
    let (cb, rb) = b.split_at(ca.len());
    for (x, y) in ca.chunks_exact(4).zip(cb.chunks_exact(4)) {
        for k in 0..4 {
            s[k] += x[k] * y[k];
        }
    }
    let tail: f64 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    (s[0] + s[1]) + (s[2] + s[3]) + tail
}

/// The four dot products of rows a0, a1 with rows b0, b1 (equal lengths), each summed
/// exactly as [`dot4`] sums it (the same bits), in one pass: each loaded value feeds two
/// products. Returns [a0.b0, a0.b1, a1.b0, a1.b1].
pub fn dot4_2x2(a0: &[f64], a1: &[f64], b0: &[f64], b1: &[f64]) -> [f64; 4] {
    let n = a0.len();
    let (a1, b0, b1) = (&a1[..n], &b0[..n], &b1[..n]);
    let (mut s0, mut s1, mut s2, mut s3) = ([0.0f64; 4], [0.0f64; 4], [0.0f64; 4], [0.0f64; 4]);
    let c = n / 4 * 4;
    for (((x0, x1), y0), y1) in a0[..c]
        .chunks_exact(4)
        .zip(a1[..c].chunks_exact(4))
        .zip(b0[..c].chunks_exact(4))
        .zip(b1[..c].chunks_exact(4))
    {
        for t in 0..4 {
            s0[t] += x0[t] * y0[t];
            s1[t] += x0[t] * y1[t];
            s2[t] += x1[t] * y0[t];
            s3[t] += x1[t] * y1[t];
        }
    }
    let s = [s0, s1, s2, s3];
    let mut out = [0.0; 4];
    for (e, (o, acc)) in out.iter_mut().zip(&s).enumerate() {
        let (x, y) = match e {
            0 => (a0, b0),
            1 => (a0, b1),
            2 => (a1, b0),
            _ => (a1, b1),
        };
        let tail: f64 = x[c..].iter().zip(&y[c..]).map(|(p, q)| p * q).sum();
        *o = (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail;
    }
    out
}

/// The Gram R R^T (d x d, column-major, full) of `d` row-major rows of length `len`, every
/// entry [`dot4`] of its two rows (the same bits), computed two rows by two rows.
pub fn row_gram(rows: &[f64], d: usize, len: usize) -> Vec<f64> {
    let row = |a: usize| &rows[a * len..(a + 1) * len];
    let mut g = vec![0.0; d * d];
    let mut put = |a: usize, b: usize, v: f64| {
        g[a * d + b] = v;
        g[b * d + a] = v;
    };
    let mut a = 0;
    while a < d {
        let a1 = (a + 1).min(d - 1);
        let mut b = a;
        while b < d {
            let b1 = (b + 1).min(d - 1);
            let [v00, v01, v10, v11] = dot4_2x2(row(a), row(a1), row(b), row(b1));
            put(a, b, v00);
            put(a, b1, v01);
            put(a1, b, v10);
            put(a1, b1, v11);
            b += 2;
        }
        a += 2;
    }
    g
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use lpvid::kernel::{shifted_kernel, theorem10};

    /// Samples [u (r), y (l), 1, p (m - 1)] of a small deterministic record (also the data of
    /// the eq. (25) test of [`crate::pbsid::dual`]).
    pub(crate) fn record(r: usize, l: usize, m: usize, n: usize) -> Vec<f64> {
        let w = r + l + m;
        (0..n * w)
            .map(|i| {
                let (k, j) = (i / w, i % w);
                if j == r + l {
                    1.0
                } else {
                    ((k * 13 + j * 7) % 17) as f64 / 8.0 - 1.0 + 0.1 * (k as f64 * 0.9).sin()
                }
            })
            .collect()
    }

    /// Every entry the sweep gives equals the core's per-entry functions: Theorem 10 with
    /// its shifted start, and eq. (25) by `shifted_kernel` (row block t + 1).
    #[test]
    fn sweep_equals_theorem10_and_shifted_kernel_entry_by_entry() {
        let (r, l, m, p) = (1, 2, 3, 4);
        let n = 23;
        let data = record(r, l, m, n);
        let slab = Slab::new(&data, r, l, m).unwrap();
        let mut sw = KernelSweep::new(&slab, p);
        let s0 = -(p as isize - 1);
        let len = n - p + p - 1;
        // visit windows out of order too, so the ring is rebuilt
        for b in [0usize, 1, 2, 7, 8, 3, n - p] {
            sw.window(b, s0, len, |t, ks| {
                for (idx, &k) in ks.iter().enumerate() {
                    let s = s0 + idx as isize;
                    if s + (t as isize) < 0 || s + p as isize > n as isize {
                        continue;
                    }
                    let e = theorem10(&slab, s, &slab, b, t, p);
                    assert!(
                        (e - k).abs() <= 1e-12 * (1.0 + e.abs()),
                        "{b} {s} {t}: {e} {k}"
                    );
                    let a = (s + t as isize) as usize;
                    let e25 = shifted_kernel(&slab, a, &slab, b, t + 1, p);
                    assert!(
                        (e25 - k).abs() <= 1e-12 * (1.0 + e25.abs()),
                        "eq. (25) {b} {a} {t}: {e25} {k}"
                    );
                }
            });
        }
    }

    /// The tiled Gram is dot4 entry by entry, to the bit (odd and even sizes and lengths).
    #[test]
    fn row_gram_is_dot4_to_the_bit() {
        for (d, len) in [(1, 3), (5, 70), (6, 9), (7, 71)] {
            let rows: Vec<f64> = (0..d * len)
                .map(|i| ((i * 37 % 101) as f64 * 0.13).sin())
                .collect();
            let g = row_gram(&rows, d, len);
            for a in 0..d {
                for b in 0..d {
                    let want = dot4(&rows[a * len..(a + 1) * len], &rows[b * len..(b + 1) * len]);
                    assert_eq!(g[a * d + b].to_bits(), want.to_bits(), "{d} {len} {a} {b}");
                }
            }
        }
    }

    #[test]
    fn dot4_matches_plain_sum() {
        let a: Vec<f64> = (0..11).map(|k| k as f64 * 0.5 - 2.0).collect();
        let b: Vec<f64> = (0..11).map(|k| (k as f64).sin()).collect();
        let e: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot4(&a, &b) - e).abs() < 1e-12);
    }
}
