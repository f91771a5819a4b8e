//! Kernel construction (issue 3): the N x N kernel matrix Z^T Z of the dual problem (19) by
//! Theorem 10 of the kernel paper (products of mu and z inner products, never forming Z)
//! against forming Z of eq. (12) explicitly (q x N, column k = z_k^p) and multiplying it
//! with faer's blocked SIMD product (lower triangle only, like a BLAS syrk), in the same run,
//! at p = 8, 10, 12, 14 on B2 (N = 75, s = 1, q up to 65 532) and B3 (N = 250, r = l = 2,
//! q up to 131 064; Z then takes 247 MB). Both single-threaded. The two matrices agree to
//! rounding (checked here before timing, and by `tests/kernel_explicit.rs`).
//!
//! Group `kernel_sweep_threads` (issue 16, both cores): the two sweeps a kernel-form fit runs
//! (the kernel matrix of (19) and Gamma K Z of eq. (25), `pbsid::dual_kernel_matrix_with` /
//! `dual_gamma_kz_matrix_with`) on one thread against two, in the same run, on B2 N = 75
//! p = 5, B3 N = 250 p = 8 and B1 N = 1000 p = 5; it sets `pbsid::SWEEP_SPLIT_MIN_WORK`.
//!
//! Group `sweep_after_reduction` (issue 16, whole process): the sweep of eq. (25) on two
//! threads as a B1 p = 5 fit runs it, right after the tridiagonal reduction of the 995 x 995
//! kernel on faer's pool (untimed), with the second half on a scoped thread of its own
//! (before) against both halves on that pool (now), in the same run.
//!
//! `cargo bench -p lpvid-host --bench kernel -- --warm-up-time 1 --measurement-time 3`

#[path = "kernel/explicit.rs"]
mod explicit;

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use faer::Par;
use lpvid::{PbsidDims, Slab};
use lpvid_host::systems;

fn kernel_construction(c: &mut Criterion) {
    let cases = [
        ("B2", systems::b2(75, 25.0, 1).train),
        ("B3", systems::b3(250, 1).train),
    ];
    for (name, sig) in &cases {
        let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
        let rows = explicit::slab_rows(sig);
        let slab = Slab::new(&rows, r, l, s + 1).unwrap();
        let mut group = c.benchmark_group(format!("kernel_{name}"));
        group.sample_size(10);
        for p in [8usize, 10, 12, 14] {
            let dims = PbsidDims::new(r, l, s, p).unwrap();
            let q = dims.q().unwrap();
            let nb = sig.len() - p;
            eprintln!(
                "{name} p={p}: N = {nb} windows, q = {q}, Z = {:.1} MB",
                (q * nb * 8) as f64 / 1e6
            );
            // same matrix both ways (to rounding) before anything is timed
            let (k10, kz) = explicit::both(&dims, &slab, nb);
            let d = explicit::rel_diff(&k10, &kz);
            assert!(d < 1e-12, "{name} p={p}: relative difference {d:e}");
            eprintln!("{name} p={p}: max relative difference {d:.1e}");
            let mut z = vec![0.0f64; q * nb];
            explicit::form_z(&dims, &slab, nb, &mut z);
            let id = format!("{name} p={p}");
            group.bench_function(BenchmarkId::new("theorem 10", &id), |b| {
                b.iter(|| black_box(explicit::by_theorem10(&dims, &slab, nb)))
            });
            group.bench_function(BenchmarkId::new("explicit Z, Z^T Z", &id), |b| {
                b.iter(|| {
                    explicit::form_z(&dims, &slab, nb, &mut z);
                    black_box(explicit::gram_of_z(&z, q, nb, Par::Seq))
                })
            });
            group.bench_function(BenchmarkId::new("Z^T Z alone (Z given)", &id), |b| {
                b.iter(|| black_box(explicit::gram_of_z(&z, q, nb, Par::Seq)))
            });
        }
        group.finish();
    }
}

