//! A sensor offset on a plant whose input has a mean far from zero is named `output-offset`,
//! and a logged inlet temperature that enters the plant `unused-signal` (issue 14,
//! generality; docs/bench-diagnose.md, "A chain of mixed tanks"). The plants are drawn by a
//! generator of their own, not the family's (`diagnose::plants`): a chain of one to three
//! mixed tanks, heater power u1 in [0, 1] on the first, the outlet temperature y1 of the
//! last, the flow p1 scheduling the transport between tanks (affine in p1: the model class),
//! a logged inlet temperature `w` (slow steps), white output noise. Before the nested
//! variants (a constant channel, `w` as an input channel, each refined from the model's own
//! structure refined) the offset's subspace refit explained 75 % of the held-out error
//! without replicating, and a quasi-LPV scheduling on |y1| was named `output-nonlinearity`
//! in its place; `w` as an input channel, fitted by PBSID at the user's past window 7,
//! explained 36 % of an error it causes entirely (free-run VAF 0 %), and `coloured-noise` was
//! named. The flow squared (scheduling-nonlinearity), a flow-dependent sensor gain
//! (scheduled-output) and a dead time on the heater (input-delay) are planted on the same
//! chains in the long tier. Run in release mode.

mod diagnose_support;

use lpvid_host::data::Dataset;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

/// Levels drawn uniformly in [lo, hi), each held for a number of samples drawn in
/// [hold_min, hold_max].
fn staircase(rng: &mut StdRng, n: usize, (lo, hi): (f64, f64), hold: (usize, usize)) -> Vec<f64> {
    let mut v = Vec::with_capacity(n);
    while v.len() < n {
        let level = rng.gen_range(lo..hi);
        let h = rng.gen_range(hold.0..=hold.1);
        v.extend(std::iter::repeat_n(level, h));
    }
    v.truncate(n);
    v
}

/// What is planted in the chain.
#[derive(Clone, Copy, PartialEq)]
enum Planted {
    /// Nothing: the model class.
    Clean,
    /// A constant of random sign and size in [0.3, 1) added to the measured output.
    Offset,
    /// The inlet temperature `w` carried into the first tank by the flow (p1 (w - x1)
    /// instead of -p1 x1), times a gain in [0.5, 1).
    Inlet,
    /// The transport between tanks goes with p1^2 (a pump's flow squared), not p1.
    FlowSquared,
    /// The heater acts after a dead time of 2-5 samples.
    DeadTime,
    /// The outlet sensor's gain moves with the flow: y = (1 + c (p1 - 0.65)) x, c in
    /// [0.8, 1.5) of either sign.
    SensorGain,
}

