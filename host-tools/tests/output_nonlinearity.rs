//! The `output-nonlinearity` effect of `lpvid diagnose` on random families of plants whose
//! dynamics depend on their own output level: a cubic spring (Duffing), a pendulum (sin of the
//! angle), a tank with square-root outflow; random parameters, effect strengths, noise levels
//! (1-10 % of the output's spread) and input spectra; and clean linear plants of random order
//! 1-4 for false alarms. Each plant is identified as a user would (`pipeline::identify`, past
//! 8, order auto), then diagnosed with `--fix` on separate validation data.
//! Release mode: `cargo test --release -p lpvid-host --test output_nonlinearity -- --nocapture`
//! prints the table of every run.

mod diagnose_support;

use lpvid_host::data::Dataset;
use lpvid_host::diagnose::effects::{refined_null, versus, Eval};
use lpvid_host::diagnose::refit::{fit_spec, Spec};
use lpvid_host::diagnose::{diagnose, Options, Outcome};
use lpvid_host::model::{Factor, FactorFn, ModelFile};
use lpvid_host::pipeline::{identify, DataFile, Identified, PbsidSettings};
use lpvid_host::simulate::{run, Mode, X0};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

#[derive(Clone, Copy, Debug, PartialEq)]
enum Plant {
    Duffing,
    Pendulum,
    Tank,
    Linear,
}

/// One record of a random plant: (u, y measured). `pole` is the input filter's pole (the
/// input spectrum), `noise` the output noise as a fraction of std(y).
fn record(
    plant: Plant,
    prm: &[f64],
    n: usize,
    pole: f64,
    noise: f64,
    seed: u64,
) -> (Vec<f64>, Vec<f64>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let g = Normal::new(0.0, 1.0).unwrap();
    let gain = (1.0 - pole * pole).sqrt();
    let mut lp = 0.0;
    let mut u = Vec::with_capacity(n);
    let mut y = Vec::with_capacity(n);
    let mut x = [0.0f64; 4];
    for _ in 0..n {
        lp = pole * lp + gain * g.sample(&mut rng);
        match plant {
            Plant::Duffing => {
                // x1' = x2, x2' = -x1 - c x2 - k3 x1^3 + a u (semi-implicit Euler, h = 0.1)
                let (c, k3, a) = (prm[0], prm[1], prm[2]);
                let uk = a * lp;
                y.push(x[0]);
                let v = x[1] + 0.1 * (-x[0] - c * x[1] - k3 * x[0].powi(3) + uk);
                x = [x[0] + 0.1 * v, v, 0.0, 0.0];
                u.push(uk);
            }
            Plant::Pendulum => {
                // th'' = -w^2 sin th - c th' + a u (h = 0.05)
                let (w2, c, a) = (prm[0], prm[1], prm[2]);
                let uk = a * lp;
                y.push(x[0]);
                let v = x[1] + 0.05 * (-w2 * x[0].sin() - c * x[1] + uk);
                x = [x[0] + 0.05 * v, v, 0.0, 0.0];
                u.push(uk);
            }
            Plant::Tank => {
                // h' = -q sqrt(h) + b u with a positive pump input (h = 0.5)
                let (q, b) = (prm[0], prm[1]);
                let uk = (1.0 + prm[2] * lp).max(0.05);
                y.push(x[0]);
                x[0] = (x[0] + 0.5 * (-q * x[0].max(0.0).sqrt() + b * uk)).max(0.0);
                u.push(uk);
            }
            Plant::Linear => {
                // y(k) = -sum a_i y(k-i) + b u(k-1), poles prm[1..]
                let order = prm[0] as usize;
                let a = poly(&prm[1..=order]);
                // x holds y(k-1), ..., y(k-order)
                let yk = -(1..=order).map(|i| a[i] * x[i - 1]).sum::<f64>()
                    + u.last().copied().unwrap_or(0.0);
                y.push(yk);
                for i in (1..order).rev() {
                    x[i] = x[i - 1];
                }
                x[0] = yk;
                u.push(lp);
            }
        }
    }
    let m = y.iter().sum::<f64>() / n as f64;
    let sd = (y.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / n as f64).sqrt();
    let ym = y
        .iter()
        .map(|v| v + noise * sd * g.sample(&mut rng))
        .collect();
    (u, ym)
}

/// Coefficients [1, a1, ..., an] of prod (z - p_i) for real poles.
fn poly(p: &[f64]) -> Vec<f64> {
    let mut c = vec![1.0];
    for &r in p {
        let mut n = vec![0.0; c.len() + 1];
        for (i, v) in c.iter().enumerate() {
            n[i] += v;
            n[i + 1] -= r * v;
        }
        c = n;
    }
    c
}

