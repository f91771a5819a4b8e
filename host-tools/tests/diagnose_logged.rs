//! A logged column that enters nowhere is not named `unused-signal` (issue 14, generality;
//! docs/bench-diagnose.md, "A logged column must beat the refined structure"). The plants are
//! drawn by a generator of their own, not the family's (`diagnose::plants`): a lightly damped
//! oscillator sampled with a semi-implicit Euler step, its stiffness affine in a slow p1, its
//! output gain scheduled on p1 as well (y = (1 + c p1) x1: a weak scheduled-output effect that
//! the stiffness's scheduling mostly absorbs), white output noise, and a logged column `w`
//! drawn independently of everything. Run in release mode.

mod diagnose_support;

use lpvid_host::data::Dataset;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

/// An AR(1) signal of unit variance with a pole drawn in 0.3-0.8.
fn ar1(rng: &mut StdRng, n: usize) -> Vec<f64> {
    let a: f64 = rng.gen_range(0.3..0.8);
    let mut v = vec![0.0; n];
    for k in 1..n {
        let e: f64 = StandardNormal.sample(rng);
        v[k] = a * v[k - 1] + e;
    }
    let sd = (v.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
    v.iter().map(|x| x / sd).collect()
}

/// The oscillator's training and validation records (2000 and 1000 samples, one clock) and a
/// description of the draw.
fn oscillator(seed: u64) -> (Dataset, Dataset, String) {
    let mut rng = StdRng::seed_from_u64(seed);
    let n = 3000;
    let u = ar1(&mut rng, n);
    let w = ar1(&mut rng, n);
    let period: f64 = rng.gen_range(150.0..600.0);
    let phase: f64 = rng.gen_range(0.0..6.0);
    let p: Vec<f64> = (0..n)
        .map(|k| 0.5 + 0.45 * (2.0 * std::f64::consts::PI * k as f64 / period + phase).sin())
        .collect();
    let wn: f64 = rng.gen_range(0.15..0.6);
    let zeta: f64 = rng.gen_range(0.1..0.5);
    let a: f64 = rng.gen_range(0.3..0.6);
    let c: f64 = rng.gen_range(0.4..0.8);
    let noise: f64 = rng.gen_range(0.02..0.08);
    let (mut pos, mut vel) = (0.0f64, 0.0f64);
    let mut y = vec![0.0; n];
    for k in 0..n {
        y[k] = pos * (1.0 + c * p[k]);
        let acc = -wn * wn * (1.0 + a * p[k]) * pos - 2.0 * zeta * wn * vel + wn * wn * u[k];
        vel += acc;
        pos += vel;
    }
    let sd = (y.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
    for v in y.iter_mut() {
        let e: f64 = StandardNormal.sample(&mut rng);
        *v += noise * sd * e;
    }
    let t: Vec<f64> = (0..n).map(|k| 0.01 * k as f64).collect();
    let (train, val) = diagnose_support::train_val([&t, &u, &y, &p, &w], 2000);
    let words = format!(
        "wn {wn:.2} rad/sample, zeta {zeta:.2}, stiffness 1 + {a:.2} p1, output gain 1 + {c:.2} p1, p1 period {period:.0}, noise {:.1} %",
        100.0 * noise
    );
    (train, val, words)
}

/// On `seeds`, nothing but the planted scheduled output gain is applied; returns on how many
/// seeds `w`'s variant cleared the threshold against the subspace refit and was blocked by the
/// model's structure refined by output error.
fn logged_column_not_named(seeds: impl IntoIterator<Item = u64>) -> usize {
    let mut blocked_by_refined = 0;
    for seed in seeds {
        let (train, val, words) = oscillator(seed);
        let (_, out) = diagnose_support::identify_and_diagnose(&train, &val, 7, 2);
        let applied: Vec<&str> = out.report.applied.iter().map(|a| a.effect).collect();
        println!("seed {seed}: {words}; applied {applied:?}");
        for f in &out.report.findings {
            println!(
                "    {} ({}) {:.3} blocked {:?}",
                f.effect, f.detail, f.explained, f.blocked_by
            );
        }
        assert!(
            applied.iter().all(|e| *e == "scheduled-output"),
            "seed {seed}: {applied:?}"
        );
        blocked_by_refined += out
            .report
            .findings
            .iter()
            .filter(|f| f.effect == "unused-signal" && f.explained >= 0.10)
            .filter(|f| {
                f.blocked_by
                    .as_deref()
                    .is_some_and(|b| b.contains("not a signal the model lacks"))
            })
            .count();
    }
    blocked_by_refined
}

/// Seeds 1 and 6, where `w` as a scheduling signal explains 69.3 % and 65.7 % of the subspace
/// refit's held-out error, replicated, and the structure refined by output error 79.8 % and
/// 82.9 % (against it `w` explains -52 % and -101 %). Before the rule `w` was named on both;
/// with only that rule, `abs(u1)*u1` was named input-nonlinearity on seed 1 (36.4 %) and a
/// noise model with two more states coloured-noise on seed 6 (71.7 % of the one-step error),
/// both blocked now by the same rule. The scheduled output gain itself, refined from the
/// refined structure, explains 12.2 % at p = 1.4e-3 on seed 1: below the evidence a finding
/// needs, so nothing is named.
#[test]
fn a_logged_column_that_enters_nowhere_is_not_named() {
    assert_eq!(logged_column_not_named([1, 6]), 2);
}

/// Seeds 1-12 of the oscillator (seeds 1-6 measured: `w` clears the threshold on 1 and 6, and
/// the refined structure blocks it; on 5 it does not replicate; below 10 % on the others).
#[test]
#[ignore = "long tier: make test-long"]
fn a_logged_column_that_enters_nowhere_is_not_named_more_seeds() {
    let n = logged_column_not_named(1..=12);
    assert!(n >= 2, "{n}");
}
