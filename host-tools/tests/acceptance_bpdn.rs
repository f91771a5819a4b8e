//! Sparse estimation (issue 3, sparse paper section 4.2 and section 5): mean free-run VAF on
//! the noise-free validation data, every run counted (a diverging model scores 0).
//!
//! - B2 (Example I, N = 75, 25 dB), `--reg bpdn-sv`, 20 runs per p: at least 95 at every
//!   p in 3..14 (the toolbox: 95.0 / 92.6 / 91.3 / 92.1 at p = 5 / 8 / 10 / 12).
//! - B2 at the large past windows p = 12, 13, 14 (issue 16), 40 runs on seeds 100..140 (a
//!   family no figure was tuned on): mean at least 95.5 at each p; the spread is printed.
//! - B3 (Example II, N = 250), the best of our regularisations, 10 runs per p: at least 97
//!   at every p in 3..14. Tikhonov-GCV at every p, BPDN-SV at p = 3..8 (it is the one
//!   that holds at p = 3, where the past window truncates the n = 4 dynamics and
//!   Tikhonov-GCV picks order 2 in half the runs); the BPDN-SV sweep to p = 14 takes
//!   minutes and lives in `examples/bpdn_montecarlo.rs` (98.6-99.2 at p = 3..10).
//!
//! - B2 with the paper's own BPDN-SV score (Algorithm 1, `--bpdn-score paper`), 20 runs at
//!   p = 5 / 8 / 10: within 6 points of the toolbox's BPDN-SV (95.0 / 92.6 / 91.3), and
//!   below our default (realized-model simulation score) at each p.
//!
//! Release mode: `cargo test --release -p lpvid-host --test acceptance_bpdn -- --nocapture`.

use std::path::Path;

use lpvid_host::cli::run;
use lpvid_host::lpvss::Signals;
use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::pbsid::{fit, fit_with_validation, BpdnScore, Order, PbsidOptions, Reg};
use lpvid_host::systems::{self, Experiment};

fn vaf_with(e: &Experiment, o: &PbsidOptions) -> (f64, usize) {
    let f = fit(&e.train, o).expect("fit");
    let val: &Signals = &e.val;
    let v = mean(&vaf_per_output(&val.y, &f.model.simulate(val, None), 0));
    (v, f.order)
}

fn vaf(e: &Experiment, p: usize, reg: Reg) -> (f64, usize) {
    let mut o = PbsidOptions::new(p);
    o.reg = reg;
    vaf_with(e, &o)
}

fn mean_vaf(exp: impl Fn(u64) -> Experiment, runs: u64, p: usize, reg: Reg) -> (f64, f64) {
    let res: Vec<(f64, usize)> = (0..runs).map(|s| vaf(&exp(s), p, reg)).collect();
    let v: Vec<f64> = res.iter().map(|r| r.0).collect();
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    (mean(&v), min)
}

/// Mean and minimum VAF of BPDN-SV on B2 (N = 75, 25 dB, seeds 0..runs) with `score`.
fn b2_sv(runs: u64, p: usize, score: BpdnScore, order: Order) -> (f64, f64) {
    let v: Vec<f64> = (0..runs)
        .map(|s| {
            let mut o = PbsidOptions::new(p);
            o.reg = Reg::BpdnSv;
            o.bpdn_score = score;
            o.order = order;
            vaf_with(&systems::b2(75, 25.0, s), &o).0
        })
        .collect();
    (mean(&v), v.iter().copied().fold(f64::INFINITY, f64::min))
}

/// The sparse paper's Algorithm 1 (`BpdnScore::OneStep`: path on the first three quarters,
/// one-step error on the windows of the last quarter, order from the singular values)
/// against the MATLAB toolbox's BPDN-SV on the same recipe (BENCHMARKS.md B2), and against
/// our default. Measured (seeds 0..20, mean VAF at p = 5 / 8 / 10): paper rule 91.7 / 90.9
/// / 86.0 (with n = 2 given, as the paper's Fig. 2 does: 92.3 / 90.8 / 89.3), default
/// 96.7 / 95.9 / 95.6; toolbox 95.0 / 92.6 / 91.3. Tolerance 6 points: over 80 runs the
/// paper rule gives 89.8 / 91.0 / 89.1, so the 20-run mean moves by up to 3 points with
/// the seeds (single runs fall to 16-27 VAF), and our rule stays 1.6-5.2 below the toolbox
/// even at 80 runs (its SPGL1 root-finding visits 2-7 points of the Pareto curve, our path
/// 50 lambdas; stopping at the first rise of the validation error instead of 8 points
/// later gives 88.9 / 89.4 / 81.7).
#[test]
fn b2_paper_bpdn_sv_against_the_toolbox() {
    let toolbox = [(5usize, 95.0), (8, 92.6), (10, 91.3)];
    println!("B2, N = 75, 25 dB, 20 runs: mean / min free-run VAF of BPDN-SV");
    println!("   p   paper rule      paper, n = 2    default         toolbox");
    let mut fails = vec![];
    for (p, tb) in toolbox {
        let paper = b2_sv(20, p, BpdnScore::OneStep, Order::Auto);
        let paper2 = b2_sv(20, p, BpdnScore::OneStep, Order::Fixed(2));
        let ours = b2_sv(20, p, BpdnScore::Simulation, Order::Auto);
        println!(
            "  {p:2}   {:6.2} / {:5.2}  {:6.2} / {:5.2}  {:6.2} / {:5.2}  {tb:5.1}",
            paper.0, paper.1, paper2.0, paper2.1, ours.0, ours.1
        );
        for (what, v) in [("paper rule", paper.0), ("paper rule, n = 2", paper2.0)] {
            if (v - tb).abs() > 6.0 {
                fails.push(format!("p = {p}: {what} {v:.2} vs toolbox {tb}"));
            }
        }
        if ours.0 <= paper.0 || ours.0 <= paper2.0 {
            fails.push(format!(
                "p = {p}: default {:.2} does not beat the paper rule {:.2} / {:.2}",
                ours.0, paper.0, paper2.0
            ));
        }
    }
    assert!(fails.is_empty(), "{fails:?}");
}

