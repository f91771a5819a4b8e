//! Clean plants of the family (the user's model has the plant's structure) and the rules that
//! keep them clean (issue 14, helper h21cn; docs/bench-diagnose.md, "coloured-noise and
//! order-too-low against the structure refined"): a `coloured-noise` finding needs a
//! refined free-run residual that is not white, an `order-too-low` or `input-delay` finding
//! its structure refined beating the model's structure refined (`states::states_check`). Run
//! in release mode.

mod diagnose_support;

use diagnose_support::family::{
    assert_evidence, assert_refined_not_coloured, blocked_finding, diagnose_one, diagnose_one_auto,
    fix_ratio, named_first, number_after, run_one, states,
};
use lpvid_host::diagnose::plants::Shape;

/// clean plant 31002 (order 4, affine in p1, past window 7, white output noise 1.9 %): an AR
/// noise model on top of K explained 10.2 % of the subspace refit's one-step error,
/// replicated (9.0 %, 3.4 %), and was named. The structure refined by output error explains
/// 68 % of that error with no noise model, and its free-run residual is white (Ljung-Box
/// p = 0.50): the noise is not coloured. Nothing is named now. Since 2026-12-03 the noise
/// model must also beat the refined structure's one-step error (`effects::needs_refined_null`),
/// a rule tested before the white residual: against it the noise model explains -180.8 %.
#[test]
fn a_noise_model_over_a_white_refined_residual_is_not_a_finding() {
    let (_, out) = diagnose_one("clean", 31002, 1500);
    let (cn, why) = blocked_finding(&out.report, "coloured-noise");
    // above the noise threshold against the subspace refit, blocked by the refined structure
    assert!(cn.explained >= 0.10, "{}", cn.explained);
    assert_refined_not_coloured(why, 0.01);
}

/// clean plant 121000 (a fresh range; order 4, pole 0.79, affine in p1, past window 7,
/// white output noise 6.8 %): an AR model of the free-run residual explained 23 % of the
/// subspace refit's one-step error, replicated (8.0 %, 15.3 %), and was named (1.27x), because
/// the structure refined by output error from the PBSID estimate at past 7 stopped in a local
/// minimum (training MSE 3.78e-2) and its leftover bias coloured the residual. Refined from a
/// second start, the estimate at past 9, it reaches 1.739e-2 (the noise floor), its residual
/// is white, and nothing is named; the Lur'e channels that matched the refinement's own gain
/// (52 % each) explain nothing beyond it.
#[test]
#[ignore = "long tier: make test-long"]
fn a_refinement_stuck_in_a_local_minimum_is_not_coloured_noise() {
    let (_, out) = diagnose_one("clean", 121000, 1500);
    let (cn, why) = blocked_finding(&out.report, "coloured-noise");
    assert!(cn.explained >= 0.10, "{}", cn.explained);
    assert_refined_not_coloured(why, 0.05);
    for f in out
        .report
        .findings
        .iter()
        .filter(|f| f.effect == "output-nonlinearity")
    {
        assert!(f.explained < 0.10, "{} {}", f.detail, f.explained);
    }
}

/// clean plant 127001 (a fresh range; order 3, poles 0.13-0.45, affine in p1, past window 7,
/// white input, output noise 6.8 %): the low-pass scheduling signal lowpass0.8(p1) beside p1
/// explained 14.1 % of the subspace refit's held-out error, replicated (5.3 %, 7.1 %), beat
/// the larger past window (18.3 %), and was named scheduling-noise (1.14x) on a noise-free
/// p1. Like a p1^2 basis it absorbs the bias of the subspace estimate: the user's structure
/// refined by output error predicts far better (the variant explains -225 % of its error), so
/// nothing is named.
#[test]
fn a_low_pass_scheduling_signal_absorbing_the_subspace_bias_is_not_scheduling_noise() {
    let (_, out) = diagnose_one("clean", 127001, 1500);
    let (lp, why) = blocked_finding(&out.report, "scheduling-noise");
    assert!(lp.detail.contains("lowpass"), "{}", lp.detail);
    assert!(lp.explained >= 0.10, "{}", lp.explained);
    let against = number_after(why, "against it this variant explains ");
    assert!(against < -100.0, "{against}");
}