fn csv(name: &str, u: &[f64], y: &[f64]) -> DataFile {
    let mut s = String::from("u1,y1\n");
    for (a, b) in u.iter().zip(y) {
        s.push_str(&format!("{a},{b}\n"));
    }
    DataFile::from_bytes(name, s.as_bytes()).unwrap()
}

fn mse(m: &ModelFile, ds: &Dataset) -> f64 {
    let r = run(m, ds, Mode::FreeRun, X0::Zero).unwrap();
    let e = &r.y - &r.yhat;
    e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64
}

/// The plant's own Lur'e channel as an input factor: y1^3 (Duffing), sin(y1) (pendulum),
/// sqrt|y1| (tank, whose level is never negative); None for a linear plant.
fn true_channel(plant: Plant) -> Option<Vec<Factor>> {
    let own = |pow: f64, func: Option<FactorFn>| Factor {
        pow,
        func,
        ..Factor::col("y1")
    };
    match plant {
        Plant::Duffing => Some(vec![own(3.0, None)]),
        Plant::Pendulum => Some(vec![own(1.0, Some(FactorFn::Sin))]),
        Plant::Tank => Some(vec![own(0.5, None)]),
        Plant::Linear => None,
    }
}

/// The oracle of a plant: the user's structure with the plant's true Lur'e channel added,
/// fitted as diagnose fits the catalogue's variant (`fit_spec`, the refinement through the
/// feedback) and scored as diagnose scores it (held-out free run from x0 estimated on the
/// first held-out samples, against the user's structure refined, the output-nonlinearity
/// null): (explained, p-value, held-out error ratio to the user's model with x0 estimated,
/// the same from x0 = 0). Tells an identifiable miss from one nobody could find.
fn oracle(plant: Plant, id: &Identified, train: &Dataset, val: &Dataset) -> Option<[f64; 4]> {
    let ch = true_channel(plant)?;
    let user = Spec::from_model(&id.model, &mut Vec::new()).ok()?;
    let null = refined_null(&user);
    let mut sp = refined_null(&user);
    sp.signals.inputs.push(ch);
    let f1 = fit_spec(&sp, train, &id.model.fit).ok()?;
    let f0 = fit_spec(&null, train, &id.model.fit).ok()?;
    let (e0, e1, eu) = (
        Eval::new(&f0.model, val).ok()?,
        Eval::new(&f1.model, val).ok()?,
        Eval::new(&id.model, val).ok()?,
    );
    let mode = lpvid_host::simulate::Mode::FreeRun;
    let (explained, p) = versus(&e0.loss(mode), &e1.loss(mode));
    Some([
        explained,
        p,
        eu.mse(mode) / e1.mse(mode),
        mse(&id.model, val) / mse(&f1.model, val),
    ])
}

/// One plant diagnosed with `--fix` (one step): (the user's model, the outcome, the
/// held-out data, the plant's description).
fn diagnosed(plant: Plant, seed: u64) -> (Identified, Outcome, Dataset, String, Dataset) {
    diagnosed_with(plant, seed, &PbsidSettings::new(8))
}

