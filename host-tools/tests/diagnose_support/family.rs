//! The family benchmark of `lpvid diagnose` (issue 14): random plants per planted effect
//! ([`lpvid_host::diagnose::plants`]), each identified with `lpvid pbsid` as a user would and
//! diagnosed with `--fix` (one step); the confusion matrix (for each planted effect, how often
//! each effect was named first) and the error ratio after the fix. Shared by the release test
//! in `diagnose_planted.rs` and `examples/diagnose_family.rs`.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::fmt::Write as _;

use lpvid_host::diagnose::catalogue::with_order;
use lpvid_host::diagnose::effects::{refined_null, significant, versus, Eval};
use lpvid_host::diagnose::plants::{
    family_case_shaped, family_case_with, FamilyCase, Profile, Shape,
};
use lpvid_host::diagnose::refit::{fit_spec, Noise, Spec};
use lpvid_host::diagnose::{diagnose, Options};
use lpvid_host::model::{Factor, FactorFn, ModelFile};
use lpvid_host::simulate::{simulate, Mode};

/// One diagnosed family plant.
#[derive(Debug, Clone)]
pub struct FamilyRun {
    /// Planted effect.
    pub planted: String,
    /// Seed.
    pub seed: u64,
    /// Effect named first (above the noise threshold), or "none".
    pub named: String,
    /// What the finding named first adds (its `detail`: the column, delay, shape; empty when
    /// nothing was named).
    pub detail: String,
    /// Held-out error (free-run MSE; one-step for a noise model) before / after --fix
    /// (the free run when no effect was applied but the estimate was refined; 1 when the
    /// model was not changed).
    pub ratio: f64,
    /// What was drawn.
    pub description: String,
    /// The oracle of the planted effect ([`oracle`]; None for clean plants).
    pub oracle: Option<Oracle>,
}

/// The user's model structure refit with the planted effect's TRUE structure added (what the
/// generator knows, [`lpvid_host::diagnose::plants::Planted`]), scored against the user's
/// model on the held-out record: how much a diagnosis could gain at best with the catalogue's
/// model class, at this plant's strength, noise and N.
#[derive(Debug, Clone)]
pub struct Oracle {
    /// What was added.
    pub detail: String,
    /// Held-out error of the user's model / the oracle's, as [`FamilyRun::ratio`] (same mode,
    /// same simulation); NaN when the oracle's refit failed.
    pub ratio: f64,
    /// Fraction of the user's held-out error the oracle explains and its p-value, scored as
    /// diagnose scores a variant ([`Eval`]: x0 estimated on the first held-out samples,
    /// [`versus`]: batch log-ratio t test).
    pub explained: f64,
    /// See `explained`.
    pub p_value: f64,
    /// [`identifiable`].
    pub identifiable: bool,
}

/// The identifiability rule, defined once: the planted effect is identifiable on a plant when
/// its oracle passes the test a finding of `lpvid diagnose` must pass against the user's model
/// ([`significant`]: explains at least `MIN_EXPLAINED` = 10 % of the held-out error, and the
/// held-out batch log-ratio t test gives p < `ALPHA`), with ONE variant tried (the oracle is
/// given the structure, so no Bonferroni factor for a search). The t test is the replication
/// rule: its spread is that of the error ratio over independent held-out batches, so the noise
/// level of the plant sets the bar, not a number chosen on a seed. A plant whose oracle does
/// not pass cannot be diagnosed by any rule that a finding on it would have to pass; it is
/// not evidence against the method.
pub fn identifiable(explained: f64, p_value: f64) -> bool {
    significant(explained, p_value, 1)
}

