//! Benchmarks of the LPV-ARX path (issue 4) on B6 (n_a = 4, n_b = 2, n_g = 2: 21 parameters).
//!
//! - `bciv_update_{f32,f64}`: the core's per-sample BC-IV statistics update
//!   (`BcivStats::update`: regressor window, Hermite-corrected Psi_k for the 3 powers of
//!   sigma^2, sum z y; BC-IV paper section 5.1), **compared in the same run** with the plain
//!   least-squares statistics of the same regressor (`Gram::update` of w = [phi(k); y(k)],
//!   22 values, after `ArxWindow::write_regressor`) and with the free-run simulation step
//!   that builds the instruments (`ArxWindow::simulate_step`).
//! - `arx_fit_b6`: the full `lpvid arx` fit on B6 (8000 training, 1000 calibration samples):
//!   the default BC-IV-LASSO (sigma auto, lambda by cross-validation), **compared with** the
//!   same with sigma_eta known (0.25), the paper's IV-LASSO recipe, and least squares of the
//!   full model (one statistics pass, one solve).
//!
//! `cargo bench -p lpvid-host --bench arx`; the figures are in docs/bench-arx.md.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid::arx::{ArxDims, ArxWindow};
use lpvid::bciv::{BcivDims, BcivStats};
use lpvid::{packed_len, Gram, Real};
use lpvid_host::arx::{fit, ArxOptions, Estimator, LambdaChoice, SigmaChoice};
use lpvid_host::systems::b6;

/// B6 training data as (u, y, p) rows in precision T.
fn rows<T: Real>() -> Vec<[T; 3]> {
    let (train, _, _) = b6(1);
    (0..train.len())
        .map(|k| {
            [
                T::of(train.u[(k, 0)]),
                T::of(train.y[(k, 0)]),
                T::of(train.p[(k, 0)]),
            ]
        })
        .collect()
}

fn updates<T: Real>(c: &mut Criterion, name: &str) {
    let data = rows::<T>();
    let arx = ArxDims::new(1, 1, 4, 2, 2).unwrap();
    let d = BcivDims::paper(arx).unwrap();
    let nt = d.n_theta();
    let mut theta = vec![T::ZERO; nt];
    theta[arx.index_a(1, 2).unwrap()] = T::of(0.8);
    theta[arx.index_b(0, 0, 2).unwrap()] = T::of(0.4);
    let mut group = c.benchmark_group(format!("bciv_update_{name}"));
    group.sample_size(50);

    // BC-IV statistics (zeta precomputed by a simulation window, as on the device)
    let mut st = BcivStats::new(
        d,
        vec![T::ZERO; d.storage_len()],
        vec![T::ZERO; d.window_len()],
    )
    .unwrap();
    let mut sim = ArxWindow::new(arx, vec![T::ZERO; arx.window_len()]).unwrap();
    let mut zetas = Vec::with_capacity(data.len());
    for (k, r) in data.iter().enumerate() {
        if k < arx.depth() {
            sim.push(&[r[0]], T::ZERO, &[r[2]]).unwrap();
            zetas.push(vec![T::ZERO; arx.chi_len()]);
            continue;
        }
        sim.simulate_step(&theta, &[r[0]], &[r[2]]).unwrap();
        let mut z = vec![T::ZERO; arx.chi_len()];
        sim.write_chi(&mut z).unwrap();
        zetas.push(z);
    }
    let mut k = 0usize;
    group.bench_function(
        BenchmarkId::new(
            "core BcivStats::update",
            "B6 21 params, 3 powers of sigma^2",
        ),
        |b| {
            b.iter(|| {
                let i = k % data.len();
                k += 1;
                let r = &data[i];
                black_box(st.update(&zetas[i], &[r[0]], r[1], &[r[2]]).unwrap())
            })
        },
    );

    // peer: plain least-squares statistics of the same regressor, sum [phi; y][phi; y]^T
    let mut g = Gram::new(nt + 1, vec![T::ZERO; packed_len(nt + 1)]).unwrap();
    let mut win = ArxWindow::new(arx, vec![T::ZERO; arx.window_len()]).unwrap();
    let mut w = vec![T::ZERO; nt + 1];
    let mut k = 0usize;
    group.bench_function(
        BenchmarkId::new("peer: LS Gram::update of [phi; y]", "B6 22 values"),
        |b| {
            b.iter(|| {
                let r = &data[k % data.len()];
                k += 1;
                win.push(&[r[0]], r[1], &[r[2]]).unwrap();
                if win.is_ready() {
                    win.write_regressor(&mut w[..nt]).unwrap();
                    w[nt] = r[1];
                    g.update(&w).unwrap();
                }
                black_box(g.count())
            })
        },
    );

    // the instrument side: one free-run simulation step (what refinement adds per sample)
    let mut sim = ArxWindow::new(arx, vec![T::ZERO; arx.window_len()]).unwrap();
    for r in &data[..arx.depth()] {
        sim.push(&[r[0]], T::ZERO, &[r[2]]).unwrap();
    }
    let mut k = 0usize;
    group.bench_function(
        BenchmarkId::new("peer: ArxWindow::simulate_step", "B6 instruments"),
        |b| {
            b.iter(|| {
                let r = &data[k % data.len()];
                k += 1;
                let y = sim.simulate_step(&theta, &[r[0]], &[r[2]]).unwrap();
                if !y.is_finite() || y.abs() > T::of(1e6) {
                    sim.clear();
                    for r in &data[..arx.depth()] {
                        sim.push(&[r[0]], T::ZERO, &[r[2]]).unwrap();
                    }
                }
                black_box(y)
            })
        },
    );
    group.finish();
}

fn bciv_update(c: &mut Criterion) {
    updates::<f32>(c, "f32");
    updates::<f64>(c, "f64");
}

fn arx_fit(c: &mut Criterion) {
    let (train, cal, _) = b6(1);
    let mut group = c.benchmark_group("arx_fit_b6");
    group.sample_size(10);
    let bc = ArxOptions::new(4, 2, 2);
    group.bench_function(
        BenchmarkId::new("BC-IV-LASSO", "sigma auto, lambda cv (lpvid arx default)"),
        |b| b.iter(|| black_box(fit(&train, Some(&cal), &bc).unwrap().report.iterations)),
    );
    let mut known = ArxOptions::new(4, 2, 2);
    known.sigma = SigmaChoice::Fixed(0.25);
    group.bench_function(
        BenchmarkId::new("peer: BC-IV-LASSO", "sigma known 0.25, lambda cv"),
        |b| b.iter(|| black_box(fit(&train, Some(&cal), &known).unwrap().report.iterations)),
    );
    let iv = ArxOptions::paper(4, 2, 2, Estimator::Iv);
    group.bench_function(BenchmarkId::new("peer: IV-LASSO", "paper recipe"), |b| {
        b.iter(|| black_box(fit(&train, Some(&cal), &iv).unwrap().report.iterations))
    });
    let mut ls = ArxOptions::new(4, 2, 2);
    ls.estimator = Estimator::Ls;
    ls.sigma = SigmaChoice::Fixed(0.0);
    ls.lambda = LambdaChoice::Fixed(0.0);
    group.bench_function(BenchmarkId::new("peer: LS", "full model, one pass"), |b| {
        b.iter(|| black_box(fit(&train, None, &ls).unwrap().report.train_cost))
    });
    group.finish();
}

criterion_group!(benches, bciv_update, arx_fit);
criterion_main!(benches);
