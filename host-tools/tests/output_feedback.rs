//! Output-dependent dynamics in the model contract (DESIGN.md section 5): a factor on one of
//! the model's outputs reads the simulated output in free run and the measured one with
//! `--predictor` and in identification; the output-error refinement goes through the
//! feedback; the initial state can be estimated from the first samples.

use lpvid_host::cli::run as cli;
use lpvid_host::data::Dataset;
use lpvid_host::lpvss::LpvSs;
use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::model::{Factor, ModelFile, ModelKind, SignalMap};
use lpvid_host::pbsid::{fit, Order, PbsidOptions};
use lpvid_host::refine::refine_through_feedback;
use lpvid_host::simulate::{run, score_from, Mode, X0};
use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde_json::json;

/// A cubic spring (Duffing oscillator, discretised): x1' = x2, x2' = -k1 x1 - c x2 - k3 x1^3 + u,
/// semi-implicit Euler with step h (x2 first, then x1 with the new x2); y = x1 (+ white noise of `noise` times std(y)). Input: a low-passed
/// Gaussian. Returns (u, y measured, y clean).
fn duffing(
    n: usize,
    k3: f64,
    x0: [f64; 2],
    noise: f64,
    seed: u64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let g = Normal::new(0.0, 1.0).unwrap();
    let (h, k1, c) = (0.1, 1.0, 0.3);
    let mut x = x0;
    let mut lp = 0.0;
    let (mut u, mut y) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        lp = 0.8 * lp + 0.4 * g.sample(&mut rng);
        u.push(lp);
        y.push(x[0]);
        let acc = -k1 * x[0] - c * x[1] - k3 * x[0].powi(3) + lp;
        let v = x[1] + h * acc;
        x = [x[0] + h * v, v];
    }
    let sd = (y.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
    let ym = y
        .iter()
        .map(|v| v + noise * sd * g.sample(&mut rng))
        .collect();
    (u, ym, y)
}

/// The Duffing plant above written as a model file: inputs u1 and the Lur'e channel y1^3.
fn duffing_model(k3: f64) -> ModelFile {
    let h = 0.1;
    let ss = LpvSs {
        a: vec![DMatrix::from_row_slice(
            2,
            2,
            &[1.0 - h * h, h * (1.0 - 0.3 * h), -h, 1.0 - 0.3 * h],
        )],
        b: vec![DMatrix::from_row_slice(
            2,
            2,
            &[h * h, -h * h * k3, h, -h * k3],
        )],
        k: vec![DMatrix::zeros(2, 1)],
        c: vec![DMatrix::from_row_slice(1, 2, &[1.0, 0.0])],
        d: vec![DMatrix::zeros(1, 2)],
    };
    ModelFile {
        kind: ModelKind::Ss(ss),
        signals: SignalMap {
            inputs: vec![
                vec![Factor::col("u1")],
                vec![Factor {
                    pow: 3.0,
                    ..Factor::col("y1")
                }],
            ],
            scheduling: vec![vec![]],
            outputs: vec![vec![Factor::col("y1")]],
        },
        fit: json!({}),
    }
}

fn csv(u: &[f64], y: &[f64]) -> Dataset {
    let mut s = String::from("u1,y1\n");
    for (a, b) in u.iter().zip(y) {
        s.push_str(&format!("{a},{b}\n"));
    }
    Dataset::parse("d.csv", s.as_bytes()).unwrap()
}