/// The oracle's structure: the user's [`Spec`] with the planted effect's true structure, the
/// way the catalogue of `diagnose::catalogue::candidates` writes that idea (an input channel, a
/// scheduling basis function, a flag of [`Spec`]), with the true parameter where the catalogue
/// searches one (the delay, the frequency, the order, the shape and scale of the feedback).
/// `input-nonlinearity` of the tanh kind has no exact factor: its leading odd term u^3 and
/// |u| u. `scheduling-noise`: the same structure, refit on the noise-free p1 (the returned
/// training record). `clean`: the plant's order when the user's model has another (under
/// `--order auto`), else None. On a MIMO plant the channel-specific structures name the
/// planted channel (`u{input + 1}`, `y{output + 1}` of [`Planted`]); `feedthrough`
/// estimates all of D, `output-offset` adds one constant input channel (it reaches every
/// output), `coloured-noise` a noise model on every output: the catalogue's own structures,
/// which are not per channel.
///
/// [`Planted`]: lpvid_host::diagnose::plants::Planted
fn oracle_spec(
    case: &FamilyCase,
    user: &Spec,
    user_states: Option<usize>,
) -> Option<(String, Spec, lpvid_host::data::Dataset)> {
    let pl = &case.planted;
    let (un, yn) = (format!("u{}", pl.input + 1), format!("y{}", pl.output + 1));
    let (un, yn) = (un.as_str(), yn.as_str());
    let mut sp = user.clone();
    let mut train = case.train.clone();
    let plain = |col: &str, pow: f64, delay: usize, func: Option<FactorFn>| Factor {
        pow,
        delay,
        func,
        ..Factor::col(col)
    };
    let detail = match case.effect.as_str() {
        "output-offset" => {
            sp.signals.inputs.push(vec![]);
            "constant input channel".to_string()
        }
        "feedthrough" => {
            sp.opts.feedthrough = true;
            "feedthrough D".to_string()
        }
        "scheduled-output" => {
            sp.scheduled_output = true;
            "output equation C^(i), D^(i)".to_string()
        }
        "scheduling-nonlinearity" => {
            sp.signals.scheduling.push(vec![plain("p1", 2.0, 0, None)]);
            "scheduling basis p1^2".to_string()
        }
        "input-nonlinearity" => {
            let u = plain(un, 1.0, 0, None);
            let abs_u = vec![plain(un, 1.0, 0, Some(FactorFn::Abs)), u.clone()];
            match pl.input_nl? {
                0 => sp.signals.inputs.push(abs_u),
                1 => sp.signals.inputs.push(vec![plain(un, 2.0, 0, None)]),
                _ => {
                    sp.signals.inputs.push(vec![plain(un, 3.0, 0, None)]);
                    sp.signals.inputs.push(abs_u);
                }
            }
            let words = ["|u| u", "u^2", "u^3 and |u| u (tanh)"][pl.input_nl? as usize];
            format!("input channel {}", words.replace('u', un))
        }
        "input-delay" => {
            // the user's channel of the delayed input (the first of a SISO plant)
            let i = sp
                .signals
                .inputs
                .iter()
                .position(|ch| ch.len() == 1 && ch[0].col == un)?;
            sp.signals.inputs[i] = vec![plain(un, 1.0, pl.delay, None)];
            format!("{un} delayed {} samples", pl.delay)
        }
        "periodic-disturbance" => {
            let (om, harm) = pl.sine?;
            let h = if harm { 2 } else { 1 };
            for i in 1..=h {
                for func in [FactorFn::Sin, FactorFn::Cos] {
                    sp.signals.inputs.push(vec![Factor {
                        omega: Some(i as f64 * om / pl.ts),
                        ..plain("t", 1.0, 0, Some(func))
                    }]);
                }
            }
            format!("sin/cos of the true frequency {om:.4} rad/sample, {h} harmonic(s)")
        }
        "order-too-low" => {
            sp = with_order(&sp, pl.states);
            format!("order {}", pl.states)
        }
        // a clean plant whose user model (`--order auto`) has another number of states: the
        // user's structure at the plant's, so that a finding about a model a state short is
        // told apart from a false alarm about the plant
        "clean" if user_states != Some(pl.states) => {
            sp = with_order(&sp, pl.states);
            format!(
                "order {} (the plant's; the user's model has {})",
                pl.states,
                user_states.map_or("?".to_string(), |n| n.to_string())
            )
        }
        "coloured-noise" => {
            // the plant is y = G u + v + e with v an AR(1): output error plus AR noise (the
            // catalogue's Box-Jenkins-like variant) is its true structure
            sp.noise = Noise::OutputError;
            "output error + AR noise model".to_string()
        }
        "unused-signal" => {
            sp.signals.inputs.push(vec![plain("w", 1.0, 0, None)]);
            "input channel w".to_string()
        }
        "output-nonlinearity" => {
            let (kind, scale) = pl.output_nl?;
            let y = plain(yn, 1.0, 0, None);
            let ch = match kind {
                0 => vec![plain(yn, 3.0, 0, None)],
                1 => vec![Factor {
                    omega: Some(1.0 / scale),
                    ..plain(yn, 1.0, 0, Some(FactorFn::Sin))
                }],
                _ => vec![plain(yn, 1.0, 0, Some(FactorFn::Sign)), {
                    let mut f = y;
                    f.pow = 0.5;
                    f
                }],
            };
            sp.signals.inputs.push(ch);
            let words = [
                "feedback y^3",
                "feedback sin(y/scale)",
                "feedback sign(y) sqrt|y|",
            ];
            words[kind as usize].replace('y', yn)
        }
        "scheduling-noise" => {
            let p = pl.p1_train.as_ref()?;
            let j = train.names.iter().position(|c| c == "p1")?;
            train.cols[j] = p.clone();
            "refit on the noise-free p1".to_string()
        }
        _ => return None,
    };
    Some((detail, sp, train))
}

