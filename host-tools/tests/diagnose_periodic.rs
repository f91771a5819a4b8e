//! Periodic disturbances on plants whose own refit diverges (issue 14; docs/bench-diagnose.md,
//! "tenth session"): the residual the catalogue designs frequencies from falls back to the
//! one-step prediction, then to a least-squares ARX residual (`diagnose::design_residual`),
//! and a harmonic series is grouped under a fundamental only when its 1P or 2P line is seen
//! (`catalogue::periodic_lines`). Run in release mode.

mod diagnose_support;

use diagnose_support::family::{diagnose_one_auto, fix_ratio, run_one};
use lpvid_host::diagnose::plants::Shape;

/// periodic-disturbance plant 53002 (order 3, affine in p1, past window 7, a sinusoid at
/// 0.540 rad/sample, 8.2 % noise): the user's refit diverges in free run on the training and
/// the validation records (error ratio 5.5e156 after the fix) and its one-step predictor is
/// unstable (spectral radius 1.17), so no line was seen and coloured-noise was named. From the
/// ARX residual the lines at 0.540 and 0.900 rad/sample were first grouped as 3P and 5P of an
/// unseen 0.180 (a series too long a regression to be tried); each is now tried alone and the
/// planted one is named.
#[test]
#[ignore = "long tier: make test-long"]
fn a_line_is_found_when_the_refit_diverges() {
    let run = run_one("periodic-disturbance", 53002, 1500);
    println!("{} {:.2} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "periodic-disturbance");
    let oracle = run.oracle.as_ref().expect("an oracle").ratio;
    assert!(
        run.ratio >= 5.0 && run.ratio >= 0.3 * oracle,
        "{} against the oracle's {oracle}",
        run.ratio
    );
}

/// periodic-disturbance plant 21002 (order 4, affine in p1, a sinusoid at 0.803 rad/sample
/// and its 2P, 3.3 % noise): its lines at 0.803 and 1.607 were grouped as 2P and 4P of an
/// unseen 0.402 (with a third line at 1.205), and the series under 0.402 explained -1.7 %;
/// coloured-noise was named. Grouped under the seen 0.803, the fundamental is named.
#[test]
#[ignore = "long tier: make test-long"]
fn a_series_is_not_grouped_under_an_unseen_fundamental() {
    let run = run_one("periodic-disturbance", 21002, 1500);
    println!("{} {:.2} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "periodic-disturbance");
    assert!(run.ratio >= 3.0, "{}", run.ratio);
}

/// periodic-disturbance plant 79002 (order 1, affine in p1, past window 7, a sinusoid at
/// 0.818 rad/sample and its 2P, 9.6 % noise): a line at 0.409 rad/sample is seen as well, so
/// the series is grouped under it (1P, 2P, 4P). Its regression at 1P..2P (1524 regressors: the
/// Kronecker regressor of a scheduled model at past 7 is 254 per channel) was beyond the
/// primal form's limit and only the scheduling effects took the kernel form: the one series
/// tried, 1P alone, explained -0.3 %, and coloured-noise was named. Every variant now takes
/// the kernel form beyond that limit: 1P..4P explains 94 % and is named.
#[test]
fn a_long_harmonic_series_of_a_scheduled_model_is_tried_in_the_kernel_form() {
    let run = run_one("periodic-disturbance", 79002, 1500);
    println!("{} {:.2} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "periodic-disturbance");
    let oracle = run.oracle.as_ref().expect("an oracle").ratio;
    assert!(
        run.ratio >= 8.0 && run.ratio >= 0.5 * oracle,
        "{} against the oracle's {oracle}",
        run.ratio
    );
}

/// periodic-disturbance plant 246100 at 800 rows (order 4, affine in p1, white input, a
/// sinusoid at 1.349 rad/sample and its 2P, 6.4 % noise), the order left to `--order auto`
/// (2 states): one more state refined from the model's structure refined explained 26 % of
/// that structure's held-out error, the two harmonics 50 % of the PBSID refit's, and the
/// parsimony rule named the state (28 coefficients against 35: the harmonics did not beat it
/// head to head at ALPHA / variants, p = 2.3e-3 on 32 batches); the fix was 1.39x against the
/// oracle's 1.94x. The series is now also refined from the refined structure (52 %), and
/// the encompassing test fits both together: each adds to the other (73 % and 58 %), the
/// lower held-out error, the harmonics, first. Measured 2.16x.
#[test]
fn a_series_and_a_missing_state_are_judged_by_the_structure_with_both() {
    let (_, out) = diagnose_one_auto("periodic-disturbance", 246100, 800, Shape::SISO);
    let first = out.report.applied.first().expect("a fix applied");
    println!("{}: {}", first.effect, first.detail);
    assert_eq!(first.effect, "periodic-disturbance");
    let top = out.report.steps[0].findings.first().expect("a finding");
    assert!(
        top.evidence
            .iter()
            .any(|e| e.contains("encompassing test of order-too-low and periodic-disturbance")),
        "{:?}",
        top.evidence
    );
    let ratio = fix_ratio(&out);
    assert!(ratio >= 1.8, "{ratio}");
}
