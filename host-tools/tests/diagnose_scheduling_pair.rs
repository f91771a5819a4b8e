//! The encompassing test of the two scheduling effects judged like with like (issue 14,
//! helper h21sched; docs/bench-diagnose.md, "The scheduling pair judged like with like"):
//! when the comprehensive structure of a scheduled output equation and a p^2 basis cannot be
//! fitted the way the two findings are, each effect is judged by its variant refined from the
//! model's own structure refined, against the comprehensive structure refined the same way.
//! Run in release mode.

mod diagnose_support;

use diagnose_support::family::{diagnose_one, run_one};

/// (explained in %, p) of the comprehensive structure against `effect`'s, read from the
/// encompassing test's evidence line ("explains 31.3 % of scheduled-output's held-out error
/// (p = 1.0e-3)").
fn against(line: &str, effect: &str) -> (f64, f64) {
    let key = format!(" % of {effect}'s");
    let at = line.find(&key).expect("the effect's comparison");
    let pct: f64 = line[..at]
        .rsplit(' ')
        .next()
        .and_then(|v| v.parse().ok())
        .expect("a percentage");
    let rest = &line[at..];
    let p0 = rest.find("(p = ").expect("a p-value") + 5;
    let p: f64 = rest[p0..]
        .split(')')
        .next()
        .and_then(|v| v.parse().ok())
        .expect("a p-value");
    (pct, p)
}

/// scheduling-nonlinearity plant 35000 of the family (order 4, p1^2 in A and B, strength 0.87,
/// past window 7): the refined scheduled output equation (72.5 % of the refined structure's
/// error) and p1^2 + p1^3 fitted by PBSID were both findings, the output equation first by
/// its lower own held-out error (error ratio 6.20): the encompassing test was not asked, and
/// fitted the PBSID way its comprehensive structure has too many regressors for a verdict.
/// Asked, and judged like with like, the structure
/// with both explains 31.3 % of the refined output equation's held-out error (p = 1.0e-3) and
/// -5.5 % of the refined p1^2's: p1^2 is named (error ratio 4.87, its oracle's 3.58). With the
/// refinement kept frozen-stable (helper h22sref) the refined p1^2 replicates on the halves
/// (54 %, 76 %) and is the finding itself, the same test gives 31.3 % and -0.9 %, ratio 8.97.
#[test]
#[ignore = "long tier: make test-long"]
fn the_scheduling_pair_is_judged_like_with_like() {
    let (_, out) = diagnose_one("scheduling-nonlinearity", 35000, 1500);
    let f = out.report.findings.first().expect("findings");
    println!("{} ({})\n{:#?}", f.effect, f.detail, f.evidence);
    assert_eq!(f.effect, "scheduling-nonlinearity");
    assert!(f.significant, "{:?}", f.blocked_by);
    let line = &f.evidence[0];
    // like with like: the pair's refined variants (h21sched), or since the refinement is kept
    // frozen-stable (helper h22sref) the refined p1^2 is itself the finding, nested in the
    // same refined structure as the refined output equation
    assert!(
        line.starts_with("encompassing test of scheduled-output and scheduling-nonlinearity")
            && (line.contains("each effect judged by its variant refined the same way")
                || f.detail
                    .contains("p1^2, refined from the model's own structure refined"))
            && line.contains("so scheduling-nonlinearity is the effect"),
        "{line}"
    );
    // the p^2 basis adds to the output equation (>= 10 % at p < alpha / 2), not the reverse
    let (sn_adds, p_sn) = against(line, "scheduled-output");
    let (so_adds, p_so) = against(line, "scheduling-nonlinearity");
    assert!(sn_adds >= 10.0 && p_sn < 5e-3, "{sn_adds} {p_sn}");
    assert!(so_adds < 10.0 || p_so >= 5e-3, "{so_adds} {p_so}");
    let run = run_one("scheduling-nonlinearity", 35000, 1500);
    println!("named {} ratio {:.2}", run.named, run.ratio);
    assert_eq!(run.named, "scheduling-nonlinearity");
    assert!(run.ratio > 3.0, "{}", run.ratio);
}

