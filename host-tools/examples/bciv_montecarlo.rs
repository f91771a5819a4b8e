//! Monte-Carlo study of the BC-IV paper's example (lpv-bias-corrected-iv-lasso.md section 6,
//! BENCHMARKS.md B6): IV-LASSO vs BC-IV-LASSO over 100 runs, printed like the paper's
//! Table 1 (mean and standard deviation of the a_{i,j}), Table 2 (validation BFR) and Fig. 1
//! (the sigma_eta chosen from the calibration cost).
//!
//! ```text
//! cargo run --release -p lpvid-host --example bciv_montecarlo            # 100 runs
//! cargo run --release -p lpvid-host --example bciv_montecarlo -- 20      # fewer runs
//! ```
//!
//! Each run draws a new B6 data set (`systems::b6(seed)`, seeds 0..runs: 8000 training,
//! 1000 calibration, 1000 noise-free validation samples, sigma_eta = 0.25, sigma_nu = 0.06)
//! and fits, with n_a = 4, n_b = 2, n_g = 2 (21 parameters):
//! - **IV-LASSO (paper recipe)**: `ArxOptions::paper(.., Estimator::Iv)`: plain l1 on the IV
//!   cost (8), lambda by the lowest calibration cost of the penalised estimate over a grid
//!   reaching 1e-6 lambda_max (the IV calibration cost falls toward lambda -> 0, so the
//!   grid's end matters; see `ArxOptions::paper`);
//! - **IV (full model)**: refined-instrument IV of all 21 parameters, no penalty;
//! - **BC-IV-LASSO (ours)**: `ArxOptions::new(4, 2, 2)`, the `lpvid arx` default: adaptive l1
//!   on the bias-corrected cost (10), lambda by cross-validation on the calibration cost,
//!   sigma_eta from the sparsest self-consistent (structure, sigma) pair, de-biased refit.
//!
//! Sign convention: the paper writes y = +a_{1,2} p^2 y(k-1) (a_{1,2} = -0.8); the lpv-arx
//! model file writes y = -sum a_i y(k-i), so the paper's figures are printed negated.
//! Runs are spread over the available cores; the numbers do not depend on the thread count.

use std::time::Instant;

use lpvid_host::arx::{fit, model_file, ArxFit, ArxOptions, Estimator, LambdaChoice, SigmaChoice};
use lpvid_host::data::Dataset;
use lpvid_host::lpvss::Signals;
use lpvid_host::model::SignalMap;
use lpvid_host::pipeline::score;
use lpvid_host::simulate::Mode;
use lpvid_host::systems::b6;
use serde_json::json;

/// The paper's Table 1 (means and standard deviations of a_{1,0}..a_{4,2}), in its sign
/// convention, and Table 2.
const PAPER_MEAN_IV: [f64; 12] = [
    -0.1715, 0.0, -0.3882, 0.1619, 0.0, -0.0040, 0.0044, 0.0, 0.0, 0.0146, 0.0, -0.0011,
];
const PAPER_MEAN_BC: [f64; 12] = [
    -0.0302, 0.0, -0.7120, 0.0026, 0.0, 0.0107, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0015,
];
const PAPER_STD_IV: [f64; 12] = [
    0.0279, 0.0050, 0.0241, 0.0313, 0.0040, 0.0129, 0.0264, 0.0027, 0.0041, 0.0117, 0.0022, 0.0057,
];
const PAPER_STD_BC: [f64; 12] = [
    0.0358, 0.0019, 0.0457, 0.0066, 0.0031, 0.0152, 0.0, 0.0029, 0.0016, 0.0012, 0.0014, 0.0051,
];
const PAPER_BFR_IV: f64 = 0.6061;
const PAPER_BFR_BC: f64 = 0.9146;

/// One fit's figures.
#[derive(Clone)]
struct Run {
    a: Vec<f64>,
    b02: f64,
    bfr: f64,
    sigma: f64,
    exact: bool,
    iterations: usize,
    seconds: f64,
}

fn bfr_of(f: &ArxFit, val: &Signals) -> f64 {
    let map = SignalMap::standard(1, 1, 1);
    let model = model_file(f, &map, json!({})).expect("model file");
    let ds = Dataset::from_signals(val, "validation");
    score(&model, &ds, Mode::FreeRun).expect("score").bfr_mean / 100.0
}

fn one(seed: u64, opts: &ArxOptions) -> Run {
    let (train, cal, val) = b6(seed);
    let t0 = Instant::now();
    let f = fit(&train, Some(&cal), opts).expect("fit");
    let seconds = t0.elapsed().as_secs_f64();
    let a = f.model.a.iter().flatten().copied().collect();
    Run {
        a,
        b02: f.model.b[0][0][2],
        bfr: bfr_of(&f, &val),
        sigma: f.report.sigma_p,
        exact: f.report.support_names == ["a1[p1^2]", "b0[p1^2]"],
        iterations: f.report.iterations,
        seconds,
    }
}

