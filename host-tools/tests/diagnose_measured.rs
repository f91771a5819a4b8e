//! `lpvid diagnose --fix` on measured data (../shared/data, see its README): smart rotor at
//! both speeds, cascaded tanks, EMPS, Silverbox, unbalanced disk. Each run identifies a model
//! with `lpvid pbsid` as a user would (settings below), diagnoses it with --fix --max-steps 3
//! and asserts that the validation error drops when a finding was applied (scored as diagnose
//! scores it: from an initial state estimated on the first samples). The figures are in
//! docs/diagnose-measured.md. Tests skip with a message when ../shared/data is absent.
//! Run in release mode: `cargo test --release --test diagnose_measured -- --nocapture`.

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

fn run(case: &Case) {
    let Some(data) = shared_data() else {
        println!(
            "SKIPPED {}: ../shared/data (measured data, see its README) is not next to the checkout",
            case.name
        );
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let train = segment(&data, case.train, "");
    let val = segment(&data, case.val, "");
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
        assert!(after < before, "{}: {before} -> {after}", case.name);
        let after_vaf = out.report.after.as_ref().unwrap().vaf_mean;
        if mode == Mode::FreeRun {
            assert!(
                after_vaf > out.report.before.vaf_mean,
                "{}: VAF {} -> {after_vaf}",
                case.name,
                out.report.before.vaf_mean
            );
        }
    } else {
        println!("{}: no finding above the noise threshold", case.name);
    }
}

#[test]
fn smart_rotor_370() {
    run(&CASES[0]);
}

#[test]
fn smart_rotor_430() {
    run(&CASES[1]);
}

#[test]
fn cascaded_tanks() {
    run(&CASES[2]);
}

#[test]
fn emps() {
    run(&CASES[3]);
}

#[test]
fn silverbox() {
    run(&CASES[4]);
}

#[test]
fn unbalanced_disk() {
    run(&CASES[5]);
}

/// The acceptance run of issue 14 (periodic disturbances on measured data): the smart rotor
/// at 370 rpm, rows 0-6999 to train and 7000-9999 to validate (`t` kept, so the phase of a
/// rotor harmonic carries from one to the other). `periodic-disturbance` is named first, as a
/// harmonic series of the 1P rotor frequency (370 rpm = 38.746 rad/s) with its harmonics, and
/// the free-run VAF after --fix reaches 97.5 / 94.5 %.
#[test]
fn smart_rotor_370_rotor_harmonics() {
    let Some(data) = shared_data() else {
        println!(
            "SKIPPED: ../shared/data (measured data, see its README) is not next to the checkout"
        );
        return;
    };
    let (out, _model) = diagnose_rows(&data, "smart-rotor-370rpm.csv", 7000, 10000, 3);
    let r = &out.report;
    println!("{}", report::summary(r, &[]));
    let f = &r.steps[0].findings[0];
    assert_eq!(f.effect, "periodic-disturbance");
    assert!(f.significant);
    // the fundamental and at least its second harmonic
    assert!(f.detail.contains("its harmonics"), "{}", f.detail);
    let om: f64 = f
        .detail
        .split(" of ")
        .find_map(|s| s.split(" rad/s").next().and_then(|v| v.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no rad/s in {}", f.detail));
    let one_p = 370.0 / 60.0 * 2.0 * std::f64::consts::PI;
    assert!((om / one_p - 1.0).abs() < 1e-3, "{om} vs 1P {one_p}");
    assert_eq!(r.applied[0].effect, "periodic-disturbance");
    let after = r.after.as_ref().unwrap();
    println!("smart rotor 370: VAF {:?} -> {:?}", r.before.vaf, after.vaf);
    assert!(
        after.vaf[0] >= 97.5 && after.vaf[1] >= 94.5,
        "{:?}",
        after.vaf
    );
}

/// The same split of the 430 rpm record (printed for the spread; its model from the
/// singular-value gap is far too small, so order-too-low comes first there).
#[test]
fn smart_rotor_430_same_split() {
    let Some(data) = shared_data() else {
        println!(
            "SKIPPED: ../shared/data (measured data, see its README) is not next to the checkout"
        );
        return;
    };
    let (out, _model) = diagnose_rows(&data, "smart-rotor-430rpm.csv", 7000, 10000, 3);
    let r = &out.report;
    println!("{}", report::summary(r, &[]));
    let after = r.after.as_ref().unwrap();
    println!("smart rotor 430: VAF {:?} -> {:?}", r.before.vaf, after.vaf);
    assert!(after.vaf_mean > r.before.vaf_mean);
    // the rotor harmonics are among the effects applied (1P of 430 rpm = 45.03 rad/s)
    assert!(
        r.applied.iter().any(|a| a.effect == "periodic-disturbance")
            || r.steps.iter().any(|s| s
                .findings
                .iter()
                .any(|f| f.effect == "periodic-disturbance")),
    );
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
