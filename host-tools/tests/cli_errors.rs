//! Bad input through the command line: each case gives one clear error naming the file,
//! line and column, never panics, and writes nothing.

use lpvid_host::cli::run;
use std::path::Path;

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.display().to_string()
}

/// Run `lpvid pbsid` on `train`, expecting failure; returns the message and checks that
/// the output model was not written.
fn pbsid_err(dir: &Path, train: &str, past: &str) -> String {
    let out = dir.join("m.json");
    let mut sink = Vec::new();
    let args = [
        "lpvid",
        "pbsid",
        "--train",
        train,
        "--past",
        past,
        "--out",
        out.to_str().unwrap(),
    ];
    let err = run(args, &mut sink).expect_err("the command must fail");
    assert!(!out.exists(), "nothing may be written on error");
    err.to_string()
}

fn good_rows(n: usize) -> String {
    let mut s = String::from("u1,y1,p1\n");
    for k in 0..n {
        let f = k as f64;
        s.push_str(&format!(
            "{},{},{}\n",
            (0.7 * f).sin(),
            (0.3 * f).cos(),
            0.5 + 0.4 * (0.1 * f).sin()
        ));
    }
    s
}

#[test]
fn missing_output_column() {
    let dir = tempfile::tempdir().unwrap();
    let f = write(dir.path(), "t.csv", "u1,p1\n1,2\n3,4\n");
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("t.csv:1") && e.contains("y1"), "{e}");
}

#[test]
fn nan_and_inf_are_located() {
    let dir = tempfile::tempdir().unwrap();
    let mut lines: Vec<String> = good_rows(50).lines().map(String::from).collect();
    lines[7] = "0.1,nan,0.5".into();
    let f = write(dir.path(), "n.csv", &(lines.join("\n") + "\n"));
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("n.csv:8") && e.contains("y1"), "{e}");
    lines[7] = "0.1,0.2,inf".into();
    let f = write(dir.path(), "i.csv", &(lines.join("\n") + "\n"));
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("i.csv:8") && e.contains("p1"), "{e}");
}

#[test]
fn ragged_row() {
    let dir = tempfile::tempdir().unwrap();
    let mut lines: Vec<String> = good_rows(30).lines().map(String::from).collect();
    lines[12] = "0.1,0.2".into();
    let f = write(dir.path(), "r.csv", &(lines.join("\n") + "\n"));
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(
        e.contains("r.csv:13") && e.contains("expected 3 fields"),
        "{e}"
    );
}

#[test]
fn empty_file() {
    let dir = tempfile::tempdir().unwrap();
    let f = write(dir.path(), "e.csv", "");
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("e.csv") && e.contains("empty"), "{e}");
    let f = write(dir.path(), "h.csv", "u1,y1,p1\n");
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("h.csv") && e.contains("no data"), "{e}");
}

#[test]
fn fewer_samples_than_the_window_needs() {
    let dir = tempfile::tempdir().unwrap();
    let f = write(dir.path(), "s.csv", &good_rows(5));
    let e = pbsid_err(dir.path(), &f, "4");
    assert!(
        e.contains("s.csv:6") && e.contains("past window of 4"),
        "{e}"
    );
}

#[test]
fn constant_input_is_rank_deficient() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = String::from("u1,u2,y1,p1\n");
    for k in 0..60 {
        let f = k as f64;
        s.push_str(&format!("{},0.5,{},{}\n", f.sin(), f.cos(), 0.1 * f));
    }
    let f = write(dir.path(), "c.csv", &s);
    let e = pbsid_err(dir.path(), &f, "2");
    assert!(e.contains("c.csv") && e.contains("'u2' is constant"), "{e}");
}

#[test]
fn unknown_model_type() {
    let dir = tempfile::tempdir().unwrap();
    let m = write(
        dir.path(),
        "m.json",
        "{\n  \"type\": \"lpv-foo\",\n  \"A\": []\n}\n",
    );
    let d = write(dir.path(), "d.csv", &good_rows(20));
    let mut sink = Vec::new();
    let err = run(
        ["lpvid", "validate", "--model", &m, "--data", &d],
        &mut sink,
    )
    .unwrap_err();
    let e = err.to_string();
    assert!(
        e.contains("m.json:2") && e.contains("lpv-foo") && e.contains("lpv-ss"),
        "{e}"
    );
}

#[test]
fn model_needs_a_column_the_data_lacks() {
    let dir = tempfile::tempdir().unwrap();
    let train = write(dir.path(), "t.csv", &good_rows(200));
    let out = dir.path().join("m.json");
    let mut sink = Vec::new();
    run(
        [
            "lpvid",
            "pbsid",
            "--train",
            &train,
            "--past",
            "2",
            "--order",
            "1",
            "--out",
            out.to_str().unwrap(),
        ],
        &mut sink,
    )
    .unwrap();
    let other = write(dir.path(), "o.csv", "u1,y1\n1,2\n3,4\n");
    let err = run(
        [
            "lpvid",
            "validate",
            "--model",
            out.to_str().unwrap(),
            "--data",
            &other,
        ],
        &mut sink,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("o.csv:1") && err.contains("p1"), "{err}");
}

#[test]
fn help_on_every_command() {
    for cmd in ["demo", "pbsid", "validate", "simulate"] {
        let mut out = Vec::new();
        run(["lpvid", cmd, "--help"], &mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(text.contains("Usage"), "{cmd}: {text}");
    }
}

#[test]
fn end_to_end_pbsid_validate_simulate() {
    let dir = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("fixtures");
    let train = root.join("b3-train.csv");
    let val = root.join("b3-val.csv");
    let out = dir.path().join("b3.json");
    let mut sink = Vec::new();
    run(
        [
            "lpvid",
            "pbsid",
            "--train",
            train.to_str().unwrap(),
            "--val",
            val.to_str().unwrap(),
            "--past",
            "5",
            "--out",
            out.to_str().unwrap(),
            "--json",
        ],
        &mut sink,
    )
    .unwrap();
    let summary: serde_json::Value = serde_json::from_slice(&sink).unwrap();
    assert_eq!(summary["order"], 4);
    assert!(
        summary["val"]["vaf_mean"].as_f64().unwrap() > 97.0,
        "{summary}"
    );
    let mut sink = Vec::new();
    run(
        [
            "lpvid",
            "validate",
            "--model",
            out.to_str().unwrap(),
            "--data",
            val.to_str().unwrap(),
            "--json",
        ],
        &mut sink,
    )
    .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&sink).unwrap();
    assert_eq!(v["score"]["vaf_mean"], summary["val"]["vaf_mean"]);
    let sim = dir.path().join("sim.csv");
    run(
        [
            "lpvid",
            "simulate",
            "--model",
            out.to_str().unwrap(),
            "--data",
            val.to_str().unwrap(),
            "--out",
            sim.to_str().unwrap(),
        ],
        &mut Vec::new(),
    )
    .unwrap();
    let text = std::fs::read_to_string(&sim).unwrap();
    assert!(text.lines().next().unwrap().ends_with("yhat1,yhat2"));
    let mut sink = Vec::new();
    run(["lpvid", "demo", "--json"], &mut sink).unwrap();
    let d: serde_json::Value = serde_json::from_slice(&sink).unwrap();
    assert_eq!(d["order"], 4);
    assert!(d["val"]["vaf_mean"].as_f64().unwrap() > 99.9);
}
