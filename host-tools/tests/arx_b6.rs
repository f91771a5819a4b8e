//! Acceptance tests of the host LPV-ARX identification (issue 4) on benchmark B6
//! (BENCHMARKS.md; lpv-bias-corrected-iv-lasso.md section 6, Tables 1-2, Fig. 1) and on a
//! system of our own with two scheduling signals and two inputs. Monte-Carlo with fixed
//! seeds, run in release mode (`cargo test --release`); the summary numbers are printed
//! (`-- --nocapture`).
//!
//! Sign convention: the paper's example writes y = +a_{1,2} p^2 y(k-1) with a_{1,2} = -0.8;
//! the lpv-arx model file writes y = -sum a_i y(k-i), so the truth is a_{1,2} = +0.8 here.

use lpvid_host::arx::{
    fit, model_file, ArxFit, ArxOptions, Estimator, LambdaChoice, Precision, SigmaChoice,
};
use lpvid_host::cli;
use lpvid_host::data::Dataset;
use lpvid_host::lpvss::Signals;
use lpvid_host::model::{ModelFile, ModelKind, SignalMap};
use lpvid_host::pipeline::score;
use lpvid_host::simulate::Mode;
use lpvid_host::systems::{b6, b6_with};
use nalgebra::DMatrix;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use serde_json::{json, Value};

/// Monte-Carlo runs in CI (the example `bciv_montecarlo` runs 100).
const RUNS: u64 = 20;

/// The true B6 structure in our naming.
const B6_TRUTH: [&str; 2] = ["a1[p1^2]", "b0[p1^2]"];

/// One run's figures.
struct Run {
    a10: f64,
    a12: f64,
    a20: f64,
    b02: f64,
    sigma: f64,
    bfr: f64,
    exact: bool,
    support: Vec<String>,
}

/// Validation BFR (fraction) of a fit: the model file as written, simulated in free run by
/// the same code `lpvid validate` uses, on the noise-free validation set.
fn bfr_of(f: &ArxFit, val: &Signals) -> f64 {
    let map = SignalMap::standard(val.u.ncols(), 1, val.p.ncols());
    let model = model_file(f, &map, json!({})).unwrap();
    let ds = Dataset::from_signals(val, "validation");
    score(&model, &ds, Mode::FreeRun).unwrap().bfr_mean / 100.0
}

fn b6_run(seed: u64, opts: &ArxOptions) -> Run {
    let (train, cal, val) = b6(seed);
    let f = fit(&train, Some(&cal), opts).unwrap();
    let d = f.dims;
    Run {
        a10: f.report.theta[d.index_a(1, 0).unwrap()],
        a12: f.report.theta[d.index_a(1, 2).unwrap()],
        a20: f.report.theta[d.index_a(2, 0).unwrap()],
        b02: f.report.theta[d.index_b(0, 0, 2).unwrap()],
        sigma: f.report.sigma_p,
        bfr: bfr_of(&f, &val),
        exact: f.report.support_names == B6_TRUTH,
        support: f.report.support_names.clone(),
    }
}

struct Summary {
    a10: f64,
    a12: f64,
    a20: f64,
    a12_sd: f64,
    b02: f64,
    sigma: f64,
    bfr: f64,
    exact: usize,
    n: usize,
}