/// [`diagnosed`] with the user's model identified with `settings`.
fn diagnosed_with(
    plant: Plant,
    seed: u64,
    settings: &PbsidSettings,
) -> (Identified, Outcome, Dataset, String, Dataset) {
    let mut rng = StdRng::seed_from_u64(seed);
    let prm: Vec<f64> = match plant {
        Plant::Duffing => vec![
            rng.gen_range(0.2..0.6),
            rng.gen_range(0.5..3.0),
            rng.gen_range(0.6..1.2),
        ],
        Plant::Pendulum => {
            // the torque stays below what would swing it over the top most of the time
            // (|a u| < w^2 for |u| < 1.4-2.5), but not always: pendulums 4013 and 4015 go
            // over the top (to 15 rad) in their training / held-out records, as does every
            // missed pendulum of seeds 1000-8000 but 3010 (docs/bench-diagnose.md, h23pend)
            let w2: f64 = rng.gen_range(2.0..6.0);
            vec![w2, rng.gen_range(0.3..1.0), w2 * rng.gen_range(0.4..0.7)]
        }
        Plant::Tank => vec![
            rng.gen_range(0.3..0.8),
            rng.gen_range(0.3..0.8),
            rng.gen_range(0.4..0.8),
        ],
        Plant::Linear => {
            let order = rng.gen_range(1..=3usize);
            let mut v = vec![order as f64];
            for _ in 0..order {
                v.push(rng.gen_range(0.3..0.9));
            }
            v
        }
    };
    let pole = rng.gen_range(0.5..0.9);
    let noise = rng.gen_range(0.01..0.10);
    let (u, y) = record(plant, &prm, 3000, pole, noise, seed * 7 + 1);
    let (uv, yv) = record(plant, &prm, 1500, pole, noise, seed * 7 + 2);
    let train = csv("train.csv", &u, &y);
    let val = csv("val.csv", &uv, &yv).data;
    // LPVID_DUMP=DIR writes the records, to trace a plant through the command line
    if let Ok(dir) = std::env::var("LPVID_DUMP") {
        let stem = format!("{dir}/{plant:?}{seed}");
        train
            .data
            .write_csv(std::path::Path::new(&format!("{stem}.train.csv")))
            .unwrap();
        val.write_csv(std::path::Path::new(&format!("{stem}.val.csv")))
            .unwrap();
    }
    let id = identify(&train, None, settings).unwrap();
    let o = diagnose(
        &id.model,
        &train.data,
        &val,
        &Options {
            fix: true,
            max_steps: 1,
            threads: 0,
        },
    )
    .unwrap();
    let desc = format!(
        "{plant:?} seed {seed}: prm {prm:.2?}, input pole {pole:.2}, noise {:.1} %, order {}",
        100.0 * noise,
        id.fit.order
    );
    (id, o, val, desc, train.data)
}

/// Outcome of one plant: (named output-nonlinearity first, applied, error ratio before/after,
/// any finding at all).
fn one(plant: Plant, seed: u64) -> (bool, bool, f64, bool, String) {
    let (id, o, val, desc, train) = diagnosed(plant, seed);
    let first = o
        .report
        .findings
        .first()
        .filter(|f| f.significant)
        .map(|f| f.effect)
        .unwrap_or("none");
    let applied = o.report.applied.first().map(|a| a.effect);
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    if std::env::var("LPVID_VERBOSE").is_ok() {
        if let Some([ex, p, r_est, r_zero]) = oracle(plant, &id, &train, &val) {
            println!(
                "    oracle (true channel, refined): explained {ex:.3} of the refined null, p {p:.1e}; ratio to the user's model {r_est:.2} (x0 estimated), {r_zero:.2} (x0 = 0)"
            );
        }
        for f in o.report.findings.iter().take(4) {
            println!(
                "    finding {} {} {:.3} p {:.1e} rep {:?} sig {} blocked {:?}",
                f.effect,
                f.detail,
                f.explained,
                f.p_value,
                f.replication,
                f.significant,
                f.blocked_by
            );
        }
        // the first line of the first finding's evidence: the ranking rule that put it there
        // (parsimony, the encompassing test), when one did
        if let Some(e) = o.report.findings.first().and_then(|f| f.evidence.first()) {
            println!("    first evidence: {e}");
        }
        for v in &o.report.steps[0].variants_scored {
            println!(
                "    {} {} {:.3} p {:.1e} {:?}",
                v.effect, v.detail, v.explained, v.p_value, v.error
            );
        }
    }
    let line = format!(
        "{desc}: first {first}, applied {}, error ratio {ratio:.2}",
        applied.unwrap_or("nothing"),
    );
    (
        first == "output-nonlinearity",
        applied == Some("output-nonlinearity"),
        ratio,
        first != "none",
        line,
    )
}