/// The held-out free-run error before the fix of a diagnosis over its error after (each model
/// from its estimated initial state); panics when no fix was applied.
pub fn fix_ratio(out: &lpvid_host::diagnose::Outcome) -> f64 {
    let after = out.after_eval.as_ref().expect("a fix applied");
    out.before_eval.mse(Mode::FreeRun) / after.mse(Mode::FreeRun)
}

/// The oracle of `case` against the user's `model` ([`Oracle`]), in `mode`; for a clean
/// plant only when the model's order is not the plant's (the plant's order is then the
/// oracle), else None. The refit is the diagnosis's own ([`fit_spec`], the user's `fit`
/// record extended).
pub fn oracle(case: &FamilyCase, model: &ModelFile, mode: Mode) -> Option<Oracle> {
    let mut notes = Vec::new();
    let user = Spec::from_model(model, &mut notes).ok()?;
    let (mut detail, sp, train) = oracle_spec(case, &user, states(model))?;
    let failed = |detail: &str, why: String| Oracle {
        detail: format!("{detail}: {why}"),
        ratio: f64::NAN,
        explained: f64::NEG_INFINITY,
        p_value: 1.0,
        identifiable: false,
    };
    let fitted = match fit_spec(&sp, &train, &model.fit) {
        Ok(f) => f,
        // a scheduled output equation whose PBSID regression is too long (two scheduling
        // signals at past 7: 19677 regressors) takes the catalogue's other route, refined
        // from the model's structure refined
        Err(e) if sp.scheduled_output => {
            let nested = Spec {
                nested_in: Some(Box::new(refined_null(&user))),
                ..sp.clone()
            };
            match fit_spec(&nested, &train, &model.fit) {
                Ok(f) => {
                    detail.push_str(", refined from the model's own structure refined");
                    f
                }
                Err(e2) => return Some(failed(&detail, format!("{e}; refined: {e2}"))),
            }
        }
        Err(e) => return Some(failed(&detail, e.to_string())),
    };
    let (e0, e1) = match (
        Eval::new(model, &case.val),
        Eval::new(&fitted.model, &case.val),
    ) {
        (Ok(a), Ok(b)) => (a, b),
        (Err(e), _) | (_, Err(e)) => return Some(failed(&detail, e.to_string())),
    };
    let (explained, p_value) = versus(&e0.loss(mode), &e1.loss(mode));
    let mut ratio = mse(model, &case.val, mode) / mse(&fitted.model, &case.val, mode).max(1e-300);
    if case.effect == "scheduling-noise" {
        detail.push_str(&refined_on_both(&user, case, &train, &model.fit, mode));
    }
    let mut identifiable = identifiable(explained, p_value);
    // the plant's order where the user's model has fewer states: also as the catalogue's
    // nested variant writes it (refined from the user's structure refined, judged against
    // that refined structure), whose bias can hide a missing state from the subspace refit
    let more_states = matches!(case.effect.as_str(), "clean" | "order-too-low")
        && states(model).is_some_and(|n| n < case.planted.states);
    if more_states && !identifiable {
        if let Some((x, p, r)) = nested_order(&user, &sp, case, model, mode) {
            let _ = write!(
                detail,
                "; refined from the user's structure refined: explains {:.1} % of its held-out error (p = {p:.1e}), {r:.2}x the user's model",
                100.0 * x
            );
            if self::identifiable(x, p) {
                identifiable = true;
                ratio = ratio.max(r);
            }
        }
    }
    Some(Oracle {
        detail,
        ratio,
        explained,
        p_value,
        identifiable,
    })
}

