//! The model file's smoothed factor (`"smooth": a`, a causal first-order low-pass of a data
//! column, docs/model-format.md): every consumer runs the filtered column or refuses the model
//! naming the factor.

use std::path::{Path, PathBuf};

use lpvid_host::cli;
use lpvid_host::data::Dataset;
use lpvid_host::model::{low_pass, Factor, ModelFile};
use lpvid_host::simulate::{run, score_from, Mode, X0};
use lpvid_host::stream::{score_streaming_chunks, simulate_streaming_chunks};

/// A scheduled first-order model reading lowpass0.6(p1) (or p1 plainly).
fn model(smooth: Option<f64>) -> ModelFile {
    let sched = match smooth {
        Some(a) => format!("[{{\"col\": \"p1\", \"smooth\": {a}}}]"),
        None => "[{\"col\": \"p1\"}]".into(),
    };
    let text = format!(
        r#"{{
  "type": "lpv-ss",
  "scheduling": [[], {sched}],
  "A": [[[0.6]], [[0.3]]],
  "B": [[[1.0]], [[0.5]]],
  "K": [[[0.2]], [[0.1]]],
  "C": [[1.0]],
  "D": [[0.0]]
}}"#
    );
    ModelFile::from_json_str("m.json", &text).unwrap()
}

/// u1 a deterministic pseudo-random input, p1 a sinusoid with a sawtooth "noise", y1 anything.
fn data(n: usize) -> Dataset {
    let u: Vec<f64> = (0..n)
        .map(|k| ((k * 7919) % 13) as f64 / 6.0 - 1.0)
        .collect();
    let p: Vec<f64> = (0..n)
        .map(|k| 0.7 * (0.02 * k as f64).sin() + 0.1 * (((k * 31) % 7) as f64 / 3.0 - 1.0))
        .collect();
    let y: Vec<f64> = (0..n).map(|k| (0.05 * k as f64).cos()).collect();
    Dataset {
        source: "d.csv".into(),
        names: vec!["u1".into(), "y1".into(), "p1".into()],
        cols: vec![u, y, p],
    }
}

fn write(dir: &Path, name: &str, ds: &Dataset) -> PathBuf {
    let p = dir.join(name);
    ds.write_csv(&p).unwrap();
    p
}

#[test]
fn simulation_and_scores_run_the_filtered_column() {
    let ds = data(600);
    let smoothed = model(Some(0.6));
    // the plain model on data whose p1 is filtered beforehand: the same run to the bit
    let mut pre = ds.clone();
    pre.cols[2] = low_pass(&ds.cols[2], 0.6);
    for mode in [Mode::FreeRun, Mode::Predictor] {
        let a = run(&smoothed, &ds, mode, X0::Zero).unwrap();
        let b = run(&model(None), &pre, mode, X0::Zero).unwrap();
        assert_eq!(a.yhat, b.yhat);
        let c = run(&model(None), &ds, mode, X0::Zero).unwrap();
        let diff = (&a.yhat - &c.yhat).amax();
        assert!(diff > 1e-3, "the filter changes the output ({diff:.2e})");
    }
    // the low-pass starts at the first value: p1 constant is read unchanged
    let mut flat = ds.clone();
    flat.cols[2] = vec![0.4; 600];
    let a = run(&smoothed, &flat, Mode::FreeRun, X0::Zero).unwrap();
    let b = run(&model(None), &flat, Mode::FreeRun, X0::Zero).unwrap();
    assert_eq!(a.yhat, b.yhat);
}

#[test]
fn streamed_validate_and_simulate_hand_smoothing_to_the_in_memory_path() {
    let dir = tempfile::tempdir().unwrap();
    let ds = data(3000);
    let path = write(dir.path(), "d.csv", &ds);
    let read = Dataset::read_csv(&path).unwrap();
    // chunks of 500 rows would restart the filter: the streamed path declines it
    let m = model(Some(0.6));
    assert!(score_streaming_chunks(&m, &path, Mode::FreeRun, X0::Zero, 500).is_none());
    let out = dir.path().join("sim.csv");
    assert!(simulate_streaming_chunks(&m, &path, Mode::FreeRun, X0::Zero, &out, 500).is_none());
    // the plain model still streams, with the in-memory score
    let plain = model(None);
    let (s, rows) = score_streaming_chunks(&plain, &path, Mode::FreeRun, X0::Zero, 500).unwrap();
    assert_eq!(rows, 3000);
    let mem = score_from(&plain, &read, Mode::FreeRun, X0::Zero).unwrap();
    assert!((s.vaf_mean - mem.vaf_mean).abs() < 1e-9);
    // the CLI gives the in-memory numbers for the smoothed model
    let mp = dir.path().join("m.json");
    m.write(&mp).unwrap();
    let mut sink = Vec::new();
    let args = [
        "lpvid",
        "validate",
        "--model",
        mp.to_str().unwrap(),
        "--data",
        path.to_str().unwrap(),
        "--json",
    ];
    cli::run(args.iter().map(|s| s.to_string()), &mut sink).unwrap();
    let v: serde_json::Value = serde_json::from_slice(&sink).unwrap();
    let mem = score_from(&m, &read, Mode::FreeRun, X0::Zero).unwrap();
    let vaf = v
        .pointer("/score/vaf_mean")
        .and_then(|x| x.as_f64())
        .unwrap();
    assert!((vaf - mem.vaf_mean).abs() < 1e-9, "{v}");
}

#[test]
fn the_device_push_refuses_a_non_plain_signal_map_naming_the_signal() {
    let dir = tempfile::tempdir().unwrap();
    let mp = dir.path().join("m.json");
    model(Some(0.6)).write(&mp).unwrap();
    let mut sink = Vec::new();
    let args = [
        "lpvid",
        "device",
        "--port",
        "/nonexistent/tty",
        "push",
        mp.to_str().unwrap(),
    ];
    let e = cli::run(args.iter().map(|s| s.to_string()), &mut sink)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("scheduling[1] is lowpass0.6(p1) where the device reads p1")
            && e.contains("\"smooth\"")
            && e.contains("device"),
        "{e}"
    );
    // any other signal the device's frame does not carry as it is: an own-output feedback
    // channel y1^3 in place of u1 (before, only "smooth" was refused and such a model was
    // pushed and run on the raw u1)
    let mut cubic = model(None);
    cubic.signals.inputs[0] = vec![Factor {
        pow: 3.0,
        ..Factor::col("y1")
    }];
    cubic.write(&mp).unwrap();
    let e = cli::run(args.iter().map(|s| s.to_string()), &mut sink)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("inputs[0] is y1^3 where the device reads u1"),
        "{e}"
    );
    // the plain model gets past the file check to the port
    model(None).write(&mp).unwrap();
    let e = cli::run(args.iter().map(|s| s.to_string()), &mut sink)
        .unwrap_err()
        .to_string();
    assert!(!e.contains("smooth"), "{e}");
}

#[test]
fn a_factor_built_in_code_is_checked_when_evaluated() {
    let mut m = model(None);
    m.signals.scheduling[1] = vec![Factor {
        smooth: Some(1.0),
        ..Factor::col("p1")
    }];
    let e = m.signals.evaluate(&data(10)).unwrap_err();
    assert!(
        e.message.contains("\"smooth\" 1 is not a low-pass pole"),
        "{e}"
    );
}
