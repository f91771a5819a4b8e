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

/// How the operating point moves.
#[derive(Clone, Copy, PartialEq)]
enum Shape {
    /// p1 rises from -1 to 1 over the training record and falls back over the validation one.
    Sweep,
    /// p1 a random walk (steps of standard deviation 0.05) reflected at -1 and 1, from 0: it
    /// dwells in part of the range for hundreds of samples.
    Walk,
}

/// Training (2000 samples) and validation (1000) records of plant `seed` with `effect`
/// planted and p1 moving as `shape` says, the plant's order and its words.
fn plant(effect: &str, seed: u64, shape: Shape) -> (Dataset, Dataset, usize, String) {
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
    let mut walk = 0.0f64;
    let mut record = |len: usize, rising: bool| {
        let mut x = DVector::zeros(n);
        let (mut u, mut y, mut p) = (vec![], vec![], vec![]);
        for k in 0..len {
            let ramp = -1.0 + 2.0 * k as f64 / (len - 1) as f64;
            let pk = match shape {
                Shape::Sweep if rising => ramp,
                Shape::Sweep => -ramp,
                Shape::Walk => {
                    walk += 0.05 * normal(&mut rng);
                    if walk > 1.0 {
                        walk = 2.0 - walk;
                    }
                    if walk < -1.0 {
                        walk = -2.0 - walk;
                    }
                    walk
                }
            };
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
fn named_first(effect: &str, seeds: std::ops::Range<u64>, shape: Shape) -> usize {
    let mut named = 0;
    for seed in seeds {
        let (train, val, n, words) = plant(effect, seed, shape);
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
        if std::env::var("LPVID_SWEEP_SUMMARY").is_ok() {
            println!(
                "{}",
                lpvid_host::diagnose::report::summary(&out.report, &[])
            );
        }
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

/// Per effect (and clean plants), how many of the seeds of `LPVID_SEEDS` (default 1-6) had it
/// named first on operating points moving as `shape`; asserts the scheduled output gain on
/// at least half, the p1^2 dependence on at least a third and no finding on at least five
/// clean plants in six.
fn named_on(shape: Shape) {
    let (first, count) = diagnose_support::env_seeds("LPVID_SEEDS", (1, 6));
    let mut rows = vec![];
    for effect in ["scheduled-output", "scheduling-nonlinearity", "clean"] {
        let named = named_first(effect, first..first + count, shape);
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

/// The two scheduling effects and clean plants on a swept operating point. Measured (the
/// docs' section), seeds 1-6: scheduled-output 6 of 6, p1^2 3 of 6, clean 0 findings in 6
/// (p1^2 2 of 6 before a half was replicated inside its own operating range). The p1^2
/// misses: a variant that replicates neither on the whole held-out record nor inside each
/// half's range, variants the refined structure matches on a record where p1^2 matters only
/// near the ends of the sweep, and a full-data test without the power (p = 2e-2).
#[test]
#[ignore = "long tier: make test-long"]
fn the_scheduling_effects_are_named_on_a_swept_operating_point() {
    named_on(Shape::Sweep);
}

/// The same plants with p1 a reflected random walk.
#[test]
#[ignore = "long tier: make test-long"]
fn the_scheduling_effects_are_named_on_a_wandering_operating_point() {
    named_on(Shape::Walk);
}
