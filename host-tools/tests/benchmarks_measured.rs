//! The public benchmarks of ../shared/data on their splits, before and after
//! `lpvid diagnose --fix` (diagnose holds out the last fifth of the training data; the test
//! set is never seen): docs/benchmarks-measured.md has the table beside the published
//! figures. Each test asserts the improvement it measured (release mode, `-- --nocapture`
//! prints the run); tests skip with a message when ../shared/data is absent.

mod benchmarks_support;

use benchmarks_support::{benches, describe, run_bench_at, shared_data, Bench, Result};

/// The benchmark `name` run with the user's model at past window 10 (None without the data).
fn bench(name: &str) -> Option<(Bench, Result)> {
    bench_at(name, 10)
}

/// [`bench`] with the user's model identified at past window `past`.
fn bench_at(name: &str, past: usize) -> Option<(Bench, Result)> {
    let Some(dir) = shared_data() else {
        eprintln!("skipped: ../shared/data not found");
        return None;
    };
    let b = benches().into_iter().find(|b| b.name == name).unwrap();
    let r = run_bench_at(&dir, &b, past);
    println!("{}", describe(&b, &r));
    Some((b, r))
}

fn applied(r: &Result) -> Vec<&'static str> {
    r.outcome.report.applied.iter().map(|a| a.effect).collect()
}

/// The Silverbox's acceptance on the full arrow: output-nonlinearity applied, and the RMSE
/// from about 15 mV to at most 2.5 mV from the zero and from an estimated initial state.
fn assert_cubic_found(r: &Result) {
    assert!(
        applied(r).contains(&"output-nonlinearity"),
        "{:?}",
        applied(r)
    );
    let (_, before, _, after, after_est) = r.rmse[0];
    assert!(before > 0.010, "{before}");
    assert!(
        after <= 0.0025 && after_est <= 0.0025,
        "{after} {after_est}"
    );
}

/// Silverbox, trained on the multisine part, tested on the arrow: the cubic spring is found
/// as a Lur'e feedback y^3 and the arrow's RMSE drops from about 15 mV to below the 2.5 mV
/// target (the recurrent-network baselines: LSTM 2.68 mV, GRU 2.80 mV).
#[test]
#[ignore = "long tier: make test-long"]
fn silverbox_arrow() {
    let Some((_, r)) = bench("silverbox") else {
        return;
    };
    assert_cubic_found(&r);
    // without extrapolation (the first 32000 samples of the arrow)
    let (_, b2, _, a2, _) = r.rmse[1];
    assert!(a2 < b2 / 5.0 && a2 <= 0.0025, "{b2} {a2}");
}

/// Silverbox as [`silverbox_arrow`] from a user model at past 5, where `--order auto` keeps
/// three states (at past 10 two): the diagnosis must not depend on the model having no state
/// to spare. Before the Lur'e channels were also tried with a constant channel
/// (`diagnose::output`, `has_mean`), y1^3 explained 99.7 % of the held-out error but leaned
/// on its estimated start (a spare slow state held the offset), and the arrow stayed at
/// 14.1 mV.
#[test]
#[ignore = "long tier: make test-long"]
fn silverbox_arrow_from_three_states() {
    let Some((_, r)) = bench_at("silverbox", 5) else {
        return;
    };
    assert_eq!(r.model.fit["order"], 3, "{}", r.model.fit["order_reason"]);
    assert_cubic_found(&r);
}

/// Unbalanced disk (train on rows 18000-27999, test on 31500-34999): the gravity torque of the
/// off-centre mass is found as an output feedback and the test RMSE drops below the 0.12 rad
/// target (linear 0.219 rad and a good neural net 0.095 rad on the benchmark's hidden test).
#[test]
#[ignore = "long tier: make test-long"]
fn unbalanced_disk() {
    let Some((_, r)) = bench("disk") else {
        return;
    };
    assert!(
        applied(&r).contains(&"output-nonlinearity"),
        "{:?}",
        applied(&r)
    );
    let (_, before, _, after, _) = r.rmse[0];
    assert!(after < before / 2.0 && after <= 0.12, "{before} {after}");
}