/// The free run goes through the model's own simulated output: the true Duffing model
/// reproduces the clean output to rounding, whatever the measured y column holds, while the
/// one-step predictor reads the measured column.
#[test]
fn free_run_reads_the_simulated_output_and_the_predictor_the_measured_one() {
    let (u, ym, yc) = duffing(3000, 2.0, [0.0, 0.0], 0.05, 1);
    let model = duffing_model(2.0);
    let r = run(&model, &csv(&u, &ym), Mode::FreeRun, X0::Zero).unwrap();
    let err = (0..yc.len())
        .map(|k| (r.yhat[(k, 0)] - yc[k]).abs())
        .fold(0.0, f64::max);
    assert!(err < 1e-9, "free run differs from the plant by {err}");
    // a measured column of zeros changes nothing in free run ...
    let zeros = vec![0.0; u.len()];
    let r0 = run(&model, &csv(&u, &zeros), Mode::FreeRun, X0::Zero).unwrap();
    assert_eq!(r0.yhat, r.yhat);
    // ... but the predictor reads it (y1^3 from the data)
    let p = run(&model, &csv(&u, &ym), Mode::Predictor, X0::Zero).unwrap();
    let p0 = run(&model, &csv(&u, &zeros), Mode::Predictor, X0::Zero).unwrap();
    assert!((&p.yhat - &p0.yhat).amax() > 0.1);
    // the same plant without its feedback channel is far off
    let mut linear = model.clone();
    if let ModelKind::Ss(ss) = &mut linear.kind {
        ss.b[0][(0, 1)] = 0.0;
        ss.b[0][(1, 1)] = 0.0;
    }
    let lin = score_from(&linear, &csv(&u, &yc), Mode::FreeRun, X0::Zero).unwrap();
    let full = score_from(&model, &csv(&u, &yc), Mode::FreeRun, X0::Zero).unwrap();
    println!(
        "VAF linear part {:.2} %, with y^3 fed back {:.6} %",
        lin.vaf_mean, full.vaf_mean
    );
    assert!(full.vaf_mean > 99.9999 && lin.vaf_mean < 90.0);
}

/// Identification with the measured output in the feedback channel (PBSID), then the
/// output-error refinement through the feedback: on random Duffing plants (k3, noise, seed)
/// the refined feedback model beats the best linear model of the same order by far on
/// held-out data.
#[test]
fn pbsid_then_refinement_through_the_feedback_fits_cubic_springs() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut lines = Vec::new();
    for trial in 0..4 {
        let k3 = rng.gen_range(0.5..3.0);
        let noise = rng.gen_range(0.01..0.05);
        let (u, ym, _) = duffing(4000, k3, [0.0, 0.0], noise, 100 + trial);
        let (uv, _, yv) = duffing(2000, k3, [0.0, 0.0], 0.0, 200 + trial);
        let (train, val) = (csv(&u, &ym), csv(&uv, &yv));
        let mut o = PbsidOptions::new(8);
        o.order = Order::Fixed(2);
        // linear: u1 only
        let lin_map = SignalMap::standard(1, 1, 0);
        let lin = fit(&lin_map.evaluate(&train).unwrap(), &o).unwrap();
        let lin_model = ModelFile {
            kind: ModelKind::Ss(lin.model.clone()),
            signals: lin_map,
            fit: json!({}),
        };
        let lin_vaf = score_from(&lin_model, &val, Mode::FreeRun, X0::Zero)
            .unwrap()
            .vaf_mean;
        // feedback channel y1^3 read from the measured output, then refined through the loop
        let fb_map = duffing_model(1.0).signals;
        let sig = fb_map.evaluate(&train).unwrap();
        let f = fit(&sig, &o).unwrap();
        let fb = fb_map.feedback(&train).unwrap();
        let refined = refine_through_feedback(&f.model, &sig, &fb, false, 40);
        let score = |m: &LpvSs| {
            let mf = ModelFile {
                kind: ModelKind::Ss(m.clone()),
                signals: fb_map.clone(),
                fit: json!({}),
            };
            score_from(&mf, &val, Mode::FreeRun, X0::Zero)
                .unwrap()
                .vaf_mean
        };
        let (v_pbsid, v_ref) = (score(&f.model), score(&refined.model));
        lines.push(format!(
            "k3 {k3:.2} noise {:.1} %: linear {lin_vaf:.2} %, y^3 PBSID {v_pbsid:.2} %, refined {v_ref:.3} % ({} it)",
            100.0 * noise,
            refined.iterations
        ));
        assert!(v_ref > 99.0, "{}", lines.join("\n"));
        assert!(v_ref > lin_vaf + 2.0, "{}", lines.join("\n"));
        assert!(refined.mse_after <= refined.mse_before);
    }
    println!("{}", lines.join("\n"));
}

