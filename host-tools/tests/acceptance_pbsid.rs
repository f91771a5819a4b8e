//! Issue 2 acceptance: LPV-PBSID_opt on the benchmark systems of BENCHMARKS.md, Monte-Carlo
//! with fixed seeds, asserting the numbers the issue asks for (run in release mode:
//! `cargo test --release`). Every run is counted; a diverging model scores VAF 0.

use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::pbsid::{fit, Order, PbsidOptions, Reg};
use lpvid_host::systems::{self, Experiment};

/// Mean validation VAF over outputs of one fit; 0 when the fit fails.
fn vaf_of(exp: &Experiment, opts: &PbsidOptions) -> (f64, Option<usize>) {
    match fit(&exp.train, opts) {
        Ok(f) => {
            let yh = f.model.simulate(&exp.val, None);
            (mean(&vaf_per_output(&exp.val.y, &yh, 0)), Some(f.order))
        }
        Err(_) => (0.0, None),
    }
}

fn opts(p: usize, reg: Reg, order: Order) -> PbsidOptions {
    let mut o = PbsidOptions::new(p);
    o.reg = reg;
    o.order = order;
    o
}

/// Monte-Carlo: mean VAF and the fraction of runs whose order equals `n_true`.
fn monte_carlo(
    runs: u64,
    gen: impl Fn(u64) -> Experiment,
    o: &PbsidOptions,
    n_true: usize,
) -> (f64, f64) {
    let mut v = Vec::new();
    let mut hits = 0;
    for seed in 0..runs {
        let (vaf, order) = vaf_of(&gen(seed), o);
        v.push(vaf);
        if order == Some(n_true) {
            hits += 1;
        }
    }
    (mean(&v), hits as f64 / runs as f64)
}

#[test]
fn b1_p3_n1000_40db() {
    let o = opts(3, Reg::TikhonovGcv, Order::Auto);
    // 40 runs (the issue asks for 20): the mean of 20 fluctuates by about 0.02
    let (vaf, order_ok) = monte_carlo(40, |s| systems::b1(1000, 0.05, s), &o, 4);
    println!("B1 p=3 N=1000 40 dB: mean VAF {vaf:.3} (paper 98.0-98.4, toolbox 99.92), order 4 in {:.0}%", order_ok * 100.0);
    assert!(vaf >= 99.9, "mean VAF {vaf}");
    assert!(order_ok >= 0.95, "order auto picked n=4 in {order_ok}");
}

#[test]
fn b1_p3_n500_40db() {
    let o = opts(3, Reg::TikhonovGcv, Order::Auto);
    let (vaf, _) = monte_carlo(20, |s| systems::b1(500, 0.05, s), &o, 4);
    println!("B1 p=3 N=500 40 dB: mean VAF {vaf:.3} (paper 93.2/96.8, toolbox 99.49)");
    assert!(vaf >= 99.5, "mean VAF {vaf}");
}

#[test]
fn b1_p5_n1000_40db_kernel_path() {
    let o = opts(5, Reg::TikhonovGcv, Order::Auto);
    let (vaf, order_ok) = monte_carlo(20, |s| systems::b1(1000, 0.05, s), &o, 4);
    println!("B1 p=5 N=1000 40 dB: mean VAF {vaf:.3} (paper 17-21 / 94.8-95.1, toolbox 99.76), order 4 in {:.0}%", order_ok * 100.0);
    assert!(vaf >= 99.8, "mean VAF {vaf}");
}

#[test]
fn b3_p5() {
    let o = opts(5, Reg::TikhonovGcv, Order::Auto);
    let (vaf, order_ok) = monte_carlo(20, |s| systems::b3(250, s), &o, 4);
    println!(
        "B3 p=5 N=250: mean VAF {vaf:.3} (toolbox Tikhonov-GCV 96.4), order 4 in {:.0}%",
        order_ok * 100.0
    );
    assert!(vaf >= 97.0, "mean VAF {vaf}");
    assert!(order_ok >= 0.95, "order auto picked n=4 in {order_ok}");
}

