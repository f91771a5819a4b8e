//! Where the time of a small `lpvid pbsid` process goes, and what the issue-16 changes are
//! compared against, each pair in the same run:
//!
//! - `process_stages_B1_p3_N1000`: the stages of `lpvid pbsid --train fixtures/b1-train.csv
//!   --past 3` one by one (CSV parse, fit, observer step with the stability report, the
//!   free-run score, the model JSON);
//! - `stability_B1_p3`: the box maximum of the predictor's spectral radius by the dense
//!   lattice with nalgebra's Schur decomposition (before), the dense lattice with
//!   `SmallEig`, and the coarse lattice + ascent (now); the stability regions;
//! - `tridiagonal_seq_vs_par`: faer's tridiagonal reduction on one thread vs the pool;
//! - `gram_two_halves_B1_p3`: the plain statistics on one thread vs two halves on two
//!   threads merged with the core's merge;
//! - `streamed_vs_in_memory_B1_p3_N20000`: the primal fit from the whole record vs the
//!   two streamed passes over chunks of 8192 samples;
//! - `order_check_regression_B1_p3`: without a validation file, the fit and the order
//!   check's own regression on the first four fifths one after the other (before, and now
//!   when no core is to spare) vs beside each other on two threads (now on an idle core).
//!
//! Issue 16, helper h25p3 (whole process of small fits), each pair in the same run:
//! - `tridiagonal_block_B2_p5`: the 70 x 70 kernel of B2 p = 5 reduced with faer's block of
//!   8 reflectors (before) vs one by one (now, up to 128 rows), with Q^T b and Q x (in a
//!   process the block's first product also waited for the sysfs cache probe: not here,
//!   where it ran once before the timing);
//! - `order_check_orders_B1_p3`: the order check's scores of n0, n0 + 1, n0 + 2 on the
//!   validation file one after the other (before, and now when no core is to spare) vs
//!   n0 + 1 on a second thread (now on an idle core);
//! - `stability_report_B1_p3`: the stability regions and the box maximum one after the
//!   other vs side by side;
//! - `csv_train_and_val_B1`: the validation and training files parsed one after the other
//!   vs side by side.
//!
//! Twenty-ninth session (the streamed fit's pass 2):
//! - `pass_two_states_B1_p3_8192_windows`: the states x = T z of one chunk's windows, each
//!   regressor written as pass 2 writes it, by a nalgebra matrix-vector product per window
//!   (before) vs one contiguous dot product per row of T (now, `pbsid::stream::PassTwo`).

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid::window::write_pbsid_regressor;
use lpvid::{stat_vector_len, write_stat_vector, PbsidDims, Slab, StatsLayout};
use lpvid_host::kernel_sweep::dot4;
use lpvid_host::linalg::{gram_from_rows_split, schur_spectral_radius, Tridiagonal};
use lpvid_host::lpvss::Signals;
use lpvid_host::observer::{
    max_predictor_radius, max_predictor_radius_dense, observer_step, predictor_matrix,
    stability_regions, ObserverRequest, SchedBox, REGION_WIDEN, REPORT_GRID,
};
use lpvid_host::pbsid::stream::PassOne;
use lpvid_host::pbsid::{fit, state_candidates, PbsidFit, PbsidOptions, Solver};
use lpvid_host::pipeline::{identify, DataFile, PbsidSettings};
use lpvid_host::simulate::{score, Mode};
use lpvid_host::systems;

const B1: &[u8] = include_bytes!("../../fixtures/b1-train.csv");

fn stages(c: &mut Criterion) {
    let mut group = c.benchmark_group("process_stages_B1_p3_N1000");
    group.sample_size(20);
    let settings = PbsidSettings::new(3);
    group.bench_function("csv_parse", |b| {
        b.iter(|| black_box(DataFile::from_bytes("b1-train.csv", B1).unwrap().data.len()))
    });
    let train = DataFile::from_bytes("b1-train.csv", B1).unwrap();
    let (map, sig) = lpvid_host::pipeline::training_signals(&train.data, 3).unwrap();
    group.bench_function("fit", |b| {
        b.iter(|| black_box(fit(&sig, &settings.fit).unwrap().order))
    });
    let f = fit(&sig, &settings.fit).unwrap();
    let names: Vec<String> = (1..=3).map(|j| format!("p{j}")).collect();
    group.bench_function("observer_step", |b| {
        b.iter(|| {
            let st = observer_step(
                &f.model,
                f.states.as_ref(),
                &sig,
                3,
                &names,
                &ObserverRequest::default(),
                false,
            )
            .unwrap();
            black_box(st.max_rho)
        })
    });
    let id = identify(&train, None, &settings).unwrap();
    group.bench_function("free_run_score", |b| {
        b.iter(|| {
            black_box(
                score(&id.model, &train.data, Mode::FreeRun)
                    .unwrap()
                    .vaf_mean,
            )
        })
    });
    group.bench_function("model_json", |b| {
        b.iter(|| black_box(id.model.to_json_string().len()))
    });
    group.bench_function("identify_all", |b| {
        b.iter(|| black_box(identify(&train, None, &settings).unwrap().fit.order))
    });
    let _ = map;
    group.finish();
}

