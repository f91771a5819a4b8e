//! The next-variant retry on a failed replication (issue 14, helper h18r), a training half
//! whose refit runs away refit one past sample longer (lead, seventeenth session), the
//! two-level input rule and the cubic of the input-nonlinearity candidates, and the
//! encompassing test between the scheduling effects (helper h19so), on plants of the family
//! (docs/bench-diagnose.md, "The next-variant retry on a failed replication, for every
//! effect; two-level inputs" and "The encompassing test between scheduled-output and
//! scheduling-nonlinearity"). Run in release mode.

mod diagnose_support;

use diagnose_support::family::{diagnose_one, run_one};

/// scheduling-nonlinearity plant 3002 of the family: the refined p1^2 has the lowest
/// held-out error of the effect (96.7 % of the refined null) but its refit on the first
/// training half at the user's past window ran away on the held-out record (-4.5e17 %).
/// Until such a half was refit one past sample longer (`replicate::Halves`), the next variant
/// that passes every full-data test, the unrefined p1^2 (96.2 %), was replicated in its place
/// and named (the alternatives of `replicate::alternatives`). Now the refined p1^2 is refit
/// on that half at past 8, both it and its null, replicates there and is named itself, the
/// widened half in its evidence.
#[test]
#[ignore = "long tier: make test-long"]
fn a_half_whose_refit_runs_away_is_refit_one_past_sample_longer() {
    let (_, out) = diagnose_one("scheduling-nonlinearity", 3002, 1500);
    let r = &out.report;
    let f = r
        .findings
        .iter()
        .find(|f| f.effect == "scheduling-nonlinearity")
        .expect("a scheduling-nonlinearity finding");
    println!(
        "{} ({}) explained {:.3} p {:.1e} rep {:?} significant {}",
        f.effect, f.detail, f.explained, f.p_value, f.replication, f.significant
    );
    assert!(f.significant, "{:?}", f.blocked_by);
    assert!(f.detail.contains("refined"), "{}", f.detail);
    let rep = f.replication.as_ref().expect("replicated on the halves");
    assert!(rep.iter().all(|e| *e > 0.5), "{rep:?}");
    let why = f
        .evidence
        .iter()
        .find(|e| e.starts_with("refit on each half"))
        .expect("the replication in the evidence");
    println!("{why}");
    assert!(
        why.contains("on the first half the variant's refit ran away from the held-out data, so both were refit there one past sample longer: past window 8 (was 7)"),
        "{why}"
    );
}

