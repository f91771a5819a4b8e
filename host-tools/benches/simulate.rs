//! The free run through own-output feedback (`simulate::free_run_ss`), the sample loop the
//! output-error refinement repeats once per parameter and iteration (a forward-difference
//! Jacobian column is one run; multiple shooting on the unbalanced disk spends about 75 % of
//! its time in it). Compared in the same run with its peers: the plain free run of the same
//! model with the feedback channels read from data (`LpvSs::simulate`), and the state update
//! written with nalgebra's matrix-vector products (`A x + B u` per sample, the obvious way).
//! Model: six states, one measured input, |y1| y1 and sin(y1) fed back and a constant
//! channel (the shape of the disk's fits), and the same with a quasi-LPV weight on y1^2 (two
//! local models); 8 000 samples (the disk's training record).
//!
//! `refine jacobian`: the Jacobian of the refinement's free-run residual over those models'
//! parameters (every entry of A, B, C and the initial state), exact by forward sensitivities
//! (`refine::JacobianMethod::Exact`, what the refinement descends with) against forward
//! differences (one free run per parameter, what it descended with before), in the same run.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid_host::lpvss::{LpvSs, Signals};
use lpvid_host::model::{Factor, FactorFn, Feedback, Loop, OwnFactor};
use lpvid_host::refine::{free_run_jacobian, JacobianMethod};
use lpvid_host::simulate::free_run_ss;
use nalgebra::{DMatrix, DVector};

const N: usize = 8000;
const STATES: usize = 6;

/// A stable model of `m` local models on four input channels (u1, |y1| y1, sin y1, 1).
fn model(m: usize) -> LpvSs {
    let mut seed = 11u64;
    let mut rnd = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let (n, r) = (STATES, 4);
    let a: Vec<DMatrix<f64>> = (0..m)
        .map(|i| {
            let scale = if i == 0 { 0.9 } else { 0.05 };
            DMatrix::from_fn(
                n,
                n,
                |p, q| {
                    if p == q {
                        scale
                    } else {
                        0.1 * scale * rnd()
                    }
                },
            )
        })
        .collect();
    LpvSs {
        a,
        b: (0..m)
            .map(|_| DMatrix::from_fn(n, r, |_, _| 0.1 * rnd()))
            .collect(),
        k: (0..m).map(|_| DMatrix::zeros(n, 1)).collect(),
        c: vec![DMatrix::from_fn(1, n, |_, _| rnd())],
        d: vec![DMatrix::zeros(1, r)],
    }
}

/// The own-output factor `f` of y1 at the same sample.
fn own(func: Option<FactorFn>, pow: f64) -> OwnFactor {
    OwnFactor {
        output: 0,
        factor: Factor {
            func,
            pow,
            ..Factor::col("y1")
        },
    }
}

/// The record and the feedback: |y1| y1 and sin(y1) as input channels 1 and 2, and with
/// `scheduled` y1^2 as the scheduling signal.
fn record(scheduled: bool) -> (Signals, Feedback) {
    let u = DMatrix::from_fn(N, 4, |k, j| match j {
        0 => (0.01 * k as f64).sin() + 0.3 * (0.37 * k as f64).cos(),
        3 => 1.0,
        _ => 0.0,
    });
    let sig = Signals {
        u,
        y: DMatrix::zeros(N, 1),
        p: DMatrix::zeros(N, usize::from(scheduled)),
    };
    let loop_of = |f: Vec<OwnFactor>| Loop {
        data: vec![1.0; N],
        own: f,
    };
    let fb = Feedback {
        inputs: vec![
            (
                1,
                loop_of(vec![own(Some(FactorFn::Abs), 1.0), own(None, 1.0)]),
            ),
            (2, loop_of(vec![own(Some(FactorFn::Sin), 1.0)])),
        ],
        scheduling: if scheduled {
            vec![(0, loop_of(vec![own(None, 2.0)]))]
        } else {
            vec![]
        },
    };
    (sig, fb)
}

/// The state update written with nalgebra's products, A(mu) x + B(mu) u per sample, on the
/// inputs read from data (the peer of the sample loop's row-by-row sums).
fn nalgebra_loop(m: &LpvSs, sig: &Signals) -> DMatrix<f64> {
    let mut x = DVector::zeros(m.n());
    let mut out = DMatrix::zeros(sig.len(), m.l());
    for k in 0..sig.len() {
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        out.set_row(k, &(&m.c[0] * &x).transpose());
        let mut xn = DVector::zeros(m.n());
        for (i, w) in mu.iter().enumerate().take(m.m()) {
            xn += (&m.a[i] * &x + &m.b[i] * &u) * *w;
        }
        x = xn;
    }
    out
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("free run");
    group.sample_size(20);
    for (models, scheduled) in [(1, false), (2, true)] {
        let m = model(models);
        let (sig, fb) = record(scheduled);
        let id = format!("n={STATES} m={models} N={N}");
        let x0 = DVector::zeros(STATES);
        group.bench_function(BenchmarkId::new("through the feedback", &id), |b| {
            b.iter(|| black_box(free_run_ss(&m, &sig, &fb, &x0, N)))
        });
        group.bench_function(BenchmarkId::new("inputs from data", &id), |b| {
            b.iter(|| black_box(m.simulate(&sig, None)))
        });
        group.bench_function(BenchmarkId::new("nalgebra products", &id), |b| {
            b.iter(|| black_box(nalgebra_loop(&m, &sig)))
        });
    }
    group.finish();
}

fn jacobian(c: &mut Criterion) {
    let mut group = c.benchmark_group("refine jacobian");
    group.sample_size(10);
    for (models, scheduled) in [(1, false), (2, true)] {
        let m = model(models);
        let (sig, fb) = record(scheduled);
        let x0 = DVector::zeros(STATES);
        let params = free_run_jacobian(&m, &x0, &sig, &fb, &[], JacobianMethod::Exact)
            .expect("a stable run")
            .ncols();
        let id = format!("n={STATES} m={models} N={N} parameters={params}");
        for (name, method) in [
            ("exact (forward sensitivities)", JacobianMethod::Exact),
            ("forward differences", JacobianMethod::ForwardDifference),
        ] {
            group.bench_function(BenchmarkId::new(name, &id), |b| {
                b.iter(|| black_box(free_run_jacobian(&m, &x0, &sig, &fb, &[], method)))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench, jacobian);
criterion_main!(benches);