/// The seeds of each family: 1..=3, or `LPVID_SEEDS=FIRST,COUNT` to measure the spread on
/// others (the assertions then judge those).
fn seeds() -> std::ops::RangeInclusive<u64> {
    let v: Vec<u64> = std::env::var("LPVID_SEEDS")
        .ok()
        .map(|s| s.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .unwrap_or_default();
    match v[..] {
        [first, count] if count > 0 => first..=first + count - 1,
        _ => 1..=3,
    }
}

/// Recall and error ratio of `output-nonlinearity` on the three nonlinear families, and no
/// output-nonlinearity finding on clean linear plants. The figures asserted are those
/// measured on these seeds (docs/bench-diagnose.md has the spread); a plant whose
/// nonlinearity is too weak to matter at its noise level may honestly be left alone.
#[test]
#[ignore = "long tier: make test-long"]
fn output_nonlinearity_on_random_plant_families() {
    let mut lines = Vec::new();
    let mut named = 0;
    let mut total = 0;
    let mut ratios = Vec::new();
    let only = std::env::var("LPVID_PLANT").ok();
    for plant in [Plant::Duffing, Plant::Pendulum, Plant::Tank] {
        if only.as_deref().is_some_and(|p| p != format!("{plant:?}")) {
            continue;
        }
        for seed in seeds() {
            let (hit, applied, ratio, _, line) = one(plant, seed + 10 * plant as u64);
            total += 1;
            named += usize::from(hit);
            if applied {
                ratios.push(ratio);
                // never applied when it does not help on held-out data
                assert!(ratio > 1.0, "{line}");
            }
            lines.push(line);
        }
    }
    let mut false_alarms = 0;
    for seed in 1..=4u64 {
        let (hit, applied, ratio, _, line) = one(Plant::Linear, 100 + seed);
        false_alarms += usize::from(hit);
        if applied {
            assert!(ratio > 1.0, "{line}");
        }
        lines.push(line);
    }
    ratios.sort_by(f64::total_cmp);
    let median = ratios.get(ratios.len() / 2).copied().unwrap_or(0.0);
    println!("{}", lines.join("\n"));
    println!(
        "output-nonlinearity named first in {named} of {total} nonlinear plants; error ratio after --fix: median {median:.2}, range {:.2}-{:.2}; false alarms on clean linear plants: {false_alarms} of 4",
        ratios.first().copied().unwrap_or(0.0),
        ratios.last().copied().unwrap_or(0.0)
    );
    let text = lines.join("\n");
    // measured on these seeds: 7 of 9 (Duffing 3/3, tank 3/3, pendulum 1/3). Duffing seed 2
    // was missed (6 of 9) while diagnose replicated only the effect's best variant, the
    // quasi-LPV scheduling on y^2, whose refits on the training halves do not hold up; its
    // next variants are now replicated in its place (replicate::MAX_ALTERNATIVES). The
    // pendulum's sin is close to linear at small angles and noise hides it at larger ones
    // (seeds 12, 13: nothing found, nothing applied).
    assert!(named * 3 >= total * 2, "{text}");
    assert!(median >= 3.0, "{text}");
    assert_eq!(false_alarms, 0, "{text}");
}

/// Family plant output-nonlinearity 217003 (order 4, a sin of the output, low-pass input,
/// noise 10 %, past window 15): the second training half saw y1 in [-4.1, 5.0] while the
/// held-out record reaches -9.4 and 8.3. That half's sin(omega y1) refit (omega 0.51, the first
/// half's 0.68) runs at VAF 0 on the held-out record, so the variant that explains 94 % held
/// out did not replicate (97.2 % and -9663 %) and nothing was named (the oracle's ratio
/// 15.5x). The output fed back is the operating point of an own-output variant: the half is
/// now scored on the held-out stretches where y1 stays inside the range it saw
/// (`replicate::Halves::replicate_within_range`; measured 27.4 % there, 15.5x applied).
#[test]
#[ignore = "long tier: make test-long"]
fn an_own_output_channel_is_replicated_inside_the_output_range_a_half_saw() {
    let (_, out) = diagnose_support::family::diagnose_one("output-nonlinearity", 217003, 1500);
    let f = out.report.findings.first().expect("a finding");
    println!(
        "{} ({}) explained {:.3} rep {:?} within range {} {:?}",
        f.effect, f.detail, f.explained, f.replication, f.replicated_within_range, f.blocked_by
    );
    assert_eq!(f.effect, "output-nonlinearity");
    assert!(f.significant, "{:?}", f.blocked_by);
    assert!(f.replicated_within_range);
    let a = out.report.applied.first().expect("applied");
    assert_eq!(a.effect, "output-nonlinearity");
    // the held-out error drops as the oracle's does (15.5x), not by a little
    assert!(
        a.mse_before / a.mse_after > 5.0,
        "{} {}",
        a.mse_before,
        a.mse_after
    );
}

/// Family plant output-nonlinearity 238102 (three fast poles, affine in p1, a cubic spring,
/// low-pass input) under `--order auto` (two states): y1^3 and sin(y1) explained 81 % of the
/// held-out error, but their refits on the first training half, which saw y1 in
/// [-0.64, 0.44], ran away on the held-out record, which reaches -0.95 and 0.89 in 31 samples
/// of brief excursions (none 25 long), and nothing was named (oracle 20.17x). Every sample
/// beyond a half's range of an output fed back now cuts the held-out stretches the half is
/// scored on (`replicate::support_parts`): y1^3 replicates inside the range and is applied.
#[test]
fn a_brief_excursion_beyond_a_halfs_output_range_is_scored_inside_it() {
    use diagnose_support::family::{diagnose_one_auto, named_first};
    let (_, out) = diagnose_one_auto(
        "output-nonlinearity",
        238102,
        1500,
        lpvid_host::diagnose::plants::Shape::SISO,
    );
    let f = named_first(&out.report, "output-nonlinearity");
    assert!(f.replicated_within_range);
    let a = out.report.applied.first().expect("applied");
    // the oracle's ratio is 20.17x
    let ratio = a.mse_before / a.mse_after;
    assert!(ratio > 10.0, "{ratio}");
}

/// A fix must forget where its simulation starts (`diagnose::memory`). On this tank (fresh
/// seed 1024 of the family, found by `LPVID_SEEDS=1004,1 LPVID_PLANT=Tank`) the Lur'e
/// sin(3.5 y1) refit explained 84 % of the held-out error from the initial state estimated on
/// the first held-out samples, with a slow mode that used that state as an offset: from the
/// zero state (the tank starts empty) the applied fix was 3x worse than the user's model.
/// Now that variant is blocked by name of the rule, and what is applied improves the held-out
/// error from the zero state as well (or, since the refinement is kept frozen-stable, an
/// own-output refit that does not lean on its start is applied: quasi-LPV y1^2, 15.35x).
#[test]
fn a_fix_that_leans_on_its_estimated_start_is_not_applied() {
    let (id, o, val, desc, _) = diagnosed(Plant::Tank, 1024);
    let steps = &o.report.steps;
    let leaning: Vec<_> = steps[0]
        .findings
        .iter()
        .filter(|f| {
            f.blocked_by
                .as_deref()
                .is_some_and(|b| b.contains("leans on the initial state"))
        })
        .collect();
    // since the refinement is kept frozen-stable over the training operating points (helper
    // h22sref) the quasi-LPV y1^2 scheduling refit explains 84 % without leaning on its start
    // and is applied (15.35x from the zero state): no leaning variant is then in the way
    let applied_own = o
        .report
        .applied
        .first()
        .is_some_and(|a| a.detail.contains("of the model's own output"));
    assert!(
        leaning.iter().any(|f| f.effect == "output-nonlinearity") || applied_own,
        "{:#?}",
        steps[0].findings
    );
    assert!(leaning.iter().all(|f| !f.significant));
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(
        o.report.applied.is_empty() || ratio > 1.0,
        "{desc}: applied {:?}, error ratio from the zero state {ratio:.2}",
        o.report.applied.first().map(|a| &a.detail)
    );
}

/// A sin channel's frequency is refined with the matrices (`refine::refine_with_frequencies`,
/// the last stage of `pipeline::fit_map_frequencies`). On the family's output-nonlinearity
/// plant 15002 (a Lur'e sin(y1 / scale) plant, order 2, noise 6 %) the catalogue's variants
/// sin(y1) and sin(0.378 y1) (omega = 1 / the output's spread) explained -99.5 % and -6204 % of
/// the refined null's held-out error with omega held where the heuristics put it, and nothing
/// was named (ratio 1.00) although the oracle with the true scale reached 54.4x; with omega
/// refined from the spread's guess the variant explains 97.6 %, replicates and is applied at
/// 55.5x (docs/bench-diagnose.md, h19pn section).
#[test]
#[ignore = "long tier: make test-long"]
fn a_sin_channels_frequency_follows_the_data() {
    let r = diagnose_support::family::run_one("output-nonlinearity", 15002, 1500);
    println!("{}: named {}, ratio {:.2}", r.description, r.named, r.ratio);
    assert_eq!(r.named, "output-nonlinearity", "{}", r.description);
    assert!(r.ratio >= 10.0, "{:.2}", r.ratio);
}

/// Order-too-low against output-nonlinearity on the physical pendulum 1017 (user's order 2,
/// found by `LPVID_SEEDS=1000,8 LPVID_PLANT=Pendulum`). The own-output channel explains about
/// 74 % of the refined null's held-out error and replicates, but the parsimony rule named the
/// larger past window 10 (22.5 % of the PBSID null, 1.29x), as the richer structure did not
/// beat it head to head at ALPHA / (variants tried). The encompassing test
/// (`encompass::encompass_order`: the channel at past window 10, refined, explains most of the
/// past window's refined error, which adds nothing to the channel) then named the channel.
/// Since the states check (`states::states_check`, helper h21cn) the past window is judged
/// against the user's structure refined, where it adds nothing (-0.0 %), so it is not a
/// finding and the encompassing test is not reached: either way the channel is named and
/// applied (measured 5.21x; its oracle, the true sin(y1) channel in the user's structure,
/// 5.74x from the zero state).
#[test]
fn an_own_output_channel_that_adds_to_a_larger_past_window_is_named() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 1017);
    for g in &o.report.findings {
        println!(
            "{} ({}) {} {:?}",
            g.effect, g.detail, g.significant, g.blocked_by
        );
    }
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    let encompassed = f.evidence[0]
        .starts_with("encompassing test of order-too-low and output-nonlinearity")
        && f.evidence[0].contains(
            "output-nonlinearity adds to order-too-low and order-too-low adds nothing to it",
        );
    let order = o
        .report
        .findings
        .iter()
        .find(|g| g.effect == "order-too-low");
    let refined_away = order.is_some_and(|g| {
        !g.significant
            && g.blocked_by
                .as_deref()
                .is_some_and(|b| b.contains("refined the same way"))
    });
    assert!(
        encompassed || refined_away,
        "{desc}: {:#?}",
        o.report.findings
    );
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 4.0, "{desc}: error ratio {ratio:.2}");
}