/// Smart rotor at 370 rpm (rows 0-6999 train, 7000-9999 test, `t` kept): the rotor's
/// periodic disturbance is named first as a harmonic series of the 1P fundamental (frequency
/// by least squares, phase carried by `t`) and the free-run VAF on the test rows reaches the
/// goal of issue 14 (97.5 % / 94.5 %; a refit with 1P and 2P at the exact rotor frequency
/// gave about 98.2 / 95.6). Measured: 1P..6P refined from the model's structure refined first
/// (66 % of that structure's held-out error), then an AR model of the free-run residual; VAF
/// 98.77 / 96.84 from x0 = 0, RMSE 0.556 -> 0.289 (2026-12-07; 1P..4P by PBSID before, 98.25 /
/// 95.84); 98.76 / 96.85 and 0.2895 since the refinement weighs each output by its variance
/// (2026-12-08).
#[test]
#[ignore = "long tier: make test-long"]
fn smart_rotor() {
    assert_rotor_harmonics("rotor", 370.0, [97.5, 94.5], 1.5);
}

/// The same run on the 430 rpm record, which no setting of the diagnosis was chosen on
/// (first run 2026-12-07): the fundamental must be the rotor's 1P at 430 rpm. Measured: 1P..6P
/// of 45.028215 rad/s refined first, then AR innovation states; VAF 98.06 / 95.91 from x0 = 0
/// (98.68 / 96.96 estimated), RMSE 0.628 -> 0.434 (0.589 -> 0.363 estimated; 98.06 / 95.92 and
/// 0.4337 with each output weighed by its variance in the refinement, 2026-12-08); with the series
/// fitted by PBSID alone (1P..4P, 36.5 %) 97.63 / 95.54 and 0.466.
#[test]
#[ignore = "long tier: make test-long"]
fn smart_rotor_430rpm() {
    assert_rotor_harmonics("rotor430", 430.0, [97.0, 94.5], 1.25);
}