/// feedthrough plant 103001 of the family (a fresh range): estimating D explains 96.7 % of
/// the held-out error, and its refit on the second training half at the user's past window
/// 5 puts a frozen pole of A(p1) outside the unit circle for p1 > 0.75 (spectral radius 1.23
/// at p1 = 1), so its free run on the held-out record runs away (-2.6e6 %; at past 4 and 6
/// that half's refit gives a held-out VAF of 99.2 %). The effect has one variant, so nothing
/// was named. Now that half is refit at past 6, replicates, and D is applied at the oracle's
/// ratio (measured 27.64x).
#[test]
#[ignore = "long tier: make test-long"]
fn a_feedthrough_whose_half_refit_runs_away_is_named() {
    let run = run_one("feedthrough", 103001, 1500);
    println!("{} {:.2} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "feedthrough");
    let oracle = run.oracle.as_ref().expect("an oracle").ratio;
    assert!(
        run.ratio >= 10.0 && run.ratio >= 0.5 * oracle,
        "{} against the oracle's {oracle}",
        run.ratio
    );
}

/// The family's saturating inputs (the tanh kind of input-nonlinearity; plants 217002, 215200
/// and 215202, inputs of both signs): the variant refined from the model's structure refined
/// had the even and odd channels u^2 and |u| u and reached a third to two thirds of the
/// oracle's gain (the true shape's u^3 and |u| u: 5.67x of 8.28x, 3.49x of 8.00x, 4.27x of
/// 13.57x). With the cubic beside them (`catalogue`, input-nonlinearity) it reaches the
/// oracle's (measured 21.85x, 9.01x, 13.61x).
#[test]
#[ignore = "long tier: make test-long"]
fn a_saturating_input_is_fitted_with_its_cubic() {
    for seed in [217002, 215200, 215202] {
        let run = run_one("input-nonlinearity", seed, 1500);
        println!("{seed} {} {:.2} {:?}", run.named, run.ratio, run.oracle);
        assert_eq!(run.named, "input-nonlinearity");
        let oracle = run.oracle.as_ref().expect("an oracle").ratio;
        assert!(
            run.ratio >= 0.8 * oracle,
            "{seed}: {} against the oracle's {oracle}",
            run.ratio
        );
    }
}

/// output-offset plant 9000 of the family has a random binary input: u1^2 is a constant plus
/// a multiple of u1, and was a replicated finding explaining what the offset explains
/// (99.7 %). It is no longer tried, the step says why, and output-offset is named.
#[test]
fn two_level_input_has_no_input_nonlinearity_duplicates() {
    let (_, out) = diagnose_one("output-offset", 9000, 1500);
    let r = &out.report;
    let st = &r.steps[0];
    assert!(
        st.not_applicable
            .iter()
            .any(|(e, why)| e == "input-nonlinearity" && why.contains("takes two values")),
        "{:?}",
        st.not_applicable
    );
    assert!(
        !st.variants_scored
            .iter()
            .any(|v| v.effect == "input-nonlinearity"),
        "an input-nonlinearity variant was scored"
    );
    let first = r.findings.first().expect("findings");
    assert_eq!(first.effect, "output-offset");
    assert!(first.significant);
}

/// The numbers of the encompassing test's evidence line: the two explained percentages
/// (what the structure with both explains of the simpler finding's and of the richer
/// finding's held-out error) and their p-values.
fn encompassing_numbers(line: &str) -> ((f64, f64), (f64, f64)) {
    let num = |s: &str| -> f64 {
        let end = s
            .find(|c: char| !(c.is_ascii_digit() || "+-.e".contains(c)))
            .unwrap_or(s.len());
        s[..end].parse().unwrap()
    };
    let mut pct = line
        .match_indices(" explains ")
        .map(|(i, _)| num(&line[i + 10..]));
    let after_and = line.find("% of scheduled-output's").unwrap();
    let second = line[after_and..].find(" and ").unwrap() + after_and + 5;
    let mut ps = line
        .match_indices("(p = ")
        .map(|(i, _)| num(&line[i + 5..]));
    (
        (pct.next().unwrap(), ps.next().unwrap()),
        (num(&line[second..]), ps.next().unwrap()),
    )
}

/// scheduling-nonlinearity plant 1002 of the family (a p1^2 term planted in A(p), B(p)): the
/// refined p1^2 explains 79.5 % of the refined null, the refined scheduled output equation
/// 56.7 %; p1^2 has the lower held-out error but does not beat the output equation head to
/// head at ALPHA / (variants tried) (p = 4.4e-4, needs < 2.9e-4), so the parsimony rule alone
/// named scheduled-output (32 free coefficients against 40). The encompassing test fits the
/// structure with both: it explains 52.1 % of the output equation's held-out error
/// (p = 4.2e-4) and -0.9 % of p1^2's, so p1^2 adds to the output equation and the output
/// equation adds nothing to p1^2: scheduling-nonlinearity is named, with the test in its
/// evidence. (With the parsimony rule alone scheduled-output was named: checked.)
#[test]
fn the_encompassing_test_names_the_planted_scheduling_nonlinearity() {
    let (_, out) = diagnose_one("scheduling-nonlinearity", 1002, 1500);
    let r = &out.report;
    let first = r.findings.first().expect("findings");
    for e in &first.evidence {
        println!("{e}");
    }
    assert_eq!(first.effect, "scheduling-nonlinearity");
    assert!(first.significant);
    let line = &first.evidence[0];
    assert!(
        line.starts_with("encompassing test of scheduled-output and scheduling-nonlinearity"),
        "{line}"
    );
    assert!(
        line.contains("scheduling-nonlinearity is the effect"),
        "{line}"
    );
    let ((richer_adds, p_r), (simpler_adds, p_s)) = encompassing_numbers(line);
    println!("richer adds {richer_adds} % p {p_r}; simpler adds {simpler_adds} % p {p_s}");
    // p1^2 adds to the output equation: >= 10 % at p < ALPHA / 2
    assert!(richer_adds >= 10.0 && p_r < 5e-3, "{line}");
    // the output equation adds nothing to p1^2
    assert!(simpler_adds < 10.0 || p_s >= 5e-3, "{line}");
    // the output equation stays a finding, after it
    assert!(
        r.findings
            .iter()
            .any(|f| f.effect == "scheduled-output" && f.significant),
        "the output equation is still a (second) finding"
    );
}

/// output-offset plant 31002 of the family (order 4, random binary input): a Lur'e sqrt|y1|
/// fitted with the output-error refinement (36.8 % of the refined null) had a lower held-out
/// error than the planted offset fitted by PBSID (88.4 % of the PBSID null) and one free
/// coefficient fewer, so it was named first and applied (123x). Compared like with like, the
/// offset's structure refined the same way has the lower error and beats the Lur'e variant
/// head to head: the offset is named first, and its fix reaches its oracle's ratio (63.5x).
#[test]
#[ignore = "long tier: make test-long"]
fn a_refined_finding_is_compared_like_with_like() {
    let run = diagnose_support::family::run_one("output-offset", 31002, 1500);
    println!("{} {:.2} {:?}", run.named, run.ratio, run.oracle);
    assert_eq!(run.named, "output-offset");
    let oracle = run.oracle.as_ref().expect("an oracle").ratio;
    assert!(
        run.ratio >= 0.8 * oracle && run.ratio > 10.0,
        "{} vs {oracle}",
        run.ratio
    );
    let (_, out) = diagnose_one("output-offset", 31002, 1500);
    let first = out.report.findings.first().expect("findings");
    let line = &first.evidence[0];
    println!("{line}");
    assert!(
        line.starts_with("ranked before output-nonlinearity"),
        "{line}"
    );
    // the two errors in the line: the offset refined, then the Lur'e variant's
    let nums: Vec<f64> = line
        .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == 'e' || c == '-'))
        .filter_map(|w| w.parse::<f64>().ok())
        .filter(|v| *v > 0.0 && *v < 1.0)
        .collect();
    assert!(nums.len() >= 2 && nums[0] <= nums[1], "{line}");
}

