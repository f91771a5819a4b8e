//! `lpvid diagnose --fix` on measured data (../shared/data, see its README): smart rotor at
//! both speeds, cascaded tanks, EMPS, Silverbox, unbalanced disk, the runs of
//! docs/diagnose-measured.md. Each run identifies a model with `lpvid pbsid` as a user would
//! (settings below), diagnoses it with --fix --max-steps 3 and checks that the validation
//! error drops when a finding was applied (scored as diagnose scores it: from an initial state
//! estimated on the first samples); it exits non-zero when one does not.
//!
//! It also runs the 430 rpm record on the split of the 370 rpm acceptance run (name
//! `smart rotor 430 rpm 7000`).
//!
//! `cargo run --release -p lpvid-host --example diagnose_measured [-- NAME...]` from
//! host-tools/ (names as printed, e.g. `Silverbox`). The acceptance figures on these data
//! sets are asserted by tests/benchmarks_measured.rs on the benchmarks' standard splits; this
//! example reproduces the table of other splits (about 10 minutes on 2 cores), so CI does not
//! run it.

#[path = "../tests/diagnose_support/mod.rs"]
mod diagnose_support;

use std::path::Path;

use diagnose_support::shared_data;
use lpvid_host::data::Dataset;
use lpvid_host::diagnose::effects::x0_samples;
use lpvid_host::diagnose::{diagnose, report, Options};
use lpvid_host::model::ModelFile;
use lpvid_host::simulate::{run as run_model, Mode, X0};

