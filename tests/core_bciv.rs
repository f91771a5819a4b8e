//! BC-IV statistics of the core (BC-IV paper, section 5): the Hermite correction is
//! unbiased (Monte-Carlo), statistics merge, bad samples leave no trace, the costs computed
//! from statistics equal the costs computed from data, and on the B6 system the
//! bias-corrected estimate is consistent where plain IV is not. With a counting global
//! allocator: the f32 device path (two scheduling signals, noise ratios, merge, Psi, the
//! normal equations, the cost, the Lasso path and refit) allocates nothing (the f64 path:
//! tests/core_lasso.rs).

use std::ops::ControlFlow;

use lpvid::arx::{write_basis, ArxDims, ArxWindow};
use lpvid::bciv::{BcivDims, BcivStats};
use lpvid::lasso::{
    refit, refit_work_len, work_len, CoordinateDescent, Dense, Penalty, Problem, Settings,
};
use lpvid::{Error, Real};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

mod common;
use common::counting_alloc::{count_allocs, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

type Stats<T> = BcivStats<T, Vec<T>, Vec<T>>;

fn new_stats<T: Real>(d: BcivDims) -> Stats<T> {
    BcivStats::new(
        d,
        vec![T::ZERO; d.storage_len()],
        vec![T::ZERO; d.window_len()],
    )
    .unwrap()
}

fn normal(rng: &mut StdRng) -> f64 {
    // Box-Muller
    let u1: f64 = rng.gen::<f64>().max(1e-300);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

fn kron(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter()
        .flat_map(|x| b.iter().map(move |y| x * y))
        .collect()
}

/// E[Psi(sigma^2)] = E[Omega] with Omega = sum z(k) [chi(k) (x) pbasis(p_o(k))]^T (condition
/// (12) of the paper), checked by Monte-Carlo over the scheduling noise for one and for two
/// scheduling signals (independent noise, ratio rho_2 = 0.5: the factors multiply).
fn hermite_monte_carlo(s: usize, ng: usize, ngz: usize, rho: &[f64]) {
    let arx = ArxDims::new(1, s, 1, 0, ng).unwrap();
    let nzeta = 2;
    let d = BcivDims::new(arx, nzeta, ngz).unwrap();
    let (nz, nt) = (d.n_z(), d.n_theta());
    let sigma = 0.3f64;
    let n = 400;
    let runs = 400;
    let mut rng = StdRng::seed_from_u64(11 + s as u64);
    // fixed noise-free data: chi, zeta, p_o (independent of eta)
    let chi: Vec<Vec<f64>> = (0..n).map(|_| vec![normal(&mut rng), rng.gen()]).collect();
    let zeta: Vec<Vec<f64>> = (0..n).map(|_| vec![normal(&mut rng), rng.gen()]).collect();
    let po: Vec<Vec<f64>> = (0..n)
        .map(|_| (0..s).map(|_| 1.2 * normal(&mut rng)).collect())
        .collect();
    let nbas = arx.n_basis().unwrap();
    let nbz = nz / nzeta;
    let mut mean_diff = vec![0.0; nz * nt];
    let mut mean_bias = vec![0.0; nz * nt];
    let mut mean_sq = vec![0.0; nz * nt];
    let mut psi = vec![0.0; nz * nt];
    let mut m0 = vec![0.0; nz * nt];
    for _ in 0..runs {
        let mut st = new_stats::<f64>(d);
        st.set_noise_ratios(rho).unwrap();
        let mut omega = vec![0.0; nz * nt];
        for k in 0..n {
            let p: Vec<f64> = (0..s)
                .map(|i| po[k][i] + sigma * rho[i].sqrt() * normal(&mut rng))
                .collect();
            st.accumulate(&zeta[k], &chi[k], 0.0, &p).unwrap();
            let mut bz = vec![0.0; nbz];
            write_basis(s, ngz, &p, &mut bz).unwrap();
            let mut bo = vec![0.0; nbas];
            write_basis(s, ng, &po[k], &mut bo).unwrap();
            let z = kron(&zeta[k], &bz);
            let phio = kron(&chi[k], &bo);
            for a in 0..nz {
                for b in 0..nt {
                    omega[a * nt + b] += z[a] * phio[b];
                }
            }
        }
        st.eval_psi(sigma * sigma, &mut psi).unwrap();
        st.eval_psi(0.0, &mut m0).unwrap();
        assert_eq!(&m0[..], st.moment(0).unwrap());
        for i in 0..nz * nt {
            let dlt = (psi[i] - omega[i]) / n as f64;
            mean_diff[i] += dlt / runs as f64;
            mean_sq[i] += dlt * dlt / runs as f64;
            mean_bias[i] += (m0[i] - omega[i]) / n as f64 / runs as f64;
        }
    }
    // every entry of the mean difference within 4.5 standard errors of zero, and the
    // uncorrected bias clearly larger
    let mut worst: f64 = 0.0;
    for i in 0..nz * nt {
        let var = (mean_sq[i] - mean_diff[i] * mean_diff[i]).max(0.0);
        let se = (var / runs as f64).sqrt() + 1e-12;
        worst = worst.max(mean_diff[i].abs() / se);
    }
    let bias = mean_bias.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    let resid = mean_diff.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    println!("s = {s}: worst |E[Psi - Omega]| / se = {worst:.2}, max bias {bias:.4}, max residual {resid:.5}");
    assert!(worst < 4.5, "Hermite correction biased: {worst}");
    assert!(bias > 3.0 * resid, "bias {bias} vs residual {resid}");
}

#[test]
fn hermite_correction_is_unbiased_one_signal() {
    hermite_monte_carlo(1, 2, 2, &[1.0]);
}

#[test]
fn hermite_correction_is_unbiased_two_signals() {
    hermite_monte_carlo(2, 2, 1, &[1.0, 0.5]);
}

/// The B6 data-generating system (BENCHMARKS.md B6) in our sign convention:
/// y_o(k) = -a_{1,2} p_o^2 y_o(k-1) + b_{0,2} p_o^2 u(k) with a_{1,2} = +0.8, b_{0,2} = 0.4.
struct B6 {
    u: Vec<f64>,
    y: Vec<f64>,
    p: Vec<f64>,
}

fn b6(n: usize, rng: &mut StdRng, sigma_eta: f64) -> B6 {
    let mut yo = 0.0;
    let (mut u, mut y, mut p) = (vec![], vec![], vec![]);
    for k in 0..n {
        let po = (0.1 * k as f64).sin() + 0.2 * normal(rng);
        let uk: f64 = rng.gen();
        yo = -0.8 * po * po * yo + 0.4 * po * po * uk;
        u.push(uk);
        y.push(yo + 0.06 * normal(rng));
        p.push(po + sigma_eta * normal(rng));
    }
    B6 { u, y, p }
}

fn b6_dims() -> ArxDims {
    ArxDims::new(1, 1, 4, 2, 2).unwrap()
}

fn true_theta() -> Vec<f64> {
    let d = b6_dims();
    let mut th = vec![0.0; d.n_theta().unwrap()];
    th[d.index_a(1, 2).unwrap()] = 0.8;
    th[d.index_b(0, 0, 2).unwrap()] = 0.4;
    th
}

/// Accumulate the BC-IV statistics of a data set with instruments simulated from `model`
/// (section 4: zeta(k) = [-yhat(k-1).., u(k)..], yhat the free-run simulation on the
/// measured, noisy scheduling).
fn accumulate<T: Real>(data: &B6, model: &[f64]) -> Stats<T> {
    let arx = b6_dims();
    let d = BcivDims::paper(arx).unwrap();
    let mut st = new_stats::<T>(d);
    let model_t: Vec<T> = model.iter().map(|v| T::of(*v)).collect();
    let mut sim = ArxWindow::new(arx, vec![T::ZERO; arx.window_len()]).unwrap();
    let mut zeta = vec![T::ZERO; arx.chi_len()];
    for k in 0..data.u.len() {
        let (u, p, y) = ([T::of(data.u[k])], [T::of(data.p[k])], T::of(data.y[k]));
        if k < arx.depth() {
            sim.push(&u, y, &p).unwrap();
            assert!(!st.update(&zeta, &u, y, &p).unwrap());
            continue;
        }
        sim.simulate_step(&model_t, &u, &p).unwrap();
        sim.write_chi(&mut zeta).unwrap();
        assert!(st.update(&zeta, &u, y, &p).unwrap());
    }
    st
}

/// Unpenalised minimiser of the bias-corrected cost J_CIV(theta, 0, N) at sigma^2 (the
/// paper's de-biased refit, section 5.2) on the full support.
fn estimate<T: Real>(st: &Stats<T>, sigma2: T) -> Vec<T> {
    estimate_on(st, sigma2, None)
}

/// The same, restricted to `support` (None: every column).
fn estimate_on<T: Real>(st: &Stats<T>, sigma2: T, support: Option<&[usize]>) -> Vec<T> {
    let d = st.dims();
    let (nz, nt) = (d.n_z(), d.n_theta());
    let mut psi = vec![T::ZERO; nz * nt];
    let mut h = vec![T::ZERO; nt * nt];
    let mut g = vec![T::ZERO; nt];
    st.normal_equations(sigma2, &mut psi, &mut h, &mut g)
        .unwrap();
    let hm = Dense::new(&h, nt).unwrap();
    // unpenalised columns form the support, +inf weights exclude the others
    let w: Vec<T> = (0..nt)
        .map(|j| match support {
            Some(sup) if !sup.contains(&j) => T::of(f64::INFINITY),
            _ => T::ZERO,
        })
        .collect();
    let prob = Problem::new(&hm, &g, 1, Penalty::L1)
        .unwrap()
        .with_weights(&w)
        .unwrap();
    let mut theta = vec![T::ZERO; nt];
    let mut work = vec![T::ZERO; refit_work_len(nt)];
    let k = refit(&prob, &mut theta, &mut work).unwrap();
    assert_eq!(k, support.map_or(nt, |s| s.len()));
    theta
}

#[test]
fn b6_bias_corrected_iv_is_consistent_plain_iv_is_not() {
    let mut rng = StdRng::seed_from_u64(2017);
    let d = b6_dims();
    let ia = d.index_a(1, 2).unwrap();
    let ib = d.index_b(0, 0, 2).unwrap();
    let sup = [ia, ib];
    let runs = 5;
    let (mut a_bc, mut a_iv, mut b_bc, mut a_full) = (0.0, 0.0, 0.0, 0.0);
    for _ in 0..runs {
        let data = b6(8000, &mut rng, 0.25);
        let st = accumulate::<f64>(&data, &true_theta());
        // the refit on the true structure (what BC-IV-LASSO selects), and the full model
        let th_bc = estimate_on(&st, 0.25 * 0.25, Some(&sup));
        let th_iv = estimate_on(&st, 0.0, Some(&sup));
        let th_full = estimate(&st, 0.25 * 0.25);
        println!(
            "run: a12 BC-IV {:.4}, IV {:.4}, BC-IV full support {:.4}",
            th_bc[ia], th_iv[ia], th_full[ia]
        );
        a_bc += th_bc[ia] / runs as f64;
        b_bc += th_bc[ib] / runs as f64;
        a_iv += th_iv[ia] / runs as f64;
        a_full += th_full[ia] / runs as f64;
    }
    println!("mean a12: BC-IV {a_bc:.4}, IV {a_iv:.4}, full {a_full:.4}; b02 BC-IV {b_bc:.4}");
    assert!((a_bc - 0.8).abs() < 0.04, "BC-IV a12 {a_bc}");
    assert!((b_bc - 0.4).abs() < 0.04, "BC-IV b02 {b_bc}");
    assert!(
        (a_iv - 0.8).abs() > 0.08,
        "plain IV should be biased: {a_iv}"
    );
    // the over-parametrised 21-parameter BC-IV is consistent too, with a larger variance
    assert!(
        (a_full - 0.8).abs() < 0.1,
        "BC-IV full support a12 {a_full}"
    );
}

#[test]
fn b6_sigma_search_on_calibration_statistics() {
    // Section 5.3: theta(sigma) from training statistics, J_CIV(theta(sigma), 0, N_c) on
    // calibration statistics; the grid minimum sits near the true sigma = 0.25.
    let mut rng = StdRng::seed_from_u64(99);
    let runs = 4;
    let grid: Vec<f64> = (0..=20).map(|i| 0.025 * i as f64).collect();
    let mut mean_best = 0.0;
    for _ in 0..runs {
        let train = accumulate::<f64>(&b6(8000, &mut rng, 0.25), &true_theta());
        let cal = accumulate::<f64>(&b6(1000, &mut rng, 0.25), &true_theta());
        let mut best = (f64::MAX, 0.0);
        let d = b6_dims();
        let sup = [d.index_a(1, 2).unwrap(), d.index_b(0, 0, 2).unwrap()];
        for s in &grid {
            let th = estimate_on(&train, s * s, Some(&sup));
            let j = cal.civ_cost(s * s, &th).unwrap();
            if j < best.0 {
                best = (j, *s);
            }
        }
        mean_best += best.1 / runs as f64;
    }
    println!("mean sigma from the calibration grid: {mean_best:.3}");
    assert!((mean_best - 0.25).abs() <= 0.05, "sigma {mean_best}");
}

#[test]
fn costs_from_statistics_equal_costs_from_data() {
    let mut rng = StdRng::seed_from_u64(5);
    let data = b6(600, &mut rng, 0.25);
    let model: Vec<f64> = true_theta().iter().map(|v| v * 0.9 + 0.01).collect();
    let st = accumulate::<f64>(&data, &model);
    let arx = b6_dims();
    let (nz, nt) = (st.dims().n_z(), st.dims().n_theta());
    // explicit z(k), phi(k) from the data
    let mut sim = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    let mut win = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    let theta: Vec<f64> = (0..nt).map(|i| ((i * 7 % 5) as f64 - 2.0) * 0.1).collect();
    let mut r_iv = vec![0.0; nz];
    let mut n = 0usize;
    for k in 0..data.u.len() {
        let (u, p, y) = ([data.u[k]], [data.p[k]], data.y[k]);
        win.push(&u, y, &p).unwrap();
        if k < arx.depth() {
            sim.push(&u, y, &p).unwrap();
            continue;
        }
        sim.simulate_step(&model, &u, &p).unwrap();
        let mut zeta = vec![0.0; arx.chi_len()];
        sim.write_chi(&mut zeta).unwrap();
        let mut bz = vec![0.0; 3];
        write_basis(1, 2, &p, &mut bz).unwrap();
        let z = kron(&zeta, &bz);
        let mut phi = vec![0.0; nt];
        win.write_regressor(&mut phi).unwrap();
        let e = y - phi.iter().zip(&theta).map(|(a, b)| a * b).sum::<f64>();
        for a in 0..nz {
            r_iv[a] += z[a] * e;
        }
        n += 1;
    }
    assert_eq!(st.count(), n as u64);
    let j_iv: f64 = r_iv.iter().map(|v| (v / n as f64).powi(2)).sum();
    let j = st.civ_cost(0.0, &theta).unwrap();
    assert!((j - j_iv).abs() <= 1e-10 * j_iv.max(1e-12), "{j} vs {j_iv}");
    // J_CIV(theta) = theta^T H theta - 2 g^T theta + ||Z^T Y / N||^2 at any sigma
    let s2 = 0.07;
    let mut psi = vec![0.0; nz * nt];
    let mut h = vec![0.0; nt * nt];
    let mut g = vec![0.0; nt];
    st.normal_equations(s2, &mut psi, &mut h, &mut g).unwrap();
    let mut quad = 0.0;
    for a in 0..nt {
        for b in 0..nt {
            quad += theta[a] * h[a * nt + b] * theta[b];
        }
    }
    let lin: f64 = g.iter().zip(&theta).map(|(a, b)| a * b).sum();
    let c: f64 = st.zy().iter().map(|v| (v / n as f64).powi(2)).sum();
    let j2 = st.civ_cost(s2, &theta).unwrap();
    assert!((j2 - (quad - 2.0 * lin + c)).abs() <= 1e-9 * j2.max(1e-9));
    // and with Psi materialised
    let mut res = 0.0;
    for a in 0..nz {
        let pt: f64 = (0..nt).map(|b| psi[a * nt + b] * theta[b]).sum();
        res += ((st.zy()[a] - pt) / n as f64).powi(2);
    }
    assert!((res - j2).abs() <= 1e-12 * j2.max(1e-9));
    // bad sigma and bad theta are errors, not panics
    assert!(st.civ_cost(-1.0, &theta).is_err());
    assert!(st.civ_cost(f64::NAN, &theta).is_err());
    assert!(st.civ_cost(0.0, &theta[1..]).is_err());
}

#[test]
fn statistics_merge_two_halves_equal_the_whole() {
    let mut rng = StdRng::seed_from_u64(8);
    let data = b6(1000, &mut rng, 0.25);
    let whole = accumulate::<f64>(&data, &true_theta());
    let first = B6 {
        u: data.u[..500].to_vec(),
        y: data.y[..500].to_vec(),
        p: data.p[..500].to_vec(),
    };
    let second = B6 {
        u: data.u[500..].to_vec(),
        y: data.y[500..].to_vec(),
        p: data.p[500..].to_vec(),
    };
    // the halves are separate experiments, so the regressors of the first samples of the
    // second half are missing from both: compare against the whole built the same way
    let mut a = accumulate::<f64>(&first, &true_theta());
    let b = accumulate::<f64>(&second, &true_theta());
    let mut manual = accumulate::<f64>(&first, &true_theta());
    manual.break_window();
    a.merge(&b).unwrap();
    assert_eq!(a.count(), b.count() + 496);
    // same data through one accumulator with a window break
    let arx = b6_dims();
    let mut sim = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    let mut zeta = vec![0.0; arx.chi_len()];
    for k in 500..1000 {
        let (u, p, y) = ([data.u[k]], [data.p[k]], data.y[k]);
        if k < 500 + arx.depth() {
            sim.push(&u, y, &p).unwrap();
            manual.update(&zeta, &u, y, &p).unwrap();
            continue;
        }
        sim.simulate_step(&true_theta(), &u, &p).unwrap();
        sim.write_chi(&mut zeta).unwrap();
        manual.update(&zeta, &u, y, &p).unwrap();
    }
    assert_eq!(a.count(), manual.count());
    for (x, y) in a.values().iter().zip(manual.values()) {
        assert!((x - y).abs() <= 1e-9 * (1.0 + y.abs()), "{x} vs {y}");
    }
    assert!(whole.count() > a.count());
    // shapes must agree
    let other = new_stats::<f64>(BcivDims::new(arx, 3, 2).unwrap());
    assert_eq!(a.merge(&other), Err(Error::Mismatch));
    let mut ratios = new_stats::<f64>(BcivDims::paper(arx).unwrap());
    ratios.set_noise_ratios(&[0.5]).unwrap();
    assert_eq!(a.merge(&ratios), Err(Error::Mismatch));
}

#[test]
fn bad_samples_leave_the_statistics_untouched() {
    let arx = b6_dims();
    let d = BcivDims::paper(arx).unwrap();
    let mut st = new_stats::<f64>(d);
    let mut twin = new_stats::<f64>(d);
    let zeta = vec![0.3; arx.chi_len()];
    for k in 0..10 {
        let x = k as f64 * 0.1;
        st.update(&zeta, &[x], 1.0 - x, &[x]).unwrap();
        twin.update(&zeta, &[x], 1.0 - x, &[x]).unwrap();
    }
    let before = st.values().to_vec();
    let n = st.count();
    let bad_zeta = {
        let mut z = zeta.clone();
        z[2] = f64::NAN;
        z
    };
    assert!(st.update(&bad_zeta, &[0.5], 0.1, &[0.2]).is_err());
    assert!(st.update(&zeta, &[f64::INFINITY], 0.1, &[0.2]).is_err());
    assert!(st.update(&zeta, &[0.5], f64::NAN, &[0.2]).is_err());
    assert!(st.update(&zeta, &[0.5], 0.1, &[f64::NAN]).is_err());
    assert!(st.update(&zeta[1..], &[0.5], 0.1, &[0.2]).is_err());
    assert!(st.update(&zeta, &[0.5, 1.0], 0.1, &[0.2]).is_err());
    // finite but overflowing products
    assert_eq!(
        st.update(&zeta, &[0.5], 0.1, &[1e200]),
        Err(Error::Overflow)
    );
    assert_eq!(
        st.accumulate(
            &vec![1e300; arx.chi_len()],
            &vec![1e300; arx.chi_len()],
            0.0,
            &[0.1]
        ),
        Err(Error::Overflow)
    );
    assert_eq!(st.values(), &before[..]);
    assert_eq!(st.count(), n);
    // and the window is as before: the next good sample matches the twin exactly
    st.update(&zeta, &[0.7], 0.2, &[0.3]).unwrap();
    twin.update(&zeta, &[0.7], 0.2, &[0.3]).unwrap();
    assert_eq!(st.values(), twin.values());
    // configuration errors
    assert!(st.set_noise_ratios(&[1.0]).is_err()); // after accumulating
    let mut fresh = new_stats::<f64>(d);
    assert!(fresh.set_noise_ratios(&[-1.0]).is_err());
    let mut psi = vec![0.0; d.n_z() * d.n_theta()];
    let mut h = vec![0.0; d.n_theta() * d.n_theta()];
    let mut g = vec![0.0; d.n_theta()];
    assert!(fresh
        .normal_equations(0.1, &mut psi, &mut h, &mut g)
        .is_err()); // no samples
    assert!(fresh.civ_cost(0.1, &g).is_err());
    assert!(BcivStats::new(d, vec![0.0; 10], vec![0.0; d.window_len()]).is_err());
}

#[test]
fn f32_statistics_agree_with_f64() {
    let mut rng = StdRng::seed_from_u64(31);
    let data = b6(8000, &mut rng, 0.25);
    let s64 = accumulate::<f64>(&data, &true_theta());
    let s32 = accumulate::<f32>(&data, &true_theta());
    let t64 = estimate(&s64, 0.0625);
    let t32 = estimate(&s32, 0.0625f32);
    let ia = b6_dims().index_a(1, 2).unwrap();
    println!("a12: f64 {:.5}, f32 {:.5}", t64[ia], t32[ia]);
    assert!((t64[ia] - t32[ia] as f64).abs() < 0.01);
    let j64 = s64.civ_cost(0.0625, &t64).unwrap();
    let t64_32: Vec<f32> = t64.iter().map(|v| *v as f32).collect();
    let j32 = s32.civ_cost(0.0625, &t64_32).unwrap();
    assert!((j64 - j32 as f64).abs() < 1e-3 * (1.0 + j64));
}

/// The whole BC-IV-LASSO recipe on statistics only (what the host drives): adaptive weights
/// from the unpenalised BC-IV estimate, lambda path on the training statistics at sigma,
/// the de-biased refit (section 5.2) of each path point's support scored by
/// J_CIV(theta, 0, N_c) on the calibration statistics, the best one kept.
#[test]
fn b6_bciv_lasso_selects_the_true_structure() {
    use lpvid::lasso::{work_len, CoordinateDescent, Settings};
    use std::ops::ControlFlow;
    let mut rng = StdRng::seed_from_u64(4242);
    let d = b6_dims();
    let nt = d.n_theta().unwrap();
    let truth: Vec<usize> = vec![d.index_a(1, 2).unwrap(), d.index_b(0, 0, 2).unwrap()];
    let runs = 5;
    let mut exact = 0;
    for _ in 0..runs {
        let train = accumulate::<f64>(&b6(8000, &mut rng, 0.25), &true_theta());
        let cal = accumulate::<f64>(&b6(1000, &mut rng, 0.25), &true_theta());
        let s2 = 0.0625;
        let dims = train.dims();
        let mut psi = vec![0.0; dims.n_z() * nt];
        let mut h = vec![0.0; nt * nt];
        let mut g = vec![0.0; nt];
        train
            .normal_equations(s2, &mut psi, &mut h, &mut g)
            .unwrap();
        let hm = Dense::new(&h, nt).unwrap();
        // adaptive Lasso: weights from the unpenalised (consistent) BC-IV estimate
        let full = estimate(&train, s2);
        let w: Vec<f64> = full.iter().map(|v| 1.0 / v.abs().max(1e-12)).collect();
        let prob = Problem::new(&hm, &g, 1, Penalty::L1)
            .unwrap()
            .with_weights(&w)
            .unwrap();
        let mut cd = CoordinateDescent::new(1, nt, vec![0.0; work_len(1, nt)]).unwrap();
        let settings = Settings {
            n_lambda: 60,
            lambda_min_ratio: 1e-3,
            ..Settings::default()
        };
        let mut theta = vec![0.0; nt];
        let mut best = (f64::MAX, vec![0.0; nt], 0.0);
        let mut work = vec![0.0; refit_work_len(nt)];
        cd.path(&prob, &settings, &mut theta, |fit, th| {
            // score the de-biased refit of this support on the calibration statistics
            let mut t = th.to_vec();
            if refit(&prob, &mut t, &mut work).is_ok() {
                let j = cal.civ_cost(s2, &t).unwrap();
                if j < best.0 {
                    best = (j, t, fit.lambda);
                }
            }
            ControlFlow::Continue(())
        })
        .unwrap();
        let support: Vec<usize> = (0..nt).filter(|j| best.1[*j] != 0.0).collect();
        println!(
            "lambda {:.3e}, support {support:?}, a12 {:.4}",
            best.2, best.1[truth[0]]
        );
        if support == truth {
            exact += 1;
        }
    }
    println!("exact structure in {exact}/{runs} runs");
    assert!(exact >= 4, "exact structure in {exact}/{runs} runs");
}

/// Issue 4: zero heap allocations in the core's updates and solver, here in f32 as on the
/// device, with two scheduling signals and two inputs (the Hermite factors of both signals
/// multiply, noise ratios set), merging two accumulators, evaluating Psi(sigma^2) of
/// section 5.1, the normal equations and cost (10), the Lasso path and the refit.
#[test]
fn zero_allocations_f32_two_signals() {
    let arx = ArxDims::new(2, 2, 2, 1, 2).unwrap();
    let d = BcivDims::paper(arx).unwrap();
    let (nt, nz) = (d.n_theta(), d.n_z());
    let mut rng = StdRng::seed_from_u64(21);
    let n = 600;
    let data: Vec<([f32; 2], f32, [f32; 2])> = (0..n)
        .map(|k| {
            let kf = k as f64;
            let u = [rng.gen::<f32>(), rng.gen::<f32>() - 0.5];
            let p = [
                ((0.1 * kf).sin() + 0.2 * normal(&mut rng)) as f32,
                ((0.037 * kf).cos() + 0.2 * normal(&mut rng)) as f32,
            ];
            (u, (0.3 * normal(&mut rng)) as f32, p)
        })
        .collect();
    let mut a: Stats<f32> = new_stats(d);
    let mut b: Stats<f32> = new_stats(d);
    a.set_noise_ratios(&[1.0, 0.5]).unwrap();
    b.set_noise_ratios(&[1.0, 0.5]).unwrap();
    let mut sim = ArxWindow::new(arx, vec![0.0f32; arx.window_len()]).unwrap();
    let mut model = vec![0.0f32; nt];
    model[arx.index_a(1, 3).unwrap()] = 0.4;
    model[arx.index_b(0, 0, 5).unwrap()] = 0.3;
    let mut zeta = vec![0.0f32; arx.chi_len()];
    let mut psi = vec![0.0f32; nz * nt];
    let mut h = vec![0.0f32; nt * nt];
    let mut g = vec![0.0f32; nt];
    let mut theta = vec![0.0f32; nt];
    let mut best = vec![0.0f32; nt];
    let mut work = vec![0.0f32; work_len(1, nt)];
    let mut rwork = vec![0.0f32; refit_work_len(nt)];
    let (res, allocs) = count_allocs(|| -> Result<(u64, usize, f32), Error> {
        for (k, (u, y, p)) in data.iter().enumerate() {
            let st = if k < n / 2 { &mut a } else { &mut b };
            if k == n / 2 {
                st.break_window();
            }
            if k < arx.depth() {
                sim.push(u, *y, p)?;
            } else {
                sim.simulate_step(&model, u, p)?;
                sim.write_chi(&mut zeta)?;
            }
            st.update(&zeta, u, *y, p)?;
        }
        a.merge(&b)?;
        a.eval_psi(0.04, &mut psi)?;
        a.normal_equations(0.04, &mut psi, &mut h, &mut g)?;
        let hm = Dense::new(&h, nt)?;
        let prob = Problem::new(&hm, &g, 1, Penalty::L1)?;
        let mut cd = CoordinateDescent::new(1, nt, &mut work[..])?;
        let settings = Settings {
            n_lambda: 15,
            ..Settings::default()
        };
        let mut best_cost = f32::MAX;
        let points = cd.path(&prob, &settings, &mut theta, |_, th| {
            let j = a.civ_cost(0.04, th).unwrap_or(f32::MAX);
            if j < best_cost {
                best_cost = j;
                best.copy_from_slice(th);
            }
            ControlFlow::Continue(())
        })?;
        theta.copy_from_slice(&best);
        refit(&prob, &mut theta, &mut rwork)?;
        Ok((a.count(), points, a.civ_cost(0.04, &theta)?))
    });
    let (count, points, cost) = res.unwrap();
    assert_eq!(count, (n - 2 * arx.depth()) as u64);
    assert_eq!(points, 15);
    assert!(cost.is_finite() && cost >= 0.0, "{cost}");
    assert_eq!(allocs, 0, "the f32 core path allocated {allocs} times");
    // the counter does count
    let (_, c) = count_allocs(|| vec![1u8; 8]);
    assert!(c >= 1);
}