/// The plant's order `sp` nested in the user's structure refined (`diagnose::catalogue`'s
/// `order-too-low` variant refined from that structure): the fraction of the refined
/// structure's held-out error it explains, its p-value, and the user's model's held-out
/// error over its own. None when a fit fails.
fn nested_order(
    user: &Spec,
    sp: &Spec,
    case: &FamilyCase,
    model: &ModelFile,
    mode: Mode,
) -> Option<(f64, f64, f64)> {
    let null = refined_null(user);
    let nested = Spec {
        nested_in: Some(Box::new(null.clone())),
        ..sp.clone()
    };
    let f0 = fit_spec(&null, &case.train, &model.fit).ok()?;
    let f1 = fit_spec(&nested, &case.train, &model.fit).ok()?;
    let e0 = Eval::new(&f0.model, &case.val).ok()?;
    let e1 = Eval::new(&f1.model, &case.val).ok()?;
    let (x, p) = versus(&e0.loss(mode), &e1.loss(mode));
    let r = mse(model, &case.val, mode) / mse(&f1.model, &case.val, mode).max(1e-300);
    Some((x, p, r))
}

/// The scheduling-noise oracle like with like, in words: the user's structure refined by
/// output error (`refined_null`, what the diagnosis judges the low-pass and latent variants
/// against) on the measured p1 against the same refinement on the noise-free p1 (`clean`):
/// how much of the refined structure's held-out error the sensor noise leaves.
fn refined_on_both(
    user: &Spec,
    case: &FamilyCase,
    clean: &lpvid_host::data::Dataset,
    fit: &serde_json::Value,
    mode: Mode,
) -> String {
    let refined = refined_null(user);
    let eval = |train: &lpvid_host::data::Dataset| {
        fit_spec(&refined, train, fit)
            .ok()
            .and_then(|f| Eval::new(&f.model, &case.val).ok())
    };
    match (eval(&case.train), eval(clean)) {
        (Some(noisy), Some(free)) => {
            let (x, p) = versus(&noisy.loss(mode), &free.loss(mode));
            format!(
                "; like with like, the structure refined on each: explains {:.1} % (p = {p:.1e}, identifiable {})",
                100.0 * x,
                identifiable(x, p)
            )
        }
        _ => "; like with like: a refined fit failed".to_string(),
    }
}

/// The mode the planted effect is judged in: one-step prediction for coloured noise (a
/// noise model changes only the predictor), free run otherwise.
fn oracle_mode(effect: &str) -> Mode {
    if effect == "coloured-noise" {
        Mode::Predictor
    } else {
        Mode::FreeRun
    }
}

fn mse(model: &ModelFile, ds: &lpvid_host::data::Dataset, mode: Mode) -> f64 {
    match simulate(model, ds, mode) {
        Ok((y, yh)) => {
            let e = &y - &yh;
            let v = e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64;
            if v.is_finite() {
                v
            } else {
                f64::INFINITY
            }
        }
        Err(_) => f64::INFINITY,
    }
}

/// The user's model of a family case: `lpvid pbsid` on its training record with the case's
/// options (the command line a user runs), read back from its output file.
fn user_model(case: &FamilyCase) -> Result<ModelFile, String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let tp = dir.path().join("train.csv");
    let mp = dir.path().join("model.json");
    case.train.write_csv(&tp).map_err(|e| e.to_string())?;
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(case.pbsid_args.iter().cloned());
    cli.extend(["--out".to_string(), mp.display().to_string()]);
    lpvid_host::cli::run(cli, &mut Vec::new()).map_err(|e| e.to_string())?;
    ModelFile::read(&mp).map_err(|e| e.to_string())
}

/// The finding of `effect` in a report that names nothing (every finding printed with the
/// rule that blocked it; none significant, nothing applied), and that rule.
pub fn blocked_finding<'r>(
    report: &'r lpvid_host::diagnose::Report,
    effect: &str,
) -> (&'r lpvid_host::diagnose::effects::Finding, &'r str) {
    for f in &report.findings {
        println!(
            "{} ({}) {:.3} {:?}",
            f.effect, f.detail, f.explained, f.blocked_by
        );
    }
    assert!(report.findings.iter().all(|f| !f.significant));
    assert!(report.applied.is_empty());
    let f = report
        .findings
        .iter()
        .find(|f| f.effect == effect)
        .unwrap_or_else(|| panic!("a {effect} finding"));
    (f, f.blocked_by.as_deref().unwrap_or(""))
}

/// The first finding of a report, printed, asserted to be a significant `effect`.
pub fn named_first<'r>(
    report: &'r lpvid_host::diagnose::Report,
    effect: &str,
) -> &'r lpvid_host::diagnose::effects::Finding {
    let f = report.findings.first().expect("findings");
    println!(
        "{} ({}) {:.3} {:?} {:?}",
        f.effect, f.detail, f.explained, f.replication, f.evidence
    );
    assert_eq!(f.effect, effect);
    assert!(f.significant, "{:?}", f.blocked_by);
    f
}