/// The B1 p = 3 fit, its scheduling box and the mean operating point (the stability benches'
/// common set-up).
fn b1_stability_setup() -> (PbsidFit, SchedBox, Vec<f64>) {
    let train = DataFile::from_bytes("b1-train.csv", B1).unwrap();
    let (_, sig) = lpvid_host::pipeline::training_signals(&train.data, 3).unwrap();
    let f = fit(&sig, &PbsidOptions::new(3)).unwrap();
    let names: Vec<String> = (1..=3).map(|j| format!("p{j}")).collect();
    let sbox = SchedBox::from_signals(&names, &sig);
    let reference: Vec<f64> = (0..3).map(|j| sig.p.column(j).mean()).collect();
    (f, sbox, reference)
}

fn stability(c: &mut Criterion) {
    let (f, sbox, reference) = b1_stability_setup();
    let mut group = c.benchmark_group("stability_B1_p3");
    group.sample_size(10);
    group.bench_function("box_max_dense_nalgebra_schur(before)", |b| {
        b.iter(|| {
            black_box(
                sbox.grid(REPORT_GRID)
                    .iter()
                    .map(|mu| schur_spectral_radius(&predictor_matrix(&f.model, mu)))
                    .fold(0.0, f64::max),
            )
        })
    });
    group.bench_function("box_max_dense_small_eig", |b| {
        b.iter(|| black_box(max_predictor_radius_dense(&f.model, &sbox, REPORT_GRID)))
    });
    group.bench_function("box_max_coarse_and_ascent(now)", |b| {
        b.iter(|| black_box(max_predictor_radius(&f.model, &sbox, REPORT_GRID)))
    });
    group.bench_function("regions_adaptive_march(now)", |b| {
        b.iter(|| black_box(stability_regions(&f.model, &sbox, &reference, REGION_WIDEN).len()))
    });
    group.finish();
}

fn tridiagonal(c: &mut Criterion) {
    let mut group = c.benchmark_group("tridiagonal_seq_vs_par");
    group.sample_size(10);
    for n in [422usize, 995] {
        let x = nalgebra::DMatrix::<f64>::from_fn(n, n + 50, |i, j| {
            ((i * 31 + j * 17) % 101) as f64 / 101.0 - 0.5
        });
        let a = &x * x.transpose();
        group.bench_function(BenchmarkId::new("one_thread", n), |b| {
            b.iter(|| black_box(Tridiagonal::new_with(&a, faer::Par::Seq).dim()))
        });
        group.bench_function(BenchmarkId::new("thread_pool", n), |b| {
            b.iter(|| black_box(Tridiagonal::new_with(&a, faer::Par::rayon(0)).dim()))
        });
    }
    group.finish();
}

fn raw_rows(sig: &Signals) -> Vec<f64> {
    let mut rows = Vec::new();
    for k in 0..sig.len() {
        rows.extend(sig.u.row(k).iter());
        rows.extend(sig.y.row(k).iter());
        rows.push(1.0);
        rows.extend(sig.p.row(k).iter());
    }
    rows
}

fn gram_halves(c: &mut Criterion) {
    let mut group = c.benchmark_group("gram_two_halves_B1_p3");
    group.sample_size(10);
    for n in [1000usize, 20_000] {
        let exp = systems::b1(n, 0.05, 3);
        let rows = raw_rows(&exp.train);
        let dims = PbsidDims::new(2, 3, 3, 3).unwrap();
        let slab = Slab::new(&rows, 2, 3, 4).unwrap();
        let len = stat_vector_len(&dims, StatsLayout::Plain).unwrap();
        let windows = n - 3;
        let row =
            |k: usize, d: &mut [f64]| write_stat_vector(&dims, StatsLayout::Plain, &slab, k, d);
        group.bench_function(BenchmarkId::new("one_thread", n), |b| {
            b.iter(|| {
                black_box(
                    gram_from_rows_split(len, windows, row, false)
                        .unwrap()
                        .dim(),
                )
            })
        });
        group.bench_function(BenchmarkId::new("two_halves_merged", n), |b| {
            b.iter(|| black_box(gram_from_rows_split(len, windows, row, true).unwrap().dim()))
        });
    }
    group.finish();
}