/// scheduled-output plant 35003 of the family (order 1, output gain 1 + 0.61 p1): both
/// scheduling effects are findings and the refined output equation comes first by its own
/// held-out error, where the parsimony rule does not ask the encompassing test; asked now,
/// the output equation adds to the refined p1^2 and p1^2 adds nothing to it: it stays first.
#[test]
fn a_planted_scheduled_output_stays_first() {
    let (_, out) = diagnose_one("scheduled-output", 35003, 1500);
    let f = out.report.findings.first().expect("findings");
    println!("{} ({})\n{:#?}", f.effect, f.detail, f.evidence);
    assert_eq!(f.effect, "scheduled-output");
    assert!(f.significant, "{:?}", f.blocked_by);
    let line = &f.evidence[0];
    assert!(
        line.starts_with("encompassing test of scheduled-output and scheduling-nonlinearity")
            && line.contains("so scheduled-output is the effect"),
        "{line}"
    );
    let (so_adds, p_so) = against(line, "scheduling-nonlinearity");
    assert!(so_adds >= 10.0 && p_so < 5e-3, "{so_adds} {p_so}");
}

/// scheduling-nonlinearity plants 113000 and 113002 of the family (a fresh range; order 2,
/// p1^2 in A and B, noise 9.6 % and 8.6 %): a scheduled output equation and p1^2 are both
/// findings, and the structure with both explains 4-5 % of the output equation's held-out
/// error (under the 10 % a comparison needs) and nothing of p1^2's: the data do not tell them
/// apart. The parsimony rule then named the output equation by its coefficient count (18
/// against 21); now the lower own held-out error decides, as for a pair that parsimony did
/// not reorder: p1^2 is named. On 113002 the PBSID fit of the structure with both lost to
/// the p1^2 it nests (-254 % of its error): that comparison is void, and the pair is judged
/// like with like on the refined variants.
#[test]
#[ignore = "long tier: make test-long"]
fn a_scheduling_pair_the_data_cannot_tell_apart_names_the_lower_held_out_error() {
    for seed in [113000, 113002] {
        let (_, out) = diagnose_one("scheduling-nonlinearity", seed, 1500);
        let f = out.report.findings.first().expect("findings");
        println!("{seed}: {} ({})\n{:#?}", f.effect, f.detail, f.evidence);
        assert_eq!(f.effect, "scheduling-nonlinearity", "seed {seed}");
        assert!(f.significant, "{:?}", f.blocked_by);
        let line = &f.evidence[0];
        assert!(
            line.starts_with("encompassing test of scheduled-output and scheduling-nonlinearity")
                && line.contains("neither adds to the other")
                && line.contains("scheduling-nonlinearity first (the lower held-out error"),
            "{line}"
        );
        let (sn_adds, _) = against(line, "scheduled-output");
        let (so_adds, _) = against(line, "scheduling-nonlinearity");
        assert!(sn_adds > 0.0 && sn_adds < 10.0, "{sn_adds}");
        assert!(so_adds > -10.0 && so_adds < 1.0, "{so_adds}");
        if seed == 113002 {
            assert!(
                line.contains("each effect judged by its variant refined the same way"),
                "{line}"
            );
        }
        let other = out
            .report
            .findings
            .iter()
            .find(|g| g.effect == "scheduled-output")
            .expect("the output equation is a finding too");
        assert!(other.significant && other.explained < f.explained);
    }
}

/// scheduled-output plant 3001 of the family (order 1, random binary input): the PBSID fit of
/// the structure with both scheduling effects lost to the p1^2 it nests (-158 % of its
/// held-out error), which read as "neither adds". That comparison is now void and the pair
/// is judged like with like: the output equation adds 42 % to the refined p1^2, p1^2
/// nothing to it, so the output equation is the effect by the test, not by a tie.
#[test]
fn a_comprehensive_fit_that_loses_to_what_it_nests_is_no_verdict() {
    let (_, out) = diagnose_one("scheduled-output", 3001, 1500);
    let f = out.report.findings.first().expect("findings");
    println!("{} ({})\n{:#?}", f.effect, f.detail, f.evidence);
    assert_eq!(f.effect, "scheduled-output");
    let line = &f.evidence[0];
    assert!(
        line.contains("each effect judged by its variant refined the same way")
            && line.contains("so scheduled-output is the effect"),
        "{line}"
    );
    let (so_adds, p_so) = against(line, "scheduling-nonlinearity");
    assert!(so_adds >= 10.0 && p_so < 5e-3, "{so_adds} {p_so}");
    let (sn_adds, _) = against(line, "scheduled-output");
    assert!(sn_adds < 10.0, "{sn_adds}");
}
