//! BPDN-SV at large past windows (issue 16): B2 (sparse paper Example I, N = 75, 25 dB,
//! seed 0), the scaled-free raw record, p = 8 / 14, each in the same process:
//! - `engine covariance` against `engine sample-space`: the path, realization and score of
//!   one past window ([`bpdn::select_by_simulation_with`]) with the core's covariance-update
//!   engine and with the residual engine of `pbsid::sample_cd` (the same problems);
//! - `one depth` (the sample-space engine at depth p only, the BPDN-SV of before) against
//!   `depths 1..=p, 1 thread` and `depths 1..=p, 2 threads`
//!   ([`sparse::sv_over_depths_with`], what `fit` runs).
//!
//! - group `free_run_scorer`: BPDN-SV's free-run scorer (`bpdn::FreeRun`) on a B2 record of
//!   500 samples (the validation file of `scripts/compare-toolbox.sh`), models of order 2 / 4
//!   / 8 with one C and one D as the realizations are: `one C, D, r fixed` (the kernel with
//!   the input count fixed at compile time, what `error_below` runs) against `order fixed`
//!   (`error_below_order`, the scorer before), the same bits;
//! - group `realize_for_scoring`: one order of a path point's `OrderSweep` (B2 training
//!   record, states of order 4) packed for the scorer: `realize_scorer` (straight from the
//!   least-squares solution) against `realize + FreeRun::new` (through `LpvSs`; both form the normal equations the same way).
//!
//! - group `order_sweep`: a path point's realizations at every order, old and new side by
//!   side (see [`order_sweep`]).
//!
//! Run: `cargo bench -p lpvid-host --bench bpdn`.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid::{PbsidDims, Samples, Slab};
use lpvid_host::pbsid::bpdn::{self, Engine, LazyGram};
use lpvid_host::pbsid::{sparse, PbsidOptions, Reg};
use lpvid_host::systems;
use nalgebra::DMatrix;

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

/// A stable model of order `n` with B2's sizes (r = l = 1, m = 2), one C and one D.
fn scored_model(n: usize) -> lpvid_host::lpvss::LpvSs {
    let mut model = systems::b2_truth();
    let f =
        |i: usize, j: usize, s: usize| 0.9 / n as f64 * ((i * 7 + j * 3 + s * 5 + n) as f64).sin();
    model.a = (0..2)
        .map(|s| DMatrix::from_fn(n, n, |i, j| f(i, j, s)))
        .collect();
    model.b = (0..2)
        .map(|s| DMatrix::from_fn(n, 1, |i, j| f(i + 11, j, s)))
        .collect();
    model.k = (0..2).map(|_| DMatrix::zeros(n, 1)).collect();
    model.c = vec![DMatrix::from_fn(1, n, |i, j| f(i + 5, j, 0))];
    model.d = vec![DMatrix::from_fn(1, 1, |i, j| f(i + 9, j, 0))];
    model
}

fn scorer(c: &mut Criterion) {
    let e = systems::b2(500, 25.0, 1);
    let record = bpdn::ScoredRecord::new(&e.train, 2);
    let mut group = c.benchmark_group("free_run_scorer");
    for n in [2usize, 4, 8] {
        let run = bpdn::FreeRun::new(&scored_model(n));
        assert_eq!(
            run.error_below(&record, f64::INFINITY).to_bits(),
            run.error_below_order(&record, f64::INFINITY).to_bits()
        );
        group.bench_function(BenchmarkId::new("one C, D, r fixed", n), |b| {
            b.iter(|| black_box(run.error_below(black_box(&record), f64::INFINITY)))
        });
        group.bench_function(BenchmarkId::new("order fixed (before)", n), |b| {
            b.iter(|| black_box(run.error_below_order(black_box(&record), f64::INFINITY)))
        });
    }
    group.finish();
}

fn realize_for_scoring(c: &mut Criterion) {
    use lpvid_host::pbsid::realize::OrderSweep;
    let data = rows();
    let slab = Slab::new(&data, 1, 1, 2).unwrap();
    let p = 5;
    let dims = PbsidDims::new(1, 1, 1, p).unwrap();
    let cols = slab.len() - p + 1;
    let states = DMatrix::from_fn(4, cols, |i, k| {
        (0..p)
            .map(|j| ((i * 5 + j * 2) as f64 * 0.41).cos() * slab.y(k + j)[0])
            .sum::<f64>()
    });
    let sweep = OrderSweep::new(&dims, &slab, &states, true).unwrap();
    let mut group = c.benchmark_group("realize_for_scoring");
    for n in [2usize, 4] {
        assert!(sweep
            .realize_scorer(n)
            .unwrap()
            .same_packing(&bpdn::FreeRun::new(&sweep.realize(n).unwrap())));
        group.bench_function(BenchmarkId::new("realize_scorer", n), |b| {
            b.iter(|| black_box(sweep.realize_scorer(black_box(n)).unwrap()))
        });
        group.bench_function(
            BenchmarkId::new("realize + FreeRun::new (through LpvSs)", n),
            |b| b.iter(|| black_box(bpdn::FreeRun::new(&sweep.realize(black_box(n)).unwrap()))),
        );
    }
    group.finish();
}