fn streamed(c: &mut Criterion) {
    let exp = systems::b1(20_000, 0.05, 4);
    let mut o = PbsidOptions::new(3);
    o.solver = Solver::Primal;
    let mut group = c.benchmark_group("streamed_vs_in_memory_B1_p3_N20000");
    group.sample_size(10);
    group.bench_function("in_memory", |b| {
        b.iter(|| black_box(fit(&exp.train, &o).unwrap().order))
    });
    let pieces: Vec<Signals> = (0..exp.train.len())
        .step_by(8192)
        .map(|k| exp.train.slice(k, 8192.min(exp.train.len() - k)))
        .collect();
    group.bench_function("streamed_chunks_8192", |b| {
        b.iter(|| {
            let mut one = PassOne::new(2, 3, 3, &o).unwrap();
            for c in &pieces {
                one.update(c).unwrap();
            }
            let Ok(mut two) = one.finish(&o) else {
                panic!()
            };
            for c in &pieces {
                two.update(c).unwrap();
            }
            black_box(two.finish().unwrap().order)
        })
    });
    group.finish();
}

fn pass_two_states(c: &mut Criterion) {
    let dims = PbsidDims::new(2, 3, 3, 3).unwrap();
    let q = dims.q().unwrap();
    let n = 4;
    let exp = systems::b1(8192 + 3, 0.05, 4);
    let sig = &exp.train;
    let mut rows = Vec::with_capacity(sig.len() * 9);
    for k in 0..sig.len() {
        rows.extend(sig.u.row(k).iter());
        rows.extend(sig.y.row(k).iter());
        rows.push(1.0);
        rows.extend(sig.p.row(k).iter());
    }
    let slab = Slab::new(&rows, 2, 3, 4).unwrap();
    let windows = sig.len() - 3;
    let t = nalgebra::DMatrix::from_fn(n, q, |i, j| ((i * 7 + j * 13) % 17) as f64 / 17.0 - 0.5);
    let t_rows = t.transpose();
    let mut group = c.benchmark_group("pass_two_states_B1_p3_8192_windows");
    group.sample_size(20);
    group.bench_function("matrix_vector_per_window(before)", |b| {
        let mut z = vec![0.0; q];
        b.iter(|| {
            let mut acc = 0.0;
            for k in 0..windows {
                write_pbsid_regressor(&dims, &slab, k, &mut z);
                let x = &t * nalgebra::DVector::from_column_slice(&z);
                acc += x[n - 1];
            }
            black_box(acc)
        })
    });
    group.bench_function("dot_per_row_of_T(now)", |b| {
        let mut z = vec![0.0; q];
        let mut x = vec![0.0; n];
        b.iter(|| {
            let mut acc = 0.0;
            for k in 0..windows {
                write_pbsid_regressor(&dims, &slab, k, &mut z);
                for (xi, ti) in x.iter_mut().zip(t_rows.column_iter()) {
                    *xi = dot4(ti.as_slice(), &z);
                }
                acc += x[n - 1];
            }
            black_box(acc)
        })
    });
    group.finish();
}

fn order_check_regression(c: &mut Criterion) {
    let train = DataFile::from_bytes("b1-train.csv", B1).unwrap();
    let (_, sig) = lpvid_host::pipeline::training_signals(&train.data, 3).unwrap();
    let head = sig.slice(0, sig.len() - sig.len() / 5);
    let opts = PbsidOptions::new(3);
    let fit_and_head = || {
        let f = state_candidates(&sig, None, &opts).unwrap();
        let model = f.realize(&sig, &opts, None).unwrap();
        (model.order, f)
    };
    let mut group = c.benchmark_group("order_check_regression_B1_p3");
    group.sample_size(20);
    group.bench_function("after_the_fit(before)", |b| {
        b.iter(|| {
            let (order, _) = fit_and_head();
            let h = state_candidates(&head, None, &opts).unwrap();
            black_box((order, h.singular_values()[0]))
        })
    });
    group.bench_function("beside_the_fit(now, a core to spare)", |b| {
        b.iter(|| {
            std::thread::scope(|sc| {
                let w = sc.spawn(|| state_candidates(&head, None, &opts).unwrap());
                let (order, _) = fit_and_head();
                let h = w.join().unwrap();
                black_box((order, h.singular_values()[0]))
            })
        })
    });
    group.finish();
}