/// The tank's outflow through its level, named with the constant its channel needs. On the
/// physical tank 4024 (fresh range, found by `LPVID_SEEDS=4004,1 LPVID_PLANT=Tank`) the
/// own-output variant with the lowest held-out error, a Lur'e sin(5.5 y1), replicated but
/// leaned on its estimated start (0.303 against its own error of 0.005 at the end of the
/// record) and was blocked; the effect's next variant that passed every rule was named in its
/// place (`diagnose::judge`, second chance: measured 11.25x; that rule is covered by
/// `diagnose_alternatives`). A level does not swing about zero, so since the Lur'e channels are
/// also tried with a constant input channel where the residual has a mean
/// (`diagnose::output::has_mean`), the true channel sqrt|y1| with its constant is named
/// directly, and no variant leans on its start (measured 18.29x). Its refinement's initial
/// state, which the constant channel can stand for, is now held (`refine::Layout::
/// start_is_redundant`): 44.34x, where D of the constant had slid with the rounding of J'J
/// (18.29x or 8.16x here, 2.31x on the CI machine, for the same training error).
#[test]
fn a_tank_outflow_is_named_with_its_constant() {
    let (id, o, val, desc, _) = diagnosed(Plant::Tank, 4024);
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    assert!(
        f.detail.contains("sqrt|y1|") && f.detail.ends_with("with a constant input channel []"),
        "{desc}: {f:#?}"
    );
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    println!("{desc}: error ratio {ratio:.2}");
    assert!(ratio >= 20.0, "{desc}: error ratio {ratio:.2}");
}

