//! Benchmarks of the spine (issue 2): the core's per-sample statistics update for B1 with
//! p = 3 and p = 5 in f32 and f64 (compared in the same run with the core's batched update
//! of the same statistics; the host's syrk path is in `benches/gram_syrk.rs`), and the full LPV-PBSID_opt fit on B1 (primal vs kernel form on
//! the same data; the MATLAB PBSID toolbox needs 0.25 s and 1.1 s for p = 3 and p = 5 on this
//! machine, see BENCHMARKS.md).

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid::{
    packed_len, stat_vector_len, window_storage_len, Gram, PbsidDims, PbsidStats, Real, Slab,
    StatsLayout,
};
use lpvid_host::pbsid::{fit, PbsidOptions, Reg, Solver};
use lpvid_host::systems;

fn rows<T: Real>(sig: &lpvid_host::lpvss::Signals) -> Vec<Vec<T>> {
    (0..sig.len())
        .map(|k| {
            let mut r: Vec<T> = sig.u.row(k).iter().map(|v| T::of(*v)).collect();
            r.extend(sig.y.row(k).iter().map(|v| T::of(*v)));
            r.extend(sig.p.row(k).iter().map(|v| T::of(*v)));
            r
        })
        .collect()
}

fn stats_update<T: Real>(c: &mut Criterion, name: &str) {
    let exp = systems::b1(1000, 0.05, 1);
    let data = rows::<T>(&exp.train);
    let mut group = c.benchmark_group(format!("stats_update_{name}"));
    for p in [3usize, 5] {
        group.sample_size(if p == 5 { 10 } else { 30 });
        let dims = PbsidDims::new(2, 3, 3, p).unwrap();
        let len = stat_vector_len(&dims, StatsLayout::Plain).unwrap();
        let mut st = PbsidStats::with_storage(
            dims,
            StatsLayout::Plain,
            vec![T::ZERO; window_storage_len(2, 3, 3, p)],
            vec![T::ZERO; packed_len(len)],
            vec![T::ZERO; len],
        )
        .unwrap();
        for row in &data[..p] {
            st.update(&row[..2], &row[2..5], &row[5..]).unwrap();
        }
        let mut k = p;
        group.bench_function(
            BenchmarkId::new("core per-sample update", format!("B1 p={p}")),
            |b| {
                b.iter(|| {
                    let row = &data[k % data.len()];
                    k += 1;
                    black_box(st.update(&row[..2], &row[2..5], &row[5..]).unwrap())
                })
            },
        );
        // the host's path: 16 statistic vectors written from a slab, one rank-16 update
        let flat: Vec<T> = data
            .iter()
            .flat_map(|r| {
                let mut v = r[..5].to_vec();
                v.push(T::ONE);
                v.extend_from_slice(&r[5..]);
                v
            })
            .collect();
        let slab = Slab::new(&flat, 2, 3, 4).unwrap();
        let mut gram = Gram::new(len, vec![T::ZERO; packed_len(len)]).unwrap();
        let mut buf = vec![T::ZERO; 16 * len];
        let mut k0 = 0usize;
        let mut fill = |buf: &mut [T]| {
            for i in 0..16 {
                let k = (k0 + i) % (data.len() - p - 1);
                lpvid::write_stat_vector(
                    &dims,
                    StatsLayout::Plain,
                    &slab,
                    k,
                    &mut buf[i * len..(i + 1) * len],
                );
            }
            k0 += 16;
        };
        group.bench_function(
            BenchmarkId::new("core batched update (per 16 samples)", format!("B1 p={p}")),
            |b| {
                b.iter(|| {
                    fill(&mut buf);
                    gram.update_batch(&buf, 16).unwrap();
                })
            },
        );
    }
    group.finish();
}