/// `--bpdn-score` on the command line: documented in --help, recorded in the model's fit
/// record, the same model as the library call (with and without `--val`), and refused
/// without `--reg bpdn-sv`.
#[test]
fn bpdn_score_on_the_command_line() {
    let mut help = Vec::new();
    run(["lpvid", "pbsid", "--help"], &mut help).unwrap();
    let help = String::from_utf8(help).unwrap();
    assert!(help.contains("--bpdn-score"), "{help}");
    let dir = tempfile::tempdir().unwrap();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("fixtures");
    let train = fixtures.join("b2-train.csv");
    let val = fixtures.join("b2-val.csv");
    let out = dir.path().join("m.json");
    let exp = systems::b2(75, 25.0, 1);
    for (flag, score, reg, with_val) in [
        (Some("paper"), BpdnScore::OneStep, "bpdn-sv", false),
        (Some("paper"), BpdnScore::OneStep, "bpdn-sv", true),
        (None, BpdnScore::Simulation, "bpdn-sv", false),
        (Some("simulation"), BpdnScore::Simulation, "bpdn-sv", false),
        (Some("paper"), BpdnScore::OneStep, "tikhonov-gcv", false),
    ] {
        let mut args = vec![
            "lpvid",
            "pbsid",
            "--train",
            train.to_str().unwrap(),
            "--past",
            "8",
            "--reg",
            reg,
            "--out",
            out.to_str().unwrap(),
            "--json",
        ];
        if let Some(f) = flag {
            args.extend(["--bpdn-score", f]);
        }
        if with_val {
            args.extend(["--val", val.to_str().unwrap()]);
        }
        let mut sink = Vec::new();
        let res = run(args.clone(), &mut sink);
        if reg != "bpdn-sv" {
            let err = res
                .expect_err("--bpdn-score needs --reg bpdn-sv")
                .to_string();
            assert!(err.contains("--bpdn-score"), "{err}");
            continue;
        }
        res.unwrap();
        let summary: serde_json::Value = serde_json::from_slice(&sink).unwrap();
        assert_eq!(summary["fit"]["reg"], "bpdn-sv");
        assert_eq!(summary["fit"]["bpdn_score"], score.name(), "{args:?}");
        let mut o = PbsidOptions::new(8);
        o.reg = Reg::BpdnSv;
        o.bpdn_score = score;
        let f = fit_with_validation(&exp.train, with_val.then_some(&exp.val), &o).unwrap();
        assert_eq!(summary["order"], f.order);
        let model = lpvid_host::model::ModelFile::read(&out).unwrap();
        let ds = lpvid_host::data::Dataset::read_csv(&val).unwrap();
        let (y, yh) =
            lpvid_host::simulate::simulate(&model, &ds, lpvid_host::simulate::Mode::FreeRun)
                .unwrap();
        let cli_vaf = mean(&vaf_per_output(&y, &yh, 0));
        let lib_vaf = mean(&vaf_per_output(
            &exp.val.y,
            &f.model.simulate(&exp.val, None),
            0,
        ));
        println!(
            "--bpdn-score {flag:?}{}: order {}, VAF {cli_vaf:.3}",
            if with_val { " --val" } else { "" },
            f.order
        );
        assert!((cli_vaf - lib_vaf).abs() < 1e-6, "{cli_vaf} vs {lib_vaf}");
        if score == BpdnScore::OneStep {
            assert!(
                summary["fit"]["solver_reason"]
                    .as_str()
                    .unwrap()
                    .contains("Algorithm 1"),
                "{summary}"
            );
        }
    }
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

/// Issue 16: BPDN-SV stays at the level of the small past windows at p = 12..14 (before the
/// search over past windows of `sparse::sv_over_depths` it gave 95.2-95.8 on other seed
/// families, 94.9 on one). 40 runs per p, seeds 100..140.
#[test]
fn b2_bpdn_sv_large_past_windows_40_runs() {
    println!("B2, N = 75, 25 dB, 40 runs (seeds 100..140): free-run VAF of BPDN-SV");
    println!("   p    mean     std     min");
    let mut fails = vec![];
    for p in 12..=14 {
        let v: Vec<f64> = (100..140)
            .map(|s| vaf(&systems::b2(75, 25.0, s), p, Reg::BpdnSv).0)
            .collect();
        let m = mean(&v);
        let std = (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
        let min = v.iter().copied().fold(f64::INFINITY, f64::min);
        println!("  {p:2}   {m:6.2}  {std:6.2}  {min:6.2}");
        if m < 95.5 {
            fails.push((p, m));
        }
    }
    assert!(
        fails.is_empty(),
        "mean VAF below 95.5 at (p, VAF) {fails:?}"
    );
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
