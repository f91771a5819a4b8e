//! The diagnosis on multi-input multi-output family plants (issue 14, helper h26mimo;
//! docs/bench-diagnose.md, "MIMO plant families"): the generator's 2x2 plants
//! (`plants::family_case_shaped`) with the effect planted on one drawn channel. The finding
//! must name that channel (the delayed input, the output fed back) and the fix must reach the
//! error ratio measured (half of it asserted); a clean 2x2 plant gets no finding. Run in
//! release mode.

mod diagnose_support;

use diagnose_support::family::{
    assert_refined_not_coloured, blocked_finding, diagnose_one_auto, diagnose_one_shaped,
    named_first, number_after, run_one_shaped, states,
};
use lpvid_host::diagnose::plants::Shape;

fn two_by_two() -> Shape {
    Shape::parse("2x2").unwrap()
}

/// 2x2 plant 93000 (order 4, poles -0.19, 0.37, 0.58e^+-0.25i, low-pass inputs, past 6), a
/// dead time of 4 samples on u2 only: input-delay is named with u2 delayed 4 samples (u1 is
/// left as it is), 21.01x after the fix, the oracle's ratio (u2 delayed 4 in the user's
/// structure).
#[test]
fn a_delay_on_the_second_input_is_named_on_that_input() {
    let r = run_one_shaped("input-delay", 93000, 1500, None, two_by_two());
    println!("{} ({}) {:.2} {:?}", r.named, r.detail, r.ratio, r.oracle);
    assert_eq!(r.named, "input-delay");
    assert!(r.detail.contains("u2(k-4) instead of u2"), "{}", r.detail);
    assert!(r.ratio > 10.0, "{}", r.ratio);
    let o = r.oracle.expect("an oracle");
    assert!(
        o.identifiable && o.detail.contains("u2 delayed 4"),
        "{}",
        o.detail
    );
}

/// The same plant with a signed square root of y2 fed back along u2's direction (nonlinear
/// share 0.26 of y2): output-nonlinearity is named with a feedback of y2, 5.94x after the fix
/// (oracle 15.32x: the true sign(y2) sqrt|y2| channel).
#[test]
fn an_own_output_feedback_of_the_second_output_is_named_on_that_output() {
    let r = run_one_shaped("output-nonlinearity", 93000, 1500, None, two_by_two());
    println!("{} ({}) {:.2} {:?}", r.named, r.detail, r.ratio, r.oracle);
    assert_eq!(r.named, "output-nonlinearity");
    assert!(r.detail.contains("y2"), "{}", r.detail);
    assert!(r.ratio > 3.0, "{}", r.ratio);
}

/// The same plant with nothing planted: no finding (the largest, coloured-noise, explains
/// 1.3 % of the held-out error), nothing applied.
#[test]
fn a_clean_two_by_two_plant_has_no_finding() {
    let r = run_one_shaped("clean", 93000, 1500, None, two_by_two());
    println!("{} ({}) {:.2}", r.named, r.detail, r.ratio);
    assert_eq!(r.named, "none");
    assert_eq!(r.ratio, 1.0);
}

