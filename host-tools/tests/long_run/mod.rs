//! The long f32 accumulation run shared by the `f32_long_run` test (10^8 samples) and the
//! `f32_long_run` example (10^9): a B2-like plant (r = l = s = 1, n = 2) simulated sample by
//! sample in f64, rounded to f32, fed to the core's f32 statistics (compensated, what the
//! device runs), to plain-summed f32 statistics (for contrast) and to compensated f64
//! statistics of the same f32 samples (the reference).

use lpvid::window::{window_storage_len, PbsidDims};
use lpvid::{gram_storage_len, packed_len, stat_vector_len, PbsidStats, StatsLayout};
use lpvid_host::lpvss::Signals;
use lpvid_host::metrics::vaf;
use lpvid_host::pbsid::{fit_from_stats, Order, PbsidOptions};
use lpvid_host::systems::b2_truth;
use nalgebra::DMatrix;

type St<T> = PbsidStats<T, Vec<T>, Vec<T>, Vec<T>>;

/// Past window of the run.
pub const P: usize = 2;

/// What a run measured.
#[derive(Debug)]
pub struct LongRun {
    /// Samples streamed.
    pub samples: u64,
    /// Largest |f32 - ref| / |ref| over the entries with |ref| >= 1e-3 sqrt(ref_ii ref_jj).
    pub rel_compensated: f64,
    /// Largest |f32 - ref| / sqrt(ref_ii ref_jj) over all entries.
    pub normed_compensated: f64,
    /// The same two for plain f32 summation.
    pub rel_plain: f64,
    /// See `normed_compensated`.
    pub normed_plain: f64,
    /// Free-run VAF (%) on a noise-free validation record: model from the f64 reference,
    /// from the compensated f32 statistics, from the plain f32 statistics.
    pub vaf_f64: f64,
    /// See `vaf_f64`.
    pub vaf_f32: f64,
    /// See `vaf_f64`; the error when no model can be fitted at all (at 10^8 samples the
    /// plain sums make the scheduling look constant).
    pub vaf_plain: Result<f64, String>,
}

/// xorshift64*: a fast deterministic uniform stream in [0, 1).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Zero mean, unit variance (uniform on +-sqrt 3).
    fn unit(&mut self) -> f64 {
        (2.0 * self.next() - 1.0) * 3f64.sqrt()
    }
}

fn stats<T: lpvid::Real>(dims: PbsidDims, gram: usize) -> St<T> {
    let len = stat_vector_len(&dims, StatsLayout::Extended).unwrap();
    PbsidStats::with_storage(
        dims,
        StatsLayout::Extended,
        vec![T::ZERO; window_storage_len(1, 1, 1, P)],
        vec![T::ZERO; gram],
        vec![T::ZERO; len],
    )
    .unwrap()
}

/// B2's scheduling mu2_k = cos(2 pi k / 10) + 0.2.
fn sched(k: u64) -> f64 {
    (2.0 * std::f64::consts::PI * (k % 10) as f64 / 10.0).cos() + 0.2
}

/// Visit the `n` samples (u, y, p) of the B2 plant with process and measurement noise (seed
/// `seed`), simulated in f64 and rounded to f32: the same stream on every call.
fn samples(n: u64, seed: u64, mut visit: impl FnMut(f32, f32, f32)) {
    let t = b2_truth();
    let (a0, a1, b0) = (&t.a[0], &t.a[1], &t.b[0]);
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
    let mut x = [0.0f64; 2];
    let (sw, sv) = (0.02, 0.1);
    for k in 0..n {
        let mu = sched(k);
        let u = rng.unit();
        let y = x[0] + sv * rng.unit();
        visit(u as f32, y as f32, mu as f32);
        let a = |i: usize, j: usize| a0[(i, j)] + mu * a1[(i, j)];
        let x0 = a(0, 0) * x[0] + a(0, 1) * x[1] + b0[(0, 0)] * u + sw * rng.unit();
        let x1 = a(1, 0) * x[0] + a(1, 1) * x[1] + b0[(1, 0)] * u + sw * rng.unit();
        x = [x0, x1];
    }
}

/// Stream `n` samples of the B2 plant (seed `seed`) into the three statistics: the f64
/// reference on one thread, the two f32 sums on another (the stream is regenerated on each,
/// so the two cores of a test machine halve the wall time).
pub fn run(n: u64, seed: u64) -> LongRun {
    let dims = PbsidDims::new(1, 1, 1, P).unwrap();
    let len = stat_vector_len(&dims, StatsLayout::Extended).unwrap();
    let ((s32, plain), s64) = std::thread::scope(|scope| {
        let reference = scope.spawn(|| {
            let mut s64 = stats::<f64>(dims, gram_storage_len(len));
            samples(n, seed, |u, y, p| {
                s64.update(&[u as f64], &[y as f64], &[p as f64]).unwrap();
            });
            s64
        });
        let mut s32 = stats::<f32>(dims, gram_storage_len(len));
        let mut plain = stats::<f32>(dims, packed_len(len));
        samples(n, seed, |u, y, p| {
            s32.update(&[u], &[y], &[p]).unwrap();
            plain.update(&[u], &[y], &[p]).unwrap();
        });
        ((s32, plain), reference.join().unwrap())
    });
    let t = b2_truth();
    let reference = s64.gram();
    let err = |g: &St<f32>| {
        let (mut rel, mut normed) = (0.0f64, 0.0f64);
        for i in 0..len {
            for j in i..len {
                let r = reference.get(i, j);
                let scale = (reference.get(i, i) * reference.get(j, j)).sqrt();
                let e = (g.gram().get(i, j) as f64 - r).abs();
                normed = normed.max(e / scale);
                if r.abs() >= 1e-3 * scale {
                    rel = rel.max(e / r.abs());
                }
            }
        }
        (rel, normed)
    };
    let (rel_compensated, normed_compensated) = err(&s32);
    let (rel_plain, normed_plain) = err(&plain);
    // validation: noise-free, fresh input
    let nv = 2000;
    let mut vr = Rng(seed ^ 0x5151);
    let mut val = Signals {
        u: DMatrix::from_fn(nv, 1, |_, _| vr.unit()),
        y: DMatrix::zeros(nv, 1),
        p: DMatrix::from_fn(nv, 1, |k, _| sched(k as u64)),
    };
    val.y = t.simulate(&val, None);
    let mut o = PbsidOptions::new(P);
    o.order = Order::Fixed(2);
    let score = |packed: Vec<f64>, count: u64| {
        let mut g = lpvid::Gram::new(len, vec![0.0; packed_len(len)]).unwrap();
        g.load(&packed, count).unwrap();
        let fit = fit_from_stats(&g, &dims, &o).map_err(|e| e.to_string())?;
        let yhat = fit.model.simulate(&val, None);
        Ok::<f64, String>(vaf(val.y.as_slice(), yhat.as_slice()))
    };
    let to64 = |g: &St<f32>| g.gram().packed().iter().map(|v| *v as f64).collect();
    LongRun {
        samples: n,
        rel_compensated,
        normed_compensated,
        rel_plain,
        normed_plain,
        vaf_f64: score(reference.packed().to_vec(), reference.count()).unwrap(),
        vaf_f32: score(to64(&s32), s32.gram().count()).unwrap(),
        vaf_plain: score(to64(&plain), plain.gram().count()),
    }
}