/// An own-output channel fitted at the model's own order when the data do not ask for more
/// (`diagnose::output::fit`, BIC on the training free-run error). On the physical tank 4025
/// (fresh range, found by `LPVID_SEEDS=4005,1 LPVID_PLANT=Tank`; the user's model has order 1,
/// as the tank) PBSID with the measured level in the Lur'e sqrt|y1| channel chose order 2,
/// whose refinement beat the order-1 fit by 0.1 % of training MSE (11 free coefficients
/// against 5): the parsimony rule then put output-offset (6 coefficients, 2.83x) first, as
/// the richer channel did not beat it head to head. Now the channel is fitted at order 1
/// (BIC), is the simpler and better structure, and is applied: measured 20.16x, its oracle's
/// ratio (the true sqrt|y1| channel refined, 20.16x from the zero state).
#[test]
fn an_own_output_channel_is_fitted_at_the_models_order_when_the_data_allow() {
    let (id, o, val, desc, _) = diagnosed(Plant::Tank, 4025);
    assert_eq!(id.fit.order, 1, "{desc}");
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    let choice = &o.model.fit["order_choice"];
    let orders: Vec<u64> = choice["orders"]
        .as_array()
        .map(|a| a.iter().filter_map(serde_json::Value::as_u64).collect())
        .unwrap_or_default();
    assert_eq!(orders, [2, 1], "{desc}: {choice}");
    let bic: Vec<f64> = choice["bic"]
        .as_array()
        .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect())
        .unwrap_or_default();
    assert!(bic.len() == 2 && bic[1] < bic[0], "{desc}: {choice}");
    assert_eq!(o.model.fit["states"], 1, "{desc}");
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 15.0, "{desc}: error ratio {ratio:.2}");
}