/// Group `order_sweep` (2026-11-27, h24b1): one BPDN-SV path point of B2 (p = 5, training
/// record of seed 0, the states of a dense [C K^p, D]) realized at every candidate order,
/// old and new side by side:
/// - the states of the point: `states row-major` (what BPDN-SV forms now) against `states
///   column-major` (the nalgebra products before);
/// - `Grams by dot products` (`OrderSweep::new`) against `Grams by the core's batch update`
///   (`OrderSweep::with_core_grams`, the sweep before), states of order 5;
/// - `orders 1..=5, nested factors` (`realize_scorer`: one Cholesky factor per equation
///   for all orders) against `orders 1..=5, per order` (`realize_scorer_per_order`: each
///   order's normal equations formed in the innovation basis and solved on their own);
/// - at a point whose Gamma K Z has rank 1 (a [C K^p, D] with one active column in the
///   last lag block), `orders 1..=rank realized and scored` (what BPDN-SV does now)
///   against `orders 1..=5` (before: the orders above the rank tie the rank order's score).
fn order_sweep(c: &mut Criterion) {
    use lpvid::window::write_pbsid_regressor;
    use lpvid_host::pbsid::realize::{states_from_gkz, states_from_gkz_rows, OrderSweep};
    let e = systems::b2(75, 25.0, 0);
    let data = rows();
    let slab = Slab::new(&data, 1, 1, 2).unwrap();
    let p = 5;
    let dims = PbsidDims::new(1, 1, 1, p).unwrap();
    let windows = slab.len() - p;
    let all: Vec<usize> = (0..windows).collect();
    let (g, _) = LazyGram::build(&dims, &slab, &all, true).unwrap();
    let mut z_last = vec![0.0; dims.q().unwrap()];
    write_pbsid_regressor(&dims, &slab, windows, &mut z_last);
    // a dense [C K^p, D] (every column active): Gamma K Z of full rank, states of order 5
    let dense: Vec<f64> = (0..g.regressors())
        .map(|j| 0.2 * (j as f64 * 0.7).sin())
        .collect();
    let gkz = bpdn::gamma_kz(&dims, p, &dense, &g, &z_last);
    let (sv, states) = states_from_gkz(&gkz, windows).unwrap();
    assert_eq!(bpdn::numerical_rank(&sv), 5);
    let mut group = c.benchmark_group("order_sweep");
    group.bench_function(
        "states row-major (gamma_kz_rows, states_from_gkz_rows)",
        |b| {
            b.iter(|| {
                let gkz = bpdn::gamma_kz_rows(&dims, p, black_box(&dense), &g, &z_last);
                black_box(states_from_gkz_rows(&gkz, 5, windows).unwrap())
            })
        },
    );
    group.bench_function(
        "states column-major (gamma_kz, states_from_gkz; before)",
        |b| {
            b.iter(|| {
                let gkz = bpdn::gamma_kz(&dims, p, black_box(&dense), &g, &z_last);
                black_box(states_from_gkz(&gkz, windows).unwrap())
            })
        },
    );
    group.bench_function("Grams by dot products", |b| {
        b.iter(|| black_box(OrderSweep::new(&dims, &slab, black_box(&states), true).unwrap()))
    });
    group.bench_function("Grams by the core's batch update", |b| {
        b.iter(|| {
            black_box(OrderSweep::with_core_grams(&dims, &slab, black_box(&states), true).unwrap())
        })
    });
    let sweep = OrderSweep::new(&dims, &slab, &states, true).unwrap();
    for n in 1..=5 {
        assert!(sweep.realize_scorer(n).is_ok());
    }
    group.bench_function("orders 1..=5, nested factors", |b| {
        b.iter(|| {
            for n in 1..=5 {
                black_box(sweep.realize_scorer(black_box(n)).unwrap());
            }
        })
    });
    group.bench_function("orders 1..=5, per order", |b| {
        b.iter(|| {
            for n in 1..=5 {
                black_box(sweep.realize_scorer_per_order(black_box(n)).unwrap());
            }
        })
    });
    // a point of rank 1
    let mut theta = vec![0.0; g.regressors()];
    theta[dims.block_offset(p)] = 0.7;
    theta[g.regressors() - 1] = 0.3;
    let gkz = bpdn::gamma_kz(&dims, p, &theta, &g, &z_last);
    let (sv, x) = states_from_gkz(&gkz, windows).unwrap();
    let rank = bpdn::numerical_rank(&sv);
    assert_eq!(rank, 1);
    let val = &e.val;
    let record = bpdn::ScoredRecord::new(val, 2);
    let score_upto = |top: usize| {
        let sweep = OrderSweep::new(&dims, &slab, &x.rows(0, top).into_owned(), true).unwrap();
        let mut best = f64::INFINITY;
        for n in 1..=top {
            best = best.min(sweep.realize_scorer(n).unwrap().error_below(&record, best));
        }
        best
    };
    group.bench_function("rank-1 point, orders 1..=rank realized and scored", |b| {
        b.iter(|| black_box(score_upto(black_box(rank))))
    });
    group.bench_function("rank-1 point, orders 1..=5 (before)", |b| {
        b.iter(|| black_box(score_upto(black_box(5))))
    });
    group.finish();
}

criterion_group!(
    bpdn_bench,
    compare,
    scorer,
    realize_for_scoring,
    order_sweep
);
criterion_main!(bpdn_bench);
