//! Issue 5 acceptance: H-infinity observer gains by the LMI (30) of the sparse paper
//! (papers/lpv-pbsid-sparse-bpdn-hinf-observer.md section 3.4, Appendix A), solved with
//! clarabel, checked here with our own eigenvalues (nalgebra's symmetric eigensolver, a
//! different code path from the faer one the library's certificate uses), and Table 1 of
//! the paper reproduced on B2 (Monte-Carlo, fixed seeds, release mode).

use lpvid_host::cli;
use lpvid_host::data::Dataset;
use lpvid_host::lpvss::{scheduled, LpvSs, Signals};
use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::observer::{
    align_states, design_hinf, hinf_observer, hinf_observer_refined, max_predictor_radius,
    noise_covariance, stability_regions, HinfDesign, HinfOptions, NoiseCov, SchedBox,
};
use lpvid_host::pbsid::{fit, Order, PbsidOptions, Reg};
use lpvid_host::refine::refine_output_error;
use lpvid_host::systems;
use nalgebra::{DMatrix, SymmetricEigen};
use serde_json::Value;

/// Smallest eigenvalue of a symmetric matrix (nalgebra, symmetrised first).
fn min_eig(m: &DMatrix<f64>) -> f64 {
    let s = (m + m.transpose()) * 0.5;
    SymmetricEigen::new(s).eigenvalues.min()
}

fn sym_sqrt(m: &DMatrix<f64>) -> DMatrix<f64> {
    let e = SymmetricEigen::new((m + m.transpose()) * 0.5);
    let d = DMatrix::from_diagonal(&e.eigenvalues.map(|v| v.max(0.0).sqrt()));
    &e.eigenvectors * d * e.eigenvectors.transpose()
}

fn the_box(lo: f64, hi: f64) -> SchedBox {
    SchedBox {
        names: vec!["p1".into()],
        lo: vec![lo],
        hi: vec![hi],
        source: vec!["test".into()],
    }
}

/// What the independent check found.
#[derive(Debug)]
struct Check {
    p_minus_i: f64,
    vertex_lmi: f64,
    grid_brl: f64,
    grid_lyap: f64,
    grid_rho: f64,
}

impl Check {
    fn ok(&self) -> bool {
        self.p_minus_i > 0.0
            && self.vertex_lmi > 0.0
            && self.grid_brl > 0.0
            && self.grid_lyap > 0.0
            && self.grid_rho < 1.0
    }
}