/// The output-error refinement kept stable where the own-output channels are bounded
/// (`refine::bounded_feedback`): a sin of the output cannot hold an unstable linear mode once
/// the output leaves the range where it pulls back, so a Lur'e sin fit with a pole of A above
/// 1 diverges there. On the physical pendulum 6016 (found by `LPVID_SEEDS=6006,1
/// LPVID_PLANT=Pendulum`; its angle reaches 3.07 rad on the training record) the sin
/// variants explained 97.3 % of the refined null's held-out error but did not replicate, and
/// the next variant |y1|*y1 was applied at 3.40x; guarded, sin(1.86 y1) replicates (96.0 %,
/// 98.6 %) and is applied at 55.25x (its oracle, the true sin(y1) channel, 31.08x).
#[test]
fn a_bounded_own_output_channel_is_refined_with_a_stable_linear_part() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 6016);
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    assert!(f.detail.contains("sin("), "{desc}: {}", f.detail);
    let lpvid_host::model::ModelKind::Ss(m) = &o.model.kind else {
        panic!("{desc}: an lpv-ss fix");
    };
    let radius = m.a[0]
        .complex_eigenvalues()
        .iter()
        .map(|c| c.norm())
        .fold(0.0, f64::max);
    assert!(
        radius <= 1.0 + 1e-9,
        "{desc}: spectral radius of A {radius}"
    );
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 25.0, "{desc}: error ratio {ratio:.2}");
}

/// The noise threshold's test is the exact Wilcoxon signed-rank test of the held-out batch
/// log ratios (`significance::signed_rank_p`, helper h24wil). On the physical pendulum 8014 (found by
/// `LPVID_SEEDS=8004,1 LPVID_PLANT=Pendulum`; its angle stays within 1.2 rad) the Lur'e y1^3
/// channel improved 19 of 20 held-out batches (the one worse batch has the second smallest
/// |log ratio|) and explained 20.7 % of the refined null's error, but a few batches with a
/// large ratio inflated the spread of the t test of their mean (t = 3.63, p = 8.8e-4 against
/// the Bonferroni level 3.6e-4) and nothing was named. The signed-rank test gives p = 2.9e-6
/// (W- = 2) and the fix is applied: measured 11.18x, its oracle's ratio.
#[test]
fn an_own_output_channel_that_improves_nearly_every_batch_is_named() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 8014);
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    let level = 0.01 / o.report.steps[0].variants as f64;
    assert!(f.p_value < level, "{desc}: p {} level {level}", f.p_value);
    // the t test of the same batch log ratios would not have passed
    let t_p = lpvid_host::diagnose::stats::t_sf(f.t, 19.0);
    assert!(t_p > level, "{desc}: t {} (p {t_p}) level {level}", f.t);
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    println!(
        "{desc}: {} explains {:.3}, signed-rank p {:.1e}, t {:.2} (t-test p {t_p:.1e}), level {level:.1e}, error ratio {ratio:.2}",
        f.detail, f.explained, f.p_value, f.t
    );
    assert!(ratio >= 8.0, "{desc}: error ratio {ratio:.2}");
}

/// A pendulum whose records go over the top is fitted by multiple shooting
/// (`refine::shooting_start`, a start of `pipeline::fit_map`). On the physical pendulum 225013
/// (found by `LPVID_SEEDS=225003,1 LPVID_PLANT=Pendulum`; its training angle reaches 3.66 rad
/// in the second half, its held-out one -8.1 rad) the descent on the whole record's free-run
/// error stopped at a training MSE of 0.24 with the true sin(y1) channel (0.0034 from the
/// multiple-shooting start), and on the second training half PBSID read one state for the
/// loop where the full record's fit has two; a half now refits an own-output variant at the
/// order of its full-data fit (`replicate::as_fitted`). Before, nothing was named (the sin
/// variant did not replicate: 6.6 % on that half); now the sin channel is applied at its
/// oracle's ratio (measured 167.09x from the zero state).
#[test]
fn a_pendulum_over_the_top_is_fitted_by_multiple_shooting() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 225013);
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant, "{desc}: {f:#?}");
    assert!(f.detail.contains("sin("), "{desc}: {}", f.detail);
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 100.0, "{desc}: error ratio {ratio:.2}");
}