/// An effect is a finding when one of its variants passes every rule (`diagnose::judge`,
/// second chance): on the output-offset plant 213001 of the family (found by
/// `diagnose_family 2 1500 213000`) the order-too-low variant with the lowest held-out
/// error, order 3, replicated but the model's own structure refined by output error removes
/// its error as well; order 4, the effect's next variant, passes every rule in its place and
/// is a finding beside the planted offset (named first). The default tier has the same rule
/// on the physical tank 4024 (`output_nonlinearity`).
#[test]
#[ignore = "long tier: make test-long"]
fn an_effect_whose_best_variant_fails_a_later_rule_is_named_by_the_next() {
    let (_, out) = diagnose_one("output-offset", 213001, 1500);
    let r = &out.report;
    assert_eq!(r.findings[0].effect, "output-offset", "{:#?}", r.findings);
    let f = r
        .findings
        .iter()
        .find(|f| f.effect == "order-too-low")
        .expect("an order-too-low finding");
    println!("{}: {:#?}", f.detail, f.evidence);
    assert!(f.significant, "{f:#?}");
    assert!(
        f.evidence.iter().any(|e| e
            .starts_with("in place of the variant with a lower held-out error")
            && e.contains("refined by output error removes that error as well")),
        "{:#?}",
        f.evidence
    );
}