#[test]
fn b2_order_auto() {
    let o = opts(5, Reg::TikhonovGcv, Order::Auto);
    let (vaf, order_ok) = monte_carlo(20, |s| systems::b2(75, 25.0, s), &o, 2);
    println!(
        "B2 p=5 N=75 25 dB: mean VAF {vaf:.3}, order 2 in {:.0}%",
        order_ok * 100.0
    );
    assert!(order_ok >= 0.95, "order auto picked n=2 in {order_ok}");
}

#[test]
fn noise_free_data_is_fitted_exactly() {
    // B1 and B4 admit an exact finite-window predictor (kernel paper Table 2 and Fig. 3
    // report 100.0): the fit must be exact.
    let o = opts(3, Reg::None, Order::Fixed(4));
    let (b1, _) = monte_carlo(5, |s| systems::b1(1000, 0.0, s), &o, 4);
    let o4 = opts(4, Reg::None, Order::Fixed(2));
    let (b4, _) = monte_carlo(5, |s| systems::b4(500, None, s), &o4, 2);
    // B2 and B3 have no exact finite-window predictor: the subspace estimate keeps the
    // truncation bias of section 4.1 (about 95 and 99.93), which the output-error
    // refinement removes.
    let mut o2 = opts(5, Reg::None, Order::Fixed(2));
    o2.refine = true;
    let (b2, _) = monte_carlo(5, |s| systems::b2(75, f64::INFINITY, s), &o2, 2);
    let mut o3 = opts(3, Reg::None, Order::Fixed(4));
    o3.refine = true;
    let (b3, _) = monte_carlo(
        5,
        |s| {
            let mut e = systems::b3(250, s);
            let truth = e.truth.clone().expect("B3 truth");
            e.train.y = truth.simulate(&e.train, None);
            e
        },
        &o3,
        4,
    );
    println!("noise-free: B1 {b1:.4}, B4 {b4:.4}, B2 {b2:.4} (refined), B3 {b3:.4} (refined)");
    for (name, v) in [("B1", b1), ("B4", b4), ("B2", b2), ("B3", b3)] {
        assert!(v >= 99.99, "{name} noise-free mean VAF {v}");
    }
}

#[test]
fn b4_past_window_tradeoff() {
    // Kernel paper section 7.3, Fig. 3: bias at small p, variance at large p.
    let runs = 10;
    let mut clean = Vec::new();
    let mut noisy = Vec::new();
    println!("B4 bilinear, N = 500, {runs} runs: mean VAF vs p");
    println!("   p   noise-free   15 dB");
    for p in 1..=8usize {
        let o = opts(p, Reg::None, Order::Fixed(p.min(2)));
        let (c, _) = monte_carlo(runs, |s| systems::b4(500, None, s), &o, 2);
        let (n, _) = monte_carlo(runs, |s| systems::b4(500, Some(15.0), s), &o, 2);
        println!("  {p:2}   {c:10.3}   {n:6.3}");
        clean.push(c);
        noisy.push(n);
    }
    // bias: a window too short to hold the two states misses the dynamics
    assert!(
        clean[0] < 95.0 && noisy[0] < 95.0,
        "p = 1 should be biased: {clean:?}"
    );
    // noise-free: no variance, any p >= 2 is exact
    assert!(clean[1..].iter().all(|&v| v > 99.9), "{clean:?}");
    // 15 dB: the best p is moderate, and the largest windows lose to it (variance)
    let best = noisy.iter().cloned().fold(f64::MIN, f64::max);
    let argbest = noisy.iter().position(|&v| v == best).unwrap() + 1;
    assert!((2..=6).contains(&argbest), "best p {argbest}: {noisy:?}");
    assert!(noisy[7] < best - 2.0 && noisy[6] < best - 2.0, "{noisy:?}");
}