/// Assert that one of a finding's evidence lines contains `text`.
pub fn assert_evidence(f: &lpvid_host::diagnose::effects::Finding, text: &str) {
    assert!(
        f.evidence.iter().any(|e| e.contains(text)),
        "{text}: {:?}",
        f.evidence
    );
}

/// The number written right after `marker` in `text` (a p-value or a percentage in a
/// finding's words).
pub fn number_after(text: &str, marker: &str) -> f64 {
    text.split(marker)
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.trim_end_matches([',', ';', ')']).parse().ok())
        .unwrap_or_else(|| panic!("a number after {marker:?} in {text}"))
}

/// Assert that `why`, the rule that blocked a `coloured-noise` finding, is one of the two that
/// judge a noise model against the model's structure refined by output error: that
/// structure's one-step error is lower (`effects::needs_refined_null`, tested first) or its
/// free-run residual is white with a Ljung-Box p-value of at least `white_p`
/// (`states::states_check`).
pub fn assert_refined_not_coloured(why: &str, white_p: f64) {
    if why.contains("is white (Ljung-Box p = ") {
        let p = number_after(why, "Ljung-Box p = ");
        assert!(p >= white_p, "{p}");
    } else {
        assert!(why.contains("not coloured noise"), "{why}");
        let against = number_after(why, "this variant explains ");
        assert!(against < 0.0, "{against}");
    }
}

/// Draw the plant of `effect` with `seed` (records of `n` samples), identify it with the
/// user's `lpvid pbsid` options and diagnose it with `--fix` (one step): the user's model and
/// the outcome, for tests that look into the report.
pub fn diagnose_one(
    effect: &str,
    seed: u64,
    n: usize,
) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    diagnose_one_shaped(effect, seed, n, Shape::SISO)
}

/// [`diagnose_one`] for a plant of `shape` (inputs x outputs).
pub fn diagnose_one_shaped(
    effect: &str,
    seed: u64,
    n: usize,
    shape: Shape,
) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    diagnose_case(family_case_shaped(effect, seed, n, shape).unwrap())
}

/// The states of an LPV state-space model (None for an LPV-ARX model).
pub fn states(model: &ModelFile) -> Option<usize> {
    match &model.kind {
        lpvid_host::model::ModelKind::Ss(ss) => Some(ss.n()),
        _ => None,
    }
}

/// [`diagnose_one_shaped`] with the user's order left to `--order auto` (what
/// `LPVID_FAMILY_ORDER=auto` does in the family run).
pub fn diagnose_one_auto(
    effect: &str,
    seed: u64,
    n: usize,
    shape: Shape,
) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    let mut case = family_case_shaped(effect, seed, n, shape).unwrap();
    leave_order_to_auto(&mut case);
    diagnose_case(case)
}

/// The user's model of a drawn `case` and its diagnosis with `--fix` (one step).
fn diagnose_case(case: FamilyCase) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    let model = user_model(&case).unwrap();
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 2,
    };
    let out = diagnose(&model, &case.train, &case.val, &opts).unwrap();
    (model, out)
}

/// [`diagnose_one_auto`] with the user's past window `past` in place of the drawn one (what
/// `LPVID_FAMILY_PAST` does in the family run).
pub fn diagnose_one_auto_past(
    effect: &str,
    seed: u64,
    n: usize,
    past: usize,
) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    let mut case = family_case_shaped(effect, seed, n, Shape::SISO).unwrap();
    leave_order_to_auto(&mut case);
    set_user_past(&mut case, past);
    diagnose_case(case)
}

/// The user's `lpvid pbsid` options with past window `p` in place of the drawn one.
fn set_user_past(case: &mut FamilyCase, p: usize) {
    if let Some(i) = case.pbsid_args.iter().position(|a| a == "--past") {
        case.pbsid_args[i + 1] = p.to_string();
    }
}

/// The user's `lpvid pbsid` options with `--order auto` in place of the plant's order (a user
/// who does not know it).
fn leave_order_to_auto(case: &mut FamilyCase) {
    if let Some(i) = case.pbsid_args.iter().position(|a| a == "--order") {
        case.pbsid_args[i + 1] = "auto".into();
    }
}

/// Draw, identify and diagnose the plant of `effect` with `seed` (records of `n` samples).
pub fn run_one(effect: &str, seed: u64, n: usize) -> FamilyRun {
    run_one_with(effect, seed, n, None)
}

