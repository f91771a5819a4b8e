//! Issue 7 acceptance: for every effect of the catalogue (DESIGN.md section 6) a plant of our
//! own with that effect (several seeds), a model identified without it by `lpvid pbsid`, and
//! `diagnose --fix`: the effect must be named first and the validation error variance (mean
//! square error about zero; one-step for coloured-noise, free run otherwise) must drop at
//! least 2x. A clean plant must give no finding above the noise threshold in >= 90 % of seeds.
//! Run in release mode: `cargo test --release --test diagnose_planted`; one seed per effect
//! and ten clean seeds there, more with `-- --include-ignored` (`make test-long`).

mod diagnose_support;

use diagnose_support::{mse, run_case};
use lpvid_host::simulate::Mode;

/// The seeds of `make test` (one plant per effect) and the more of `make test-long`.
const SEEDS: [u64; 1] = [1];
const MORE_SEEDS: [u64; 2] = [2, 3];

/// The catalogue's effects these tests plant: the family's, without the clean plant and
/// output-nonlinearity (tested on its own plants in `output_nonlinearity.rs`).
fn planted_effects() -> impl Iterator<Item = &'static str> {
    lpvid_host::diagnose::plants::FAMILY_EFFECTS
        .into_iter()
        .filter(|e| !matches!(*e, "clean" | "output-nonlinearity"))
}

fn check(effect: &str) {
    check_seeds(effect, &SEEDS);
}

fn check_seeds(effect: &str, seeds: &[u64]) {
    for &seed in seeds {
        let case = run_case(effect, seed);
        let r = &case.outcome.report;
        let names: Vec<String> = r
            .findings
            .iter()
            .take(4)
            .map(|f| {
                format!(
                    "{} {:.3} p={:.1e}{}",
                    f.effect,
                    f.explained,
                    f.p_value,
                    if f.significant { "*" } else { "" }
                )
            })
            .collect();
        println!("{effect} seed {seed}: {}", names.join(" | "));
        if std::env::var("DIAG_VERBOSE").is_ok() {
            for v in &r.steps[0].variants_scored {
                println!(
                    "    {:<24} {:>9.4} p={:.1e} {}",
                    v.effect, v.explained, v.p_value, v.detail
                );
            }
            for f in &r.findings {
                println!(
                    "    finding {} {:.3} sig {} repl {:?}",
                    f.effect, f.explained, f.significant, f.replication
                );
            }
        }
        let first = r.findings.first().expect("findings");
        assert_eq!(first.effect, effect, "seed {seed}: {names:?}");
        assert!(first.significant, "seed {seed}: {names:?}");
        assert_eq!(r.applied.len(), 1, "seed {seed}");
        let mode = if effect == "coloured-noise" {
            Mode::Predictor
        } else {
            Mode::FreeRun
        };
        let before = mse(&case.before, &case.val, mode);
        let after = mse(&case.outcome.model, &case.val, mode);
        println!(
            "{effect} seed {seed}: validation MSE {before:.4e} -> {after:.4e} ({:.1}x), VAF {:.2} -> {:.2}",
            before / after,
            r.before.vaf_mean,
            r.after.as_ref().unwrap().vaf_mean
        );
        assert!(before >= 2.0 * after, "seed {seed}: {before} -> {after}");
    }
}

#[test]
fn output_offset() {
    check("output-offset");
}

#[test]
fn feedthrough() {
    check("feedthrough");
}

#[test]
fn scheduled_output() {
    check("scheduled-output");
}

#[test]
fn scheduling_nonlinearity() {
    check("scheduling-nonlinearity");
}

#[test]
fn input_nonlinearity() {
    check("input-nonlinearity");
}

#[test]
fn input_delay() {
    check("input-delay");
}

#[test]
fn scheduling_noise() {
    check("scheduling-noise");
}

#[test]
fn periodic_disturbance() {
    check("periodic-disturbance");
}

#[test]
fn order_too_low() {
    check("order-too-low");
}

#[test]
fn coloured_noise() {
    check("coloured-noise");
}

#[test]
fn unused_signal() {
    check("unused-signal");
}

/// The same acceptance on two more seeds per effect (long tier: 22 diagnoses).
#[test]
#[ignore = "long tier: make test-long"]
fn every_effect_on_more_seeds() {
    for effect in planted_effects() {
        check_seeds(effect, &MORE_SEEDS);
    }
}

/// Clean plants: at most one false alarm in ten seeds (100..110 here, 110..130 in the long
/// tier: the rule holds on each set).
#[test]
fn clean_plant_no_false_alarms() {
    clean_plants((100..110).collect());
}

#[test]
#[ignore = "long tier: make test-long"]
fn clean_plant_no_false_alarms_more_seeds() {
    clean_plants((110..130).collect());
}

