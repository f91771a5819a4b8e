//! The output-error refinement kept frozen-stable over the scheduling range of the training
//! data (issue 14, helper h22sref; docs/bench-diagnose.md, "A refinement kept stable over
//! the scheduling range"): `refine::FrozenGuard` admits a Levenberg-Marquardt step only when
//! the frozen A(mu) stays stable at the operating points the training record visits (or no
//! less stable than before). And `--fix` when no effect is a finding but the structure's
//! estimate is biased: the structure refined by output error is the model written
//! (`diagnose::RefinedFix`). A model so refined, or written by a fix refined from the user's
//! structure refined (a scheduled output equation included), is refit refined when diagnosed
//! again. Run in release mode.

mod diagnose_support;

use diagnose_support::family::{diagnose_one, diagnose_one_auto};
use lpvid_host::diagnose::effects::refined_null;
use lpvid_host::diagnose::plants::family_case;
use lpvid_host::diagnose::plants::Shape;
use lpvid_host::diagnose::refit::{fit_spec, Spec};
use lpvid_host::linalg::spectral_radius;
use lpvid_host::model::{Factor, ModelKind};
use lpvid_host::simulate::{score_from, Mode, X0};

/// scheduling-nonlinearity plant 37000 of the family (order 4, p1^2 in A and B, strength 0.51,
/// past window 7): the p1^2 basis refined from the user's structure refined diverged on the
/// held-out record (docs, helper h21sched, cause 3), so only the PBSID p1^2 + p1^3 was a
/// candidate, and it did not replicate (-496 % on a training half). Refined under the guard,
/// the p1^2 variant is a replicated finding (measured: 46.8 % of the refined structure's
/// held-out error, halves 73.3 % and 50.8 %), and its frozen A(mu) has spectral radius below
/// 1 at every training sample's mu = [1, p1, p1^2] (not only at the guard's 200 points;
/// measured 1.000000 to six digits: the data pull the fit to the boundary, the guard holds it).
/// What comes first is not changed here: the encompassing test now has both refined
/// variants and finds that the data do not tell the scheduled output equation and p1^2
/// apart (the output equation stays first by its lower held-out error).
#[test]
#[ignore = "long tier: make test-long"]
fn the_refined_p2_basis_stays_stable_and_is_a_finding() {
    let seed = 37000;
    let (model, out) = diagnose_one("scheduling-nonlinearity", seed, 1500);
    let f = out
        .report
        .findings
        .iter()
        .find(|f| {
            f.effect == "scheduling-nonlinearity"
                && f.detail
                    .contains("p1^2, refined from the model's own structure refined")
        })
        .expect("the refined p1^2 variant is a finding");
    println!(
        "{} ({}) explained {:.3} p {:.1e} rep {:?} sig {} {:?}",
        f.effect, f.detail, f.explained, f.p_value, f.replication, f.significant, f.blocked_by
    );
    assert!(f.significant, "{:?}", f.blocked_by);
    assert!(f.explained > 0.3, "{}", f.explained);
    let rep = f.replication.as_ref().expect("replicated on the halves");
    assert!(rep.iter().all(|e| *e > 0.1), "{rep:?}");

    // the same variant refitted on the training record: its frozen A(mu) at every sample
    let case = family_case("scheduling-nonlinearity", seed, 1500).unwrap();
    let spec = Spec::from_model(&model, &mut vec![]).unwrap();
    let mut sp = spec.clone();
    sp.signals.scheduling.push(vec![Factor {
        pow: 2.0,
        ..Factor::col("p1")
    }]);
    sp.nested_in = Some(Box::new(refined_null(&spec)));
    let fitted = fit_spec(&sp, &case.train, &model.fit).unwrap();
    let ModelKind::Ss(ss) = &fitted.model.kind else {
        panic!("an lpv-ss model")
    };
    let sig = sp.signals.evaluate(&case.train).unwrap();
    assert_eq!(ss.a.len(), 3);
    let rho = (0..sig.len())
        .map(|k| spectral_radius(&ss.a_at(&sig.mu(k))))
        .fold(0.0, f64::max);
    let reported = fitted.model.fit["nested_refinement"]["frozen_radius"]
        .as_f64()
        .expect("the refinement reports its frozen radius");
    println!("frozen radius over the training samples {rho:.6} (the guard's points {reported:.6})");
    assert!(rho < 1.0, "{rho}");
    assert!(reported <= rho + 1e-12, "{reported} {rho}");
}

