//! `lpvid diagnose --fix` on the measured smart rotor at 430 rpm (../shared/data, see its
//! README): rows 0-6999 to train, 7000-9999 to validate, the split the 370 rpm acceptance
//! run of tests/benchmarks_measured.rs uses, on the other speed. The other measured data sets
//! are asserted on their benchmarks' splits in tests/benchmarks_measured.rs; the runs of
//! docs/diagnose-measured.md are the `diagnose_measured` example. The test skips with a
//! message when ../shared/data is absent.
//! Run in release mode: `cargo test --release --test diagnose_measured -- --nocapture`.

mod diagnose_support;

use std::path::Path;

use diagnose_support::shared_data;
use lpvid_host::data::Dataset;
use lpvid_host::diagnose::{diagnose, report, Options};
use lpvid_host::model::ModelFile;

fn segment(dir: &Path, (file, lo, hi): (&str, usize, usize), tag: &str) -> Dataset {
    let ds = Dataset::read_csv(&dir.join(file)).unwrap();
    let hi = hi.min(ds.len());
    Dataset {
        source: format!("{file}[{lo}..{hi}]{tag}"),
        names: ds.names.clone(),
        cols: ds.cols.iter().map(|c| c[lo..hi].to_vec()).collect(),
    }
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