/// Clean 2x2 plant 93002 (order 3, poles 0.09, 0.09, 0.05, affine in p1, random binary
/// inputs, past window 4, output noise 2.7 %): the user's structure refined by output error
/// stops in a local minimum (training MSE 4.2252e-3 from every past window 3-10; order 4
/// reaches 4.0476e-3), and five own-output channels each explained 21.1 % of its held-out
/// error: output-nonlinearity sin(0.344 y1) was named at 9.02x. Refined from that variant's
/// fit with the channel linearised, the same structure reaches 4.0955e-3 and the variant
/// explains nothing beyond it; the refined structure from that start has a white residual,
/// so the noise model that would take its place is not a finding either; nor is a sinusoid
/// whose gain is the refit's, not its own.
#[test]
fn an_own_output_channel_that_only_escapes_a_local_minimum_is_not_a_finding() {
    let (_, out) = diagnose_one_shaped("clean", 93002, 1500, two_by_two());
    // since the refinement weighs each output by its variance (2026-12-08) the first
    // training half's refit of the own-output variant explains nothing (-0.8 %, the second
    // 21.8 %): it is blocked by the replication before the linear stand-ins are reached
    let (own, why) = blocked_finding(&out.report, "output-nonlinearity");
    assert!(own.explained >= 0.10, "{}", own.explained);
    if !why.contains("not replicated") {
        assert!(why.contains("linear stand-ins"), "{why}");
        let against = number_after(why, "against it this variant explains ");
        assert!(against < 5.0, "{against}");
    }
    let (_, why) = blocked_finding(&out.report, "coloured-noise");
    assert_refined_not_coloured(why, 0.01);
    // sin and cos of a line no periodogram shows (period 5.6 samples) explained 16.4 % of the
    // held-out error, replicated: what adding two channels moved in the refit's estimate of
    // the rest; the same fit without them does as well (measured: they explain 0.2 %). Since
    // 2026-12-07 the series is also refined from the model's structure refined, and that
    // variant, which escapes the same local minimum, comes first: it is not replicated (each
    // training half's refit explains -1.0 % and -1.1 %)
    let (periodic, why) = blocked_finding(&out.report, "periodic-disturbance");
    if periodic.explained >= 0.10 {
        if why.contains("not replicated") {
            assert!(periodic.detail.contains("refined"), "{}", periodic.detail);
        } else {
            assert!(why.contains("without its sinusoids"), "{why}");
            let own = number_after(why, "against it the sinusoids explain ");
            assert!(own < 5.0, "{own}");
        }
    }
    assert!(out.report.applied.is_empty(), "{:?}", out.report.applied);
}

/// 2x1 plant 233002 (order 1, pole 0.52, white inputs, past window 5, output noise 6.4 %
/// coloured, strength 0.25), the user's order left to `--order auto` (one state). One more
/// state for the noise dynamics explains 24.4 % of the held-out one-step error. On the first
/// training half `--order auto` reads two states, so the null structure refit there with the
/// automatic order was that variant itself: it explained exactly 0.0 % of its error and the
/// effect did not replicate. Refit at the order its fit on the whole record took (one state,
/// `replicate::at_order`), the first half explains 24.1 % and coloured-noise is named.
#[test]
fn a_noise_state_replicates_against_the_null_at_the_order_it_was_fitted() {
    let (model, out) =
        diagnose_one_auto("coloured-noise", 233002, 1000, Shape::parse("2x1").unwrap());
    assert_eq!(states(&model), Some(1), "--order auto");
    let f = named_first(&out.report, "coloured-noise");
    let rep = f.replication.as_ref().expect("replicated on the halves");
    assert!(rep.iter().all(|&e| e > 0.15), "{rep:?}");
    assert_eq!(out.report.applied.len(), 1);
}

/// 1x2 plant 246200 (two states, poles 0.47e^+-1.51i, low-pass input, past 5) with a direct
/// feedthrough on u1 -> y1, the user's order left to `--order auto`: without D it reads seven
/// states, and that structure refit on the second training half runs away on the held-out
/// record at every past window from 4 to 7 (a frozen pole outside the unit circle). The D
/// variant (two states) explains 99.9 % held out; the second half, whose null has no free run
/// to compare with, is judged on the two refits' one-step predictions
/// (`replicate::Halves`), where D explains 99.9 % too, and feedthrough is named (oracle 316x;
/// before, the half scored -inf and nothing was applied).
#[test]
fn a_half_whose_null_runs_away_is_judged_on_the_predictions() {
    let (model, out) = diagnose_one_auto("feedthrough", 246200, 1500, Shape::parse("1x2").unwrap());
    assert_eq!(states(&model), Some(7), "--order auto without D");
    let f = named_first(&out.report, "feedthrough");
    let rep = f.replication.as_ref().expect("replicated on the halves");
    assert!(rep.iter().all(|&e| e > 0.9), "{rep:?}");
    assert!(
        f.evidence.iter().any(
            |e| e.contains("second half the null structure's refit ran away")
                && e.contains("one-step predictions")
        ),
        "{:?}",
        f.evidence
    );
    assert_eq!(out.report.applied.len(), 1);
}