fn sweep_threads(c: &mut Criterion) {
    let cases = [
        ("B2 N=75 p=5", systems::b2(75, 25.0, 1).train, 5usize),
        ("B3 N=250 p=8", systems::b3(250, 1).train, 8),
        ("B1 N=1000 p=5", systems::b1(1000, 0.1, 1).train, 5),
    ];
    let mut group = c.benchmark_group("kernel_sweep_threads");
    group.sample_size(10);
    for (name, sig, p) in &cases {
        let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
        let rows = explicit::slab_rows(sig);
        let slab = Slab::new(&rows, r, l, s + 1).unwrap();
        let dims = PbsidDims::new(r, l, s, *p).unwrap();
        let nb = sig.len() - p;
        let alpha = nalgebra::DMatrix::from_fn(l, nb, |j, a| ((j * nb + a) as f64 * 0.37).cos());
        eprintln!(
            "{name}: kernel sweep work {:.2e}, Gamma K Z sweep work {:.2e} (split from {:.0e})",
            (nb * nb / 2 * p) as f64,
            ((nb + 1) * (nb + p) * p) as f64,
            lpvid_host::pbsid::SWEEP_SPLIT_MIN_WORK
        );
        for workers in [1usize, 2] {
            group.bench_function(
                BenchmarkId::new(format!("kernel matrix, {workers} thread(s)"), name),
                |b| {
                    b.iter(|| {
                        black_box(lpvid_host::pbsid::dual_kernel_matrix_with(
                            &slab, *p, nb, true, workers,
                        ))
                    })
                },
            );
            group.bench_function(
                BenchmarkId::new(format!("Gamma K Z, {workers} thread(s)"), name),
                |b| {
                    b.iter(|| {
                        black_box(lpvid_host::pbsid::dual_gamma_kz_matrix_with(
                            &dims,
                            *p,
                            &slab,
                            &alpha,
                            nb + 1,
                            workers,
                        ))
                    })
                },
            );
        }
    }
    group.finish();
}

fn sweep_after_reduction(c: &mut Criterion) {
    let sig = systems::b1(1000, 0.1, 1).train;
    let p = 5usize;
    let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
    let rows = explicit::slab_rows(&sig);
    let slab = Slab::new(&rows, r, l, s + 1).unwrap();
    let dims = PbsidDims::new(r, l, s, p).unwrap();
    let nb = sig.len() - p;
    let g = lpvid_host::pbsid::dual_kernel_matrix(&slab, p, nb, true);
    let alpha = nalgebra::DMatrix::from_fn(l, nb, |j, a| ((j * nb + a) as f64 * 0.37).cos());
    type Sweep = fn(
        &PbsidDims,
        usize,
        &Slab<'_, f64>,
        &nalgebra::DMatrix<f64>,
        usize,
        usize,
    ) -> nalgebra::DMatrix<f64>;
    let cases: [(&str, Sweep); 2] = [
        (
            "Gamma K Z, scoped second thread (before)",
            lpvid_host::pbsid::dual::dual_gamma_kz_matrix_scoped,
        ),
        (
            "Gamma K Z, both halves on the pool (now)",
            lpvid_host::pbsid::dual_gamma_kz_matrix_with,
        ),
    ];
    assert_eq!(
        cases[0].1(&dims, p, &slab, &alpha, nb + 1, 2),
        cases[1].1(&dims, p, &slab, &alpha, nb + 1, 2)
    );
    let mut group = c.benchmark_group("sweep_after_reduction");
    group.sample_size(10);
    for (name, sweep) in cases {
        group.bench_function(BenchmarkId::new(name, "B1 N=1000 p=5"), |b| {
            b.iter_custom(|iters| {
                let mut total = std::time::Duration::ZERO;
                for _ in 0..iters {
                    black_box(lpvid_host::linalg::Tridiagonal::new(&g).dim());
                    let t = std::time::Instant::now();
                    black_box(sweep(&dims, p, &slab, &alpha, nb + 1, 2));
                    total += t.elapsed();
                }
                total
            })
        });
    }
    group.finish();
}

criterion_group!(
    benches,
    kernel_construction,
    sweep_threads,
    sweep_after_reduction
);
criterion_main!(benches);
