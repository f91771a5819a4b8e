//! Issue 15, data loss: an output aimed at an input is refused before any work, a failed
//! run changes no file, a non-regular destination is written through (never replaced), and
//! a write error there is an error.

use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use lpvid_host::cli::run;

const TRAIN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/b1-train.csv");

/// Bytes and modification time of a file, to prove it did not change.
fn snapshot(p: &Path) -> (Vec<u8>, SystemTime) {
    (
        std::fs::read(p).unwrap(),
        std::fs::metadata(p).unwrap().modified().unwrap(),
    )
}

fn lpvid(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut full = vec!["lpvid"];
    full.extend_from_slice(args);
    run(full, &mut out)
        .map(|_| String::from_utf8_lossy(&out).into_owned())
        .map_err(|e| e.to_string())
}

fn train_copy(dir: &Path) -> PathBuf {
    let p = dir.join("t.csv");
    std::fs::copy(TRAIN, &p).unwrap();
    p
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A model fitted on the fixture, written to `dir/m.json`.
fn model(dir: &Path) -> PathBuf {
    let t = train_copy(dir);
    let m = dir.join("m.json");
    lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&m)]).unwrap();
    m
}

#[test]
fn pbsid_out_equal_to_train_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let t = train_copy(dir.path());
    let before = snapshot(&t);
    let e = lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&t)]).unwrap_err();
    assert!(
        e.contains("--out") && e.contains("--train") && e.contains("same file"),
        "{e}"
    );
    assert_eq!(snapshot(&t), before);
    // the same file under another name: ./t.csv, a hard link, a symbolic link
    let hard = dir.path().join("hard.csv");
    std::fs::hard_link(&t, &hard).unwrap();
    let soft = dir.path().join("soft.csv");
    std::os::unix::fs::symlink(&t, &soft).unwrap();
    let dotted = dir.path().join(".").join("t.csv");
    for alias in [&hard, &soft, &dotted] {
        let e = lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(alias)]).unwrap_err();
        assert!(e.contains("same file"), "{alias:?}: {e}");
        assert_eq!(snapshot(&t), before);
    }
    // the validation file too
    let v = dir.path().join("v.csv");
    std::fs::copy(TRAIN, &v).unwrap();
    let vb = snapshot(&v);
    let e = lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--val",
        s(&v),
        "--past",
        "2",
        "--out",
        s(&v),
    ])
    .unwrap_err();
    assert!(e.contains("--val"), "{e}");
    assert_eq!(snapshot(&v), vb);
}

#[test]
fn diagnose_outputs_aimed_at_the_model_or_each_other_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let m = model(dir.path());
    let t = dir.path().join("t.csv");
    let before = snapshot(&m);
    let base = [
        "diagnose",
        "--model",
        s(&m),
        "--train",
        s(&t),
        "--val",
        s(&t),
    ];
    let mut args = base.to_vec();
    args.extend(["--fix", "--out", s(&m), "--json", s(&m)]);
    let e = lpvid(&args).unwrap_err();
    assert!(e.contains("--model") && e.contains("same file"), "{e}");
    assert_eq!(snapshot(&m), before);
    let o = dir.path().join("o.json");
    let mut args = base.to_vec();
    args.extend(["--fix", "--out", s(&o), "--json", s(&o)]);
    let e = lpvid(&args).unwrap_err();
    assert!(
        e.contains("--out") && e.contains("--json") && e.contains("same file"),
        "{e}"
    );
    assert!(!o.exists());
}

#[test]
fn a_failed_run_changes_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let m = model(dir.path());
    let t = dir.path().join("t.csv");
    let o = dir.path().join("o.json");
    std::fs::write(&o, "old").unwrap();
    let before = snapshot(&o);
    // --json in a missing directory: refused before any work, --out untouched
    let e = lpvid(&[
        "diagnose",
        "--model",
        s(&m),
        "--train",
        s(&t),
        "--val",
        s(&t),
        "--fix",
        "--out",
        s(&o),
        "--json",
        "/nonexistent-dir/r.json",
    ])
    .unwrap_err();
    assert!(
        e.contains("/nonexistent-dir") && e.contains("does not exist"),
        "{e}"
    );
    assert_eq!(snapshot(&o), before);
    // a directory that is a regular file
    let under_file = t.join("r.json");
    let e = lpvid(&[
        "diagnose",
        "--model",
        s(&m),
        "--train",
        s(&t),
        "--val",
        s(&t),
        "--json",
        s(&under_file),
        "--plots",
        s(&dir.path().join("plots")),
    ])
    .unwrap_err();
    assert!(e.contains("not a directory"), "{e}");
    assert!(!dir.path().join("plots").exists());
    // a failing fit leaves an existing --out as it was
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, "u1,y1,p1\n1,2,3\n2,3,nan\n").unwrap();
    let e = lpvid(&["pbsid", "--train", s(&bad), "--past", "2", "--out", s(&o)]).unwrap_err();
    assert!(e.contains("bad.csv:3"), "{e}");
    assert_eq!(snapshot(&o), before);
    // no temporary file is left behind anywhere
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
}

#[test]
fn simulate_out_equal_to_data_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let m = model(dir.path());
    let t = dir.path().join("t.csv");
    let before = snapshot(&t);
    let e = lpvid(&[
        "simulate",
        "--model",
        s(&m),
        "--data",
        s(&t),
        "--out",
        s(&t),
    ])
    .unwrap_err();
    assert!(e.contains("--data") && e.contains("same file"), "{e}");
    assert_eq!(snapshot(&t), before);
    let mb = snapshot(&m);
    let e = lpvid(&[
        "simulate",
        "--model",
        s(&m),
        "--data",
        s(&t),
        "--out",
        s(&m),
    ])
    .unwrap_err();
    assert!(e.contains("--model"), "{e}");
    assert_eq!(snapshot(&m), mb);
}

#[test]
fn non_regular_destinations_are_written_through() {
    let dir = tempfile::tempdir().unwrap();
    let t = train_copy(dir.path());
    // /dev/full: the write fails, the error says so, and the node stays a device
    let e = lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "2",
        "--out",
        "/dev/full",
    ])
    .unwrap_err();
    assert!(e.contains("/dev/full") && e.contains("cannot write"), "{e}");
    assert!(std::fs::metadata("/dev/full")
        .unwrap()
        .file_type()
        .is_char_device());
    // /dev/null: accepted, written through
    lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "2",
        "--out",
        "/dev/null",
    ])
    .unwrap();
    assert!(std::fs::metadata("/dev/null")
        .unwrap()
        .file_type()
        .is_char_device());
    // a FIFO: a reader gets the model, the FIFO stays a FIFO
    let fifo = dir.path().join("model.fifo");
    let ok = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success());
    if ok {
        let f2 = fifo.clone();
        let reader = std::thread::spawn(move || std::fs::read_to_string(f2).unwrap());
        lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&fifo)]).unwrap();
        let text = reader.join().unwrap();
        assert!(text.contains("\"lpv-ss\""), "{text}");
        assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    }
}

#[test]
fn a_symlinked_output_replaces_its_target_not_the_link() {
    let dir = tempfile::tempdir().unwrap();
    let t = train_copy(dir.path());
    let target = dir.path().join("real.json");
    std::fs::write(&target, "old").unwrap();
    let link = dir.path().join("link.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&link)]).unwrap();
    assert!(std::fs::symlink_metadata(&link)
        .unwrap()
        .file_type()
        .is_symlink());
    assert!(std::fs::read_to_string(&target).unwrap().contains("lpv-ss"));
}
