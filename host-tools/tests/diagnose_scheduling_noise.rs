//! Scheduling-noise on LPV state-space plants (issue 14; docs/bench-diagnose.md, "eleventh
//! session"): the catalogue's variant that keeps the measured scheduling signal and adds its
//! causal low-pass as one more scheduling signal (`catalogue::Catalogue::smoothed_scheduling`),
//! nested in the user's structure. The BC-IV path (LPV-ARX) was the only scheduling-noise
//! variant before; on the family's state-space plants it was never named. Twelfth session: the
//! user's structure refitted on the scheduling sequence the outputs say the plant saw
//! (`diagnose::latent`, `refit::fit_latent`), for scheduling signals whose white part is the
//! plant's own (no low-pass can separate the sensor's noise from it). Thirteenth session: each
//! round of that refit refined by output error, the variant judged against the user's
//! structure refined the same way. Run in release mode.

mod diagnose_support;

use diagnose_support::family::{diagnose_one, run_one};
use lpvid_host::diagnose::plants::family_case;

/// scheduling-noise plants 41001 (order 3, affine in p1, a slowly varying p1) and 9002 (order
/// 1, random binary input): the oracle (the user's structure refit on the noise-free p1)
/// reaches 1.39x and 6.80x of the held-out error. Nothing was named on either before the
/// eleventh session (the BC-IV variants, LPV-ARX models, explained little of a state-space
/// plant); on 41001 the low-pass scheduling signal is named (1.22x), on 9002 the BC-IV model
/// (4.80x).
#[test]
fn a_noisy_scheduling_sensor_is_named_on_a_state_space_plant() {
    for (seed, at_least) in [(41001, 1.15), (9002, 3.0)] {
        let run = run_one("scheduling-noise", seed, 1500);
        println!("{seed}: {} {:.3} {:?}", run.named, run.ratio, run.oracle);
        assert_eq!(run.named, "scheduling-noise", "{seed}");
        assert!(run.ratio >= at_least, "{seed}: {}", run.ratio);
    }
    let (_, out) = diagnose_one("scheduling-noise", 41001, 1500);
    let first = out.report.findings.first().expect("a finding");
    assert!(first.detail.contains("lowpass"), "{}", first.detail);
    assert!(first.significant);
}

/// scheduling-noise plants 21002 (order 4, low-pass input, sensor noise 0.19 std(p1)), 31000
/// (order 3, sensor noise 0.24 std(p1)) and 1000 (order 3, random binary input, 0.26 std(p1)):
/// the oracle reaches 3.72x, 3.35x and 3.44x. The first two were not named before the twelfth
/// session (the low-pass variants explained under 5 %: the plant's p1 has a white part of its
/// own); the latent-sequence refit gained 1.86x and 2.04x with its rounds refitted by PBSID,
/// and on 1000 it drifted (0.71x after four rounds). Each round refined by output error and
/// judged against the user's structure refined the same way: 3.57x, 3.95x and 4.80x.
#[test]
fn the_outputs_locate_a_noisy_scheduling_signal_with_a_white_part() {
    for (seed, at_least) in [(21002, 2.5), (31000, 3.0), (1000, 3.0)] {
        let run = run_one("scheduling-noise", seed, 1500);
        println!("{seed}: {} {:.3} {:?}", run.named, run.ratio, run.oracle);
        assert_eq!(run.named, "scheduling-noise", "{seed}");
        assert!(run.ratio >= at_least, "{seed}: {}", run.ratio);
    }
    let (_, out) = diagnose_one("scheduling-noise", 31000, 1500);
    let first = out.report.findings.first().expect("a finding");
    assert!(first.detail.contains("re-estimated"), "{}", first.detail);
    assert!(
        first.detail.contains("refined by output error"),
        "{}",
        first.detail
    );
    let est = &out.model.fit["scheduling_estimate"];
    assert_eq!(est["columns"][0], "p1", "{est}");
    assert!(est["rounds"].as_u64().is_some_and(|r| r >= 1), "{est}");
}

/// The clean scheduled plants of two seed ranges (the user's structure is the plant's, the
/// scheduling signal noise-free, some with a white part the plant responds to): the variant
/// nests the model, so it has nothing to add and no scheduling-noise finding is significant.
#[test]
fn a_noise_free_scheduling_signal_gives_no_scheduling_noise_finding() {
    let mut scheduled = 0;
    for seed in [1000, 1002, 1003, 3000, 3001, 53002] {
        let case = family_case("clean", seed, 1500).unwrap();
        if case.train.column("p1").is_none() {
            continue;
        }
        let (_, out) = diagnose_one("clean", seed, 1500);
        scheduled += 1;
        for f in &out.report.findings {
            println!(
                "clean {seed}: {} {:.3} significant {}",
                f.effect, f.explained, f.significant
            );
            assert!(
                !(f.effect == "scheduling-noise" && f.significant),
                "clean {seed}: {} {:.3}",
                f.detail,
                f.explained
            );
        }
    }
    assert_eq!(scheduled, 6);
}