/// [`run_one`] with the validation (held-out) record cut to its first `val_len` samples (a
/// short held-out record, as the cascaded tanks' 205 samples).
pub fn run_one_with(effect: &str, seed: u64, n: usize, val_len: Option<usize>) -> FamilyRun {
    run_one_shaped(effect, seed, n, val_len, Shape::SISO)
}

/// [`run_one_with`] for a plant of `shape` (inputs x outputs).
pub fn run_one_shaped(
    effect: &str,
    seed: u64,
    n: usize,
    val_len: Option<usize>,
    shape: Shape,
) -> FamilyRun {
    // LPVID_FAMILY_SCHEDULING=operating-points: a scheduled plant's p1 moves between held
    // levels (plants::Profile::OperatingPoints) instead of the family's drawn signals;
    // =two-signals: a second scheduling signal p2 (plants::Profile::TwoSignals)
    let profile = match std::env::var("LPVID_FAMILY_SCHEDULING").as_deref() {
        Ok("operating-points") => Profile::OperatingPoints,
        Ok("two-signals") => Profile::TwoSignals,
        _ => Profile::Drawn,
    };
    run_one_profiled(effect, seed, n, val_len, shape, profile)
}

/// [`run_one_shaped`] with the scheduling signals of a scheduled plant drawn as `profile`
/// says (the environment is not read).
pub fn run_one_profiled(
    effect: &str,
    seed: u64,
    n: usize,
    val_len: Option<usize>,
    shape: Shape,
    profile: Profile,
) -> FamilyRun {
    let mut case = family_case_with(effect, seed, n, shape, profile).unwrap();
    if let Some(v) = val_len {
        for c in case.val.cols.iter_mut() {
            c.truncate(v);
        }
    }
    // LPVID_FAMILY_ORDER=auto: the user leaves the order to `--order auto` (a user who does
    // not know it), instead of the plant's order; order-too-low keeps its order too small
    if std::env::var("LPVID_FAMILY_ORDER").as_deref() == Ok("auto") && effect != "order-too-low" {
        leave_order_to_auto(&mut case);
    }
    // LPVID_FAMILY_PAST=P: the user's past window P for every plant (a user who does not
    // know the plant's slowest pole), instead of the one drawn from it
    if let Some(p) = std::env::var("LPVID_FAMILY_PAST")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
    {
        set_user_past(&mut case, p);
    }
    // LPVID_FAMILY_DUMP=DIR: the case's records and the user's `lpvid pbsid` options as
    // files, so a miss can be traced through the command line (`lpvid pbsid`, `diagnose`)
    if let Ok(dir) = std::env::var("LPVID_FAMILY_DUMP") {
        if let Err(e) = case.dump(std::path::Path::new(&dir)) {
            eprintln!("LPVID_FAMILY_DUMP: {e}");
        }
    }
    let fail = |why: String| FamilyRun {
        planted: effect.to_string(),
        seed,
        named: format!("error: {why}"),
        detail: String::new(),
        ratio: 1.0,
        description: case.description.clone(),
        oracle: None,
    };
    let model = match user_model(&case) {
        Ok(m) => m,
        Err(e) => return fail(e),
    };
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 1,
    };
    let out = match diagnose(&model, &case.train, &case.val, &opts) {
        Ok(o) => o,
        Err(e) => return fail(e.to_string()),
    };
    let r = &out.report;
    if std::env::var("LPVID_FAMILY_VERBOSE").is_ok() {
        // per-plant detail: the findings (with the rule that blocked each) and the
        // output-nonlinearity variants, for tracing a miss to its cause
        let mut v = format!("{effect} seed {seed}: {}\n", case.description);
        for f in r.findings.iter().take(4) {
            let _ = writeln!(
                v,
                "    finding {} ({}) explained {:.3} p {:.1e} rep {:?} sig {} blocked {:?}",
                f.effect,
                f.detail,
                f.explained,
                f.p_value,
                f.replication,
                f.significant,
                f.blocked_by
            );
            // the evidence lines of the rules that block or reorder findings
            for e in f.evidence.iter().filter(|e| {
                [
                    "larger past window",
                    "encompassing test",
                    "preferred to",
                    "frequency of",
                    "in place of",
                    "ran away",
                ]
                .iter()
                .any(|k| e.contains(k))
            }) {
                let _ = writeln!(v, "      {e}");
            }
        }
        for s in r.steps.iter().take(1).flat_map(|st| &st.variants_scored) {
            if s.effect == "output-nonlinearity"
                || s.effect == "periodic-disturbance"
                || s.effect == "scheduling-noise"
                || s.explained > 0.05
            {
                let _ = writeln!(
                    v,
                    "    variant {} {} explained {:.3} p {:.1e} {:?}",
                    s.effect, s.detail, s.explained, s.p_value, s.error
                );
            }
        }
        print!("{v}");
    }
    let top = r.findings.first().filter(|f| f.significant);
    let named = top.map_or("none".to_string(), |f| f.effect.to_string());
    let detail = top.map_or(String::new(), |f| f.detail.clone());
    let ratio = match r.applied.first() {
        Some(a) => {
            let mode = if a.residual == "one-step" {
                Mode::Predictor
            } else {
                Mode::FreeRun
            };
            mse(&model, &case.val, mode) / mse(&out.model, &case.val, mode).max(1e-300)
        }
        // no effect, the structure's estimate refined (report.refined): free run
        None if r.refined.is_some() => {
            mse(&model, &case.val, Mode::FreeRun)
                / mse(&out.model, &case.val, Mode::FreeRun).max(1e-300)
        }
        None => 1.0,
    };
    let oracle = oracle(&case, &model, oracle_mode(effect));
    FamilyRun {
        planted: effect.to_string(),
        seed,
        named,
        detail,
        ratio,
        description: case.description,
        oracle,
    }
}