/// clean plant 31003 (order 4, affine in p1, past window 7): order 6 explained 27.2 % of the
/// subspace refit's free-run error, replicated (6.5 %, 15.5 %), and was named (1.24x); a noise
/// model with two more states 23.5 % of the one-step error. Refined by output error like the
/// user's structure, order 6 explains -57 % of the refined structure's error, and the refined
/// residual is white (p = 0.044): neither is a finding.
#[test]
#[ignore = "long tier: make test-long"]
fn a_larger_order_the_refined_structure_matches_is_not_a_finding() {
    let (_, out) = diagnose_one("clean", 31003, 1500);
    let r = &out.report;
    let (otl, why) = blocked_finding(r, "order-too-low");
    assert!(otl.explained >= 0.2, "{}", otl.explained);
    assert!(why.contains("refined the same way"), "{why}");
    let explained = number_after(why, "this structure explains ");
    assert!(explained < 10.0, "{explained}");
    let cn = r.findings.iter().find(|f| f.effect == "coloured-noise");
    if let Some(cn) = cn {
        assert!(!cn.significant);
    }
}

/// clean plant 67003 (order 4, poles 0.06, -0.10, -0.41, -0.28, affine in p1, past window
/// 7): the input delayed by one sample explained 91 % of the subspace refit's free-run error,
/// replicated (93 %, 96 %), beat the larger past window (92 %), and was named input-delay at
/// 9.46x. A delayed channel adds memory that absorbs the estimate's bias: refined by output
/// error like the user's structure it explains nothing beyond it. The same plant with a
/// planted dead time of 2 samples is still named input-delay, at its oracle's ratio.
#[test]
#[ignore = "long tier: make test-long"]
fn a_delay_the_refined_structure_matches_is_not_a_finding() {
    let (_, out) = diagnose_one("clean", 67003, 1500);
    let (d, why) = blocked_finding(&out.report, "input-delay");
    assert!(d.explained >= 0.5, "{}", d.explained);
    assert!(why.contains("refined the same way"), "{why}");
    assert!(why.contains("not a dead time of the input"), "{why}");
    let explained = number_after(why, "this structure explains ");
    assert!(explained < 10.0, "{explained}");
    let run = run_one("input-delay", 67003, 1500);
    assert_eq!(run.named, "input-delay", "{run:?}");
    let oracle = run.oracle.as_ref().expect("oracle").ratio;
    assert!(run.ratio >= 0.8 * oracle, "{} against {oracle}", run.ratio);
}

/// input-delay plant 236001 (order 4, poles 0.46, 0.49e^+-2.20i, 0.47, affine in p1, a dead
/// time of 4 samples) with the user's order left to `--order auto`: the singular values read
/// one state, the free-run check seven, which hold the dead time. u1(k-4) at seven states
/// explained 74.6 % of the refit's held-out error, but refined like the model's structure it
/// predicts alike (-1.1 %), so the delay was blocked as the estimate's bias. With the states
/// the dead time held given back (order 7 + 1 - 4 = 4, `catalogue::fewer_states_delays`) the
/// delayed structure refined is not worse than the seven states refined
/// (`states::fewer_states`): input-delay is named, at the plant's order, and the fix reaches
/// the oracle's error ratio (1.90x).
#[test]
fn a_dead_time_the_automatic_order_held_in_states_is_given_back() {
    let (model, out) = diagnose_one_auto("input-delay", 236001, 1000, Shape::SISO);
    assert_eq!(states(&model), Some(7), "--order auto");
    let f = named_first(&out.report, "input-delay");
    assert!(f.detail.contains("u1(k-4) instead of u1"), "{}", f.detail);
    assert!(f.detail.contains("order 4, was 7"), "{}", f.detail);
    assert_evidence(f, "stood for a dead time");
    assert_eq!(states(&out.model), Some(4));
    let ratio = fix_ratio(&out);
    assert!(ratio > 1.7, "{ratio}");
}

/// Clean 2x1 plant 243601 (four states, poles 0.62, 0.56, 0.57, 0.29, affine in p1, white
/// inputs, past window 7, noise 1.8 %) under `--order auto` (three states): a p1^2 basis
/// refined from the model's structure refined explained 35.7 % of that structure's held-out
/// error, replicated, and was named scheduling-nonlinearity (5.26x): the fourth state the
/// subspace estimate missed, which the order variants by PBSID (judged against the subspace
/// refit, 4.3 %) did not show. One more state refined from the refined structure explains
/// 85.2 % of its error: order-too-low is named, and the fix has four states (27.05x; asserted
/// above 7).
#[test]
fn a_state_the_subspace_estimate_missed_is_found_refined() {
    let shape = Shape::parse("2x1").unwrap();
    let (model, out) = diagnose_one_auto("clean", 243601, 1500, shape);
    assert_eq!(states(&model), Some(3), "--order auto");
    let f = named_first(&out.report, "order-too-low");
    assert!(
        f.detail.contains("order 4 (was 3), refined from"),
        "{}",
        f.detail
    );
    assert!(f.explained > 0.7, "{}", f.explained);
    assert_eq!(states(&out.model), Some(4));
    let ratio = fix_ratio(&out);
    println!("error ratio {ratio:.2}");
    assert!(ratio > 7.0, "{ratio}");
}