fn clean_plants(seeds: Vec<u64>) {
    // (seed, best effect, explained, p, significant), three diagnoses at a time
    let results = std::sync::Mutex::new(Vec::new());
    let next = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|s| {
        for _ in 0..3 {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(&seed) = seeds.get(i) else { break };
                let case = run_case("clean", seed);
                let r = &case.outcome.report;
                let f = r.findings.first().unwrap();
                if f.significant {
                    assert_eq!(r.applied.len(), 1);
                } else {
                    // no fix; a score after only when the estimate was refined
                    assert!(r.applied.is_empty());
                    assert_eq!(r.after.is_some(), r.refined.is_some());
                    assert!(r.stopped.contains("nothing explains"), "{}", r.stopped);
                }
                results.lock().unwrap().push((
                    seed,
                    f.effect,
                    f.explained,
                    f.p_value,
                    f.significant,
                ));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);
    for (seed, effect, explained, p, sig) in &results {
        println!("clean seed {seed}: best {effect} {explained:.3} p={p:.1e} significant {sig}");
    }
    let alarms = results.iter().filter(|r| r.4).count();
    println!(
        "clean plant: {alarms} false alarms in {} seeds",
        seeds.len()
    );
    assert!(alarms * 10 <= seeds.len(), "{alarms} false alarms");
}

/// The family benchmark at a small size (issue 14): one random plant per planted effect
/// (plus a clean plant), N = 1500, one --fix step each; prints the confusion matrix and
/// asserts the goals that hold at this size (see docs/bench-diagnose.md for the full run).
#[test]
fn plant_family_confusion_matrix() {
    family_matrix(&[500]);
}

/// The same on two plants per effect (long tier).
#[test]
#[ignore = "long tier: make test-long"]
fn plant_family_confusion_matrix_two_seeds() {
    family_matrix(&[500, 501]);
}

fn family_matrix(seeds: &[u64]) {
    use diagnose_support::family::{matrix, run_family, summary};
    use lpvid_host::diagnose::plants::FAMILY_EFFECTS;
    let t0 = std::time::Instant::now();
    let runs = run_family(&FAMILY_EFFECTS, seeds, 1500, 2);
    for r in &runs {
        println!(
            "{:<24} seed {}: named {:<24} ratio {:.2} ({})",
            r.planted, r.seed, r.named, r.ratio, r.description
        );
    }
    println!("{}", matrix(&runs));
    println!("{:.0} s", t0.elapsed().as_secs_f64());
    let sum = summary(&runs);
    // every run finished (no refit error escaped as a failure of the diagnosis)
    assert!(runs.iter().all(|r| !r.named.starts_with("error")));
    // a fix never makes the held-out error worse
    for r in &runs {
        assert!(
            r.ratio >= 1.0 - 1e-9,
            "{} seed {}: ratio {}",
            r.planted,
            r.seed,
            r.ratio
        );
    }
    // the effects that meet the recall goal on the published family (docs/bench-diagnose.md):
    // named first on at least 90 % of these plants together, and a median error ratio >= 3
    let solid = [
        "output-offset",
        "feedthrough",
        "input-delay",
        "unused-signal",
        "periodic-disturbance",
        "scheduling-nonlinearity",
        // since the family plants x(k+1) = A x + B u + dir g(y(k)) with the nonlinear share of
        // the output as its strength: 15 of 16 named, median ratio 8 (docs/bench-diagnose.md)
        "output-nonlinearity",
    ];
    let (hits, total): (f64, f64) = solid
        .iter()
        .map(|e| (sum[*e].0 * sum[*e].4 as f64, sum[*e].4 as f64))
        .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    assert!(hits / total >= 0.9, "recall {hits} of {total}");
    for e in solid {
        assert!(sum[e].1 >= 3.0, "{e}: median error ratio {}", sum[e].1);
    }
}

/// A finding must also beat the model's own structure with a larger past window
/// (`effects::larger_past`, issue 14): on two clean scheduled family plants whose user's past
/// window (7, the cap) truncates the slow frozen dynamics, an offset channel (seed 1002: 20.3 %
/// of the null's held-out error, replicated) and two noise states through K (seed 3000: 46.6 %
/// of the one-step error, replicated) were findings before; against the same structure with
/// past window 9 (fitted in the kernel form) they explain -4.3 % and -15.4 %: the bias of
/// the short past window, not the effect. What is applied, if anything, is that past window
/// (seed 1002: order-too-low "past window 9 (was 7)", 23.7 %, replicated; seed 3000: it
/// explains 48.3 % but does not replicate, nothing is applied).
#[test]
#[ignore = "long tier: make test-long"]
fn larger_past_window_blocks_findings_of_a_biased_model() {
    use diagnose_support::family::diagnose_one;
    for (seed, effect) in [(1002u64, "output-offset"), (3000, "coloured-noise")] {
        let (_, out) = diagnose_one("clean", seed, 1500);
        let r = &out.report;
        let st = &r.steps[0];
        // the larger structure was scored (it exceeds the catalogue's regressor limit at past
        // 9 for a scheduled model: fitted in the kernel form)
        let l = st
            .variants_scored
            .iter()
            .find(|v| v.detail.starts_with("past window 9 (was 7)"))
            .unwrap_or_else(|| panic!("seed {seed}: no larger past window variant"));
        assert!(l.error.is_none(), "seed {seed}: {:?}", l.error);
        assert_eq!(l.effect, "order-too-low");
        let f = st.findings.iter().find(|f| f.effect == effect).unwrap();
        println!(
            "clean seed {seed}: {effect} explains {:.3} (p = {:.1e}), blocked by {:?}",
            f.explained, f.p_value, f.blocked_by
        );
        assert!(f.explained >= 0.10, "seed {seed}: {}", f.explained);
        assert!(!f.significant);
        let why = f.blocked_by.as_deref().unwrap();
        assert!(why.contains("larger past window"), "seed {seed}: {why}");
        // no effect is credited with the bias: at most the larger past window is applied
        assert!(
            r.applied
                .iter()
                .all(|a| a.effect == "order-too-low" && a.detail.starts_with("past window 9")),
            "seed {seed}: {:?}",
            r.applied
        );
    }
}

/// The two scheduling effects told apart by refits of the same kind (issue 14, helper h15so):
/// each is also tried refined from the model's own structure refined (output error), the
/// added coefficients started at zero (`refit::fit_nested`), and judged against that refined
/// structure. Before, the scheduled-output plant of family seed 1002 was named
/// scheduling-nonlinearity (p1^2, 87.5 %: the nested least-squares output equation kept the
/// unrefined A(mu), B(mu) and explained 77.9 %); refined, the planted output equation
/// explains 90 % of the refined structure's held-out error and p1^2 88 %. On the
/// scheduling-nonlinearity plant of seed 5003 the refined p1^2 explains 99.5 % and the
/// refined output equation 91.5 %: the planted one is named, and its fix is applied.
#[test]
#[ignore = "long tier: make test-long"]
fn scheduling_effects_told_apart_by_refined_nested_refits() {
    use diagnose_support::family::diagnose_one;
    for (effect, seed) in [
        ("scheduled-output", 1002u64),
        ("scheduling-nonlinearity", 5003),
    ] {
        let t0 = std::time::Instant::now();
        let (_, out) = diagnose_one(effect, seed, 1500);
        let r = &out.report;
        let st = &r.steps[0];
        let refined = |e: &str| {
            st.variants_scored
                .iter()
                .find(|v| v.effect == e && v.detail.contains("refined from the model's own"))
                .unwrap_or_else(|| panic!("{effect} {seed}: no refined {e} variant"))
        };
        let (so, sn) = (
            refined("scheduled-output"),
            refined("scheduling-nonlinearity"),
        );
        println!(
            "{effect} seed {seed}: refined scheduled-output {:.3} ({:?}), refined p1^2 {:.3} ({:?}); named {:?}, {:.0} s",
            so.explained,
            so.error,
            sn.explained,
            sn.error,
            r.findings.first().map(|f| (f.effect, f.explained, f.significant)),
            t0.elapsed().as_secs_f64()
        );
        assert!(so.error.is_none() && sn.error.is_none());
        let (planted, other) = if effect == "scheduled-output" {
            (so, sn)
        } else {
            (sn, so)
        };
        assert!(
            planted.explained >= 0.5,
            "{effect} {seed}: {}",
            planted.explained
        );
        assert!(planted.explained > other.explained);
        let first = r.findings.first().unwrap();
        assert_eq!(first.effect, effect, "seed {seed}");
        assert!(first.significant);
        assert_eq!(r.applied.first().map(|a| a.effect), Some(effect));
    }
}

/// The family's coloured-noise plant 197000 (order 2, past window 8, noise strength 0.48):
/// the user's least-squares K leaves A - K C with spectral radius 1.17, its one-step
/// prediction runs away (one-step VAF 0 %, the fix's error ratio 6.5e199). The report says
/// why beside the scores it explains, and the noise model it adds predicts.
#[test]
fn an_unstable_predictor_is_named_in_the_report() {
    let (_, out) = diagnose_support::family::diagnose_one("coloured-noise", 197000, 1500);
    let r = &out.report;
    let note = r
        .notes
        .iter()
        .find(|n| n.contains("one-step predictor A(mu) - K(mu) C is unstable"))
        .unwrap_or_else(|| panic!("a note on the unstable predictor in {:?}", r.notes));
    let rho = diagnose_support::family::number_after(note, "spectral radius reaches ");
    assert!((1.0..1.5).contains(&rho), "{rho}");
    let a = r.applied.first().expect("a noise model applied");
    assert_eq!(a.effect, "coloured-noise");
    assert!(
        a.mse_after.is_finite() && a.mse_after < 1.0,
        "{}",
        a.mse_after
    );
    let text = lpvid_host::diagnose::report::summary(r, &[]);
    assert!(
        text.contains("Note: the model's one-step predictor"),
        "{text}"
    );
}