fn tridiagonal_block(c: &mut Criterion) {
    let b2 = DataFile::from_bytes(
        "b2-train.csv",
        include_bytes!("../../fixtures/b2-train.csv"),
    )
    .unwrap();
    let (_, b2sig) = lpvid_host::pipeline::training_signals(&b2.data, 5).unwrap();
    let mut o = PbsidOptions::new(5);
    o.solver = Solver::Dual;
    // a 70 x 70 symmetric positive semidefinite matrix like B2's kernel
    let n = 70;
    let x = nalgebra::DMatrix::<f64>::from_fn(n, 3 * n, |i, j| {
        ((i * 31 + j * 17) % 101) as f64 / 101.0 - 0.5
    });
    let a = &x * x.transpose();
    let b = nalgebra::DMatrix::<f64>::from_fn(n, 1, |i, _| (i as f64).sin());
    let faer_bs = faer::linalg::qr::no_pivoting::factor::recommended_block_size::<f64>(n, n);
    let mut group = c.benchmark_group("tridiagonal_block_B2_p5");
    group.sample_size(50);
    for (name, bs) in [("faer_block_8(before)", faer_bs), ("one_by_one(now)", 1)] {
        group.bench_function(name, |bn| {
            bn.iter(|| {
                let t = Tridiagonal::new_blocked(&a, faer::Par::Seq, bs);
                let y = t.to_tridiagonal(&b);
                black_box(t.from_tridiagonal(&y)[(0, 0)])
            })
        });
    }
    group.bench_function("b2_fixture_fit_kernel_form(now)", |bn| {
        bn.iter(|| black_box(fit(&b2sig, &o).unwrap().order))
    });
    group.finish();
}

fn order_check_orders(c: &mut Criterion) {
    let train = DataFile::from_bytes("b1-train.csv", B1).unwrap();
    let (map, sig) = lpvid_host::pipeline::training_signals(&train.data, 3).unwrap();
    let val_ds = DataFile::from_bytes("b1-val.csv", include_bytes!("../../fixtures/b1-val.csv"))
        .unwrap()
        .data;
    let opts = PbsidOptions::new(3);
    let cands = state_candidates(&sig, None, &opts).unwrap();
    let n0 = cands.realize(&sig, &opts, None).unwrap().order;
    let err = |o: usize| {
        let m = cands.realize(&sig, &opts, Some(o)).unwrap().model;
        let mf = lpvid_host::model::ModelFile {
            kind: lpvid_host::model::ModelKind::Ss(m),
            signals: map.clone(),
            fit: serde_json::Value::Null,
        };
        lpvid_host::pipeline::held_out_error(&mf, &val_ds).unwrap()
    };
    let mut group = c.benchmark_group("order_check_orders_B1_p3");
    group.sample_size(20);
    group.bench_function("one_after_the_other(before)", |b| {
        b.iter(|| black_box(err(n0) + err(n0 + 1) + err(n0 + 2)))
    });
    group.bench_function("n0_plus_1_beside(now, a core to spare)", |b| {
        b.iter(|| {
            std::thread::scope(|sc| {
                let next = sc.spawn(|| err(n0 + 1));
                let e = err(n0) + err(n0 + 2);
                black_box(e + next.join().unwrap())
            })
        })
    });
    group.finish();
}

fn stability_report(c: &mut Criterion) {
    let (f, sbox, reference) = b1_stability_setup();
    let mut group = c.benchmark_group("stability_report_B1_p3");
    group.sample_size(20);
    group.bench_function("one_after_the_other(before)", |b| {
        b.iter(|| {
            let r = stability_regions(&f.model, &sbox, &reference, REGION_WIDEN);
            black_box((r.len(), max_predictor_radius(&f.model, &sbox, REPORT_GRID)))
        })
    });
    group.bench_function("side_by_side(now, a core to spare)", |b| {
        b.iter(|| {
            std::thread::scope(|sc| {
                let rho = sc.spawn(|| max_predictor_radius(&f.model, &sbox, REPORT_GRID));
                let r = stability_regions(&f.model, &sbox, &reference, REGION_WIDEN);
                black_box((r.len(), rho.join().unwrap()))
            })
        })
    });
    group.finish();
}

fn csv_train_and_val(c: &mut Criterion) {
    const V: &[u8] = include_bytes!("../../fixtures/b1-val.csv");
    let mut group = c.benchmark_group("csv_train_and_val_B1");
    group.sample_size(20);
    group.bench_function("one_after_the_other(before)", |b| {
        b.iter(|| {
            let v = DataFile::from_bytes("v", V).unwrap();
            let t = DataFile::from_bytes("t", B1).unwrap();
            black_box(v.data.len() + t.data.len())
        })
    });
    group.bench_function("side_by_side(now, a core to spare)", |b| {
        b.iter(|| {
            std::thread::scope(|sc| {
                let v = sc.spawn(|| DataFile::from_bytes("v", V).unwrap());
                let t = DataFile::from_bytes("t", B1).unwrap();
                black_box(v.join().unwrap().data.len() + t.data.len())
            })
        })
    });
    group.finish();
}

fn benches(c: &mut Criterion) {
    tridiagonal_block(c);
    order_check_orders(c);
    stability_report(c);
    csv_train_and_val(c);
    order_check_regression(c);
    stages(c);
    stability(c);
    tridiagonal(c);
    gram_halves(c);
    streamed(c);
    pass_two_states(c);
}

criterion_group!(process, benches);
criterion_main!(process);
