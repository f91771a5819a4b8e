//! The scheduling effects on a record whose operating point sweeps slowly through its range
//! (issue 14, generality; docs/bench-diagnose.md, "A swept operating point: interleaved halves
//! tried, not kept"): p1 rises from -1 to 1 over the training record and
//! falls back over the validation record, as in an experiment that sweeps the operating
//! point. The first half of the training data then sees p1 in [-1, 0] and the second half
//! [0, 1], and each half's refit extrapolates over the other's range in the replication. The
//! plants are drawn by a generator of their own: order 1-3, random stable poles and a random
//! similarity, A, B affine in p1, white Gaussian input, white output noise 1-8 % of the
//! output's spread; `scheduled-output` multiplies the output by 1 + s p1 (|s| 0.5-1),
//! `scheduling-nonlinearity` adds p1^2 A2 to the state matrix. The user identifies with
//! `lpvid pbsid --past 5 --order n` (the plant's order). Long tier, release mode.

mod diagnose_support;

use diagnose_support::{normal, stable};

use lpvid_host::data::Dataset;
use lpvid_host::linalg::spectral_radius;
use nalgebra::{DMatrix, DVector};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Spectral radius of the frozen A0 + p A1 + p^2 A2 over p in [-1, 1] (21 points).
fn frozen_radius(a: &[DMatrix<f64>; 3]) -> f64 {
    (0..=20)
        .map(|i| {
            let p = -1.0 + 0.1 * i as f64;
            spectral_radius(&(&a[0] + &a[1] * p + &a[2] * (p * p)))
        })
        .fold(0.0, f64::max)
}

/// Training (2000 samples, p1 rising) and validation (1000, p1 falling) records of plant
/// `seed` with `effect` planted, the plant's order and its words.
fn plant(effect: &str, seed: u64) -> (Dataset, Dataset, usize, String) {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x5eed_5eee);
    let n = [1usize, 2, 2, 3][rng.gen_range(0..4)];
    let a0 = stable(&mut rng, n);
    let a1 = DMatrix::from_fn(n, n, |_, _| 0.3 * normal(&mut rng));
    let a2 = if effect == "scheduling-nonlinearity" {
        DMatrix::from_fn(n, n, |_, _| 0.4 * normal(&mut rng))
    } else {
        DMatrix::zeros(n, n)
    };
    let mut a = [a0, a1, a2];
    while frozen_radius(&a) >= 0.95 {
        a[1] *= 0.8;
        a[2] *= 0.8;
    }
    let b0 = DVector::from_fn(n, |_, _| normal(&mut rng));
    let b1 = DVector::from_fn(n, |_, _| 0.5 * normal(&mut rng));
    let c0 = DVector::from_fn(n, |_, _| normal(&mut rng));
    let gain: f64 = if effect == "scheduled-output" {
        rng.gen_range(0.5..1.0) * if rng.gen_bool(0.5) { 1.0 } else { -1.0 }
    } else {
        0.0
    };
    let noise: f64 = rng.gen_range(0.01..0.08);
    let mut record = |len: usize, rising: bool| {
        let mut x = DVector::zeros(n);
        let (mut u, mut y, mut p) = (vec![], vec![], vec![]);
        for k in 0..len {
            let ramp = -1.0 + 2.0 * k as f64 / (len - 1) as f64;
            let pk = if rising { ramp } else { -ramp };
            let uk = normal(&mut rng);
            y.push(c0.dot(&x) * (1.0 + gain * pk));
            x = (&a[0] + &a[1] * pk + &a[2] * (pk * pk)) * &x + (&b0 + &b1 * pk) * uk;
            u.push(uk);
            p.push(pk);
        }
        let mean = y.iter().sum::<f64>() / len as f64;
        let sd = (y.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / len as f64).sqrt();
        for v in &mut y {
            *v += noise * sd * normal(&mut rng);
        }
        Dataset {
            source: "sweep.csv".into(),
            names: ["u1", "y1", "p1"].map(String::from).to_vec(),
            cols: vec![u, y, p],
        }
    };
    let train = record(2000, true);
    let val = record(1000, false);
    let words = format!("order {n}, noise {:.1} %", 100.0 * noise);
    (train, val, n, words)
}

/// Per planted effect (and clean plants), how many of the seeds had each effect named first.
fn named_first(effect: &str, seeds: std::ops::Range<u64>) -> usize {
    let mut named = 0;
    for seed in seeds {
        let (train, val, n, words) = plant(effect, seed);
        let (_, out) =
            diagnose_support::identify_with_order_and_diagnose(&train, &val, 5, &n.to_string());
        let first = out
            .report
            .findings
            .first()
            .filter(|f| f.significant)
            .map_or("none", |f| f.effect);
        let ratio = out
            .report
            .applied
            .first()
            .map_or(1.0, |a| a.mse_before / a.mse_after);
        println!("{effect} seed {seed}: {words}: first {first}, error ratio {ratio:.2}");
        // the planted effect's finding and the rule that blocked it, when it was not first
        if let Some(f) = out
            .report
            .findings
            .iter()
            .find(|f| f.effect == effect && first != effect)
        {
            println!(
                "    {effect} explains {:.1} %: {}",
                100.0 * f.explained,
                f.blocked_by
                    .as_deref()
                    .unwrap_or("a finding, ranked below the first")
            );
        }
        let hit = if effect == "clean" {
            first == "none"
        } else {
            first == effect
        };
        named += usize::from(hit);
    }
    named
}

/// The scheduled output gain is named first on at least half of the swept plants, the p1^2
/// dependence on at least a third, and a clean swept plant has no finding on at least five
/// in six. Measured (the docs' section), seeds 1-6: scheduled-output 6 of 6, p1^2 2 of 6,
/// clean 0 findings in 6. The p1^2 misses: refits on the first or second half that
/// extrapolate over the other's range, variants the refined structure matches on a record
/// where p1^2 matters only near the ends of the sweep, and order-3 plants whose refits on a
/// half run away.
#[test]
#[ignore = "long tier: make test-long"]
fn the_scheduling_effects_are_named_on_a_swept_operating_point() {
    let (first, count) = diagnose_support::env_seeds("LPVID_SEEDS", (1, 6));
    let mut rows = vec![];
    for effect in ["scheduled-output", "scheduling-nonlinearity", "clean"] {
        let named = named_first(effect, first..first + count);
        rows.push((effect, named));
    }
    for (effect, named) in &rows {
        println!("{effect}: {named} of {count}");
    }
    for (effect, named) in rows {
        let need = match effect {
            "clean" => (5 * count).div_ceil(6),
            "scheduled-output" => count.div_ceil(2),
            _ => count.div_ceil(3),
        };
        assert!(named as u64 >= need, "{effect}: {named} of {count}");
    }
}
