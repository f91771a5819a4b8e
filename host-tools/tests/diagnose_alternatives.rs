//! The next-variant retry on a failed replication (issue 14, helper h18r) and the two-level
//! input rule of the input-nonlinearity candidates, on plants of the family
//! (docs/bench-diagnose.md, "The next-variant retry on a failed replication, for every
//! effect; two-level inputs"). Run in release mode.

mod diagnose_support;

use diagnose_support::family::diagnose_one;

/// scheduling-nonlinearity plant 17000 of the family: the refined p1^2 has the lowest
/// held-out error of the effect (68.5 % of the refined null) but its refit on the second
/// training half diverges on the held-out record (-5.7e23 %). Before, the effect was then
/// not a finding (the retry was only for output-nonlinearity); now its next variant that
/// passes every full-data test, p1^2 + p1^3 (83.3 % of the PBSID null), is replicated in
/// its place (67.9 %, 71.5 %) and is a finding, with the replaced variant in its evidence.
/// (Named first is still scheduled-output, by the parsimony rule: not asserted here.)
#[test]
fn a_failed_replication_gives_way_to_the_next_variant() {
    let (_, out) = diagnose_one("scheduling-nonlinearity", 17000, 1500);
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
    assert!(!f.detail.contains("refined"), "{}", f.detail);
    let rep = f.replication.as_ref().expect("replicated on the halves");
    assert!(rep.iter().all(|e| *e > 0.0), "{rep:?}");
    let why = f
        .evidence
        .iter()
        .find(|e| e.contains("in place of"))
        .expect("the replaced variant in the evidence");
    assert!(why.contains("refined"), "{why}");
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