fn summarise(name: &str, runs: &[Run]) -> Summary {
    let n = runs.len() as f64;
    let mean = |f: &dyn Fn(&Run) -> f64| runs.iter().map(f).sum::<f64>() / n;
    let a12 = mean(&|r| r.a12);
    let s = Summary {
        a10: mean(&|r| r.a10),
        a12,
        a20: mean(&|r| r.a20),
        a12_sd: (runs.iter().map(|r| (r.a12 - a12).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
        b02: mean(&|r| r.b02),
        sigma: mean(&|r| r.sigma),
        bfr: mean(&|r| r.bfr),
        exact: runs.iter().filter(|r| r.exact).count(),
        n: runs.len(),
    };
    println!(
        "{name}: mean a10 {:.4}, a12 {:.4} (sd {:.4}), a20 {:.4}, mean b02 {:.4}, mean sigma {:.4}, mean BFR {:.4}, \
         exact structure {}/{}",
        s.a10, s.a12, s.a12_sd, s.a20, s.b02, s.sigma, s.bfr, s.exact, s.n
    );
    for (i, r) in runs.iter().enumerate().filter(|(_, r)| !r.exact).take(3) {
        println!("  run {i}: support {:?}", r.support);
    }
    s
}

/// BENCHMARKS.md B6 / Tables 1-2 and Fig. 1 of the paper: BC-IV-LASSO with lambda by
/// cross-validation and sigma_eta from the calibration cost.
#[test]
fn b6_bciv_lasso_meets_the_paper_figures() {
    let opts = ArxOptions::new(4, 2, 2);
    let runs: Vec<Run> = (0..RUNS).map(|seed| b6_run(seed, &opts)).collect();
    let s = summarise("BC-IV-LASSO (B6)", &runs);
    // paper: mean a12 0.712 (ours must be within 0.04 of 0.8)
    assert!((s.a12 - 0.8).abs() <= 0.04, "mean a12 {}", s.a12);
    assert!((s.b02 - 0.4).abs() <= 0.04, "mean b02 {}", s.b02);
    // exact zero pattern in >= 90 % of the runs
    assert!(
        s.exact * 10 >= 9 * s.n,
        "exact structure {}/{}",
        s.exact,
        s.n
    );
    // paper: BFR 0.9146 (Table 2); ours >= 0.93
    assert!(s.bfr >= 0.93, "mean BFR {}", s.bfr);
    // paper Fig. 1: minimum at sigma = 0.25
    assert!((s.sigma - 0.25).abs() <= 0.03, "mean sigma {}", s.sigma);
}

/// The comparison is honest: without the bias correction the same data give the paper's
/// biased IV-LASSO coefficients (Table 1, our sign: a_{1,0} 0.1715, a_{1,2} 0.3882,
/// a_{2,0} -0.1619). The paper's recipe (`ArxOptions::paper`): plain l1 on the IV cost (8),
/// lambda from a grid reaching the unpenalised end by the lowest calibration cost
/// J_IV(theta_lambda, 0, N_c), refined instruments. 20 runs: a12 sd 0.04 per run, so the
/// standard error of the mean is 0.01 and the tolerances 0.05 are about 5 of them.
///
/// Validation BFR: the paper's 0.6061 is *not* reached (ours 0.52, mean over runs; the
/// per-run sd is 0.06). The cause is in the b coefficients the paper does not tabulate:
/// the same noisy p(k) in regressor and instrument attenuates b_{0,2} like a_{1,2} (ours
/// 0.235 for 0.4), and with the paper's own Table 1 a's a BFR of 0.61 needs b_{0,2} near
/// 0.4 (see `paper_iv_bfr_needs_an_unattenuated_b02`). The assertion below pins our figure
/// with its Monte-Carlo spread and checks it stays below the paper's.
#[test]
fn b6_iv_lasso_reproduces_the_paper_bias() {
    let paper = ArxOptions::paper(4, 2, 2, Estimator::Iv);
    let runs: Vec<Run> = (0..RUNS).map(|seed| b6_run(seed, &paper)).collect();
    let s = summarise("IV-LASSO, paper recipe (B6)", &runs);
    assert!(
        (s.a12 - 0.3882).abs() <= 0.05,
        "IV-LASSO mean a12 {}",
        s.a12
    );
    assert!(
        (s.a10 - 0.1715).abs() <= 0.05,
        "IV-LASSO mean a10 {}",
        s.a10
    );
    assert!(
        (s.a20 + 0.1619).abs() <= 0.05,
        "IV-LASSO mean a20 {}",
        s.a20
    );
    // b_{0,2} attenuated like a_{1,2} (the reason the BFR stays below the paper's)
    assert!((s.b02 - 0.235).abs() <= 0.03, "IV-LASSO mean b02 {}", s.b02);
    assert!(
        (s.bfr - 0.52).abs() <= 0.04 && s.bfr < 0.6061,
        "IV-LASSO mean BFR {}",
        s.bfr
    );
    assert!(
        s.exact * 10 <= s.n,
        "IV-LASSO should miss the structure: {}/{}",
        s.exact,
        s.n
    );
    // the unpenalised refined-IV estimate of the full 21-parameter model is biased the
    // same way: the bias is the noisy scheduling's, not the Lasso's
    let mut full = ArxOptions::new(4, 2, 2);
    full.estimator = Estimator::Iv;
    full.sigma = SigmaChoice::Fixed(0.0);
    full.lambda = LambdaChoice::Fixed(0.0);
    let runs: Vec<Run> = (0..RUNS).map(|seed| b6_run(seed, &full)).collect();
    let f = summarise("IV, full model, no penalty (B6)", &runs);
    assert!(f.a12 < 0.5 && f.b02 < 0.3, "IV a12 {} b02 {}", f.a12, f.b02);
    assert!(f.bfr < 0.6, "IV mean BFR {}", f.bfr);
}

/// Free-run simulation of y(k) = -sum_i a_i(p) y(k-i) + b_{0,2} p(k)^2 u(k) (a: 4 lags x
/// [1, p, p^2]) and its BFR (fraction) against `y`.
fn bfr_of_coefficients(a: &[f64; 12], b02: f64, val: &Signals) -> f64 {
    let n = val.len();
    let mut yh = vec![0.0; n];
    for k in 0..n {
        let p = val.p[(k, 0)];
        let mut v = b02 * p * p * val.u[(k, 0)];
        for i in 1..=4.min(k) {
            let c = &a[3 * (i - 1)..3 * i];
            v -= (c[0] + c[1] * p + c[2] * p * p) * yh[k - i];
        }
        yh[k] = v;
    }
    let y: Vec<f64> = val.y.column(0).iter().copied().collect();
    lpvid_host::metrics::bfr(&y, &yh) / 100.0
}

/// Why the paper's IV-LASSO BFR (0.6061) is out of reach: its own mean IV-LASSO a's
/// (Table 1, negated into our sign) reach a BFR of about 0.63 on noise-free validation data
/// only with b_{0,2} near the truth 0.4; with b_{0,2} attenuated as IV with noisy scheduling
/// attenuates it (0.235, the test above) they give about 0.44. So the paper's Table 2 figure
/// implies b estimates much less biased than its a's, or a BFR computed another way (not
/// stated; e.g. without removing the mean of y, 1 - |y - yhat| / |y|, our IV-LASSO gives 0.56).
#[test]
fn paper_iv_bfr_needs_an_unattenuated_b02() {
    let a_paper = [
        0.1715, 0.0, 0.3882, -0.1619, 0.0, 0.0040, -0.0044, 0.0, 0.0, -0.0146, 0.0, 0.0011,
    ];
    let runs = 10;
    let (mut true_b, mut attenuated) = (0.0, 0.0);
    for seed in 0..runs {
        let (_, _, val) = b6(seed);
        true_b += bfr_of_coefficients(&a_paper, 0.4, &val) / runs as f64;
        attenuated += bfr_of_coefficients(&a_paper, 0.235, &val) / runs as f64;
    }
    println!(
        "paper IV-LASSO a's: BFR {true_b:.4} with b02 = 0.4, {attenuated:.4} with b02 = 0.235"
    );
    assert!(true_b > 0.6 && true_b < 0.67, "{true_b}");
    assert!(attenuated < 0.5, "{attenuated}");
}

/// A system of our own: two scheduling signals with independent noise (the Hermite factors
/// multiply, core `bciv` module), two inputs, a product of both signals:
/// y_o(k) = -0.5 p1^2 y_o(k-1) + 0.4 p2^2 u1(k) + 0.3 p1 p2 u2(k-1),
/// p_i = p_o,i + eta_i, sigma = 0.2 on both, y = y_o + nu, sigma_nu = 0.05.
/// Model: na = 2, nb = 1, ng = 2 (6 basis functions, 36 parameters).
fn two_signal_system(n: usize, seed: u64) -> Signals {
    let mut rng = StdRng::seed_from_u64(seed);
    let (sigma, nu) = (0.2, 0.05);
    let mut u = DMatrix::zeros(n, 2);
    let mut p = DMatrix::zeros(n, 2);
    let mut y = DMatrix::zeros(n, 1);
    let mut prev = 0.0;
    let g = |rng: &mut StdRng| -> f64 { StandardNormal.sample(rng) };
    for k in 0..n {
        let kf = k as f64;
        let p1 = (0.1 * kf).sin() + 0.2 * g(&mut rng);
        let p2 = (0.037 * kf).cos() + 0.2 * g(&mut rng);
        u[(k, 0)] = rng.gen_range(0.0..1.0);
        u[(k, 1)] = rng.gen_range(-1.0..1.0);
        let u2_prev = if k > 0 { u[(k - 1, 1)] } else { 0.0 };
        let v = -0.5 * p1 * p1 * prev + 0.4 * p2 * p2 * u[(k, 0)] + 0.3 * p1 * p2 * u2_prev;
        prev = v;
        p[(k, 0)] = p1 + sigma * g(&mut rng);
        p[(k, 1)] = p2 + sigma * g(&mut rng);
        y[(k, 0)] = v + nu * g(&mut rng);
    }
    Signals { u, y, p }
}

#[test]
fn two_scheduling_signals_two_inputs_consistency() {
    let truth = ["a1[p1^2]", "b1_0[p2^2]", "b2_1[p1*p2]"];
    let opts = ArxOptions::new(2, 1, 2);
    let runs = RUNS;
    let (mut exact, mut sig) = (0, 0.0);
    let mut c = [0.0; 3];
    for seed in 0..runs {
        let train = two_signal_system(8000, 1000 + seed);
        let cal = two_signal_system(1000, 2000 + seed);
        let f = fit(&train, Some(&cal), &opts).unwrap();
        let d = f.dims;
        let th = &f.report.theta;
        let v = [
            th[d.index_a(1, 3).unwrap()],
            th[d.index_b(0, 0, 5).unwrap()],
            th[d.index_b(1, 1, 4).unwrap()],
        ];
        for (a, b) in c.iter_mut().zip(v) {
            *a += b / runs as f64;
        }
        sig += f.report.sigma_p / runs as f64;
        if f.report.support_names == truth {
            exact += 1;
        } else {
            println!("  run {seed}: support {:?}", f.report.support_names);
        }
    }
    println!(
        "two signals, two inputs: mean a1[p1^2] {:.4} (0.5), b1_0[p2^2] {:.4} (0.4), \
         b2_1[p1*p2] {:.4} (0.3), sigma {:.4} (0.2), exact structure {exact}/{runs}",
        c[0], c[1], c[2], sig
    );
    for (est, t) in c.iter().zip([0.5, 0.4, 0.3]) {
        assert!((est - t).abs() <= 0.04, "mean {est} vs {t}");
    }
    assert!(exact * 10 >= 9 * runs, "exact structure {exact}/{runs}");
    assert!((sig - 0.2).abs() <= 0.03, "mean sigma {sig}");
}

/// The device accumulates f32 statistics (and simulates the instruments in f32); the host
/// solves in f64 on what it receives. Same structure, a12 within 0.01.
#[test]
fn f32_statistics_select_the_same_structure_as_f64() {
    let mut worst: f64 = 0.0;
    for seed in 0..5 {
        let (train, cal, _) = b6(100 + seed);
        let mut o = ArxOptions::new(4, 2, 2);
        let f64_fit = fit(&train, Some(&cal), &o).unwrap();
        o.precision = Precision::F32;
        let f32_fit = fit(&train, Some(&cal), &o).unwrap();
        assert_eq!(f32_fit.report.precision, "f32");
        assert_eq!(
            f64_fit.report.support_names, f32_fit.report.support_names,
            "seed {seed}"
        );
        let d = f64_fit.dims;
        let i = d.index_a(1, 2).unwrap();
        let diff = (f64_fit.report.theta[i] - f32_fit.report.theta[i]).abs();
        println!(
            "seed {seed}: a12 f64 {:.5}, f32 {:.5}; sigma f64 {:.4}, f32 {:.4}",
            f64_fit.report.theta[i],
            f32_fit.report.theta[i],
            f64_fit.report.sigma_p,
            f32_fit.report.sigma_p
        );
        worst = worst.max(diff);
    }
    println!("largest |a12(f32) - a12(f64)| = {worst:.2e}");
    assert!(worst < 0.01, "{worst}");
}

// ---------------------------------------------------------------------------------------------
// The command line
// ---------------------------------------------------------------------------------------------

fn write_csv(dir: &std::path::Path, name: &str, sig: &Signals) -> String {
    let path = dir.join(name);
    Dataset::from_signals(sig, name).write_csv(&path).unwrap();
    path.display().to_string()
}

fn run(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut all = vec!["lpvid"];
    all.extend_from_slice(args);
    cli::run(all, &mut out).map_err(|e| e.to_string())?;
    Ok(String::from_utf8(out).unwrap())
}

#[test]
fn cli_arx_writes_a_model_validate_can_score() {
    let dir = tempfile::tempdir().unwrap();
    let (train, cal, val) = b6(7);
    let t = write_csv(dir.path(), "train.csv", &train);
    let c = write_csv(dir.path(), "calib.csv", &cal);
    let v = write_csv(dir.path(), "val.csv", &val);
    let m = dir.path().join("m.json").display().to_string();
    let text = run(&[
        "arx", "--train", &t, "--calib", &c, "--val", &v, "--na", "4", "--nb", "2", "--ng", "2",
        "--out", &m, "--json",
    ])
    .unwrap();
    let summary: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(summary["command"], "arx");
    assert_eq!(summary["support"], json!(B6_TRUTH));
    let bfr = summary["val"]["bfr_mean"].as_f64().unwrap();
    assert!(bfr > 90.0, "{bfr}");
    // the model file: lpv-arx, the basis as factor products, the fit record
    let model = ModelFile::read(std::path::Path::new(&m)).unwrap();
    let ModelKind::Arx(arx) = &model.kind else {
        panic!("not an lpv-arx model")
    };
    assert_eq!((arx.na, arx.nb, arx.a.len(), arx.b[0].len()), (4, 2, 4, 3));
    assert!((arx.a[0][2] - 0.8).abs() < 0.06, "{}", arx.a[0][2]);
    let sched: Vec<String> = model
        .signals
        .scheduling
        .iter()
        .map(|p| lpvid_host::model::describe(p))
        .collect();
    assert_eq!(sched, ["1", "p1", "p1^2"]);
    let fit = &model.fit;
    for key in [
        "method",
        "estimator",
        "lambda",
        "sigma_p",
        "support",
        "iterations",
        "train",
        "calib",
        "sigma_grid",
        "weights",
        "history",
        "costs",
    ] {
        assert!(fit.get(key).is_some(), "fit lacks {key}");
    }
    assert_eq!(fit["estimator"], "bciv");
    assert_eq!(fit["train"]["rows"], 8000);
    assert_eq!(fit["train"]["fnv1a64"].as_str().unwrap().len(), 16);
    let sp = fit["sigma_p"].as_f64().unwrap();
    assert!((sp - 0.25).abs() < 0.05, "{sp}");
    // lpvid validate scores the same model file the same way
    let vtext = run(&["validate", "--model", &m, "--data", &v, "--json"]).unwrap();
    let vj: Value = serde_json::from_str(&vtext).unwrap();
    assert!((vj["score"]["bfr_mean"].as_f64().unwrap() - bfr).abs() < 1e-9);
    // human summary of the least-squares estimator, lambda fixed, no calibration file
    let human = run(&[
        "arx",
        "--train",
        &t,
        "--na",
        "1",
        "--nb",
        "0",
        "--ng",
        "2",
        "--estimator",
        "ls",
        "--lambda",
        "0",
        "--out",
        &m,
    ])
    .unwrap();
    assert!(human.contains("LPV-ARX LS on"), "{human}");
    assert!(human.contains("model written to"), "{human}");
}

#[test]
fn cli_arx_bad_input_gets_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (train, cal, _) = b6_with(400, 200, 10, 0.25, 0.06, 3);
    let t = write_csv(dir.path(), "train.csv", &train);
    let c = write_csv(dir.path(), "calib.csv", &cal);
    let m = dir.path().join("m.json").display().to_string();
    let base = |extra: &[&str]| -> Vec<String> {
        let mut v: Vec<String> = [
            "arx", "--train", &t, "--na", "2", "--nb", "1", "--ng", "2", "--out", &m,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let fails = |extra: &[&str]| -> String {
        let args = base(extra);
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        match run(&refs) {
            Ok(out) => panic!("{extra:?} should fail, printed {out}"),
            Err(e) => e,
        }
    };
    // sigma grid empty
    let e = fails(&["--calib", &c, "--sigma-grid", "0.5:0.1:0.2"]);
    assert!(e.contains("sigma-grid") && e.contains("empty"), "{e}");
    // n_g = 0 with noise correction asked
    let args = [
        "arx", "--train", &t, "--calib", &c, "--na", "2", "--nb", "1", "--ng", "0", "--out", &m,
    ];
    let e = run(&args).unwrap_err();
    assert!(e.contains("--ng >= 1"), "{e}");
    // ... but ng = 0 without correction is a plain LPV-free ARX fit
    let m2 = dir.path().join("m2.json").display().to_string();
    let mut ok = args[..args.len() - 2].to_vec();
    ok.extend(["--sigma-p", "0", "--out", &m2]);
    let text = run(&ok).unwrap();
    assert!(text.contains("sigma_eta = 0.0000"), "{text}");
    // calibration file with other columns than training
    let mut cal2 = cal.clone();
    cal2.p = DMatrix::from_fn(cal.len(), 2, |k, j| cal.p[(k, 0)] * (1.0 + j as f64));
    let c2 = write_csv(dir.path(), "calib2.csv", &cal2);
    let e = fails(&["--calib", &c2]);
    assert!(e.contains("calib2.csv") && e.contains("p2"), "{e}");
    assert!(e.contains("calib2.csv:1:"), "{e}");
    // constant scheduling
    let mut flat = train.clone();
    flat.p.fill(0.3);
    let tf = write_csv(dir.path(), "flat.csv", &flat);
    let args = [
        "arx", "--train", &tf, "--na", "2", "--nb", "1", "--ng", "2", "--out", &m,
    ];
    let e = run(&args).unwrap_err();
    assert!(
        e.contains("flat.csv") && e.contains("p1") && e.contains("constant"),
        "{e}"
    );
    // too few samples
    let short = train.slice(0, 20);
    let ts = write_csv(dir.path(), "short.csv", &short);
    let args = [
        "arx", "--train", &ts, "--na", "2", "--nb", "1", "--ng", "2", "--out", &m,
    ];
    let e = run(&args).unwrap_err();
    assert!(e.contains("short.csv") && e.contains("rows"), "{e}");
    assert!(e.contains("short.csv:21:") && e.contains("held out"), "{e}");
    let ts2 = write_csv(dir.path(), "shorter.csv", &train.slice(0, 12));
    let args = [
        "arx", "--train", &ts2, "--calib", &c, "--na", "2", "--nb", "1", "--ng", "2", "--out", &m,
    ];
    let e = run(&args).unwrap_err();
    assert!(
        e.contains("shorter.csv:13:") && e.contains("at least 15 rows"),
        "{e}"
    );
    // the calibration file is checked the same way
    let cs = write_csv(dir.path(), "cshort.csv", &cal.slice(0, 12));
    let e = fails(&["--calib", &cs]);
    assert!(e.contains("cshort.csv") && e.contains("rows"), "{e}");
    // two outputs
    let mut two = train.clone();
    two.y = DMatrix::from_fn(train.len(), 2, |k, j| train.y[(k, 0)] + j as f64);
    let t2 = write_csv(dir.path(), "two.csv", &two);
    let args = [
        "arx", "--train", &t2, "--na", "2", "--nb", "1", "--ng", "2", "--out", &m,
    ];
    let e = run(&args).unwrap_err();
    assert!(e.contains("y2") && e.contains("one output"), "{e}");
    // sigma for a cost without correction, unknown estimator, bad lambda
    let e = fails(&["--estimator", "iv", "--sigma-p", "0.2"]);
    assert!(e.contains("bciv only"), "{e}");
    let e = fails(&["--estimator", "bcov"]);
    assert!(e.contains("bcov"), "{e}");
    let e = fails(&["--lambda=-1"]);
    assert!(e.contains("--lambda"), "{e}");
    // nothing was written by any failing run
    assert!(!std::path::Path::new(&m).exists());
}