/// Independent check of a design from its recorded (P, gamma, K, noise scale), rebuilt from
/// the paper's formulas in this file: P - I > 0; the LMI matrix (30) > 0 at every vertex;
/// on `grid` points of the box the bounded-real matrix of the error system (29) with the
/// gains K(mu) = sum mu_i K^(i) is > 0 (common Lyapunov function x' P x with
/// V(x+) - V(x) < -|x|^2 + gamma^2 |eps|^2), P - Acl' P Acl > 0, spectral radius < 1.
/// The noise is divided by the design's noise scale c (and gamma^2 with it): an exact
/// congruence of (30), so positive definiteness is unchanged; the eigenvalues are of
/// matrices whose identity blocks fix the scale.
fn check_design(
    model: &LpvSs,
    nc: &NoiseCov,
    d: &HinfDesign,
    sbox: &SchedBox,
    grid: usize,
) -> Check {
    let n = model.n();
    let l = model.l();
    let c = &model.c[0];
    let cs = d.noise_scale;
    let (q, s, r) = (&nc.q / cs, &nc.s / cs, &nc.r / cs);
    let t = d.gamma * d.gamma / cs;
    let r_inv = r.clone().try_inverse().unwrap();
    let qx_half = sym_sqrt(&(&q - &s * &r_inv * s.transpose()));
    let r_half = sym_sqrt(&r);
    let p = &d.p;
    let eye = DMatrix::<f64>::identity(n, n);
    let p_minus_i = min_eig(&(p - &eye));
    // (30) at the vertices, block by block as printed
    let mut vertex_lmi = f64::INFINITY;
    for mu in sbox.vertices() {
        let abar = scheduled(&model.a, &mu) - &s * &r_inv * c;
        let mut m = DMatrix::<f64>::zeros(4 * n, 4 * n);
        m.view_mut((0, 0), (n, n)).copy_from(p);
        m.view_mut((0, 2 * n), (n, n)).copy_from(&(p * &abar));
        m.view_mut((0, 3 * n), (n, n)).copy_from(&(p * &qx_half));
        m.view_mut((n, n), (n, n)).copy_from(&eye);
        m.view_mut((n, 2 * n), (n, n)).copy_from(&eye);
        m.view_mut((2 * n, 2 * n), (n, n))
            .copy_from(&(p + c.transpose() * &r_inv * c * t));
        m.view_mut((3 * n, 3 * n), (n, n)).copy_from(&(&eye * t));
        // lower triangle = transpose of the upper
        for i in 0..4 * n {
            for j in 0..i {
                m[(i, j)] = m[(j, i)];
            }
        }
        vertex_lmi = vertex_lmi.min(min_eig(&m));
    }
    // the error system on a dense grid
    let (mut grid_brl, mut grid_lyap, mut grid_rho) = (f64::INFINITY, f64::INFINITY, 0.0f64);
    // grid points of the box (a tensor grid of about `grid` points per signal)
    for mu in sbox.grid(grid) {
        let kmu = scheduled(&model.k, &mu);
        let acl = scheduled(&model.a, &mu) - &kmu * c;
        let mut bcl = DMatrix::zeros(n, l + n);
        bcl.view_mut((0, 0), (n, l))
            .copy_from(&((&s * &r_inv - &kmu) * &r_half));
        bcl.view_mut((0, l), (n, n)).copy_from(&qx_half);
        let dim = 3 * n + l;
        let mut m = DMatrix::<f64>::zeros(dim, dim);
        m.view_mut((0, 0), (n, n)).copy_from(p);
        m.view_mut((0, n), (n, n)).copy_from(&(p * &acl));
        m.view_mut((0, 2 * n), (n, l + n)).copy_from(&(p * &bcl));
        m.view_mut((n, n), (n, n)).copy_from(&(p - &eye));
        for i in 0..l + n {
            m[(2 * n + i, 2 * n + i)] = t;
        }
        for i in 0..dim {
            for j in 0..i {
                m[(i, j)] = m[(j, i)];
            }
        }
        grid_brl = grid_brl.min(min_eig(&m));
        grid_lyap = grid_lyap.min(min_eig(&(p - acl.transpose() * p * &acl)));
        let rho = acl
            .complex_eigenvalues()
            .iter()
            .map(|z| z.norm())
            .fold(0.0, f64::max);
        grid_rho = grid_rho.max(rho);
    }
    Check {
        p_minus_i,
        vertex_lmi,
        grid_brl,
        grid_lyap,
        grid_rho,
    }
}

#[test]
fn true_b2_design_is_certified_independently() {
    // B2 truth, w and v of equal variance (the benchmark's noise): Q = I, S = 0, R = 1.
    let truth = systems::b2_truth();
    let nc = NoiseCov {
        q: DMatrix::identity(2, 2),
        s: DMatrix::zeros(2, 1),
        r: DMatrix::identity(1, 1),
        columns: 0,
    };
    let sbox = the_box(-0.8, 1.2);
    let d = design_hinf(&truth, &nc, &sbox, &HinfOptions::default()).expect("design");
    let mut m = truth.clone();
    m.k = d.k.clone();
    let ck = check_design(&m, &nc, &d, &sbox, 5001);
    println!(
        "B2 truth: gamma {:.4}, margin {:e}, {:?}, solver {} in {} it, {:.2} ms",
        d.gamma,
        d.margin,
        ck,
        d.solver_status,
        d.iterations,
        d.solve_time * 1e3
    );
    assert!(ck.ok(), "{ck:?}");
    assert_eq!(d.vertices.len(), 2);
    // RECIPES.md: (30) as printed for the true Example I system gives a predictor with
    // spectral radius 0.58 over mu2 in [-0.8, 1.2]
    assert!((ck.grid_rho - 0.58).abs() < 0.01, "rho {}", ck.grid_rho);
    // the bound is tight-ish: gamma^2 slightly lower must violate (30) at some vertex
    let mut lower = d.clone();
    lower.gamma *= 0.999;
    let ck2 = check_design(&m, &nc, &lower, &sbox, 3);
    assert!(
        ck2.vertex_lmi < ck.vertex_lmi,
        "lower gamma should tighten the LMI"
    );
    // the recorded certificate agrees with ours
    assert!(d.certificate.ok());
    assert!((d.certificate.max_rho_grid - ck.grid_rho).abs() < 1e-3);
}