/// Run every (effect, seed) on `threads` threads.
pub fn run_family(effects: &[&str], seeds: &[u64], n: usize, threads: usize) -> Vec<FamilyRun> {
    run_family_with(effects, seeds, n, threads, None)
}

/// [`run_family`] with held-out records of `val_len` samples ([`run_one_with`]).
pub fn run_family_with(
    effects: &[&str],
    seeds: &[u64],
    n: usize,
    threads: usize,
    val_len: Option<usize>,
) -> Vec<FamilyRun> {
    run_family_shaped(effects, seeds, n, threads, val_len, Shape::SISO)
}

/// [`run_family_with`] on plants of `shape` (inputs x outputs).
pub fn run_family_shaped(
    effects: &[&str],
    seeds: &[u64],
    n: usize,
    threads: usize,
    val_len: Option<usize>,
    shape: Shape,
) -> Vec<FamilyRun> {
    let jobs: Vec<(String, u64)> = effects
        .iter()
        .flat_map(|e| seeds.iter().map(move |s| (e.to_string(), *s)))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let out = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..threads.max(1) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((e, seed)) = jobs.get(i) else { break };
                let r = run_one_shaped(e, *seed, n, val_len, shape);
                out.lock().unwrap().push(r);
            });
        }
    });
    let mut v = out.into_inner().unwrap();
    v.sort_by(|a, b| (&a.planted, a.seed).cmp(&(&b.planted, b.seed)));
    v
}

/// Per planted effect: (recall = named first correctly, or "none" for clean; median error
/// ratio; min; max; runs).
pub fn summary(runs: &[FamilyRun]) -> BTreeMap<String, (f64, f64, f64, f64, usize)> {
    let mut by: BTreeMap<String, Vec<&FamilyRun>> = BTreeMap::new();
    for r in runs {
        by.entry(r.planted.clone()).or_default().push(r);
    }
    by.into_iter()
        .map(|(e, rs)| {
            let want = if e == "clean" { "none" } else { e.as_str() };
            let hits = rs.iter().filter(|r| r.named == want).count();
            let mut ratios: Vec<f64> = rs.iter().map(|r| r.ratio).collect();
            ratios.sort_by(f64::total_cmp);
            let med = ratios[ratios.len() / 2];
            (
                e.clone(),
                (
                    hits as f64 / rs.len() as f64,
                    med,
                    ratios[0],
                    ratios[ratios.len() - 1],
                    rs.len(),
                ),
            )
        })
        .collect()
}

/// The confusion matrix as a markdown table (rows: planted; columns: named first), then
/// recall and the error ratio after --fix (median [min, max]).
pub fn matrix(runs: &[FamilyRun]) -> String {
    let mut named: Vec<String> = runs.iter().map(|r| r.named.clone()).collect();
    named.sort();
    named.dedup();
    let mut planted: Vec<String> = runs.iter().map(|r| r.planted.clone()).collect();
    planted.sort();
    planted.dedup();
    let sum = summary(runs);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| planted \\ named first | {} | recall | error ratio median [min, max] |",
        named.join(" | ")
    );
    let _ = writeln!(s, "|---|{}---|---|", "---|".repeat(named.len()));
    for p in &planted {
        let cells: Vec<String> = named
            .iter()
            .map(|n| {
                let c = runs
                    .iter()
                    .filter(|r| &r.planted == p && &r.named == n)
                    .count();
                if c == 0 {
                    ".".to_string()
                } else {
                    c.to_string()
                }
            })
            .collect();
        let (rec, med, lo, hi, _) = sum[p];
        let _ = writeln!(
            s,
            "| {p} | {} | {rec:.2} | {} [{}, {}] |",
            cells.join(" | "),
            Ratio(med),
            Ratio(lo),
            Ratio(hi)
        );
    }
    s
}

