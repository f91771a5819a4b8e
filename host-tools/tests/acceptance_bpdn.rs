//! Sparse estimation (issue 3, sparse paper section 4.2 and section 5): mean free-run VAF on
//! the noise-free validation data, every run counted (a diverging model scores 0).
//!
//! - B2 (Example I, N = 75, 25 dB), `--reg bpdn-sv`, 20 runs per p: at least 95 at every
//!   p in 3..14 (the toolbox: 95.0 / 92.6 / 91.3 / 92.1 at p = 5 / 8 / 10 / 12).
//! - B3 (Example II, N = 250), the best of our regularisations, 10 runs per p: at least 97
//!   at every p in 3..14. Tikhonov-GCV at every p, BPDN-SV at p = 3..8 (it is the one
//!   that holds at p = 3, where the past window truncates the n = 4 dynamics and
//!   Tikhonov-GCV picks order 2 in half the runs); the BPDN-SV sweep to p = 14 takes
//!   minutes and lives in `examples/bpdn_montecarlo.rs` (98.6-99.2 at p = 3..10).
//!
//! Release mode: `cargo test --release -p lpvid-host --test acceptance_bpdn -- --nocapture`.

use lpvid_host::lpvss::Signals;
use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::pbsid::{fit, PbsidOptions, Reg};
use lpvid_host::systems::{self, Experiment};

fn vaf(e: &Experiment, p: usize, reg: Reg) -> (f64, usize) {
    let mut o = PbsidOptions::new(p);
    o.reg = reg;
    let f = fit(&e.train, &o).expect("fit");
    let val: &Signals = &e.val;
    let v = mean(&vaf_per_output(&val.y, &f.model.simulate(val, None), 0));
    (v, f.order)
}

fn mean_vaf(exp: impl Fn(u64) -> Experiment, runs: u64, p: usize, reg: Reg) -> (f64, f64) {
    let res: Vec<(f64, usize)> = (0..runs).map(|s| vaf(&exp(s), p, reg)).collect();
    let v: Vec<f64> = res.iter().map(|r| r.0).collect();
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    (mean(&v), min)
}

#[test]
fn b2_bpdn_sv_over_past_windows() {
    println!("B2, N = 75, 25 dB, 20 runs: free-run VAF of BPDN-SV");
    println!("   p    mean     min");
    let mut fails = vec![];
    for p in 3..=14 {
        let (m, min) = mean_vaf(|s| systems::b2(75, 25.0, s), 20, p, Reg::BpdnSv);
        println!("  {p:2}   {m:6.2}  {min:6.2}");
        if m < 95.0 {
            fails.push((p, m));
        }
    }
    assert!(fails.is_empty(), "mean VAF below 95 at (p, VAF) {fails:?}");
}

#[test]
fn b3_best_regularisation_over_past_windows() {
    println!("B3, N = 250, 10 runs: free-run VAF (mean / min)");
    println!("   p   Tikhonov-GCV      BPDN-SV");
    let mut fails = vec![];
    for p in 3..=14 {
        let tik = mean_vaf(|s| systems::b3(250, s), 10, p, Reg::TikhonovGcv);
        let sv = (p <= 8).then(|| mean_vaf(|s| systems::b3(250, s), 10, p, Reg::BpdnSv));
        let sv_txt = sv.map_or("           -".to_string(), |(m, min)| {
            format!("{m:6.2} / {min:5.2}")
        });
        println!("  {p:2}   {:6.2} / {:5.2}   {sv_txt}", tik.0, tik.1);
        let best = sv.map_or(tik.0, |s| s.0.max(tik.0));
        if best < 97.0 {
            fails.push((p, best));
        }
        if let Some((m, _)) = sv {
            assert!(m >= 97.0, "BPDN-SV on B3 at p = {p}: {m}");
        }
    }
    assert!(
        fails.is_empty(),
        "best mean VAF below 97 at (p, VAF) {fails:?}"
    );
}
