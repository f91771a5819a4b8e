//! Shared by tests/benchmarks_measured.rs and examples/benchmarks_measured.rs: one public
//! benchmark on its split, identified as a user would (`lpvid pbsid --past 10`, order auto),
//! diagnosed with `--fix --max-steps 3` holding out the last fifth of the training data, and
//! the test RMSE (data units) before and after.

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use lpvid_host::data::Dataset;
use lpvid_host::diagnose::{diagnose, refit_on_all, Options, Outcome};
use lpvid_host::model::ModelFile;
use lpvid_host::simulate::{run, Mode, X0};

/// ../shared/data next to the checkout (tests run in host-tools/), if present.
pub fn shared_data() -> Option<PathBuf> {
    ["../../shared/data", "../shared/data"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.join("README.md").exists())
}

/// Rows [lo, hi) of a data set.
pub fn segment(ds: &Dataset, lo: usize, hi: usize, tag: &str) -> Dataset {
    let hi = hi.min(ds.len());
    Dataset {
        source: format!("{}[{lo}..{hi}]{tag}", ds.source),
        names: ds.names.clone(),
        cols: ds.cols.iter().map(|c| c[lo..hi].to_vec()).collect(),
    }
}

/// Free-run RMSE per output, mean over outputs, in the data's units (rows after the initial
/// state's samples with `X0::Estimate`).
pub fn rmse(model: &ModelFile, ds: &Dataset, x0: X0) -> f64 {
    let r = run(model, ds, Mode::FreeRun, x0).unwrap();
    let (n, l) = (r.y.nrows(), r.y.ncols());
    let mut total = 0.0;
    for j in 0..l {
        let s: f64 = (r.skip..n)
            .map(|k| (r.y[(k, j)] - r.yhat[(k, j)]).powi(2))
            .sum();
        total += (s / (n - r.skip).max(1) as f64).sqrt();
    }
    total / l as f64
}

