//! Benchmarks of the H-infinity observer design (issue 5): the LMI (30) solved with
//! clarabel for n = 2 (B2, 2 vertices) and n = 4 (4 states, 2 scheduling signals, 4
//! vertices), alone and with the independent certificate on the default grid, compared in
//! the same run with
//! - the least-squares step the observer starts from (eq. (24)-(25): [A, B] by least
//!   squares from the state sequence and the residual covariances; the least-squares gain
//!   of the spine is one least-squares problem of the same kind), and
//! - a Riccati-based frozen-point design: the steady-state Kalman predictor gain at every
//!   vertex (filter DARE by fixed-point iteration), which gives no guarantee between the
//!   vertices.
//!
//! Figures go to docs/bench-observer.md.

use criterion::{black_box, criterion_group, criterion_main, Criterion};
use lpvid_host::lpvss::{LpvSs, Signals};
use lpvid_host::observer::{
    align_states, design_hinf, noise_covariance, residual_model, HinfOptions, NoiseCov, SchedBox,
};
use lpvid_host::pbsid::{fit, Order, PbsidOptions, Reg};
use lpvid_host::refine::refine_output_error;
use lpvid_host::systems;
use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};

/// Steady-state Kalman predictor gain of the frozen system (A, C, Q, S, R): the filter DARE
/// X = A X A' + Q - (A X C' + S)(C X C' + R)^-1 (A X C' + S)' by fixed-point iteration.
fn kalman_gain(a: &DMatrix<f64>, c: &DMatrix<f64>, nc: &NoiseCov) -> (DMatrix<f64>, usize) {
    let mut x = nc.q.clone();
    for it in 0..10_000 {
        let g = a * &x * c.transpose() + &nc.s;
        let h = c * &x * c.transpose() + &nc.r;
        let hinv = h.try_inverse().expect("C X C' + R invertible");
        let next = a * &x * a.transpose() + &nc.q - &g * &hinv * g.transpose();
        // keep X symmetric: asymmetric rounding grows through an unstable A
        let next = (&next + next.transpose()) * 0.5;
        let diff = (&next - &x).amax();
        x = next;
        if diff <= 1e-12 * x.amax().max(1e-300) {
            let g = a * &x * c.transpose() + &nc.s;
            let h = c * &x * c.transpose() + &nc.r;
            return (g * h.try_inverse().unwrap(), it + 1);
        }
    }
    panic!("DARE iteration did not converge");
}

fn frozen_kalman(model: &LpvSs, nc: &NoiseCov, sbox: &SchedBox) -> Vec<DMatrix<f64>> {
    sbox.vertices()
        .iter()
        .map(|mu| kalman_gain(&model.a_at(mu), &model.c[0], nc).0)
        .collect()
}

/// n = 2: B2 identified at 25 dB (p = 5, Tikhonov-GCV, order 2), its (24)-(25) residual
/// model and states, and the data's scheduling box (2 vertices).
fn case_n2() -> (LpvSs, NoiseCov, SchedBox, Signals, DMatrix<f64>, usize) {
    let exp = systems::b2(75, 25.0, 1);
    let mut o = PbsidOptions::new(5);
    o.reg = Reg::TikhonovGcv;
    o.order = Order::Fixed(2);
    let f = fit(&exp.train, &o).expect("fit");
    let states = f.states.clone().expect("states");
    let (m, nc) = residual_model(&f.model, &exp.train, &states, 5).expect("residuals");
    let sbox = SchedBox::from_signals(&["p1".to_string()], &exp.train);
    (m, nc, sbox, exp.train, states, 5)
}