/// `--x0 estimate`: a plant started away from zero; the zero-state free run carries the
/// transient, the estimated state removes it (exactly for a linear model, through the
/// feedback for the Duffing model) and only the samples after the estimate are scored.
#[test]
fn initial_state_is_estimated_from_the_first_samples() {
    let x0 = [1.2, -0.4];
    let (u, _, yc) = duffing(1500, 2.0, x0, 0.0, 3);
    let ds = csv(&u, &yc);
    let model = duffing_model(2.0);
    let zero = score_from(&model, &ds, Mode::FreeRun, X0::Zero).unwrap();
    let est = score_from(&model, &ds, Mode::FreeRun, X0::Estimate { samples: 50 }).unwrap();
    let r = run(&model, &ds, Mode::FreeRun, X0::Estimate { samples: 50 }).unwrap();
    let x = r.x0.unwrap();
    println!(
        "VAF from x0 = 0: {:.3} %, estimated x0 = [{:.6}, {:.6}]: {:.8} %",
        zero.vaf_mean, x[0], x[1], est.vaf_mean
    );
    assert_eq!((est.skipped, zero.skipped), (50, 0));
    assert!((&x - DVector::from_column_slice(&x0)).amax() < 1e-5, "{x}");
    assert!(est.vaf_mean > 99.9999 && zero.vaf_mean < est.vaf_mean);
    // linear model: one exact least-squares step
    let mut lin = model.clone();
    if let ModelKind::Ss(ss) = &mut lin.kind {
        ss.b[0][(0, 1)] = 0.0;
        ss.b[0][(1, 1)] = 0.0;
    }
    let mut ylin = DMatrix::zeros(1500, 1);
    if let ModelKind::Ss(ss) = &lin.kind {
        let ds0 = csv(&u, &yc);
        let sig = lin.signals.evaluate(&ds0).unwrap();
        ylin = ss.run_from(&sig, &DVector::from_column_slice(&x0), false);
    }
    let yl: Vec<f64> = ylin.column(0).iter().copied().collect();
    let r = run(
        &lin,
        &csv(&u, &yl),
        Mode::FreeRun,
        X0::Estimate { samples: 20 },
    )
    .unwrap();
    assert!((r.x0.unwrap() - DVector::from_column_slice(&x0)).amax() < 1e-6);
    assert!(mean(&vaf_per_output(&r.y, &r.yhat, 20)) > 99.99999);
}

/// Through the command line: `validate --x0 estimate` says what it scored, `simulate` runs
/// through the feedback, and a model whose output would need itself is refused on reading
/// with the file, line and column.
#[test]
fn command_line_honours_feedback_and_x0() {
    let dir = tempfile::tempdir().unwrap();
    let (u, ym, _) = duffing(800, 2.0, [0.5, 0.0], 0.01, 5);
    let data = dir.path().join("d.csv");
    std::fs::write(&data, csv(&u, &ym).to_csv_bytes(&data).unwrap()).unwrap();
    let model = dir.path().join("m.json");
    duffing_model(2.0).write(&model).unwrap();
    let (m, d) = (model.to_str().unwrap(), data.to_str().unwrap());
    let mut out = Vec::new();
    cli(
        [
            "lpvid", "validate", "--model", m, "--data", d, "--x0", "estimate",
        ],
        &mut out,
    )
    .unwrap();
    let text = String::from_utf8(out).unwrap();
    assert!(
        text.contains("initial state estimated from the first 50 samples, scored on the other 750"),
        "{text}"
    );
    let vaf: f64 = text
        .lines()
        .find(|l| l.contains("mean:"))
        .and_then(|l| l.split("VAF").nth(1))
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap();
    assert!(vaf > 99.0, "{text}");
    let sim = dir.path().join("s.csv");
    let mut out = Vec::new();
    cli(
        [
            "lpvid",
            "simulate",
            "--model",
            m,
            "--data",
            d,
            "--out",
            sim.to_str().unwrap(),
        ],
        &mut out,
    )
    .unwrap();
    let s = Dataset::read_csv(&sim).unwrap();
    let yhat = s.column("yhat1").unwrap();
    let r = run(&duffing_model(2.0), &csv(&u, &ym), Mode::FreeRun, X0::Zero).unwrap();
    assert!((yhat[700] - r.yhat[(700, 0)]).abs() < 1e-9);
    // D column of the feedback channel non-zero: refused with where and why
    let text = duffing_model(2.0).to_json_string().replace(
        "\"D\": [\n    [0.0, 0.0]\n  ]",
        "\"D\": [\n    [0.0, 0.5]\n  ]",
    );
    assert!(text.contains("[0.0, 0.5]"), "{text}");
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, text).unwrap();
    let e = cli(
        [
            "lpvid",
            "validate",
            "--model",
            bad.to_str().unwrap(),
            "--data",
            d,
        ],
        &mut Vec::new(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("bad.json:5")
            && e.contains("inputs[1][0]")
            && e.contains("would need the output it is computing"),
        "{e}"
    );
}