/// input-delay plant 240107 of the family (order 4, affine in p1, a dead time of 5 samples,
/// noise 7.2 %), the user's order left to `--order auto` (7 states at past window 7): the
/// delayed input explains 89.5 % of the refit's held-out error, but the structure refined by
/// output error removes it as well (the delay explains 7.9 % more, p = 1.8e-3), so no effect
/// is a finding. With `--fix` the refined structure is the model written (measured: held-out
/// free-run error 8.6x lower, VAF 93.43 -> 99.24 %); before, the model was left as given
/// with a note naming `lpvid pbsid --refine`. Then the model written is diagnosed again and
/// judged against itself, refit refined.
#[test]
fn fix_writes_the_refined_structure_and_a_later_diagnosis_refits_it_refined() {
    let (model, out) = diagnose_one_auto("input-delay", 240107, 1500, Shape::SISO);
    let r = &out.report;
    assert!(r.applied.is_empty(), "{:?}", r.applied);
    assert!(!r.findings.iter().any(|f| f.significant));
    let fix = r.refined.as_ref().expect("the refined structure written");
    assert_eq!(fix.step, 1);
    assert!(fix.explained > 0.5 && fix.p_value < 1e-4, "{fix:?}");
    assert!(fix.mse_before / fix.mse_after > 4.0, "{fix:?}");
    // the same structure, its estimate refined
    assert_eq!(out.model.signals, model.signals);
    assert!(out.model.fit.get("refined_by_diagnose").is_some());
    // the report's after is the model written, scored as the report scores
    let case = family_case("input-delay", 240107, 1500).unwrap();
    let x0 = X0::Estimate {
        samples: lpvid_host::diagnose::effects::x0_samples(case.val.len()),
    };
    let after = score_from(&out.model, &case.val, Mode::FreeRun, x0).unwrap();
    let reported = r.after.as_ref().expect("a score after");
    assert!((after.vaf_mean - reported.vaf_mean).abs() < 1e-9);
    assert!((fix.vaf_after - reported.vaf_mean).abs() < 1e-9);
    assert!(reported.vaf_mean > r.before.vaf_mean + 3.0, "{reported:?}");
    // the summary says it, once
    let text = lpvid_host::diagnose::report::summary(r, &[]);
    assert_eq!(text.matches("Refined: ").count(), 1, "{text}");

    // The model the refined fix wrote, diagnosed again on the same records: its record says
    // it was refined by output error (`refit::REFINED_KEY`), so its refit is refined too and
    // the candidates are judged against the structure the user has. Before, the second run
    // refit it by PBSID alone (held-out VAF 93.43 % against the given 99.24 %, with a note
    // saying so) and wrote the same refined structure again as a "fix" 1.0x lower. (One test
    // with the first diagnosis above: it is the same run.)
    let refined = out.model;
    let spec = Spec::from_model(&refined, &mut vec![]).unwrap();
    assert!(spec.refined, "the record says the structure was refined");
    let second = diagnose_again(&refined, &case);
    let r = &second.report;
    assert!(r.refined.is_none(), "{:?}", r.refined);
    assert!(
        !r.notes
            .iter()
            .any(|n| n.contains("candidates are compared with the refit")),
        "{:?}",
        r.notes
    );
    // the null the candidates are judged against predicts the held-out record as the given
    // model does (refit on the same rows, from its own start)
    let null = fit_spec(&spec, &case.train, &refined.fit).unwrap();
    let x0 = X0::Estimate {
        samples: lpvid_host::diagnose::effects::x0_samples(case.val.len()),
    };
    let refit = score_from(&null.model, &case.val, Mode::FreeRun, x0).unwrap();
    println!(
        "given {:.2} %, refit {:.2} %",
        r.before.vaf_mean, refit.vaf_mean
    );
    assert!(
        (refit.vaf_mean - r.before.vaf_mean).abs() < 1.0,
        "{} {}",
        refit.vaf_mean,
        r.before.vaf_mean
    );
    assert!(r.before.vaf_mean > 98.0, "{}", r.before.vaf_mean);
}

/// A model written by a `scheduled-output` fix (its C^(i), D^(i) refined from the user's
/// structure refined) is a structure refined by output error with a scheduled output
/// equation, which the refinement through the loop cannot fit: diagnosed again (or at a
/// second `--fix` step), every variant failed to refit ("refit as lpv-ss with a constant
/// output equation"), and at a second step its candidates inherited the first step's null,
/// so an offset channel was applied to family plant scheduled-output 240101 (order 4, no
/// offset) for 87.6 % of an error its first step's structure had already removed. Now the
/// structure is refit nested in its constant-output part refined
/// (`refit::fit_refined_scheduled_output`): the variants are scored against the model as
/// written, and the order the user's `--order auto` missed is what the second run names.
#[test]
fn a_scheduled_output_fix_is_diagnosed_again_against_itself() {
    let (_, first) = diagnose_one_auto("scheduled-output", 240101, 1500, Shape::SISO);
    assert_eq!(
        first.report.applied.first().map(|a| a.effect),
        Some("scheduled-output")
    );
    let fixed = first.model;
    let spec = Spec::from_model(&fixed, &mut vec![]).unwrap();
    assert!(spec.refined && spec.scheduled_output, "{spec:?}");

    let case = family_case("scheduled-output", 240101, 1500).unwrap();
    let second = diagnose_again(&fixed, &case);
    let r = &second.report;
    let step = &r.steps[0];
    // the null is the structure as written: it predicts as the given model does
    println!(
        "given {:.2} %, null refit {:.2} %",
        r.before.vaf_mean, step.null_refit_vaf
    );
    assert!((step.null_refit_vaf - r.before.vaf_mean).abs() < 1.0);
    // every variant is refit but the own-output ones (a Lur'e channel beside a scheduled
    // output equation is not a structure the loop's refinement fits)
    let failed: Vec<_> = step
        .variants_scored
        .iter()
        .filter(|v| v.error.is_some() && v.effect != "output-nonlinearity")
        .map(|v| (v.effect, v.detail.as_str(), v.error.as_deref()))
        .collect();
    assert!(failed.is_empty(), "{failed:#?}");
    assert!(
        step.variants_scored.len() >= 30,
        "{}",
        step.variants_scored.len()
    );
    let a = r.applied.first().expect("a fix");
    println!(
        "{} ({}): {:.3e} -> {:.3e}",
        a.effect, a.detail, a.mse_before, a.mse_after
    );
    assert_eq!(a.effect, "order-too-low");
    assert!(a.mse_before / a.mse_after > 2.0);
}

/// The diagnosis (`--fix`, one step) of a model a first diagnosis of `case` wrote.
fn diagnose_again(
    model: &lpvid_host::model::ModelFile,
    case: &lpvid_host::diagnose::plants::FamilyCase,
) -> lpvid_host::diagnose::Outcome {
    let opts = lpvid_host::diagnose::Options {
        fix: true,
        max_steps: 1,
        threads: 2,
    };
    lpvid_host::diagnose::diagnose(model, &case.train, &case.val, &opts).unwrap()
}