/// Clean plant 238201 (three states, affine in p1, low-pass input) under `--order auto`
/// (two states): the latent scheduling sequence, re-estimated smoothly, explained 39.5 % of
/// its null's held-out error, replicated, and was named scheduling-noise (3.42x), because its
/// refits on p^ read three states from their singular values while its null, the structure
/// refined on the measured p, kept two. Its rounds now keep the order of the fit on the
/// measured p (`refit::fit_latent`): like with like it explains under 10 %. Since the
/// fifty-second session the state the automatic order missed is named as what it is: one
/// more state refined from the model's structure refined explains 43.0 % of that
/// structure's held-out error, and order-too-low is named (the fix has three states, 3.71x;
/// asserted above 2.5).
#[test]
fn a_state_the_automatic_order_missed_is_not_scheduling_noise() {
    let (model, out) = diagnose_one_auto("clean", 238201, 1500, Shape::SISO);
    assert_eq!(states(&model), Some(2), "--order auto");
    let f = named_first(&out.report, "order-too-low");
    assert!(
        f.detail.contains("order 3 (was 2), refined from"),
        "{}",
        f.detail
    );
    let latent = out
        .report
        .findings
        .iter()
        .find(|f| f.effect == "scheduling-noise")
        .expect("a scheduling-noise finding");
    assert!(!latent.significant, "{:?}", latent.detail);
    assert!(latent.explained < 0.1, "{}", latent.explained);
    assert_eq!(states(&out.model), Some(3));
    let ratio = fix_ratio(&out);
    println!("error ratio {ratio:.2}");
    assert!(ratio > 2.5, "{ratio}");
}

/// clean plant 37000 (order 4, affine in p1, past window 7 for frozen poles that need more):
/// the subspace refit's one-step predictor is unstable, and a past window of 9 explained
/// 95.5 % of its free-run error (named order-too-low, 18.65x). The user's structure refined
/// by output error explains 99.7 % (350x), and refined, the past window of 9 adds nothing:
/// the deficiency is the estimate, which the report says in a note, not a missing state.
#[test]
#[ignore = "long tier: make test-long"]
fn a_biased_estimate_is_a_note_not_a_missing_state() {
    let (_, out) = diagnose_one("clean", 37000, 1500);
    let r = &out.report;
    for n in &r.notes {
        println!("note: {n}");
    }
    assert!(r.findings.iter().all(|f| !f.significant));
    assert!(r.applied.is_empty());
    let note = r
        .notes
        .iter()
        .find(|n| n.contains("refined by output error (lpvid pbsid --refine) explains"))
        .expect("the refined structure's note");
    let explained = number_after(note, "explains ");
    assert!(explained > 90.0, "{explained}");
}

/// The planted effects the rules must keep: coloured-noise 33000 (AR noise, order 1, past 3)
/// is named with the refined residual not white, order-too-low 31003 (a resonant mode
/// 0.78e^+-1.32i missing, past window 7) with the pair of states refined from the structure
/// refined (order 6, was 4: 75.9 % of its error; its PBSID order 5 had explained 71.6 % of
/// it); both fixes lower the held-out error (20.64x one-step; 11.29x free run, where order 5
/// by PBSID gave 2.37x).
#[test]
#[ignore = "long tier: make test-long"]
fn coloured_noise_and_missing_states_are_still_named() {
    let (_, out) = diagnose_one("coloured-noise", 33000, 1500);
    let f = named_first(&out.report, "coloured-noise");
    assert_evidence(f, "is not white");
    let (_, out) = diagnose_one("order-too-low", 31003, 1500);
    let f = named_first(&out.report, "order-too-low");
    assert!(
        f.detail.contains("order 6 (was 4), refined from"),
        "{}",
        f.detail
    );
    assert!(f.explained > 0.7, "{}", f.explained);
    for (effect, seed, at_least) in [
        ("coloured-noise", 33000, 10.0),
        ("order-too-low", 31003, 5.0),
    ] {
        let run = run_one(effect, seed, 1500);
        println!(
            "{effect} {seed}: named {} ratio {:.2}",
            run.named, run.ratio
        );
        assert_eq!(run.named, effect);
        assert!(run.ratio > at_least, "{}", run.ratio);
    }
}
