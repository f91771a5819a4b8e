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

use diagnose_support::family::{blocked_finding, diagnose_one, fix_ratio, number_after, run_one};
use lpvid_host::diagnose::plants::family_case;

/// scheduling-noise plant 9002 (order 1, random binary input): the oracle (the user's
/// structure refit on the noise-free p1) reaches 6.80x of the held-out error. Nothing was named
/// before the eleventh session; the BC-IV model (LPV-ARX) is named now (4.80x).
#[test]
#[ignore = "long tier: make test-long"]
fn a_noisy_scheduling_sensor_is_named_on_a_state_space_plant() {
    let run = run_one("scheduling-noise", 9002, 1500);
    println!("9002: {} {:.3} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "scheduling-noise");
    assert!(run.ratio >= 3.0, "{}", run.ratio);
}

/// scheduling-noise plant 41001 (order 3, affine in p1, a slowly varying p1; the oracle 1.39x
/// of the subspace refit's held-out error): the low-pass scheduling signal beside p1
/// (`catalogue::Catalogue::smoothed_scheduling`) explains 21.8 % of the refit's error,
/// replicated, and was named (1.22x) until the twentieth session. The user's own structure
/// refined by output error predicts better than that fix (the variant explains -22.7 % of its
/// error): what the low-pass signal removed was the bias of the subspace estimate, which the
/// refinement removes too, so it is not a finding (`effects::needs_refined_null`, as for a p1^2
/// basis); the latent sequence, judged against that refined structure, explains 8.2 %, below
/// the 10 % of a finding.
#[test]
fn a_low_pass_signal_the_refined_structure_beats_is_not_named() {
    let (_, out) = diagnose_one("scheduling-noise", 41001, 1500);
    let (lp, why) = blocked_finding(&out.report, "scheduling-noise");
    assert!(lp.detail.contains("lowpass"), "{}", lp.detail);
    assert!(lp.explained >= 0.15, "{}", lp.explained);
    assert!(why.contains("refined by output error removes"), "{why}");
    let against = number_after(why, "against it this variant explains ");
    assert!(against < 0.0, "{against}");
}

/// scheduling-noise plants 21002 (order 4, low-pass input, sensor noise 0.19 std(p1)), 31000
/// (order 3, sensor noise 0.24 std(p1)) and 1000 (order 3, random binary input, 0.26 std(p1)):
/// the oracle reaches 3.72x, 3.35x and 3.44x. The first two were not named before the twelfth
/// session (the low-pass variants explained under 5 %: the plant's p1 has a white part of its
/// own); the latent-sequence refit gained 1.86x and 2.04x with its rounds refitted by PBSID,
/// and on 1000 it drifted (0.71x after four rounds). Each round refined by output error and
/// judged against the user's structure refined the same way: 3.57x, 3.95x and 4.80x.
#[test]
#[ignore = "long tier: make test-long"]
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
#[ignore = "long tier: make test-long"]
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

/// scheduling-noise plant 171006 (order 4, two resonant pairs, random binary input; p1 a slow
/// sinusoid plus a slow wander, measured with a white sensor noise of 0.091 RMS): the user's
/// structure refined on the noise-free p1 explains 88 % of the held-out error of the same
/// refinement on the measured p1. With each sample of p tied to its measurement alone the MAP
/// sequence came only from 0.091 to 0.074 RMS of the true p1, the refits drifted (-18 % after
/// eight rounds) and nothing was named. With the smoothness prior (`latent::SmoothnessPrior`,
/// a white second difference whose variance is fitted to the measured spectrum) it comes to
/// 0.039 and the fix gains 10.5x (measured 2026-12-02).
#[test]
#[ignore = "long tier: make test-long"]
fn a_slowly_wandering_scheduling_signal_is_recovered_by_its_smoothness() {
    let (_, out) = diagnose_one("scheduling-noise", 171006, 1500);
    let first = out.report.findings.first().expect("a finding");
    assert_eq!(first.effect, "scheduling-noise", "{}", first.detail);
    assert!(first.detail.contains("moving smoothly"), "{}", first.detail);
    let ratio = fix_ratio(&out);
    assert!(ratio >= 5.0, "{ratio}");
    let est = &out.model.fit["scheduling_estimate"];
    let sd = est["smoothness_prior_std"][0]
        .as_f64()
        .expect("a smoothness prior");
    // the second difference's std far below the sensor's (sqrt(6) x 0.091)
    assert!(sd > 0.0 && sd < 0.05, "{est}");
}