/// A training half whose held-out record spins beyond the range it saw is scored on the other
/// training half inside that range (`replicate::Halves`). On the physical pendulum 243212
/// (found by `LPVID_SEEDS=243202,1 LPVID_PLANT=Pendulum`) the first half only swung (y1 in
/// [-2.68, 1.82]), the held-out record spins (y1 from -16.7 to 31.1 rad) with no stretch of
/// 150 samples inside that range, and the first half's sin(y1) refit, judged on the full turns
/// it never saw, explained 4.5 % (p = 0.38): nothing was named although the sin channel
/// explains 95.2 % of the held-out error (oracle 20.5x). Scored on the second half's 891 rows
/// inside its range it explains 85.6 %, and the channel is applied.
#[test]
fn a_half_that_never_went_over_the_top_is_scored_where_it_swung() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 243212);
    let f = &o.report.findings[0];
    assert_eq!(f.effect, "output-nonlinearity", "{desc}: {f:#?}");
    assert!(f.significant && f.detail.contains("sin("), "{desc}: {f:#?}");
    let rep = f.replication.as_ref().expect("replicated");
    assert!(rep[0] > 0.5 && rep[1] > 0.5, "{desc}: {rep:?}");
    assert!(
        f.evidence
            .iter()
            .any(|e| e.contains("scored on the second training half's rows inside it")),
        "{desc}: {:#?}",
        f.evidence
    );
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 10.0, "{desc}: error ratio {ratio:.2}");
}

/// A noise model leaves the response to the inputs as it was (`diagnose::states::response_changed`).
/// On the physical pendulum 225011 (found by `LPVID_SEEDS=225001,1 LPVID_PLANT=Pendulum`; its
/// training record revolves to 14.9 rad and `--order auto` gives the user's model one state)
/// "1 more state for the noise dynamics through K" predicted 65.7 % of the one-step error
/// away and was applied, while its free run was 2.2 times worse than the user's model
/// (measured error ratio 0.46). Now the structure's refit explains 54.4 % of that variant's
/// free-run error and blocks it; nothing is applied. The user's model here has its order
/// fixed at 1: under `--order auto` the Lur'e channel sin(y1) is fitted with a second state
/// and applied ([`a_lure_channel_is_fitted_with_one_state_more_than_the_linear_model`]), and
/// the noise model no longer comes near.
#[test]
#[ignore = "long tier: make test-long"]
fn a_noise_model_that_changes_the_response_is_not_applied() {
    let mut settings = PbsidSettings::new(8);
    settings.fit.order = lpvid_host::pbsid::Order::Fixed(1);
    let (id, o, val, desc, _) = diagnosed_with(Plant::Pendulum, 225011, &settings);
    let noise = o
        .report
        .findings
        .iter()
        .find(|f| f.effect == "coloured-noise")
        .unwrap_or_else(|| panic!("{desc}: {:#?}", o.report.findings));
    assert!(!noise.significant, "{desc}: {noise:#?}");
    assert!(
        noise
            .blocked_by
            .as_deref()
            .is_some_and(|b| b.contains("leaves the response to the inputs as it was")),
        "{desc}: {noise:#?}"
    );
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 0.99, "{desc}: error ratio {ratio:.2}");
}

/// A Lur'e channel is also fitted with one state more than the user's model
/// (`diagnose::output::fit`, kept by BIC on the training free-run error). On the physical
/// pendulum 225012 (found by `LPVID_SEEDS=225002,1 LPVID_PLANT=Pendulum`; noise 1.6 %, its
/// records revolve over the top) `--order auto` reads one state: a revolving pendulum has no
/// linear response to read a second one from. Every own-output channel at that one state made
/// the held-out error worse (sin(y1) -83 %, the oracle's 0.47x) and nothing was named; sin(y1)
/// with the pendulum's two states has 7300x lower error.
#[test]
fn a_lure_channel_is_fitted_with_one_state_more_than_the_linear_model() {
    let (id, o, val, desc, _) = diagnosed(Plant::Pendulum, 225012);
    assert_eq!(id.fit.order, 1, "{desc}");
    let a = o.report.applied.first().expect("applied");
    assert_eq!(a.effect, "output-nonlinearity", "{desc}: {}", a.detail);
    assert!(a.detail.contains("sin("), "{desc}: {}", a.detail);
    assert_eq!(o.model.fit["states"], 2, "{desc}: {}", o.model.fit);
    let rule = o.model.fit["order_choice"]["rule"].as_str().unwrap_or("");
    assert!(rule.contains("one state more"), "{desc}: {rule}");
    let ratio = mse(&id.model, &val) / mse(&o.model, &val);
    assert!(ratio >= 100.0, "{desc}: error ratio {ratio:.2}");
}
