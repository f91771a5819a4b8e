//! The coordinate-descent Lasso engine of the core: l1 and l2,1 solutions agree with an
//! independent proximal-gradient (FISTA) reference, lambda_max gives zeros, warm-started
//! paths equal cold starts, f32 works, and — with a counting global allocator — the BC-IV
//! statistics updates and the solver allocate nothing.

use std::ops::ControlFlow;

use lpvid::arx::{ArxDims, ArxWindow};
use lpvid::bciv::{BcivDims, BcivStats};
use lpvid::lasso::{
    cross_from, refit, refit_work_len, work_len, CoordinateDescent, Dense, Leading, Penalty,
    Problem, Settings, SymMatrix,
};
use lpvid::stats::Gram;
use lpvid::{Error, Real};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

// ---------------------------------------------------------------- counting allocator

mod common;

use common::counting_alloc::{count_allocs, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

// ---------------------------------------------------------------- reference solver

fn normal(rng: &mut StdRng) -> f64 {
    let u1: f64 = rng.gen::<f64>().max(1e-300);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Random least-squares statistics: G = X^T X (q x q), C = Y^T X (l x q) with a sparse truth.
fn random_problem(n: usize, q: usize, l: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let x: Vec<f64> = (0..n * q)
        .map(|i| {
            normal(&mut rng)
                + if i % q == 1 {
                    0.5 * normal(&mut rng)
                } else {
                    0.0
                }
        })
        .collect();
    let mut truth = vec![0.0; l * q];
    for o in 0..l {
        for j in [0, 3, q - 2] {
            truth[o * q + j] = (1.0 + o as f64) * if j == 3 { -0.7 } else { 1.2 };
        }
    }
    let mut g = vec![0.0; q * q];
    let mut c = vec![0.0; l * q];
    for k in 0..n {
        let row = &x[k * q..(k + 1) * q];
        for i in 0..q {
            for j in 0..q {
                g[i * q + j] += row[i] * row[j];
            }
        }
        for o in 0..l {
            let y: f64 =
                (0..q).map(|j| row[j] * truth[o * q + j]).sum::<f64>() + 0.8 * normal(&mut rng);
            for j in 0..q {
                c[o * q + j] += y * row[j];
            }
        }
    }
    (g, c)
}

/// FISTA with adaptive restart on 1/2 tr(T G T^T) - tr(T C^T) + lam sum_j w_j pen(T[:, j]):
/// an independent reference (proximal gradient, not coordinate descent).
fn fista(g: &[f64], c: &[f64], l: usize, q: usize, lam: f64, w: &[f64], group: bool) -> Vec<f64> {
    // Lipschitz constant: largest eigenvalue of G by power iteration
    let mut v = vec![1.0; q];
    let mut lip = 0.0;
    for _ in 0..500 {
        let mut gv = vec![0.0; q];
        for i in 0..q {
            for j in 0..q {
                gv[i] += g[i * q + j] * v[j];
            }
        }
        let nrm = gv.iter().map(|x| x * x).sum::<f64>().sqrt();
        lip = nrm;
        v = gv.iter().map(|x| x / nrm).collect();
    }
    let step = 1.0 / (lip * 1.01);
    let prox = |z: &mut [f64]| {
        for j in 0..q {
            let thr = step * lam * w[j];
            if group {
                let nrm = (0..l).map(|o| z[o * q + j].powi(2)).sum::<f64>().sqrt();
                let f = if nrm > thr { 1.0 - thr / nrm } else { 0.0 };
                for o in 0..l {
                    z[o * q + j] *= f;
                }
            } else {
                for o in 0..l {
                    let x = z[o * q + j];
                    z[o * q + j] = x.signum() * (x.abs() - thr).max(0.0);
                }
            }
        }
    };
    let mut th = vec![0.0; l * q];
    let mut yv = th.clone();
    let mut t = 1.0f64;
    for _ in 0..200_000 {
        let mut z = yv.clone();
        for o in 0..l {
            for j in 0..q {
                let grad: f64 =
                    (0..q).map(|k| yv[o * q + k] * g[k * q + j]).sum::<f64>() - c[o * q + j];
                z[o * q + j] -= step * grad;
            }
        }
        prox(&mut z);
        let tn = (1.0 + (1.0 + 4.0 * t * t).sqrt()) / 2.0;
        let mut diff = 0.0f64;
        let mut restart = 0.0;
        for i in 0..l * q {
            diff = diff.max((z[i] - th[i]).abs());
            restart += (yv[i] - z[i]) * (z[i] - th[i]);
        }
        if restart > 0.0 {
            t = 1.0;
            yv = z.clone();
        } else {
            for i in 0..l * q {
                yv[i] = z[i] + (t - 1.0) / tn * (z[i] - th[i]);
            }
            t = tn;
        }
        th = z;
        if diff < 1e-14 {
            break;
        }
    }
    th
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

fn tight() -> Settings<f64> {
    Settings {
        tol: 1e-20,
        ..Settings::default()
    }
}

// ---------------------------------------------------------------- tests

#[test]
fn l1_matches_proximal_gradient_for_several_lambdas() {
    let (q, l) = (12, 1);
    let (g, c) = random_problem(40, q, l, 1);
    let gm = Dense::new(&g, q).unwrap();
    // adaptive-style weights with one unpenalised column
    let w: Vec<f64> = (0..q)
        .map(|j| if j == 5 { 0.0 } else { 0.5 + 0.1 * j as f64 })
        .collect();
    for weights in [None, Some(&w[..])] {
        let mut prob = Problem::new(&gm, &c, l, Penalty::L1).unwrap();
        if let Some(w) = weights {
            prob = prob.with_weights(w).unwrap();
        }
        let unit = vec![1.0; q];
        let wref = weights.unwrap_or(&unit);
        let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
        let mut th = vec![0.0; l * q];
        let lmax = cd.lambda_max(&prob, &mut th, &tight()).unwrap();
        for frac in [0.9, 0.5, 0.2, 0.05, 0.01] {
            let lam = lmax * frac;
            let mut th = vec![0.0; l * q];
            let fit = cd.solve(&prob, lam, &mut th, &tight()).unwrap();
            let reference = fista(&g, &c, l, q, lam, wref, false);
            let d = max_diff(&th, &reference);
            assert!(fit.converged, "{fit:?}");
            assert!(fit.kkt < 1e-9, "{fit:?}");
            assert!(d < 1e-7, "lambda {lam}: |cd - fista| = {d}");
            if frac == 0.9 && weights.is_none() {
                assert!(fit.active < q, "a large lambda must give a sparse solution");
            }
        }
    }
}

#[test]
fn group_lasso_matches_proximal_gradient() {
    let (q, l) = (10, 3);
    let (g, c) = random_problem(50, q, l, 2);
    let gm = Dense::new(&g, q).unwrap();
    let w: Vec<f64> = (0..q).map(|j| 1.0 + 0.2 * (j % 3) as f64).collect();
    let prob = Problem::new(&gm, &c, l, Penalty::Group)
        .unwrap()
        .with_weights(&w)
        .unwrap();
    let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
    let mut th = vec![0.0; l * q];
    let lmax = cd.lambda_max(&prob, &mut th, &tight()).unwrap();
    for frac in [0.7, 0.3, 0.1, 0.02] {
        let lam = lmax * frac;
        let mut th = vec![0.0; l * q];
        let fit = cd.solve(&prob, lam, &mut th, &tight()).unwrap();
        let reference = fista(&g, &c, l, q, lam, &w, true);
        let d = max_diff(&th, &reference);
        assert!(fit.converged && fit.kkt < 1e-9, "{fit:?}");
        assert!(d < 1e-7, "lambda {lam}: |cd - fista| = {d}");
        // whole columns are zero or non-zero together
        for j in 0..q {
            let nz = (0..l).filter(|o| th[o * q + j] != 0.0).count();
            assert!(nz == 0 || nz == l);
        }
    }
    // l1 on the same multi-output problem is l independent lassos
    let prob1 = Problem::new(&gm, &c, l, Penalty::L1)
        .unwrap()
        .with_weights(&w)
        .unwrap();
    let lam = 0.2 * lmax;
    let mut th = vec![0.0; l * q];
    cd.solve(&prob1, lam, &mut th, &tight()).unwrap();
    let reference = fista(&g, &c, l, q, lam, &w, false);
    assert!(max_diff(&th, &reference) < 1e-7);
}

#[test]
fn lambda_max_gives_zeros_and_just_below_does_not() {
    for penalty in [Penalty::L1, Penalty::Group] {
        let (q, l) = (8, 2);
        let (g, c) = random_problem(30, q, l, 3);
        let gm = Dense::new(&g, q).unwrap();
        let prob = Problem::new(&gm, &c, l, penalty).unwrap();
        let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
        let mut th = vec![1.0; l * q];
        let lmax = cd.lambda_max(&prob, &mut th, &tight()).unwrap();
        assert!(th.iter().all(|v| *v == 0.0));
        let mut th = vec![0.3; l * q]; // a warm start far away still lands on zero
        let fit = cd.solve(&prob, lmax, &mut th, &tight()).unwrap();
        assert!(th.iter().all(|v| v.abs() < 1e-12), "{th:?}");
        assert_eq!(fit.active, 0);
        let mut th = vec![0.0; l * q];
        let fit = cd.solve(&prob, lmax * 0.99, &mut th, &tight()).unwrap();
        assert_eq!(fit.active, 1);
    }
    // with an unpenalised column, lambda_max is computed after fitting it
    let (g, c) = random_problem(30, 6, 1, 4);
    let gm = Dense::new(&g, 6).unwrap();
    let w = [0.0, 1.0, 1.0, 1.0, 1.0, 1.0];
    let prob = Problem::new(&gm, &c, 1, Penalty::L1)
        .unwrap()
        .with_weights(&w)
        .unwrap();
    let mut cd = CoordinateDescent::new(1, 6, vec![0.0; work_len(1, 6)]).unwrap();
    let mut th = vec![0.0; 6];
    let lmax = cd.lambda_max(&prob, &mut th, &tight()).unwrap();
    assert!((th[0] - c[0] / g[0]).abs() < 1e-12);
    assert!(th[1..].iter().all(|v| *v == 0.0));
    let mut t2 = vec![0.0; 6];
    cd.solve(&prob, lmax, &mut t2, &tight()).unwrap();
    assert!(max_diff(&th, &t2) < 1e-12);
}

#[test]
fn warm_started_path_equals_cold_starts() {
    for (penalty, l) in [(Penalty::L1, 1), (Penalty::Group, 2)] {
        let q = 15;
        let (g, c) = random_problem(25, q, l, 5);
        let gm = Dense::new(&g, q).unwrap();
        let prob = Problem::new(&gm, &c, l, penalty).unwrap();
        let settings = Settings {
            n_lambda: 30,
            lambda_min_ratio: 1e-3,
            ..tight()
        };
        let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
        let mut path: Vec<(f64, Vec<f64>, usize)> = Vec::new();
        let mut th = vec![0.0; l * q];
        let n = cd
            .path(&prob, &settings, &mut th, |fit, theta| {
                assert!(fit.converged);
                path.push((fit.lambda, theta.to_vec(), fit.iterations));
                ControlFlow::Continue(())
            })
            .unwrap();
        assert_eq!(n, 30);
        assert!(path.windows(2).all(|w| w[1].0 < w[0].0));
        assert!((path[29].0 / path[0].0 - 1e-3).abs() < 1e-12);
        let (mut warm_iters, mut cold_iters) = (0, 0);
        let mut cold_cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
        for (lam, theta, it) in &path {
            let mut cold = vec![0.0; l * q];
            let fit = cold_cd.solve(&prob, *lam, &mut cold, &tight()).unwrap();
            assert!(
                max_diff(theta, &cold) < 1e-7,
                "lambda {lam}: {} {fit:?} warm iters {it}",
                max_diff(theta, &cold)
            );
            warm_iters += it;
            cold_iters += fit.iterations;
        }
        println!("{penalty:?}: sweeps warm {warm_iters}, cold {cold_iters}");
        assert!(warm_iters <= cold_iters);
        // the same grid through path_with, and an early stop
        let lambdas: Vec<f64> = path.iter().map(|p| p.0).collect();
        let mut th = vec![0.0; l * q];
        let mut k = 0;
        let visited = cd
            .path_with(&prob, &lambdas, &settings, &mut th, |fit, theta| {
                assert!(max_diff(theta, &path[fit.index].1) < 1e-7);
                k += 1;
                if k == 7 {
                    ControlFlow::Break(())
                } else {
                    ControlFlow::Continue(())
                }
            })
            .unwrap();
        assert_eq!(visited, 7);
    }
}

#[test]
fn refit_on_the_support_is_least_squares_on_it() {
    let (q, l) = (9, 2);
    let (g, c) = random_problem(40, q, l, 6);
    let gm = Dense::new(&g, q).unwrap();
    let prob = Problem::new(&gm, &c, l, Penalty::Group).unwrap();
    let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
    let mut th = vec![0.0; l * q];
    let lmax = cd.lambda_max(&prob, &mut th, &tight()).unwrap();
    cd.solve(&prob, 0.3 * lmax, &mut th, &tight()).unwrap();
    let support: Vec<usize> = (0..q).filter(|j| th[*j] != 0.0).collect();
    let mut work = vec![0.0; refit_work_len(q)];
    let k = refit(&prob, &mut th, &mut work).unwrap();
    assert_eq!(k, support.len());
    // residual gradient is zero on the support, theta zero off it
    for o in 0..l {
        for j in 0..q {
            if support.contains(&j) {
                let r: f64 =
                    c[o * q + j] - (0..q).map(|i| th[o * q + i] * g[i * q + j]).sum::<f64>();
                assert!(r.abs() < 1e-9 * c.iter().fold(1.0f64, |a, x| a.max(x.abs())));
            } else {
                assert_eq!(th[o * q + j], 0.0);
            }
        }
    }
    // an unpenalised lambda = 0 solve with coordinate descent reaches the same point
    let w: Vec<f64> = (0..q)
        .map(|j| {
            if support.contains(&j) {
                0.0
            } else {
                f64::INFINITY
            }
        })
        .collect();
    let pw = Problem::new(&gm, &c, l, Penalty::L1)
        .unwrap()
        .with_weights(&w)
        .unwrap();
    let mut t2 = vec![0.0; l * q];
    let fit = cd.solve(&pw, 0.0, &mut t2, &tight()).unwrap();
    assert!(fit.converged);
    assert!(max_diff(&th, &t2) < 1e-8);
    // singular restricted G
    let gs = [1.0, 1.0, 1.0, 1.0];
    let gsm = Dense::new(&gs, 2).unwrap();
    let cs = [1.0, 1.0];
    let ps = Problem::new(&gsm, &cs, 1, Penalty::L1).unwrap();
    let mut ts = [1.0, 1.0];
    let mut ws = vec![0.0; refit_work_len(2)];
    assert_eq!(refit(&ps, &mut ts, &mut ws), Err(Error::Singular));
    assert_eq!(ts, [1.0, 1.0]);
}

#[test]
fn gram_statistics_feed_the_engine_directly() {
    // PBSID-style: second moments of w = [phi; y] in a packed Gram; the leading block is G,
    // the next rows are C.
    let (q, l, n) = (6, 2, 80);
    let mut rng = StdRng::seed_from_u64(7);
    let mut gram = Gram::new(q + l, vec![0.0; (q + l) * (q + l + 1) / 2]).unwrap();
    let mut dense = vec![0.0; q * q];
    let mut cross = vec![0.0; l * q];
    for _ in 0..n {
        let mut w: Vec<f64> = (0..q).map(|_| normal(&mut rng)).collect();
        for o in 0..l {
            let y = w[o] - 0.5 * w[q - 1] + 0.1 * normal(&mut rng);
            w.push(y);
        }
        gram.update(&w).unwrap();
        for i in 0..q {
            for j in 0..q {
                dense[i * q + j] += w[i] * w[j];
            }
            for o in 0..l {
                cross[o * q + i] += w[q + o] * w[i];
            }
        }
    }
    let lead = Leading::new(&gram, q).unwrap();
    assert_eq!(SymMatrix::<f64>::dim(&lead), q);
    let mut c = vec![0.0; l * q];
    cross_from(&gram, q, l, &mut c).unwrap();
    assert!(max_diff(&c, &cross) < 1e-9);
    let p1 = Problem::new(&lead, &c, l, Penalty::Group).unwrap();
    let dm = Dense::new(&dense, q).unwrap();
    let p2 = Problem::new(&dm, &cross, l, Penalty::Group).unwrap();
    let mut cd = CoordinateDescent::new(l, q, vec![0.0; work_len(l, q)]).unwrap();
    let (mut t1, mut t2) = (vec![0.0; l * q], vec![0.0; l * q]);
    cd.solve(&p1, 5.0, &mut t1, &tight()).unwrap();
    cd.solve(&p2, 5.0, &mut t2, &tight()).unwrap();
    assert!(max_diff(&t1, &t2) < 1e-9);
}

#[test]
fn f32_engine_works() {
    let (q, l) = (10, 1);
    let (g, c) = random_problem(40, q, l, 8);
    let g32: Vec<f32> = g.iter().map(|v| *v as f32).collect();
    let c32: Vec<f32> = c.iter().map(|v| *v as f32).collect();
    let gm = Dense::new(&g32, q).unwrap();
    let prob = Problem::new(&gm, &c32, l, Penalty::L1).unwrap();
    let mut cd = CoordinateDescent::new(l, q, [0.0f32; work_len(1, 10)]).unwrap();
    let mut th = [0.0f32; 10];
    let lmax = cd.lambda_max(&prob, &mut th, &Settings::default()).unwrap();
    let lam = 0.1 * lmax;
    let fit = cd.solve(&prob, lam, &mut th, &Settings::default()).unwrap();
    assert!(fit.converged, "{fit:?}");
    let reference = fista(&g, &c, l, q, lam as f64, &vec![1.0; q], false);
    let scale = reference.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    let th64: Vec<f64> = th.iter().map(|v| *v as f64).collect();
    let d = max_diff(&th64, &reference);
    assert!(d < 1e-4 * scale, "f32 vs reference {d}");
    assert!(Settings::<f32>::default().tol as f64 > Settings::<f64>::default().tol);
}

#[test]
fn bad_problems_are_errors() {
    let g = [2.0, 0.1, 0.1, 1.0];
    let gm = Dense::new(&g, 2).unwrap();
    assert!(Dense::new(&g[..3], 2).is_err());
    assert!(Problem::new(&gm, &[1.0, f64::NAN], 1, Penalty::L1).is_err());
    assert!(Problem::new(&gm, &[1.0], 1, Penalty::L1).is_err());
    assert!(Problem::new(&gm, &[1.0, 2.0], 0, Penalty::L1).is_err());
    let prob = Problem::new(&gm, &[1.0, 2.0], 1, Penalty::L1).unwrap();
    assert!(prob.with_weights(&[1.0, -1.0]).is_err());
    assert!(prob.with_weights(&[1.0, f64::NAN]).is_err());
    assert!(prob.with_weights(&[1.0]).is_err());
    let mut cd = CoordinateDescent::new(1, 2, vec![0.0; 4]).unwrap();
    let mut th = [0.0, 0.0];
    let s = Settings::default();
    assert!(cd.solve(&prob, -1.0, &mut th, &s).is_err());
    assert!(cd.solve(&prob, f64::NAN, &mut th, &s).is_err());
    assert!(cd.solve(&prob, 0.1, &mut [f64::NAN, 0.0], &s).is_err());
    assert!(cd.solve(&prob, 0.1, &mut [0.0; 3], &s).is_err());
    let bad = Settings {
        n_lambda: 0,
        ..Settings::default()
    };
    assert!(cd
        .path(&prob, &bad, &mut th, |_, _| ControlFlow::Continue(()))
        .is_err());
    let bad = Settings {
        lambda_min_ratio: 0.0,
        ..Settings::default()
    };
    assert!(cd
        .path(&prob, &bad, &mut th, |_, _| ControlFlow::Continue(()))
        .is_err());
    let mut small = CoordinateDescent::new(1, 3, vec![0.0; 6]).unwrap();
    assert_eq!(
        small.solve(&prob, 0.1, &mut [0.0; 3], &s),
        Err(Error::Mismatch)
    );
    assert!(CoordinateDescent::<f64, _>::new(1, 2, vec![0.0; 3]).is_err());
    let gnan = [f64::NAN, 0.0, 0.0, 1.0];
    let gm = Dense::new(&gnan, 2).unwrap();
    let prob = Problem::new(&gm, &[1.0, 2.0], 1, Penalty::L1).unwrap();
    assert!(cd.solve(&prob, 0.1, &mut th, &s).is_err());
    // max_iter reached is reported, not an error
    let (g, c) = random_problem(20, 8, 1, 9);
    let gm = Dense::new(&g, 8).unwrap();
    let prob = Problem::new(&gm, &c, 1, Penalty::L1).unwrap();
    let mut cd = CoordinateDescent::new(1, 8, vec![0.0; 16]).unwrap();
    let few = Settings {
        max_iter: 2,
        ..tight()
    };
    let fit = cd.solve(&prob, 0.0, &mut [0.0; 8], &few).unwrap();
    assert!(!fit.converged);
    assert_eq!(fit.iterations, 2);
}

#[test]
fn zero_allocations_in_bciv_updates_and_the_solver() {
    // data and every buffer prepared up front
    let arx = ArxDims::new(1, 1, 4, 2, 2).unwrap();
    let d = BcivDims::paper(arx).unwrap();
    let mut rng = StdRng::seed_from_u64(10);
    let n = 2000;
    let data: Vec<(f64, f64, f64)> = {
        let mut yo = 0.0;
        (0..n)
            .map(|k| {
                let po = (0.1 * k as f64).sin() + 0.2 * normal(&mut rng);
                let u: f64 = rng.gen();
                yo = -0.8 * po * po * yo + 0.4 * po * po * u;
                (
                    u,
                    yo + 0.06 * normal(&mut rng),
                    po + 0.25 * normal(&mut rng),
                )
            })
            .collect()
    };
    let mut st = BcivStats::new(d, vec![0.0; d.storage_len()], vec![0.0; d.window_len()]).unwrap();
    let mut sim = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    let model = {
        let mut m = vec![0.0; d.n_theta()];
        m[arx.index_a(1, 2).unwrap()] = 0.8;
        m[arx.index_b(0, 0, 2).unwrap()] = 0.4;
        m
    };
    let nt = d.n_theta();
    let mut zeta = vec![0.0; arx.chi_len()];
    let mut psi = vec![0.0; d.n_z() * nt];
    let mut h = vec![0.0; nt * nt];
    let mut g = vec![0.0; nt];
    let mut theta = vec![0.0; nt];
    let mut work = vec![0.0; work_len(1, nt)];
    let mut rwork = vec![0.0; refit_work_len(nt)];
    let mut best = vec![0.0; nt];
    let lambdas = [1e-3, 1e-4, 1e-5];

    let (res, allocs) = count_allocs(|| -> Result<(usize, u64), Error> {
        for (k, (u, y, p)) in data.iter().enumerate() {
            if k < arx.depth() {
                sim.push(&[*u], *y, &[*p])?;
                st.update(&zeta, &[*u], *y, &[*p])?;
                continue;
            }
            sim.simulate_step(&model, &[*u], &[*p])?;
            sim.write_chi(&mut zeta)?;
            st.update(&zeta, &[*u], *y, &[*p])?;
        }
        // a rejected sample allocates nothing either
        assert!(st.update(&zeta, &[f64::NAN], 0.0, &[0.0]).is_err());
        st.normal_equations(0.0625, &mut psi, &mut h, &mut g)?;
        let hm = Dense::new(&h, nt)?;
        let prob = Problem::new(&hm, &g, 1, Penalty::L1)?;
        let mut cd = CoordinateDescent::new(1, nt, &mut work[..])?;
        let settings = Settings {
            n_lambda: 20,
            ..Settings::default()
        };
        let mut best_cost = f64::MAX;
        let mut points = cd.path(&prob, &settings, &mut theta, |_, th| {
            // what a cross-validation does: score each point on (here: the same) statistics
            let j = st.civ_cost(0.0625, th).unwrap_or(f64::MAX);
            if j < best_cost {
                best_cost = j;
                best.copy_from_slice(th);
            }
            ControlFlow::Continue(())
        })?;
        points += cd.path_with(&prob, &lambdas, &settings, &mut theta, |_, _| {
            ControlFlow::Continue(())
        })?;
        theta.copy_from_slice(&best);
        refit(&prob, &mut theta, &mut rwork)?;
        // the group penalty through the same engine
        let probg = Problem::new(&hm, &g, 1, Penalty::Group)?;
        cd.solve(&probg, 1e-4, &mut theta, &settings)?;
        Ok((points, st.count()))
    });
    let (points, count) = res.unwrap();
    assert_eq!(count, (n - arx.depth()) as u64);
    assert_eq!(points, 23);
    assert_eq!(allocs, 0, "the core allocated {allocs} times");
    // sanity: the counter does count
    let (_, a) = count_allocs(|| vec![1u8; 16]);
    assert!(a >= 1);
}

/// Generic smoke test: the engine compiles and runs for any `Real`.
fn generic_solve<T: Real>() -> T {
    let g = [T::of(2.0), T::of(0.5), T::of(0.5), T::of(1.0)];
    let c = [T::of(1.0), T::of(-1.0)];
    let gm = Dense::new(&g, 2).unwrap();
    let prob = Problem::new(&gm, &c, 1, Penalty::L1).unwrap();
    let mut cd = CoordinateDescent::new(1, 2, [T::ZERO; 4]).unwrap();
    let mut th = [T::ZERO; 2];
    cd.solve(&prob, T::of(0.1), &mut th, &Settings::default())
        .unwrap();
    th[0]
}

#[test]
fn generic_over_real() {
    let a = generic_solve::<f64>();
    let b = generic_solve::<f32>();
    assert!((a - b as f64).abs() < 1e-6);
}