/// A measured case: data file(s), segments (row ranges) and the `lpvid pbsid` options.
struct Case {
    name: &'static str,
    train: (&'static str, usize, usize),
    val: (&'static str, usize, usize),
    pbsid: &'static [&'static str],
}

const CASES: [Case; 6] = [
    Case {
        name: "smart rotor 370 rpm",
        train: ("smart-rotor-370rpm.csv", 0, 5000),
        val: ("smart-rotor-370rpm.csv", 5000, 10000),
        pbsid: &["--past", "10"],
    },
    Case {
        name: "smart rotor 430 rpm",
        train: ("smart-rotor-430rpm.csv", 0, 5000),
        val: ("smart-rotor-430rpm.csv", 5000, 10000),
        pbsid: &["--past", "10"],
    },
    Case {
        name: "cascaded tanks",
        train: ("cascaded-tanks-estimation.csv", 0, usize::MAX),
        val: ("cascaded-tanks-validation.csv", 0, usize::MAX),
        pbsid: &["--past", "10"],
    },
    Case {
        name: "EMPS",
        train: ("emps.csv", 0, usize::MAX),
        val: ("emps-pulses.csv", 0, usize::MAX),
        pbsid: &["--past", "10"],
    },
    Case {
        name: "Silverbox",
        train: ("silverbox-snls80mv.csv", 40960, 60960),
        val: ("silverbox-snls80mv.csv", 61440, 71440),
        pbsid: &["--past", "10"],
    },
    Case {
        name: "unbalanced disk",
        train: ("unbalanced-disk.csv", 0, 10000),
        val: ("unbalanced-disk.csv", 10000, 15000),
        pbsid: &["--past", "10"],
    },
];

fn segment(dir: &Path, (file, lo, hi): (&str, usize, usize), tag: &str) -> Dataset {
    let ds = Dataset::read_csv(&dir.join(file)).unwrap();
    let hi = hi.min(ds.len());
    Dataset {
        source: format!("{file}[{lo}..{hi}]{tag}"),
        names: ds.names.clone(),
        cols: ds.cols.iter().map(|c| c[lo..hi].to_vec()).collect(),
    }
}

/// Mean squared error as diagnose scores the held-out data: the run from an initial state
/// estimated on the first `x0_samples(N)` samples, which are not scored.
fn mse(model: &ModelFile, ds: &Dataset, mode: Mode) -> f64 {
    let x0 = X0::Estimate {
        samples: x0_samples(ds.len()),
    };
    let r = run_model(model, ds, mode, x0).unwrap();
    let e = (&r.y - &r.yhat)
        .rows(r.skip, r.y.nrows() - r.skip)
        .into_owned();
    e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64
}

/// Identify, diagnose and score one case; an error when a finding was applied and the
/// validation error did not drop.
fn run(data: &Path, case: &Case) -> Result<(), String> {
    let tmp = tempfile::tempdir().unwrap();
    let train = segment(data, case.train, "");
    let val = segment(data, case.val, "");
    let tp = tmp.path().join("train.csv");
    let vp = tmp.path().join("val.csv");
    train.write_csv(&tp).unwrap();
    val.write_csv(&vp).unwrap();
    let mp = tmp.path().join("model.json");
    let mut args: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    args.push(tp.display().to_string());
    args.extend(case.pbsid.iter().map(|s| s.to_string()));
    args.extend(["--out".to_string(), mp.display().to_string()]);
    lpvid_host::cli::run(args, &mut Vec::new()).unwrap();
    let model = ModelFile::read(&mp).unwrap();
    let train = Dataset::read_csv(&tp).unwrap();
    let val = Dataset::read_csv(&vp).unwrap();
    let t0 = std::time::Instant::now();
    let opts = Options {
        fix: true,
        max_steps: 3,
        threads: 0,
    };
    let mut out = diagnose(&model, &train, &val, &opts).unwrap();
    out.report.model = format!("{} ({})", case.name, case.pbsid.join(" "));
    println!("===== {} ({:.1} s)", case.name, t0.elapsed().as_secs_f64());
    println!("{}", report::summary(&out.report, &[]));
    if let Some(a) = out.report.applied.first() {
        // the final model against the given one, in the free run when any applied fix was
        // scored on it (a later Lur'e fix may trade one-step accuracy for the free run), else
        // in one-step prediction (noise models only)
        let free = out.report.applied.iter().any(|a| a.residual == "free-run");
        let mode = if free { Mode::FreeRun } else { Mode::Predictor };
        let a_residual = if free { "free-run" } else { a.residual };
        let before = mse(&model, &val, mode);
        let after = mse(&out.model, &val, mode);
        println!(
            "{}: {} validation MSE {before:.4e} -> {after:.4e} ({:.2}x; from x0 = 0 over every sample {:.4e} -> {:.4e})",
            case.name,
            a_residual,
            before / after,
            diagnose_support::mse(&model, &val, mode),
            diagnose_support::mse(&out.model, &val, mode),
        );
        if after >= before {
            return Err(format!("{}: validation MSE {before} -> {after}", case.name));
        }
        let after_vaf = out.report.after.as_ref().unwrap().vaf_mean;
        if mode == Mode::FreeRun && after_vaf <= out.report.before.vaf_mean {
            return Err(format!(
                "{}: VAF {} -> {after_vaf}",
                case.name, out.report.before.vaf_mean
            ));
        }
    } else {
        println!("{}: no finding above the noise threshold", case.name);
    }
    Ok(())
}

/// The 430 rpm record on the split of the 370 rpm acceptance run (rows 0-6999 / 7000-9999,
/// `--max-steps 3`; printed for the spread; its model from the
/// singular-value gap is far too small, so order-too-low comes first there).
fn smart_rotor_430_same_split(data: &Path) -> Result<(), String> {
    let (out, _model) = diagnose_rows(data, "smart-rotor-430rpm.csv", 7000, 10000, 3);
    let r = &out.report;
    println!("{}", report::summary(r, &[]));
    let after = r.after.as_ref().unwrap();
    println!("smart rotor 430: VAF {:?} -> {:?}", r.before.vaf, after.vaf);
    if after.vaf_mean <= r.before.vaf_mean {
        return Err(format!(
            "smart rotor 430 rows 7000-9999: VAF {} -> {}",
            r.before.vaf_mean, after.vaf_mean
        ));
    }
    // the rotor harmonics are among the effects found (1P of 430 rpm = 45.03 rad/s)
    let periodic = r.steps.iter().any(|s| {
        s.findings
            .iter()
            .any(|f| f.effect == "periodic-disturbance")
    });
    if !periodic {
        return Err("smart rotor 430 rows 7000-9999: no periodic-disturbance finding".into());
    }
    Ok(())
}

/// `lpvid pbsid --past 10` on rows [0, cut) of `file`, then diagnose --fix with rows
/// [cut, end) as validation data.
fn diagnose_rows(
    dir: &Path,
    file: &'static str,
    cut: usize,
    end: usize,
    steps: usize,
) -> (lpvid_host::diagnose::Outcome, ModelFile) {
    let tmp = tempfile::tempdir().unwrap();
    let train = segment(dir, (file, 0, cut), "");
    let val = segment(dir, (file, cut, end), "");
    let tp = tmp.path().join("train.csv");
    let vp = tmp.path().join("val.csv");
    train.write_csv(&tp).unwrap();
    val.write_csv(&vp).unwrap();
    let mp = tmp.path().join("model.json");
    let args: Vec<String> = [
        "lpvid",
        "pbsid",
        "--train",
        &tp.display().to_string(),
        "--past",
        "10",
        "--out",
        &mp.display().to_string(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    lpvid_host::cli::run(args, &mut Vec::new()).unwrap();
    let model = ModelFile::read(&mp).unwrap();
    let train = Dataset::read_csv(&tp).unwrap();
    let val = Dataset::read_csv(&vp).unwrap();
    let opts = Options {
        fix: true,
        max_steps: steps,
        threads: 0,
    };
    (diagnose(&model, &train, &val, &opts).unwrap(), model)
}

fn main() {
    let Some(data) = shared_data() else {
        eprintln!(
            "../shared/data (measured data, see its README) not found (run from host-tools/)"
        );
        std::process::exit(2);
    };
    let want: Vec<String> = std::env::args().skip(1).collect();
    let mut failed = Vec::new();
    for case in &CASES {
        if !want.is_empty() && !want.iter().any(|w| w == case.name) {
            continue;
        }
        if let Err(e) = run(&data, case) {
            println!("FAIL {e}");
            failed.push(e);
        }
    }
    if want.is_empty() || want.iter().any(|w| w == "smart rotor 430 rpm 7000") {
        if let Err(e) = smart_rotor_430_same_split(&data) {
            println!("FAIL {e}");
            failed.push(e);
        }
    }
    if !failed.is_empty() {
        std::process::exit(1);
    }
}