/// An error ratio as printed in the tables: two decimals, or two significant digits in
/// exponent form from 1e5 on (a diverged model's ratio, e.g. 1.8e103, printed with `{:.2}`
/// took a hundred digits of a table cell).
#[derive(Debug, Clone, Copy)]
pub struct Ratio(pub f64);

impl std::fmt::Display for Ratio {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let text = if self.0.is_finite() && self.0.abs() >= 1e5 {
            format!("{:.1e}", self.0)
        } else {
            format!("{:.2}", self.0)
        };
        // honour a width given by the caller ({:>8})
        f.pad(&text)
    }
}

/// Per planted effect (clean plants apart: [`clean_line`]): the raw recall, the plants whose
/// oracle is [`identifiable`], the recall among them, and each missed identifiable plant's
/// oracle ratio against the ratio achieved, as a markdown table (printed after [`matrix`]).
pub fn identifiable_table(runs: &[FamilyRun]) -> String {
    let mut by: BTreeMap<String, Vec<&FamilyRun>> = BTreeMap::new();
    for r in runs.iter().filter(|r| r.planted != "clean") {
        by.entry(r.planted.clone()).or_default().push(r);
    }
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| planted | recall | identifiable | recall among identifiable | named, not identifiable | oracle ratio median [min, max] | missed identifiable: seed (named) oracle ratio / achieved |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for (e, rs) in &by {
        let hits = rs.iter().filter(|r| &r.named == e).count();
        let ident: Vec<&&FamilyRun> = rs
            .iter()
            .filter(|r| r.oracle.as_ref().is_some_and(|o| o.identifiable))
            .collect();
        let ident_hits = ident.iter().filter(|r| &r.named == e).count();
        let mut ratios: Vec<f64> = rs
            .iter()
            .filter_map(|r| r.oracle.as_ref().map(|o| o.ratio))
            .filter(|v| !v.is_nan())
            .collect();
        ratios.sort_by(f64::total_cmp);
        let oracle_ratios = if ratios.is_empty() {
            "-".to_string()
        } else {
            format!(
                "{} [{}, {}]",
                Ratio(ratios[ratios.len() / 2]),
                Ratio(ratios[0]),
                Ratio(ratios[ratios.len() - 1])
            )
        };
        let missed: Vec<String> = ident
            .iter()
            .filter(|r| &r.named != e)
            .map(|r| {
                format!(
                    "{} ({}) {} / {}",
                    r.seed,
                    r.named,
                    Ratio(r.oracle.as_ref().map_or(f64::NAN, |o| o.ratio)),
                    Ratio(r.ratio)
                )
            })
            .collect();
        let among = if ident.is_empty() {
            "-".to_string()
        } else {
            format!("{:.2}", ident_hits as f64 / ident.len() as f64)
        };
        let _ = writeln!(
            s,
            "| {e} | {:.2} | {} of {} | {among} | {} | {oracle_ratios} | {} |",
            hits as f64 / rs.len() as f64,
            ident.len(),
            rs.len(),
            hits - ident_hits,
            if missed.is_empty() {
                ".".to_string()
            } else {
                missed.join("; ")
            }
        );
    }
    s
}

/// The clean plants' line: how many got a finding, and of those how many are a finding about
/// the user's model rather than the plant: the plant's own order, refit in the user's
/// structure, is [`identifiable`] against the user's model (a model `--order auto` left a
/// state or more short; [`oracle`]).
pub fn clean_line(runs: &[FamilyRun]) -> String {
    let clean: Vec<&FamilyRun> = runs.iter().filter(|r| r.planted == "clean").collect();
    let named: Vec<&&FamilyRun> = clean.iter().filter(|r| r.named != "none").collect();
    let short = named
        .iter()
        .filter(|r| r.oracle.as_ref().is_some_and(|o| o.identifiable))
        .count();
    format!(
        "clean plants with a finding: {} of {} ({:.1} %); of them {short} on a model whose plant's order is identifiable against it (a finding about the model)",
        named.len(),
        clean.len(),
        100.0 * named.len() as f64 / clean.len().max(1) as f64
    )
}