/// The rotor benchmark `name` at `rpm`: periodic-disturbance applied first as one harmonic
/// series (1P and at least 2P) of the rotor frequency within 0.1 %, the test record's free-run
/// VAF per output at least `vaf` from the zero and from an estimated initial state, and the
/// RMSE from x0 = 0 divided by at least `gain`.
fn assert_rotor_harmonics(name: &str, rpm: f64, vaf: [f64; 2], gain: f64) {
    let Some((_, r)) = bench(name) else {
        return;
    };
    let first = r.outcome.report.applied.first().expect("a fix applied");
    assert_eq!(first.effect, "periodic-disturbance", "{:?}", applied(&r));
    // the fundamental and at least its second harmonic, in one finding
    assert!(
        first.detail.contains("1P..") && !first.detail.contains("(1P..1P)"),
        "{}",
        first.detail
    );
    // the fundamental is the rotor's 1P, not a periodogram bin
    let om: f64 = first
        .detail
        .split(" of ")
        .find_map(|s| s.split(" rad/s").next().and_then(|v| v.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no rad/s in {}", first.detail));
    let one_p = rpm / 60.0 * 2.0 * std::f64::consts::PI;
    assert!((om / one_p - 1.0).abs() < 1e-3, "{om} vs 1P {one_p}");
    let (_, vaf0, vaf_est) = &r.vaf_after[0];
    for v in [vaf0, vaf_est] {
        assert!(v[0] >= vaf[0] && v[1] >= vaf[1], "{v:?}");
    }
    let (_, before, _, after, _) = r.rmse[0];
    assert!(after < before / gain, "{before} {after}");
}

/// `--order auto` never keeps an order whose held-out free run is far worse than order + 1
/// or + 2 (pipeline `check_order`, rule `pbsid::far_worse`): the chosen order satisfies the
/// rule against the orders the check compared (their errors and the paired test's p-values),
/// and the record says what was compared.
#[test]
fn order_auto_checks_the_free_run() {
    let Some(dir) = shared_data() else {
        eprintln!("skipped: ../shared/data not found");
        return;
    };
    use lpvid_host::pipeline::{identify, DataFile, PbsidSettings};
    let tmp = tempfile::tempdir().unwrap();
    let sb = lpvid_host::data::Dataset::read_csv(&dir.join("silverbox-snls80mv.csv")).unwrap();
    let part = benchmarks_support::segment(&sb, 40575, sb.len(), "");
    let p = tmp.path().join("sb.csv");
    std::fs::write(&p, part.to_csv_bytes(&p).unwrap()).unwrap();
    let files = [
        ("silverbox multisine", p.clone()),
        ("cascaded tanks", dir.join("cascaded-tanks-estimation.csv")),
        ("unbalanced disk", dir.join("unbalanced-disk.csv")),
    ];
    for (name, path) in files {
        for past in [5, 10, 20] {
            let id = identify(
                &DataFile::read(&path).unwrap(),
                None,
                &PbsidSettings::new(past),
            )
            .unwrap();
            let check = &id.model.fit["order_check"];
            println!(
                "{name}, past {past}: order {} ({})\n  {check}",
                id.fit.order, id.fit.order_reason
            );
            let seen: Vec<(u64, f64)> = check["free_run"]
                .as_array()
                .unwrap()
                .iter()
                .map(|e| (e["order"].as_u64().unwrap(), e["vaf"].as_f64().unwrap()))
                .collect();
            let n = id.fit.order as u64;
            let e = |o: u64| seen.iter().find(|s| s.0 == o).map(|s| 1.0 - s.1 / 100.0);
            let en = e(n).unwrap();
            // the paired test's p-value of each comparison the check made
            let p_of = |o: u64| {
                check["compared"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|c| c["order"] == n && c["larger"] == o)
                    .map(|c| c["p_value"].as_f64().unwrap())
            };
            for o in [n + 1, n + 2] {
                if let Some(eo) = e(o) {
                    let p = p_of(o).expect("every larger order scored was compared");
                    assert!(
                        !lpvid_host::pbsid::far_worse(en, eo, p),
                        "{name} past {past}: {check}"
                    );
                }
            }
            if name.starts_with("silverbox") && past == 20 {
                // measured: the gap gives n = 1 (free-run VAF 8.8 % on the last fifth); the
                // check moves to n = 3 (97.1 %; n = 2 gives 87.1 %)
                assert_eq!(check["gap_order"], 1, "{check}");
                assert!(n >= 2 && e(n).unwrap() < 0.1, "{check}");
            }
            if n != check["gap_order"].as_u64().unwrap() {
                // a changed order is written as a fixed rule, so diagnose's refits reproduce it
                assert_eq!(id.model.fit["order_rule"], n.to_string());
            }
        }
    }
}

/// EMPS (emps.csv -> emps-pulses.csv): the force-driven model drifts; the logged position
/// reference q_ref of the closed loop is found as an input and the test RMSE drops by more
/// than two decades (not comparable with the benchmark's force-input figures).
#[test]
#[ignore = "long tier: make test-long"]
fn emps() {
    let Some((_, r)) = bench("emps") else {
        return;
    };
    assert!(applied(&r).contains(&"unused-signal"), "{:?}", applied(&r));
    let (_, before, _, after, _) = r.rmse[0];
    assert!(after < before / 100.0, "{before} {after}");
}

/// Cascaded tanks (estimation file -> validation file): the 205 held-out rows are a short
/// record, cross-validated in 5 blocks (`diagnose::replicate::cv_folds`); the tanks' level
/// dependence is found as a Lur'e feedback sin(omega y1) and, after the selection, the chosen
/// structure is refit on all 1024 estimation rows (`diagnose::refit_on_all`), with the
/// output-error refinement run until it stalls (`refine::stalled`) rather than cut at 60
/// iterations. Measured: 1.166 -> 0.437 V from an estimated initial state (1.402 -> 0.859 V
/// from x0 = 0): the goal, 0.45 V (PNLSS), is asserted.
#[test]
fn cascaded_tanks() {
    let Some((_, r)) = bench("tanks") else {
        return;
    };
    let first = r.outcome.report.applied.first().expect("a fix applied");
    assert_eq!(first.effect, "output-nonlinearity", "{:?}", applied(&r));
    let refit = r
        .outcome
        .report
        .refit_all
        .as_ref()
        .expect("refit on all rows");
    assert_eq!(refit.rows, 1024);
    let (_, b0, b_est, a0, a_est) = r.rmse[0];
    assert!(b_est > 1.0 && b0 > 1.0, "{b0} {b_est}");
    assert!(a_est <= 0.45 && a_est < b_est / 2.0, "{b_est} {a_est}");
    assert!(a0 < b0, "{b0} {a0}");
}