fn run_all(runs: u64, opts: &ArxOptions) -> Vec<Run> {
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
        .min(runs.max(1) as usize);
    let mut out: Vec<Option<Run>> = vec![None; runs as usize];
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|t| {
                s.spawn(move || {
                    (0..runs)
                        .filter(|seed| *seed as usize % threads == t)
                        .map(|seed| (seed, one(seed, opts)))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        for h in handles {
            for (seed, r) in h.join().expect("worker") {
                out[seed as usize] = Some(r);
            }
        }
    });
    out.into_iter().map(|r| r.expect("every run")).collect()
}

fn mean_sd(v: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = v.clone().count() as f64;
    let m = v.clone().sum::<f64>() / n;
    let var = v.map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

fn main() {
    let runs: u64 = std::env::args()
        .nth(1)
        .map(|v| v.parse().expect("number of runs"))
        .unwrap_or(100);
    let iv_paper = ArxOptions::paper(4, 2, 2, Estimator::Iv);
    let mut iv_full = ArxOptions::new(4, 2, 2);
    iv_full.estimator = Estimator::Iv;
    iv_full.sigma = SigmaChoice::Fixed(0.0);
    iv_full.lambda = LambdaChoice::Fixed(0.0);
    let bc = ArxOptions::new(4, 2, 2);
    println!("B6 Monte-Carlo, {runs} runs (seeds 0..{runs}), n_a = 4, n_b = 2, n_g = 2\n");
    let t0 = Instant::now();
    let methods = [
        ("IV-LASSO (paper recipe)", run_all(runs, &iv_paper)),
        ("IV (full model)", run_all(runs, &iv_full)),
        ("BC-IV-LASSO (ours)", run_all(runs, &bc)),
    ];
    let wall = t0.elapsed().as_secs_f64();

    // Table 1, transposed: one row per coefficient, one column per method
    println!("Table 1: a_{{i,j}} in the lpv-arx convention (paper figures negated): mean (std)");
    let cell = |m: f64, sd: f64| format!("{:+.4} ({sd:.4})", if m == 0.0 { 0.0 } else { m });
    let ours: Vec<(Vec<f64>, Vec<f64>)> = methods
        .iter()
        .map(|(_, rs)| {
            (0..12)
                .map(|k| mean_sd(rs.iter().map(move |r| r.a[k])))
                .unzip()
        })
        .collect();
    print!(
        "{:<9}{:>9}{:>19}{:>19}",
        "coef", "true", "paper IV-LASSO", "paper BC-IV-L."
    );
    for (name, _) in &methods {
        print!("{:>26}", name);
    }
    println!();
    for k in 0..12 {
        let (i, j) = (k / 3 + 1, k % 3);
        print!(
            "{:<9}{:>9}{:>19}{:>19}",
            format!("a_{{{i},{j}}}"),
            if k == 2 { "+0.8" } else { "0" },
            cell(-PAPER_MEAN_IV[k], PAPER_STD_IV[k]),
            cell(-PAPER_MEAN_BC[k], PAPER_STD_BC[k])
        );
        for (m, sd) in &ours {
            print!("{:>26}", cell(m[k], sd[k]));
        }
        println!();
    }

    // Table 2 and the structure
    println!("\nTable 2: validation BFR (noise-free validation set), structure and sigma_eta");
    println!(
        "{:<26}{:>10}{:>10}{:>12}{:>10}{:>18}{:>16}{:>10}",
        "method", "BFR", "paper", "BFR std", "b_{0,2}", "exact structure", "sigma_eta", "s/run"
    );
    for (name, rs) in &methods {
        let (b, bs) = mean_sd(rs.iter().map(|r| r.bfr));
        let exact = rs.iter().filter(|r| r.exact).count();
        let (sg, sgs) = mean_sd(rs.iter().map(|r| r.sigma));
        let (b02, _) = mean_sd(rs.iter().map(|r| r.b02));
        let paper = if name.starts_with("BC") {
            format!("{PAPER_BFR_BC:.4}")
        } else if name.starts_with("IV-LASSO") {
            format!("{PAPER_BFR_IV:.4}")
        } else {
            "-".into()
        };
        let secs = rs.iter().map(|r| r.seconds).sum::<f64>() / rs.len() as f64;
        println!(
            "{name:<26}{b:>10.4}{paper:>10}{bs:>12.4}{b02:>10.4}{:>18}{:>16}{secs:>10.2}",
            format!(
                "{exact}/{} ({:.0} %)",
                rs.len(),
                100.0 * exact as f64 / rs.len() as f64
            ),
            if name.starts_with("BC") {
                format!("{sg:.4} ± {sgs:.4}")
            } else {
                "0".into()
            },
        );
    }
    let bc_runs = &methods[2].1;
    let (a12, a12s) = mean_sd(bc_runs.iter().map(|r| r.a[2]));
    let iters = bc_runs.iter().map(|r| r.iterations).sum::<usize>() as f64 / bc_runs.len() as f64;
    println!(
        "\nBC-IV-LASSO: mean a_{{1,2}} {a12:.4} ± {a12s:.4} (truth 0.8, paper 0.712 ± 0.046); \
         Fig. 1: sigma_eta minimum at 0.25 in the paper; {iters:.1} instrument refinements per run"
    );
    let iv_runs = &methods[0].1;
    let (a12, a12s) = mean_sd(iv_runs.iter().map(|r| r.a[2]));
    println!(
        "IV-LASSO (paper recipe): mean a_{{1,2}} {a12:.4} ± {a12s:.4} (paper 0.3882 ± 0.0241). \
         The paper's BFR 0.6061 is not reached: b_{{0,2}} (truth 0.4) is attenuated by the \
         scheduling noise like a_{{1,2}}; the paper does not tabulate its b's (tests/arx_b6.rs, \
         paper_iv_bfr_needs_an_unattenuated_b02)"
    );
    println!("wall time {wall:.1} s");
}