/// A benchmark: training rows of `file`, test sets (file, rows).
pub struct Bench {
    pub name: &'static str,
    pub file: &'static str,
    pub train: (usize, usize),
    pub tests: Vec<(&'static str, usize, usize)>,
}

/// What a run produced.
pub struct Result {
    pub model: ModelFile,
    pub outcome: Outcome,
    /// (test name, RMSE before x0 = 0, before x0 estimated, after x0 = 0, after estimated)
    pub rmse: Vec<(String, f64, f64, f64, f64)>,
    /// (test name, free-run VAF per output after, x0 = 0 and x0 estimated)
    pub vaf_after: Vec<(String, Vec<f64>, Vec<f64>)>,
    pub seconds: f64,
}

pub fn run_bench(dir: &Path, b: &Bench) -> Result {
    run_bench_at(dir, b, 10)
}

/// [`run_bench`] with the user's model identified at past window `past` (order auto).
pub fn run_bench_at(dir: &Path, b: &Bench, past: usize) -> Result {
    let t0 = std::time::Instant::now();
    let ds = Dataset::read_csv(&dir.join(b.file)).unwrap();
    let tr = segment(&ds, b.train.0, b.train.1, "");
    let cut = tr.len() - tr.len() / 5;
    let fit_part = segment(&tr, 0, cut, " fit");
    let hold = segment(&tr, cut, tr.len(), " held out");
    let tmp = tempfile::tempdir().unwrap();
    let tf = tmp.path().join("train.csv");
    std::fs::write(&tf, fit_part.to_csv_bytes(&tf).unwrap()).unwrap();
    let mf = tmp.path().join("m.json");
    lpvid_host::cli::run(
        [
            "lpvid",
            "pbsid",
            "--train",
            tf.to_str().unwrap(),
            "--past",
            &past.to_string(),
            "--out",
            mf.to_str().unwrap(),
        ],
        &mut Vec::new(),
    )
    .unwrap();
    let model = ModelFile::read(&mf).unwrap();
    let mut outcome = diagnose(
        &model,
        &fit_part,
        &hold,
        &Options {
            fix: true,
            max_steps: 3,
            threads: 0,
        },
    )
    .unwrap();
    // the held-out rows are the tail of the training rows: select on them, then refit the
    // chosen structure on all of them (diagnose::refit_on_all)
    refit_on_all(&mut outcome, &fit_part, &hold).unwrap();
    let mut rmse_rows = Vec::new();
    let mut vaf_rows = Vec::new();
    for &(file, lo, hi) in &b.tests {
        let t = segment(&Dataset::read_csv(&dir.join(file)).unwrap(), lo, hi, "");
        let est = X0::Estimate { samples: 50 };
        let vaf = |x0| {
            lpvid_host::simulate::score_from(&outcome.model, &t, Mode::FreeRun, x0)
                .unwrap()
                .vaf
        };
        vaf_rows.push((t.source.clone(), vaf(X0::Zero), vaf(est)));
        rmse_rows.push((
            t.source.clone(),
            rmse(&model, &t, X0::Zero),
            rmse(&model, &t, est),
            rmse(&outcome.model, &t, X0::Zero),
            rmse(&outcome.model, &t, est),
        ));
    }
    Result {
        model,
        outcome,
        rmse: rmse_rows,
        vaf_after: vaf_rows,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

/// The run in words.
pub fn describe(b: &Bench, r: &Result) -> String {
    let mut s = format!(
        "== {} ({:.0} s): model order {}\n",
        b.name,
        r.seconds,
        r.model
            .fit
            .get("order")
            .map_or("?".into(), |v| v.to_string())
    );
    for a in &r.outcome.report.applied {
        s.push_str(&format!(
            "  applied {}: {} ({:.1} %)\n",
            a.effect,
            a.detail,
            100.0 * a.explained
        ));
    }
    s.push_str(&format!("  stopped: {}\n", r.outcome.report.stopped));
    for (t, v0, ve) in &r.vaf_after {
        s.push_str(&format!(
            "  {t}: free-run VAF after {v0:.2?} % (x0 estimated {ve:.2?} %)\n"
        ));
    }
    if std::env::var("BENCH_VERBOSE").is_ok() {
        // every variant of every step, and the findings with their replication
        for st in &r.outcome.report.steps {
            s.push_str(&format!(
                "  step {}: null refit VAF {:.2}, MSE {:.4e} / {:.4e}\n",
                st.step, st.null_refit_vaf, st.null_refit_mse.0, st.null_refit_mse.1
            ));
            for v in &st.variants_scored {
                s.push_str(&format!(
                    "    {:<24} {:>9.4} p={:.1e} {:.1}s {}{}\n",
                    v.effect,
                    v.explained,
                    v.p_value,
                    v.seconds,
                    v.detail,
                    v.error
                        .as_deref()
                        .map_or(String::new(), |e| format!(" ERROR {e}"))
                ));
            }
            for f in &st.findings {
                s.push_str(&format!(
                    "    finding {:<24} {:.4} p={:.1e} sig {} repl {:?} blocked {:?}\n",
                    f.effect, f.explained, f.p_value, f.significant, f.replication, f.blocked_by
                ));
            }
        }
    }
    for (t, b0, be, a0, ae) in &r.rmse {
        s.push_str(&format!(
            "  {t}: RMSE before {b0:.4e} (x0 estimated {be:.4e}), after {a0:.4e} (x0 estimated {ae:.4e})\n"
        ));
    }
    s
}

/// The benchmarks and their splits (docs/benchmarks-measured.md).
pub fn benches() -> Vec<Bench> {
    vec![
        Bench {
            name: "silverbox",
            file: "silverbox-snls80mv.csv",
            train: (40960, 70960),
            tests: vec![
                ("silverbox-snls80mv.csv", 100, 40575),
                ("silverbox-snls80mv.csv", 100, 32000),
            ],
        },
        Bench {
            name: "tanks",
            file: "cascaded-tanks-estimation.csv",
            train: (0, usize::MAX),
            tests: vec![("cascaded-tanks-validation.csv", 0, usize::MAX)],
        },
        Bench {
            name: "disk",
            file: "unbalanced-disk.csv",
            train: (18000, 28000),
            tests: vec![("unbalanced-disk.csv", 31500, 35000)],
        },
        Bench {
            name: "emps",
            file: "emps.csv",
            train: (0, usize::MAX),
            tests: vec![("emps-pulses.csv", 0, usize::MAX)],
        },
        Bench {
            name: "rotor",
            file: "smart-rotor-370rpm.csv",
            train: (0, 7000),
            tests: vec![("smart-rotor-370rpm.csv", 7000, 10000)],
        },
        Bench {
            name: "rotor430",
            file: "smart-rotor-430rpm.csv",
            train: (0, 7000),
            tests: vec![("smart-rotor-430rpm.csv", 7000, 10000)],
        },
    ]
}