#[test]
fn two_scheduling_signals_four_vertices() {
    // n = 4 (B3's A, C) with a second scheduling signal on a small extra A^(3)
    let mut m = systems::b3_truth();
    let a3 = DMatrix::from_fn(4, 4, |i, j| if (i + j) % 3 == 0 { 0.05 } else { -0.03 });
    m.a.push(a3);
    m.b.push(DMatrix::zeros(4, 2));
    m.k.push(DMatrix::zeros(4, 2));
    let nc = NoiseCov {
        q: DMatrix::identity(4, 4) * 0.1,
        s: DMatrix::zeros(4, 2),
        r: DMatrix::identity(2, 2) * 0.25,
        columns: 0,
    };
    let sbox = SchedBox {
        names: vec!["p1".into(), "p2".into()],
        lo: vec![-0.5, -1.0],
        hi: vec![1.5, 1.0],
        source: vec!["test".into(); 2],
    };
    assert_eq!(sbox.vertices().len(), 4);
    let d = design_hinf(&m, &nc, &sbox, &HinfOptions::default()).expect("design");
    let mut mk = m.clone();
    mk.k = d.k.clone();
    // grid over the diagonal and the edges via the library grid: use a full 2-D grid here
    let mut worst_rho = 0.0f64;
    for mu in sbox.grid(61) {
        let acl = scheduled(&mk.a, &mu) - scheduled(&mk.k, &mu) * &mk.c[0];
        let rho = acl
            .complex_eigenvalues()
            .iter()
            .map(|z| z.norm())
            .fold(0.0, f64::max);
        worst_rho = worst_rho.max(rho);
    }
    let ck = check_design(&mk, &nc, &d, &sbox, 1001);
    println!(
        "n=4, 4 vertices: gamma {:.4}, {ck:?}, worst rho on a 61x61 grid {worst_rho:.4}",
        d.gamma
    );
    assert!(ck.ok(), "{ck:?}");
    assert!(worst_rho < 1.0);
    assert!(d.certificate.ok() && d.certificate.grid_points >= 3000);
}

#[test]
fn infeasible_box_is_reported_not_faked() {
    // B2's A(mu) over mu2 in [-60, 60]: no common quadratic Lyapunov function exists for any
    // observer; the design must fail (not return a gamma).
    let truth = systems::b2_truth();
    let nc = NoiseCov {
        q: DMatrix::identity(2, 2),
        s: DMatrix::zeros(2, 1),
        r: DMatrix::identity(1, 1),
        columns: 0,
    };
    let r = design_hinf(&truth, &nc, &the_box(-60.0, 60.0), &HinfOptions::default());
    println!("[-60, 60]: {r:?}");
    assert!(r.is_err(), "a design was claimed: {r:?}");
}

/// Table 1 of the sparse paper: (p, SNR) -> (LS VAF, H-infinity VAF), single runs there.
const PAPER: [(usize, f64, f64, f64); 10] = [
    (5, 15.0, 71.7, 61.7),
    (5, 25.0, 87.2, 77.3),
    (5, 50.0, 97.9, 96.4),
    (5, 75.0, 0.0, 99.5),
    (5, 100.0, 0.0, 99.7),
    (10, 15.0, 63.8, 64.5),
    (10, 25.0, 83.2, 79.1),
    (10, 50.0, 97.7, 96.9),
    (10, 75.0, 98.4, 98.8),
    (10, 100.0, 0.0, 98.2),
];

/// Monte-Carlo runs per (p, SNR) cell.
const RUNS: u64 = 30;