fn full_fit(c: &mut Criterion) {
    let exp = systems::b1(1000, 0.05, 1);
    let mut group = c.benchmark_group("pbsid_fit_B1_N1000");
    group.sample_size(10);
    for (p, solver) in [(3, Solver::Primal), (3, Solver::Dual), (5, Solver::Dual)] {
        let mut o = PbsidOptions::new(p);
        o.reg = Reg::TikhonovGcv;
        o.solver = solver;
        group.bench_function(
            BenchmarkId::new(
                format!("{} form, Tikhonov-GCV", solver.name()),
                format!("p={p}"),
            ),
            |b| b.iter(|| black_box(fit(&exp.train, &o).unwrap().order)),
        );
    }
    group.finish();
}

/// The ridge step of the kernel form at B1 p = 5 (995 x 995 kernel): the full symmetric
/// eigendecomposition GCV used before against the tridiagonal reduction that replaced it
/// (`linalg::Tridiagonal`: reduction, targets, largest eigenvalue, 100 GCV evaluations and
/// the solve), same kernel, same run.
fn ridge_step(c: &mut Criterion) {
    use lpvid_host::linalg::{sym_eig, Tridiagonal};
    let exp = systems::b1(1000, 0.05, 1);
    let p = 5;
    let rows: Vec<f64> = (0..exp.train.len())
        .flat_map(|k| {
            let mut r: Vec<f64> = exp.train.u.row(k).iter().copied().collect();
            r.extend(exp.train.y.row(k).iter());
            r.push(1.0);
            r.extend(exp.train.p.row(k).iter().map(|v| 0.2 * v));
            r
        })
        .collect();
    let (r, l, m) = (
        exp.train.u.ncols(),
        exp.train.y.ncols(),
        exp.train.p.ncols() + 1,
    );
    let slab = lpvid::Slab::new(&rows, r, l, m).unwrap();
    let nb = exp.train.len() - p;
    let g = lpvid_host::pbsid::dual_kernel_matrix(&slab, p, nb, true);
    let y = nalgebra::DMatrix::from_fn(nb, l, |k, j| exp.train.y[(k + p, j)]);
    let mut group = c.benchmark_group("ridge_step_B1_p5_kernel995");
    group.sample_size(10);
    group.bench_function("full eigendecomposition (before)", |b| {
        b.iter(|| black_box(sym_eig(&g).unwrap().0[0]))
    });
    group.bench_function("tridiagonal + O(n) GCV + solve (now)", |b| {
        b.iter(|| {
            let t = Tridiagonal::new(&g);
            let bt = t.to_tridiagonal(&y);
            let vmax = t.largest_eigenvalue();
            let mut best = (f64::INFINITY, 0.0);
            for e in 0..100 {
                let lam = vmax * 10f64.powf(-12.0 + 0.13 * e as f64);
                if let Some((xx, tr)) = t.shifted_norm_trace(lam, &bt) {
                    let gcv = lam * lam * xx / (lam * tr).powi(2);
                    if gcv < best.0 {
                        best = (gcv, lam);
                    }
                }
            }
            black_box(t.from_tridiagonal(&t.solve_shifted(best.1, &bt).unwrap()))
        })
    });
    group.finish();
    // a ridge below the shifted solve's floor (or the minimum-norm solution), after the
    // reduction every kernel fit makes: the kernel built again and fully decomposed
    // (before) against the eigenvectors of the tridiagonal T already at hand, taken back by
    // Q for the target's columns only (now), same kernel, same run
    let t = Tridiagonal::new(&g);
    let mut group = c.benchmark_group("ridge_below_shifted_floor_B1_p5_kernel995");
    group.sample_size(10);
    group.bench_function("kernel again + full eigendecomposition (before)", |b| {
        b.iter(|| {
            let g2 = lpvid_host::pbsid::dual_kernel_matrix(&slab, p, nb, true);
            let (_, v) = sym_eig(&g2).unwrap();
            black_box(&v * v.tr_mul(&y))
        })
    });
    group.bench_function("eigenvectors of the reduced T (now)", |b| {
        b.iter(|| {
            let (_, v) = t.eigen().unwrap();
            let bt = t.to_tridiagonal(&y);
            black_box(t.from_tridiagonal(&(&v * v.tr_mul(&bt))))
        })
    });
    group.finish();
    // one GCV evaluation (RSS and trace at a lambda) as separate factor / solve / trace
    // passes (before) and fused into one forward and one backward pass (now): 100 lambdas
    // over the range GCV searches, same tridiagonal, same run
    let t = Tridiagonal::new(&g);
    let bt = t.to_tridiagonal(&y);
    let vmax = t.largest_eigenvalue();
    let lams: Vec<f64> = (0..100)
        .map(|e| vmax * 10f64.powf(-14.0 + 0.15 * e as f64))
        .collect();
    let mut group = c.benchmark_group("gcv_100_evaluations_B1_p5_kernel995");
    group.sample_size(20);
    group.bench_function("factor, solves, trace (before)", |b| {
        b.iter(|| {
            let s: f64 = lams
                .iter()
                .filter_map(|&l| t.shifted_norm_trace_passes(l, &bt))
                .map(|(x, tr)| x + tr)
                .sum();
            black_box(s)
        })
    });
    group.bench_function("one forward, one backward pass (now)", |b| {
        b.iter(|| {
            let s: f64 = lams
                .iter()
                .filter_map(|&l| t.shifted_norm_trace(l, &bt))
                .map(|(x, tr)| x + tr)
                .sum();
            black_box(s)
        })
    });
    group.finish();
    // the reduction as the kernel form ran it before (the lower triangle copied into a new,
    // padded faer matrix: 8 MB of first-touch pages) against in the kernel's own storage
    // (`Tridiagonal::from_lower`, now); each iteration starts from a fresh copy of the kernel,
    // as the fit has one, in both
    let mut group = c.benchmark_group("tridiagonal_copy_vs_in_place_B1_p5_kernel995");
    group.sample_size(10);
    group.bench_function("copy into a faer matrix (before)", |b| {
        b.iter(|| {
            use faer::dyn_stack::{MemBuffer, MemStack};
            use faer::linalg::evd::tridiag;
            let g = g.clone();
            let n = g.nrows();
            let par = lpvid_host::linalg::par_for(n);
            let mut m = faer::Mat::<f64>::zeros(n, n);
            for j in 0..n {
                m.col_as_slice_mut(j)[j..].copy_from_slice(&g.column(j).as_slice()[j..]);
            }
            let bs = faer::linalg::qr::no_pivoting::factor::recommended_block_size::<f64>(n, n);
            let mut h = faer::Mat::<f64>::zeros(bs, n - 1);
            let mut buf = MemBuffer::new(tridiag::tridiag_in_place_scratch::<f64>(
                n,
                par,
                Default::default(),
            ));
            tridiag::tridiag_in_place(
                m.as_mut(),
                h.as_mut(),
                par,
                MemStack::new(&mut buf),
                Default::default(),
            );
            black_box(m[(1, 0)])
        })
    });
    group.bench_function("in the kernel's storage (now)", |b| {
        b.iter(|| black_box(Tridiagonal::from_lower(g.clone()).dim()))
    });
    group.finish();
}

/// BPDN-SV fit time on B2 (N = 75, 25 dB) against Tikhonov-GCV on the same data; the
/// toolbox's BPDN-SV takes 98 ms, 354 ms, 1.45 s and 2.6 s at p = 5, 8, 10, 12 (Octave).
fn bpdn_fit(c: &mut Criterion) {
    let exp = systems::b2(75, 25.0, 1);
    let mut group = c.benchmark_group("bpdn_sv_fit_B2_N75");
    group.sample_size(10);
    for p in [5usize, 8, 10, 12, 14] {
        for reg in [Reg::BpdnSv, Reg::TikhonovGcv] {
            let mut o = PbsidOptions::new(p);
            o.reg = reg;
            group.bench_function(
                BenchmarkId::new(format!("{reg:?}"), format!("p={p}")),
                |b| b.iter(|| black_box(fit(&exp.train, &o).unwrap().order)),
            );
        }
    }
    group.finish();
}

fn benches(c: &mut Criterion) {
    stats_update::<f32>(c, "f32");
    stats_update::<f64>(c, "f64");
    full_fit(c);
    ridge_step(c);
    bpdn_fit(c);
}

criterion_group!(spine, benches);
criterion_main!(spine);
