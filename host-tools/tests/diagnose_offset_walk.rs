//! A sensor offset on LPV plants whose scheduling signal wanders (a random walk) and whose
//! model the user identified with `--order auto` (issue 14, generality; docs/bench-diagnose.md,
//! "An offset under `--order auto`"). The plants are drawn by a generator of their own, not
//! the family's (`diagnose::plants`): order 1-3, random stable poles and a random similarity,
//! A, B affine in p1, p1 a random walk in [-1, 1], white Gaussian input, white output noise
//! 1-8 % of the output's spread, a constant 0.6 times that spread on the output. The user
//! runs `lpvid pbsid --past 5` with the default `--order auto`, whose held-out check grows the
//! order for the offset (3-5 states where the plant has 1-3). A Lur'e y1^2 or |y1| y1
//! channel then reaches the constant through the output's level; with as many free
//! coefficients as the constant channel it was named first by a held-out error lower in the
//! fourth digit of the VAF. Long tier, release mode. Beside it, in the default tier, a
//! family plant whose own-output twin stood for the offset.

mod diagnose_support;

use diagnose_support::family::diagnose_one_auto_past;
use diagnose_support::{normal, stable};

use lpvid_host::data::Dataset;
use lpvid_host::linalg::spectral_radius;
use nalgebra::{DMatrix, DVector};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Spectral radius of the frozen A0 + p A1 over p in [-1, 1] (21 points).
fn frozen_radius(a0: &DMatrix<f64>, a1: &DMatrix<f64>) -> f64 {
    (0..=20)
        .map(|i| {
            let p = -1.0 + 0.1 * i as f64;
            spectral_radius(&(a0 + a1 * p))
        })
        .fold(0.0, f64::max)
}

/// Training (2000 samples) and validation (1000) records of plant `seed`, and its words.
fn plant(seed: u64) -> (Dataset, Dataset, String) {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x0ff5_e7a1);
    let n = [1usize, 2, 2, 3][rng.gen_range(0..4)];
    let a0 = stable(&mut rng, n);
    let mut a1 = DMatrix::from_fn(n, n, |_, _| 0.3 * normal(&mut rng));
    while frozen_radius(&a0, &a1) >= 0.95 {
        a1 *= 0.8;
    }
    let b0 = DVector::from_fn(n, |_, _| normal(&mut rng));
    let b1 = DVector::from_fn(n, |_, _| 0.5 * normal(&mut rng));
    let c0 = DVector::from_fn(n, |_, _| normal(&mut rng));
    let noise: f64 = rng.gen_range(0.01..0.08);
    let mut record = |len: usize| {
        let (mut x, mut walk) = (DVector::zeros(n), 0.0f64);
        let (mut u, mut y, mut p) = (vec![], vec![], vec![]);
        for _ in 0..len {
            walk = (walk + 0.05 * normal(&mut rng)).clamp(-1.0, 1.0);
            let uk = normal(&mut rng);
            y.push(c0.dot(&x));
            x = (&a0 + &a1 * walk) * &x + (&b0 + &b1 * walk) * uk;
            u.push(uk);
            p.push(walk);
        }
        let mean = y.iter().sum::<f64>() / len as f64;
        let sd = (y.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / len as f64).sqrt();
        for v in &mut y {
            *v += 0.6 * sd + noise * sd * normal(&mut rng);
        }
        Dataset {
            source: "walk.csv".into(),
            names: ["u1", "y1", "p1"].map(String::from).to_vec(),
            cols: vec![u, y, p],
        }
    };
    let train = record(2000);
    let val = record(1000);
    let words = format!("order {n}, noise {:.1} %", 100.0 * noise);
    (train, val, words)
}

/// The offset is named first on most plants and never a function of the model's own output
/// in its place (measured on seeds 1-8: the docs' section).
#[test]
#[ignore = "long tier: make test-long"]
fn an_offset_under_order_auto_is_named_output_offset() {
    // LPVID_SEEDS=FIRST,COUNT measures the spread on other seeds (the assertions judge those)
    let (first_seed, count) = diagnose_support::env_seeds("LPVID_SEEDS", (1, 8));
    let seeds = first_seed..first_seed + count;
    let mut named = 0;
    let mut own_output = 0;
    for seed in seeds {
        let (train, val, words) = plant(seed);
        let (model, out) =
            diagnose_support::identify_with_order_and_diagnose(&train, &val, 5, "auto");
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
        // the ranking rule that put the first finding there, when one did
        let why = out.report.findings.first().map_or("", |f| {
            f.evidence
                .first()
                .filter(|e| e.starts_with("preferred to"))
                .map_or("", String::as_str)
        });
        println!(
            "seed {seed}: {words}, user's order {}: first {first}, error ratio {ratio:.1} {why}",
            model.fit["states"]
        );
        named += usize::from(first == "output-offset");
        own_output += usize::from(first == "output-nonlinearity");
    }
    println!("output-offset first on {named} of {count}, output-nonlinearity on {own_output}");
    assert!(
        4 * named >= 3 * count as usize,
        "output-offset first on {named} of {count}"
    );
    assert_eq!(own_output, 0);
}

/// Family output-offset plant 241005 (order 1, pole 0.77, affine in p1, an offset of -0.77,
/// noise 6.3 %), the user's fit at past window 8 with `--order auto` (2 states). A Lur'e
/// y1^2 with a constant channel (an own-output twin, fitted at 1 state) explained 97.7 % of
/// the refined structure's held-out error, as the offset did, and was named first (its fit
/// has fewer coefficients than the offset's at 2 states). Its linearised null could not be
/// formed (the constant channel reads no output), so the rule that asks an own-output
/// variant to add to its linear stand-in was skipped. Now its null has the constant channel
/// (`output::twin_null`): y1^2 adds 0.2 % (p = 0.2) to the offset at its own order, and the
/// offset is named (measured error ratio 87.9).
#[test]
fn an_own_output_twin_must_add_to_the_offset() {
    let (_, out) = diagnose_one_auto_past("output-offset", 241005, 1500, 8);
    let r = &out.report;
    let first = r.findings.first().expect("a finding");
    println!("first {} ({})", first.effect, first.detail);
    assert!(
        first.significant && first.effect == "output-offset",
        "{first:?}"
    );
    let applied = r.applied.first().expect("the offset applied");
    assert!(applied.mse_before / applied.mse_after > 30.0, "{applied:?}");
    let twin = r
        .findings
        .iter()
        .find(|f| {
            f.effect == "output-nonlinearity"
                && f.detail.ends_with("with a constant input channel []")
        })
        .expect("the twin scored");
    let why = twin.blocked_by.as_deref().unwrap_or_default();
    assert!(
        !twin.significant && why.contains("which the offset holds"),
        "{why}"
    );
}