/// The chain's training and validation records (3000 and 1500 samples, one clock) with
/// `planted`, a description of the draw and the number of tanks (the order the user gives).
fn tank_chain(seed: u64, planted: Planted) -> (Dataset, Dataset, String, usize) {
    let mut rng = StdRng::seed_from_u64(seed);
    let n: usize = 4500;
    let tanks = rng.gen_range(1..=3usize);
    let binary = rng.gen_bool(0.5);
    let u: Vec<f64> = if binary {
        let hold = rng.gen_range(3..12usize);
        let levels = staircase(&mut rng, n.div_ceil(hold), (0.0, 1.0), (1, 1));
        (0..n)
            .map(|k| if levels[k / hold] < 0.5 { 0.1 } else { 0.9 })
            .collect()
    } else {
        staircase(&mut rng, n, (0.0, 1.0), (5, 40))
    };
    let steps = staircase(&mut rng, n, (0.3, 1.0), (100, 400));
    let mut p = vec![steps[0]; n];
    for k in 1..n {
        p[k] = 0.95 * p[k - 1] + 0.05 * steps[k];
    }
    let af: f64 = rng.gen_range(0.15..0.45) / (tanks as f64).powf(0.3);
    let al: f64 = rng.gen_range(0.01..0.05);
    let g: f64 = rng.gen_range(0.5..1.5);
    let noise: f64 = rng.gen_range(0.01..0.05);
    let w: Vec<f64> = staircase(&mut rng, n, (-1.0, 1.0), (50, 300))
        .into_iter()
        .map(|v| {
            let e: f64 = StandardNormal.sample(&mut rng);
            v + 0.1 * e
        })
        .collect();
    let size: f64 = rng.gen_range(0.3..1.0) * if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
    let gain: f64 = rng.gen_range(0.5..1.0);
    let off = if planted == Planted::Offset {
        size
    } else {
        0.0
    };
    let gw = if planted == Planted::Inlet { gain } else { 0.0 };
    // the later effects draw from a stream of their own: the first three plants unchanged
    let mut more = StdRng::seed_from_u64(seed.wrapping_add(0x7a4b));
    let delay = if planted == Planted::DeadTime {
        more.gen_range(2..=5usize)
    } else {
        0
    };
    let slope: f64 = more.gen_range(0.8..1.5) * if more.gen_bool(0.5) { 1.0 } else { -1.0 };
    let slope = if planted == Planted::SensorGain {
        slope
    } else {
        0.0
    };
    let flow = |pk: f64| {
        if planted == Planted::FlowSquared {
            pk * pk / 0.65
        } else {
            pk
        }
    };
    let mut x = vec![0.0f64; tanks];
    let mut y = vec![0.0; n];
    for k in 0..n {
        y[k] = (1.0 + slope * (p[k] - 0.65)) * x[tanks - 1] + off;
        let mut next = x.clone();
        for i in 0..tanks {
            let upstream = if i == 0 { gw * w[k] } else { x[i - 1] };
            next[i] = x[i] + af * flow(p[k]) * (upstream - x[i]) - al * x[i];
        }
        next[0] += af * g * u[k.saturating_sub(delay)];
        x = next;
    }
    let mean = y.iter().sum::<f64>() / n as f64;
    let sd = (y.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
    for v in y.iter_mut() {
        let e: f64 = StandardNormal.sample(&mut rng);
        *v += noise * sd * e;
    }
    let t: Vec<f64> = (0..n).map(|k| k as f64).collect();
    let (train, val) = diagnose_support::train_val([&t, &u, &y, &p, &w], 3000);
    let words = format!(
        "{tanks} tank(s), {} heater, transport {af:.2} p1, loss {al:.3}, offset {off:+.2}, inlet gain {gw:.2}, dead time {delay}, sensor slope {slope:+.2}, noise {:.1} %",
        if binary { "two-level" } else { "staircase" },
        100.0 * noise
    );
    (train, val, words, tanks)
}

/// The plant of `seed` with `planted`, diagnosed with `--fix` (one step) from the model
/// `lpvid pbsid` fits at past window 7 and the plant's order: the effects applied and the
/// held-out free-run error ratio of the first (1 when nothing was applied), printed.
fn diagnosed(seed: u64, planted: Planted, effect: &str) -> (Vec<&'static str>, f64) {
    let (train, val, words, tanks) = tank_chain(seed, planted);
    // LPVID_TANK_DUMP=DIR writes the records, to trace a case through the command line
    if let Ok(dir) = std::env::var("LPVID_TANK_DUMP") {
        let stem = format!("{dir}/{effect}{seed}");
        train
            .write_csv(std::path::Path::new(&format!("{stem}.train.csv")))
            .unwrap();
        val.write_csv(std::path::Path::new(&format!("{stem}.val.csv")))
            .unwrap();
    }
    let (_, out) = diagnose_support::identify_and_diagnose(&train, &val, 7, tanks);
    let applied: Vec<&str> = out.report.applied.iter().map(|a| a.effect).collect();
    let ratio = out
        .report
        .applied
        .first()
        .map_or(1.0, |a| a.mse_before / a.mse_after);
    println!("seed {seed}: {words}; applied {applied:?}, error ratio {ratio:.1}");
    for f in out.report.findings.iter().take(4) {
        println!(
            "    {} ({}) {:.3} blocked {:?}",
            f.effect, f.detail, f.explained, f.blocked_by
        );
    }
    (applied, ratio)
}

/// The plant of `seed` with `planted`: `effect` is the one effect applied and lowers the
/// held-out free-run error at least `min_ratio` times (nothing is applied on the clean
/// plant). Returns the error ratio.
fn named(seed: u64, planted: Planted, effect: &str, min_ratio: f64) -> f64 {
    let (applied, ratio) = diagnosed(seed, planted, effect);
    if planted == Planted::Clean {
        assert!(applied.is_empty(), "seed {seed} clean: {applied:?}");
    } else {
        assert_eq!(applied, [effect], "seed {seed}");
        assert!(ratio >= min_ratio, "seed {seed}: ratio {ratio}");
    }
    ratio
}

/// How many of the plants of `seeds` with `planted` get `effect` applied alone, lowering
/// the held-out error at least 3 times.
fn recall(seeds: std::ops::RangeInclusive<u64>, planted: Planted, effect: &str) -> usize {
    seeds
        .filter(|&seed| {
            let (applied, ratio) = diagnosed(seed, planted, effect);
            applied == [effect] && ratio >= 3.0
        })
        .count()
}

/// LPVID_TANK_SEEDS=FIRST,COUNT: the chain's plants of those seeds, each planted effect and
/// the clean plant, printed and asserted (the spread across seeds, when tracing).
#[test]
#[ignore = "by hand: LPVID_TANK_SEEDS=FIRST,COUNT"]
fn the_chain_on_given_seeds() {
    let Ok(v) = std::env::var("LPVID_TANK_SEEDS") else {
        return;
    };
    let (first, count) = v.split_once(',').expect("FIRST,COUNT");
    let first: u64 = first.parse().unwrap();
    let count: u64 = count.parse().unwrap();
    let planted = std::env::var("LPVID_TANK_EFFECT").unwrap_or_default();
    for seed in first..first + count {
        let _ = std::panic::catch_unwind(|| match planted.as_str() {
            "output-offset" => named(seed, Planted::Offset, "output-offset", 5.0),
            "unused-signal" => named(seed, Planted::Inlet, "unused-signal", 5.0),
            "scheduling-nonlinearity" => {
                named(seed, Planted::FlowSquared, "scheduling-nonlinearity", 3.0)
            }
            "input-delay" => named(seed, Planted::DeadTime, "input-delay", 3.0),
            "scheduled-output" => named(seed, Planted::SensorGain, "scheduled-output", 3.0),
            _ => named(seed, Planted::Clean, "", 1.0),
        });
    }
}

#[test]
fn an_output_offset_with_a_heater_input_is_named() {
    named(1, Planted::Offset, "output-offset", 5.0);
}

#[test]
fn a_logged_inlet_temperature_is_named() {
    named(1, Planted::Inlet, "unused-signal", 5.0);
}

/// Seeds 2-7 of the chain, each planted effect and the clean plant.
#[test]
#[ignore = "long tier: make test-long"]
fn the_chain_on_more_seeds() {
    for seed in 2..=7 {
        named(seed, Planted::Offset, "output-offset", 5.0);
        named(seed, Planted::Inlet, "unused-signal", 5.0);
        named(seed, Planted::Clean, "", 1.0);
    }
}

/// The scheduling effects and a dead time on seeds 1-6 of the chain: at least 5 of 6 plants
/// each get the planted effect applied alone, lowering the held-out error 3 times or more.
/// Measured (thirty-second session): the flow squared 6 of 6 (ratios 7.9-2836); the flow-
/// dependent sensor gain 5 of 6 (seed 6 named scheduling-nonlinearity, ratio 7.9); the dead
/// time 5 of 6 (seed 1, three tanks and a dead time of 4, has a user's model of free-run VAF
/// 0 % at past window 7 and nothing is applied).
#[test]
#[ignore = "long tier: make test-long"]
fn the_chain_scheduling_effects_and_dead_time() {
    let flow = recall(1..=6, Planted::FlowSquared, "scheduling-nonlinearity");
    let sensor = recall(1..=6, Planted::SensorGain, "scheduled-output");
    let dead = recall(1..=6, Planted::DeadTime, "input-delay");
    assert!(
        flow >= 5 && sensor >= 5 && dead >= 5,
        "of 6: flow squared {flow}, sensor gain {sensor}, dead time {dead}"
    );
}
