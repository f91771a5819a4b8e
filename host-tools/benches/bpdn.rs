//! BPDN-SV at large past windows (issue 16): B2 (sparse paper Example I, N = 75, 25 dB,
//! seed 0), the scaled-free raw record, p = 8 / 14, each in the same process:
//! - `engine covariance` against `engine sample-space`: the path, realization and score of
//!   one past window ([`bpdn::select_by_simulation_with`]) with the core's covariance-update
//!   engine and with the residual engine of `pbsid::sample_cd` (the same problems);
//! - `one depth` (the sample-space engine at depth p only, the BPDN-SV of before) against
//!   `depths 1..=p, 1 thread` and `depths 1..=p, 2 threads`
//!   ([`sparse::sv_over_depths_with`], what `fit` runs).
//!
//! Run: `cargo bench -p lpvid-host --bench bpdn`.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid::{PbsidDims, Samples, Slab};
use lpvid_host::pbsid::bpdn::{self, Engine, LazyGram};
use lpvid_host::pbsid::{sparse, PbsidOptions, Reg};
use lpvid_host::systems;

/// Sample rows [u, y, 1, p] of B2's training record.
fn rows() -> Vec<f64> {
    let e = systems::b2(75, 25.0, 0);
    let t = &e.train;
    (0..t.len())
        .flat_map(|k| [t.u[(k, 0)], t.y[(k, 0)], 1.0, t.p[(k, 0)]])
        .collect()
}

fn compare(c: &mut Criterion) {
    let data = rows();
    let slab = Slab::new(&data, 1, 1, 2).unwrap();
    let mut group = c.benchmark_group("bpdn_sv_b2");
    group.sample_size(10);
    for p in [8usize, 14] {
        let dims = PbsidDims::new(1, 1, 1, p).unwrap();
        let windows: Vec<usize> = (0..slab.len() - p).collect();
        let orders = [1usize, 2, 3];
        let one = |engine: Engine| {
            let (g, y) = LazyGram::build(&dims, &slab, &windows, true).unwrap();
            bpdn::select_by_simulation_with(&dims, p, &g, &y, &slab, None, &orders, true, engine)
                .unwrap()
                .score
        };
        group.bench_function(BenchmarkId::new("engine covariance (one depth)", p), |b| {
            b.iter(|| black_box(one(Engine::Covariance)))
        });
        group.bench_function(
            BenchmarkId::new("engine sample-space (one depth)", p),
            |b| b.iter(|| black_box(one(Engine::SampleSpace))),
        );
        let mut opts = PbsidOptions::new(p);
        opts.reg = Reg::BpdnSv;
        for workers in [1usize, 2] {
            group.bench_function(
                BenchmarkId::new(format!("depths 1..=p, {workers} thread(s)"), p),
                |b| {
                    b.iter(|| {
                        black_box(
                            sparse::sv_over_depths_with(&dims, &slab, None, &opts, workers)
                                .unwrap()
                                .1,
                        )
                    })
                },
            );
        }
    }
    group.finish();
}

criterion_group!(bpdn_bench, compare);
criterion_main!(bpdn_bench);
