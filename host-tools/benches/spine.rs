//! Benchmarks of the spine (issue 2): the core's per-sample statistics update for B1 with
//! p = 3 and p = 5 in f32 and f64 (compared in the same run with the host's batched update
//! of the same statistics), and the full LPV-PBSID_opt fit on B1 (primal vs kernel form on
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
        group.bench_function(
            BenchmarkId::new("host batched update (per 16 samples)", format!("B1 p={p}")),
            |b| {
                b.iter(|| {
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

/// BPDN-SV fit time on B2 (N = 75, 25 dB) against Tikhonov-GCV on the same data; the
/// toolbox's BPDN-SV takes 98 ms, 354 ms, 1.45 s and 2.6 s at p = 5, 8, 10, 12 (Octave).
fn bpdn_fit(c: &mut Criterion) {
    let exp = systems::b2(75, 25.0, 1);
    let mut group = c.benchmark_group("bpdn_sv_fit_B2_N75");
    group.sample_size(10);
    for p in [5usize, 8, 10, 12] {
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
    bpdn_fit(c);
}

criterion_group!(spine, benches);
criterion_main!(spine);