/// n = 4 with two scheduling signals (4 vertices): B3's A, B, C with an extra small A^(3)
/// scheduled by p2; simulated (process noise 0.1 I, measurement noise 0.25 I, N = 250) so
/// that the least-squares step has a true state sequence to work from.
fn case_n4() -> (LpvSs, NoiseCov, SchedBox, Signals, DMatrix<f64>, usize) {
    let mut m = systems::b3_truth();
    m.a.push(DMatrix::from_fn(4, 4, |i, j| {
        if (i + j) % 3 == 0 {
            0.05
        } else {
            -0.03
        }
    }));
    m.b.push(DMatrix::zeros(4, 2));
    m.k = vec![DMatrix::zeros(4, 2); 3];
    let n_s = 250;
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    let mut gauss = move || -> f64 {
        // Box-Muller
        let (u1, u2): (f64, f64) = (rng.gen::<f64>().max(1e-300), rng.gen());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    };
    let mut sig = Signals {
        u: DMatrix::zeros(n_s, 2),
        y: DMatrix::zeros(n_s, 2),
        p: DMatrix::zeros(n_s, 2),
    };
    let mut x = DVector::<f64>::zeros(4);
    let mut states = DMatrix::<f64>::zeros(4, n_s + 1);
    for k in 0..n_s {
        sig.p[(k, 0)] = 0.5 + (k as f64).sin();
        sig.p[(k, 1)] = (0.3 * k as f64).cos();
        for j in 0..2 {
            sig.u[(k, j)] = gauss();
        }
        states.set_column(k, &x);
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        let y = &m.c[0] * &x + DVector::from_fn(2, |_, _| 0.5 * gauss());
        sig.y.set_row(k, &y.transpose());
        x = m.a_at(&mu) * &x
            + lpvid_host::lpvss::scheduled(&m.b, &mu) * &u
            + DVector::from_fn(4, |_, _| 0.1f64.sqrt() * gauss());
    }
    states.set_column(n_s, &x);
    let (mr, nc) = residual_model(&m, &sig, &states, 0).expect("residuals");
    let sbox = SchedBox::from_signals(&["p1".to_string(), "p2".to_string()], &sig);
    (mr, nc, sbox, sig, states, 0)
}

fn benches(c: &mut Criterion) {
    let mut group = c.benchmark_group("observer");
    group.sample_size(30);
    for (name, case) in [("n2_v2", case_n2()), ("n4_v4", case_n4())] {
        let (m, nc, sbox, sig, states, past) = case;
        let solve_only = HinfOptions {
            grid: 2,
            ..Default::default()
        };
        let d = design_hinf(&m, &nc, &sbox, &solve_only).expect("design");
        let full = design_hinf(&m, &nc, &sbox, &HinfOptions::default()).expect("design");
        eprintln!(
            "{name}: n = {}, {} vertices, gamma = {:.4e}, clarabel {} in {} iterations, clarabel's own solve time {:.3} ms; certificate on {} grid points: ok = {}",
            m.n(),
            d.vertices.len(),
            d.gamma,
            d.solver_status,
            d.iterations,
            d.solve_time * 1e3,
            full.certificate.grid_points,
            full.certificate.ok()
        );
        group.bench_function(format!("lmi_solve_{name}"), |b| {
            b.iter(|| design_hinf(black_box(&m), &nc, &sbox, &solve_only).unwrap())
        });
        group.bench_function(format!("lmi_solve_and_certificate_{name}"), |b| {
            b.iter(|| design_hinf(black_box(&m), &nc, &sbox, &HinfOptions::default()).unwrap())
        });
        group.bench_function(format!("least_squares_24_25_{name}"), |b| {
            b.iter(|| residual_model(black_box(&m), &sig, &states, past).unwrap())
        });
        group.bench_function(format!("riccati_frozen_vertices_{name}"), |b| {
            b.iter(|| frozen_kalman(black_box(&m), &nc, &sbox))
        });
    }
    group.finish();
}

/// The refined path of Table 1 (B2, p = 5, 100 dB, BPDN-SV, order 2): the output-error
/// refinement (Levenberg-Marquardt, at most 50 iterations) and the state alignment with the
/// residuals (25) that precede the LMI when `--refine` is given.
fn benches_refined(c: &mut Criterion) {
    let exp = systems::b2(75, 100.0, 1000);
    let mut o = PbsidOptions::new(5);
    o.reg = Reg::BpdnSv;
    o.order = Order::Fixed(2);
    let f = fit(&exp.train, &o).expect("fit");
    let states = f.states.clone().expect("states");
    let r = refine_output_error(&f.model, &exp.train, true, 50);
    eprintln!(
        "refine B2 p=5 100 dB: MSE {:.3e} -> {:.3e} in {} iterations",
        r.mse_before, r.mse_after, r.iterations
    );
    let mut group = c.benchmark_group("observer_refined");
    group.sample_size(20);
    group.bench_function("refine_output_error_b2_p5", |b| {
        b.iter(|| refine_output_error(black_box(&f.model), &exp.train, true, 50))
    });
    group.bench_function("align_states_and_25_b2_p5", |b| {
        b.iter(|| {
            let x = align_states(black_box(&r.model), &exp.train, &states, 5).unwrap();
            noise_covariance(&r.model, &exp.train, &x, 5).unwrap()
        })
    });
    group.finish();
}

criterion_group!(observer, benches, benches_refined);
criterion_main!(observer);