/// Table 1 of the sparse paper on B2, the paper's pipeline: BPDN-SV identification (order
/// 2, section 4.2), then the observer. The least-squares column is the identified model with
/// the K of (6)-(7), as the paper's LS column. The H-infinity column is our pipeline: the
/// output-error refinement of `lpvid_host::refine` first (it removes the finite-past-window
/// bias: B2 has its process noise outside the scheduling sum and K = 0, so no finite past
/// window gives an exact predictor, and without refinement the p = 5 model's own free-run
/// VAF at 75-100 dB is about 97-98), then Q, S, R from eq. (25) with the states aligned to
/// the refined basis, LMI (30) and gains (31). Predictor VAF on the noise-free validation
/// set (500 samples, predictor started at x = 0). Asserted in every cell: every run's
/// H-infinity predictor VAF (so the mean too) at least the paper's H-infinity figure, every
/// design certified independently and stable over mu2 in [-0.8, 1.2]; somewhere at
/// 75-100 dB the least-squares predictor is unstable there (the paper's failure).
#[test]
fn table1_b2_hinf_predictor_is_stable_at_every_snr() {
    let mut any_ls_unstable_high_snr = false;
    let mut failures = Vec::new();
    println!(
        "Table 1 (B2, N = 75, BPDN-SV, order 2, {RUNS} runs per cell, seeds 1000..; paper: single BPDN runs)"
    );
    println!(
        "  p  SNR | LS VAF mean (paper) LS unstable (Tikhonov LS unstable) | Hinf refined mean min (paper) | Hinf (24) unrefined mean | refined free-run | LS region run 0 | Hinf region run 0 | gamma run 0"
    );
    for &(p, snr, paper_ls, paper_hinf) in &PAPER {
        let (mut v_ls, mut v_h, mut v_h24, mut v_sim) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut ls_unstable = 0;
        let mut tik_unstable = 0;
        let mut region_ls0 = String::new();
        let mut region_h0 = String::new();
        let mut gamma0 = 0.0;
        for seed in 0..RUNS {
            let exp = systems::b2(75, snr, 1000 + seed);
            let mut o = PbsidOptions::new(p);
            o.reg = Reg::BpdnSv;
            o.order = Order::Fixed(2);
            let f = fit(&exp.train, &o).expect("pbsid fit");
            let ls = &f.model;
            let sbox = SchedBox::from_signals(&["p1".to_string()], &exp.train);
            // the data's range is the paper's operating range [-0.8, 1.2]
            assert!((sbox.lo[0] + 0.8).abs() < 1e-9 && (sbox.hi[0] - 1.2).abs() < 1e-9);
            let mean_p = exp.train.p.column(0).mean();
            let pred_vaf = |m: &LpvSs| mean(&vaf_per_output(&exp.val.y, &m.predict(&exp.val), 0));
            v_ls.push(pred_vaf(ls));
            let rho_ls = max_predictor_radius(ls, &sbox, 1001);
            if rho_ls >= 1.0 {
                ls_unstable += 1;
                if snr >= 75.0 {
                    any_ls_unstable_high_snr = true;
                }
            }
            if snr >= 75.0 {
                // our BPDN-SV (realized-model score) rarely leaves an unstable least-squares
                // predictor; the Tikhonov-GCV model of the same data shows the paper's
                // failure case
                let mut ot = PbsidOptions::new(p);
                ot.order = Order::Fixed(2);
                let ft = fit(&exp.train, &ot).expect("pbsid fit (Tikhonov)");
                if max_predictor_radius(&ft.model, &sbox, 1001) >= 1.0 {
                    tik_unstable += 1;
                    any_ls_unstable_high_snr = true;
                }
            }
            let states = f.states.as_ref().expect("states");
            // the paper's path without refinement, for comparison (not asserted)
            match hinf_observer(ls, &exp.train, states, p, &sbox, &Default::default()) {
                Ok((m24, _, _)) => v_h24.push(pred_vaf(&m24)),
                Err(_) => v_h24.push(0.0),
            }
            // refinement first (what `lpvid pbsid --refine` does inside the fit), then (30)
            let r = refine_output_error(ls, &exp.train, o.feedthrough, 50);
            assert!(
                r.mse_after < r.mse_before,
                "p={p} {snr} dB seed {seed}: refinement did not improve"
            );
            let (hm, nc, d) = match hinf_observer_refined(
                &r.model,
                &exp.train,
                states,
                p,
                &sbox,
                &Default::default(),
            ) {
                Ok(x) => x,
                Err(e) => {
                    failures.push(format!("p={p} {snr} dB seed {seed}: design failed: {e}"));
                    v_h.push(0.0);
                    continue;
                }
            };
            // independent check of this solution, dense grid of the range
            let ck = check_design(&hm, &nc, &d, &sbox, 2001);
            if !ck.ok() {
                failures.push(format!("p={p} {snr} dB seed {seed}: check failed {ck:?}"));
            }
            let rho_h = max_predictor_radius(&hm, &sbox, 2001);
            let reg = stability_regions(&hm, &sbox, &[mean_p], 10.0);
            if rho_h >= 1.0 || !reg[0].covers_operating {
                failures.push(format!(
                    "p={p} {snr} dB seed {seed}: Hinf predictor not stable over [-0.8, 1.2]: rho {rho_h}, {}",
                    reg[0].describe()
                ));
            }
            let vh = pred_vaf(&hm);
            if vh < paper_hinf {
                failures.push(format!(
                    "p={p} {snr} dB seed {seed}: Hinf predictor VAF {vh:.2} below the paper's {paper_hinf}"
                ));
            }
            v_h.push(vh);
            v_sim.push(mean(&vaf_per_output(
                &exp.val.y,
                &hm.simulate(&exp.val, None),
                0,
            )));
            if seed == 0 {
                let rl = stability_regions(ls, &sbox, &[mean_p], 10.0);
                let fmt = |r: &lpvid_host::observer::Region| match r.interval {
                    Some((a, b)) => format!("[{a:.1}, {b:.1}]"),
                    None => "unstable at mean".into(),
                };
                region_ls0 = fmt(&rl[0]);
                region_h0 = fmt(&reg[0]);
                gamma0 = d.gamma;
            }
        }
        let (ml, mh, mh24, ms) = (mean(&v_ls), mean(&v_h), mean(&v_h24), mean(&v_sim));
        let mh_min = v_h.iter().copied().fold(f64::INFINITY, f64::min);
        println!(
            "  {p:>2} {snr:>4} | {ml:6.2} ({paper_ls:5.1}) {ls_unstable:>2}/{RUNS} ({tik_unstable:>2}/{RUNS}) | {mh:6.2} {mh_min:6.2} ({paper_hinf:5.1}) | {mh24:6.2} | {ms:6.2} | {region_ls0:>16} | {region_h0:>14} | {gamma0:.3e}"
        );
        if mh < paper_hinf {
            failures.push(format!(
                "p={p} {snr} dB: mean Hinf predictor VAF {mh:.2} below the paper's {paper_hinf}"
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(
        any_ls_unstable_high_snr,
        "no least-squares predictor (BPDN-SV or Tikhonov-GCV model) was unstable at 75-100 dB: the paper's failure case was not reproduced"
    );
}

/// The residuals (25) of a refined model need the states in its basis. The same model in
/// another basis (A -> T A T^-1, B -> T B, C -> C T^-1) must give aligned states T x and
/// the same noise covariances up to the congruence by T (Q -> T Q T^T, R unchanged); and
/// the aligned residuals are smaller than with the subspace-basis states. B2, 100 dB.
#[test]
fn refined_model_states_are_aligned_to_its_basis() {
    let exp = systems::b2(75, 100.0, 1000);
    let mut o = PbsidOptions::new(5);
    o.reg = Reg::TikhonovGcv;
    o.order = Order::Fixed(2);
    let f = fit(&exp.train, &o).unwrap();
    let states = f.states.as_ref().unwrap();
    let r = refine_output_error(&f.model, &exp.train, true, 50);
    let x1 = align_states(&r.model, &exp.train, states, 5).unwrap();
    let nc1 = noise_covariance(&r.model, &exp.train, &x1, 5).unwrap();
    let t = DMatrix::from_row_slice(2, 2, &[2.0, 0.7, -0.4, 0.5]);
    let ti = t.clone().try_inverse().unwrap();
    let mut m2 = r.model.clone();
    for a in m2.a.iter_mut() {
        *a = &t * &*a * &ti;
    }
    for b in m2.b.iter_mut() {
        *b = &t * &*b;
    }
    for c in m2.c.iter_mut() {
        *c = &*c * &ti;
    }
    let x2 = align_states(&m2, &exp.train, states, 5).unwrap();
    let nc2 = noise_covariance(&m2, &exp.train, &x2, 5).unwrap();
    let dx = (&x2 - &t * &x1).amax() / x1.amax();
    let dq = (&nc2.q - &t * &nc1.q * t.transpose()).amax() / nc1.q.amax();
    let dr = (&nc2.r - &nc1.r).amax() / nc1.r.amax();
    let nc0 = noise_covariance(&r.model, &exp.train, states, 5).unwrap();
    println!(
        "aligned: |x2 - T x1| {dx:.2e}, Q {dq:.2e}, R {dr:.2e}; trace Q + R aligned {:.3e}, unaligned {:.3e}",
        nc1.q.trace() + nc1.r.trace(),
        nc0.q.trace() + nc0.r.trace()
    );
    assert!(dx < 1e-9 && dq < 1e-9 && dr < 1e-9, "{dx} {dq} {dr}");
    assert!(
        nc1.q.trace() + nc1.r.trace() < nc0.q.trace() + nc0.r.trace(),
        "alignment did not reduce the residuals: {nc1:?} vs {nc0:?}"
    );
}

fn write_signals(sig: &Signals, path: &std::path::Path) {
    Dataset::from_signals(sig, &path.display().to_string())
        .write_csv(path)
        .unwrap();
}

fn run_cli(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut full = vec!["lpvid"];
    full.extend_from_slice(args);
    cli::run(full, &mut out).map_err(|e| e.to_string())?;
    Ok(String::from_utf8(out).unwrap())
}

#[test]
fn cli_pbsid_hinf_records_gamma_vertices_and_stability() {
    let dir = tempfile::tempdir().unwrap();
    let exp = systems::b2(75, 100.0, 7);
    let train = dir.path().join("train.csv");
    let val = dir.path().join("val.csv");
    write_signals(&exp.train, &train);
    write_signals(&exp.val, &val);
    let (t, v) = (train.to_str().unwrap(), val.to_str().unwrap());
    let m_ls = dir.path().join("ls.json");
    let m_h = dir.path().join("hinf.json");
    let (ls_path, h_path) = (m_ls.to_str().unwrap(), m_h.to_str().unwrap());
    run_cli(&[
        "pbsid", "--train", t, "--past", "5", "--order", "2", "--out", ls_path,
    ])
    .unwrap();
    let txt = run_cli(&[
        "pbsid",
        "--train",
        t,
        "--past",
        "5",
        "--order",
        "2",
        "--observer",
        "hinf",
        "--scheduling-range",
        "p1=-0.8:1.2",
        "--out",
        h_path,
    ])
    .unwrap();
    println!("{txt}");
    assert!(txt.contains("observer: H-infinity"), "{txt}");
    assert!(txt.contains("stability region"), "{txt}");
    let json: Value = serde_json::from_str(&std::fs::read_to_string(&m_h).unwrap()).unwrap();
    let obs = &json["fit"]["observer"];
    assert_eq!(obs["used"], "hinf");
    assert!(obs["gamma"].as_f64().unwrap() > 0.0);
    assert_eq!(obs["vertices"].as_array().unwrap().len(), 2);
    assert_eq!(obs["margin"].as_f64().unwrap(), 1e-6);
    assert_eq!(obs["solver_status"], "Solved");
    assert_eq!(obs["certificate"]["ok"], true);
    let reg = &json["fit"]["stability_region"]["regions"][0];
    assert_eq!(reg["covers_operating_interval"], true);
    // the stability subcommand and validate --predictor on the written model
    let st: Value =
        serde_json::from_str(&run_cli(&["stability", "--model", h_path, "--json"]).unwrap())
            .unwrap();
    assert_eq!(st["stable_over_box"], true);
    assert_eq!(st["regions"][0]["signal"], "p1");
    let st_ls: Value = serde_json::from_str(
        &run_cli(&[
            "stability",
            "--model",
            ls_path,
            "--range",
            "p1=-0.8:1.2",
            "--json",
        ])
        .unwrap(),
    )
    .unwrap();
    println!("LS stability: {st_ls}");
    let vh: Value = serde_json::from_str(
        &run_cli(&[
            "validate",
            "--model",
            h_path,
            "--data",
            v,
            "--predictor",
            "--json",
        ])
        .unwrap(),
    )
    .unwrap();
    let vaf_h = vh["score"]["vaf_mean"].as_f64().unwrap();
    println!("predictor VAF with the H-infinity gain: {vaf_h:.2}");
    assert!(vaf_h > 95.0);
    let txt = run_cli(&["stability", "--model", h_path]).unwrap();
    assert!(txt.contains("p1 in ["), "{txt}");
    // --refine: the output-error refinement runs inside the fit, then the observer is
    // designed for the refined A, B, C, D (states aligned to its basis)
    let m_r = dir.path().join("refined.json");
    let r_path = m_r.to_str().unwrap();
    let txt = run_cli(&[
        "pbsid",
        "--train",
        t,
        "--past",
        "5",
        "--order",
        "2",
        "--refine",
        "--observer",
        "hinf",
        "--out",
        r_path,
    ])
    .unwrap();
    println!("{txt}");
    assert!(
        txt.contains("A, B, C, D of the output-error refinement"),
        "{txt}"
    );
    let json: Value = serde_json::from_str(&std::fs::read_to_string(&m_r).unwrap()).unwrap();
    let obs = &json["fit"]["observer"];
    assert_eq!(obs["used"], "hinf");
    assert_eq!(obs["certificate"]["ok"], true);
    assert!(obs["model_matrices"]
        .as_str()
        .unwrap()
        .contains("refinement"));
    let vr: Value = serde_json::from_str(
        &run_cli(&[
            "validate",
            "--model",
            r_path,
            "--data",
            v,
            "--predictor",
            "--json",
        ])
        .unwrap(),
    )
    .unwrap();
    let vaf_r = vr["score"]["vaf_mean"].as_f64().unwrap();
    println!("predictor VAF, --refine --observer hinf: {vaf_r:.3} (without --refine {vaf_h:.3})");
    // the paper's Table 1 H-infinity figure at p = 5, 100 dB is 99.7
    assert!(vaf_r >= 99.7, "{vaf_r}");
}

#[test]
fn cli_failed_design_keeps_ls_gain_and_claims_no_gamma() {
    let dir = tempfile::tempdir().unwrap();
    let exp = systems::b2(75, 25.0, 3);
    let train = dir.path().join("train.csv");
    write_signals(&exp.train, &train);
    let m = dir.path().join("m.json");
    let txt = run_cli(&[
        "pbsid",
        "--train",
        train.to_str().unwrap(),
        "--past",
        "5",
        "--order",
        "2",
        "--observer",
        "hinf",
        "--scheduling-range",
        "p1=-60:60",
        "--out",
        m.to_str().unwrap(),
    ])
    .unwrap();
    println!("{txt}");
    assert!(txt.contains("WARNING: H-infinity observer"), "{txt}");
    assert!(
        txt.contains("keeping the least-squares observer gain"),
        "{txt}"
    );
    let json: Value = serde_json::from_str(&std::fs::read_to_string(&m).unwrap()).unwrap();
    let obs = &json["fit"]["observer"];
    assert_eq!(obs["used"], "ls");
    assert!(obs.get("gamma").is_none(), "{obs}");
    assert!(
        obs["error"].as_str().unwrap().contains("infeasible")
            || obs["error"].as_str().unwrap().contains("fail")
    );
    // and the written K is the least-squares one
    let mut o = PbsidOptions::new(5);
    o.order = Order::Fixed(2);
    o.reg = Reg::TikhonovGcv;
    let f = fit(&exp.train, &o).unwrap();
    let k0 = json["K"][0][1][0].as_f64().unwrap();
    assert!(
        (k0 - f.model.k[0][(1, 0)]).abs() < 1e-6 * (1.0 + k0.abs()),
        "{k0} vs {}",
        f.model.k[0][(1, 0)]
    );
    // bad ranges are errors that name the problem
    for (spec, needle) in [
        ("q1=0:1", "no scheduling signal 'q1'"),
        ("p1=2:1", "lower bound above upper bound"),
        ("p1=a:1", "not a finite number"),
        ("p1", "expected NAME=LO:HI"),
    ] {
        let e = run_cli(&[
            "pbsid",
            "--train",
            train.to_str().unwrap(),
            "--past",
            "5",
            "--observer",
            "hinf",
            "--scheduling-range",
            spec,
            "--out",
            m.to_str().unwrap(),
        ])
        .unwrap_err();
        assert!(e.contains(needle), "{spec}: {e}");
    }
}
