//! `lpvid pbsid --stats A --stats B`: one fit from the statistics of several experiments (or
//! devices), merged; the same model as the statistics merged in memory, and a good model.

use lpvid::PbsidDims;
use lpvid_host::cli::run;
use lpvid_host::data::Dataset;
use lpvid_host::model::{ModelFile, SignalMap};
use lpvid_host::pbsid::{Order, PbsidOptions, Reg};
use lpvid_host::pipeline::score;
use lpvid_host::simulate::Mode;
use lpvid_host::statistics::Statistics;

const TRAIN: &[u8] = include_bytes!("../../fixtures/b1-train.csv");
const VAL: &[u8] = include_bytes!("../../fixtures/b1-val.csv");

/// The B1 training file as two experiments (first and second half), each one statistics.
fn halves() -> (Statistics, Statistics) {
    let ds = Dataset::parse("b1-train.csv", TRAIN).unwrap();
    let sig = SignalMap::default_for(&ds).unwrap().evaluate(&ds).unwrap();
    let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), 3).unwrap();
    let half = sig.len() / 2;
    let part = |a: usize, b: usize| lpvid_host::lpvss::Signals {
        u: sig.u.rows(a, b - a).into_owned(),
        y: sig.y.rows(a, b - a).into_owned(),
        p: sig.p.rows(a, b - a).into_owned(),
    };
    let mut s1 = Statistics::new(dims).unwrap();
    s1.add_signals(&part(0, half), "first half").unwrap();
    let mut s2 = Statistics::new(dims).unwrap();
    s2.add_signals(&part(half, sig.len()), "second half")
        .unwrap();
    (s1, s2)
}

#[test]
fn merged_statistics_files_fit_one_model() {
    let dir = tempfile::tempdir().unwrap();
    let (s1, s2) = halves();
    let a = dir.path().join("a.lpvs");
    let b = dir.path().join("b.lpvs");
    std::fs::write(&a, s1.to_bytes()).unwrap();
    std::fs::write(&b, s2.to_bytes()).unwrap();
    let out = dir.path().join("m.json");
    let mut text = Vec::new();
    run(
        [
            "lpvid",
            "pbsid",
            "--stats",
            a.to_str().unwrap(),
            "--stats",
            b.to_str().unwrap(),
            "--order",
            "4",
            "--out",
            out.to_str().unwrap(),
        ],
        &mut text,
    )
    .unwrap();
    let text = String::from_utf8(text).unwrap();
    assert!(text.contains("2 files, 2 experiments"), "{text}");
    // the same model as the statistics merged in memory
    let mut merged = s1.clone();
    merged.merge(&s2).unwrap();
    let mut opts = PbsidOptions::new(3);
    opts.order = Order::Fixed(4);
    opts.reg = Reg::TikhonovGcv; // the command line's default
    let (mem, _) = merged.identify(&opts).unwrap();
    let file = ModelFile::read(&out).unwrap();
    assert_eq!(file.to_json_string(), mem.to_json_string());
    // and a good model of B1 on fresh data (the windows at the seam are simply absent)
    let val = Dataset::parse("b1-val.csv", VAL).unwrap();
    let sc = score(&file, &val, Mode::FreeRun).unwrap();
    assert!(sc.vaf_mean > 99.0, "VAF {}", sc.vaf_mean);
}

#[test]
fn statistics_files_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let (s1, _) = halves();
    let a = dir.path().join("a.lpvs");
    let mut bytes = s1.to_bytes();
    std::fs::write(&a, &bytes).unwrap();
    let out = dir.path().join("m.json");
    // a past window that disagrees with the statistics
    let e = run(
        [
            "lpvid",
            "pbsid",
            "--stats",
            a.to_str().unwrap(),
            "--past",
            "4",
            "--out",
            out.to_str().unwrap(),
        ],
        &mut Vec::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("past window 3"), "{e}");
    assert!(!out.exists());
    // a damaged file names itself
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x55;
    let bad = dir.path().join("bad.lpvs");
    std::fs::write(&bad, &bytes).unwrap();
    let e = run(
        [
            "lpvid",
            "pbsid",
            "--stats",
            bad.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &mut Vec::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("bad.lpvs"), "{e}");
    assert!(!out.exists());
    // --stats and --train do not mix
    let e = run(
        [
            "lpvid",
            "pbsid",
            "--stats",
            a.to_str().unwrap(),
            "--train",
            "x.csv",
            "--out",
            out.to_str().unwrap(),
        ],
        &mut Vec::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("--train"), "{e}");
}
