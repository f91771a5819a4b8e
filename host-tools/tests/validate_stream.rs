//! `lpvid validate` and `lpvid simulate` in constant memory: the streamed score and the
//! streamed output CSV (host-tools/src/stream.rs) equal the in-memory ones, whatever the
//! chunk size, for the free run and the predictor, from the zero or an estimated initial
//! state, with delayed factors in the signal map; what the streamed path refuses falls back;
//! a bad row in a later chunk gives the in-memory error and writes nothing.

use std::path::{Path, PathBuf};

use lpvid_host::cli;
use lpvid_host::data::Dataset;
use lpvid_host::lpvss::Signals;
use lpvid_host::model::{Factor, FactorFn, ModelFile, ModelKind, SignalMap};
use lpvid_host::pbsid::{fit, PbsidOptions};
use lpvid_host::simulate::{run, score_from, Mode, Score, X0};
use lpvid_host::stream::{
    score_streaming_chunks, simulate_streaming_chunks, CHUNK_ROWS, STREAM_MIN_BYTES,
};
use lpvid_host::systems;

/// A model fitted by PBSID (p = 3) on a short B1 record of `seed`: an imperfect model, so
/// the scores are not all 100.
fn b1_model(seed: u64, signals: SignalMap) -> ModelFile {
    let exp = systems::b1(600, 0.1, seed);
    let f = fit(&exp.train, &PbsidOptions::new(3)).unwrap();
    ModelFile {
        kind: ModelKind::Ss(f.model),
        signals,
        fit: serde_json::json!({}),
    }
}

fn write_data(dir: &Path, name: &str, sig: &Signals) -> PathBuf {
    let path = dir.join(name);
    Dataset::from_signals(sig, name).write_csv(&path).unwrap();
    path
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-300)
}

/// The worst relative difference of two scores over VAF and BFR, outputs and means; the
/// other fields must be equal.
fn score_diff(a: &Score, b: &Score) -> f64 {
    assert_eq!(
        (&a.file, a.mode, a.skipped, a.diverged_at),
        (&b.file, b.mode, b.skipped, b.diverged_at)
    );
    assert_eq!(a.vaf.len(), b.vaf.len());
    let mut worst = rel(a.vaf_mean, b.vaf_mean).max(rel(a.bfr_mean, b.bfr_mean));
    for j in 0..a.vaf.len() {
        worst = worst
            .max(rel(a.vaf[j], b.vaf[j]))
            .max(rel(a.bfr[j], b.bfr[j]));
    }
    worst
}

/// The standard B1 map with the first scheduling signal read one sample late and the second
/// input two samples late (delayed factors cross the chunk boundaries).
fn delayed_map() -> SignalMap {
    let mut map = SignalMap::standard(2, 3, 3);
    map.scheduling[1][0].delay = 1;
    map.inputs[1][0].delay = 2;
    map
}

#[test]
fn streamed_scores_equal_the_in_memory_ones() {
    let dir = tempfile::tempdir().unwrap();
    let mut worst: f64 = 0.0;
    let mut cases = 0;
    for seed in [3u64, 41, 977] {
        let data = systems::b1(900, 0.1, seed + 1000).val;
        let path = write_data(dir.path(), &format!("v{seed}.csv"), &data);
        let ds = Dataset::read_csv(&path).unwrap();
        for map in [SignalMap::standard(2, 3, 3), delayed_map()] {
            let model = b1_model(seed, map);
            for mode in [Mode::FreeRun, Mode::Predictor] {
                for x0 in [
                    X0::Zero,
                    X0::Estimate { samples: 50 },
                    X0::Estimate { samples: 1200 },
                ] {
                    let mem = score_from(&model, &ds, mode, x0).unwrap();
                    // the estimate must matter, or the test would not see it carried
                    if x0 == (X0::Estimate { samples: 50 }) {
                        let zero = score_from(&model, &ds, mode, X0::Zero).unwrap();
                        assert_ne!(zero.vaf, mem.vaf);
                    }
                    for chunk in [1, 7, 64, 333, 5000] {
                        let (st, rows) =
                            score_streaming_chunks(&model, &path, mode, x0, chunk).unwrap();
                        assert_eq!(rows, 900);
                        let d = score_diff(&mem, &st);
                        assert!(
                            d <= 1e-12,
                            "seed {seed} {mode:?} {x0:?} chunk {chunk}: {d:e}\n{mem:?}\n{st:?}"
                        );
                        worst = worst.max(d);
                        cases += 1;
                    }
                }
            }
        }
    }
    println!("{cases} cases, worst relative difference {worst:e}");
}

#[test]
fn streamed_simulation_writes_the_in_memory_csv() {
    let dir = tempfile::tempdir().unwrap();
    for seed in [5u64, 77] {
        let data = systems::b1(700, 0.1, seed + 2000).val;
        let path = write_data(dir.path(), &format!("d{seed}.csv"), &data);
        let mut ds = Dataset::read_csv(&path).unwrap();
        // a data column named like an output, read as the first input: the output's name
        // gets '_'
        ds.names.push("yhat1".into());
        ds.cols.push(ds.cols[0].iter().map(|v| 0.5 * v).collect());
        let path = dir.path().join(format!("n{seed}.csv"));
        ds.write_csv(&path).unwrap();
        let ds = Dataset::read_csv(&path).unwrap();
        let mut map = delayed_map();
        map.inputs[0][0].col = "yhat1".into();
        let model = b1_model(seed, map);
        for mode in [Mode::FreeRun, Mode::Predictor] {
            for x0 in [X0::Zero, X0::Estimate { samples: 50 }] {
                let yhat = run(&model, &ds, mode, x0).unwrap().yhat;
                let mut whole = ds.clone();
                for j in 0..yhat.ncols() {
                    let mut name = format!("yhat{}", j + 1);
                    while whole.names.contains(&name) {
                        name.push('_');
                    }
                    whole.names.push(name);
                    whole.cols.push(yhat.column(j).iter().copied().collect());
                }
                let out = dir.path().join("out.csv");
                let expect = whole.to_csv_bytes(&out).unwrap();
                for chunk in [1, 9, 256, 10_000] {
                    let s = simulate_streaming_chunks(&model, &path, mode, x0, &out, chunk)
                        .unwrap()
                        .unwrap();
                    assert_eq!((s.rows, s.outputs), (700, 3));
                    s.staged.commit().unwrap();
                    let got = std::fs::read(&out).unwrap();
                    assert!(got == expect, "seed {seed} {mode:?} {x0:?} chunk {chunk}");
                    std::fs::remove_file(&out).unwrap();
                }
            }
        }
    }
}

#[test]
fn own_output_feedback_streams_and_the_sample_index_falls_back() {
    let dir = tempfile::tempdir().unwrap();
    let data = systems::b1(600, 0.1, 9).val;
    let path = write_data(dir.path(), "d.csv", &data);
    let ds = Dataset::read_csv(&path).unwrap();
    let out = dir.path().join("o.csv");
    let mut finite = 0;
    let mut worst: f64 = 0.0;
    // a scheduling function and an input that read the model's own outputs, one and three
    // samples back (more than a chunk of 1 or 2 rows)
    for (seed, d1, d2) in [(2u64, 1, 3), (5, 3, 1), (8, 2, 2)] {
        let mut map = SignalMap::standard(2, 3, 3);
        // p3 cos(y1(k - d1)) and u2 cos(0.5 y2(k - d2)): bounded by the data's own values
        let mut f = Factor::col("y1");
        f.delay = d1;
        f.func = Some(FactorFn::Cos);
        map.scheduling[3] = vec![Factor::col("p3"), f];
        let mut g = Factor::col("y2");
        g.delay = d2;
        g.func = Some(FactorFn::Cos);
        g.omega = Some(0.5);
        map.inputs[1].push(g);
        let model = b1_model(seed, map);
        for mode in [Mode::FreeRun, Mode::Predictor] {
            for x0 in [X0::Zero, X0::Estimate { samples: 50 }] {
                let mem = score_from(&model, &ds, mode, x0).unwrap();
                finite += usize::from(mem.diverged_at.is_none());
                let yhat = run(&model, &ds, mode, x0).unwrap().yhat;
                for chunk in [1, 2, 37, 1000] {
                    let (st, _) = score_streaming_chunks(&model, &path, mode, x0, chunk).unwrap();
                    let d = score_diff(&mem, &st);
                    assert!(
                        d <= 1e-12,
                        "seed {seed} {mode:?} {x0:?} chunk {chunk}: {d:e}"
                    );
                    worst = worst.max(d);
                    let sim = simulate_streaming_chunks(&model, &path, mode, x0, &out, chunk);
                    match sim.unwrap() {
                        Ok(s) => {
                            assert!(mem.diverged_at.is_none());
                            s.staged.commit().unwrap();
                            let got = Dataset::read_csv(&out).unwrap();
                            for j in 0..3 {
                                let col = got.column(&format!("yhat{}", j + 1)).unwrap();
                                assert!(col.iter().zip(yhat.column(j).iter()).all(|(a, b)| a == b));
                            }
                        }
                        Err(lpvid_host::stream::SimulateFailure::Diverged(k)) => {
                            assert_eq!(Some(k), mem.diverged_at)
                        }
                        Err(e) => panic!("{e:?}"),
                    }
                }
            }
        }
    }
    println!("feedback: {finite} of 12 runs finite, worst relative difference {worst:e}");
    assert!(finite >= 9, "{finite}");
    // the sample index
    let mut map = SignalMap::standard(2, 3, 3);
    map.scheduling[3] = vec![Factor::col("k")];
    let model = b1_model(2, map);
    assert!(score_streaming_chunks(&model, &path, Mode::Predictor, X0::Zero, 50).is_none());
    assert!(simulate_streaming_chunks(&model, &path, Mode::FreeRun, X0::Zero, &out, 50).is_none());
    // nothing was left behind
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 2);
}

#[test]
fn a_diverging_run_is_found_at_the_same_sample_and_writes_nothing() {
    use lpvid_host::simulate::diverged_at;
    use lpvid_host::stream::SimulateFailure;
    let dir = tempfile::tempdir().unwrap();
    let data = systems::b1(2000, 0.1, 12).val;
    let path = write_data(dir.path(), "d.csv", &data);
    let ds = Dataset::read_csv(&path).unwrap();
    let out = dir.path().join("o.csv");
    std::fs::write(&out, "keep").unwrap();
    for (seed, gain) in [(1u64, 1.5), (4, 2.0), (6, 4.0)] {
        let mut model = b1_model(seed, SignalMap::standard(2, 3, 3));
        let ModelKind::Ss(ss) = &mut model.kind else {
            panic!()
        };
        ss.a.iter_mut().for_each(|a| *a *= gain);
        for mode in [Mode::FreeRun, Mode::Predictor] {
            let mem = score_from(&model, &ds, mode, X0::Zero).unwrap();
            let k = diverged_at(&run(&model, &ds, mode, X0::Zero).unwrap().yhat);
            assert_eq!(mem.diverged_at, k);
            for chunk in [3, 100] {
                let (st, _) = score_streaming_chunks(&model, &path, mode, X0::Zero, chunk).unwrap();
                assert!(score_diff(&mem, &st) <= 1e-12, "{mem:?} {st:?}");
                let sim = simulate_streaming_chunks(&model, &path, mode, X0::Zero, &out, chunk);
                match (sim.unwrap(), k) {
                    (Err(SimulateFailure::Diverged(a)), Some(b)) => assert_eq!(a, b),
                    (Ok(s), None) => drop(s.staged),
                    (r, k) => panic!("{r:?} {k:?}"),
                }
            }
        }
    }
    // the free run diverged somewhere (the test sees the divergence)
    let mut model = b1_model(1, SignalMap::standard(2, 3, 3));
    if let ModelKind::Ss(ss) = &mut model.kind {
        ss.a.iter_mut().for_each(|a| *a *= 4.0);
    }
    assert!(score_from(&model, &ds, Mode::FreeRun, X0::Zero)
        .unwrap()
        .diverged_at
        .is_some());
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "keep");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
}

fn cli(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut all = vec!["lpvid"];
    all.extend_from_slice(args);
    cli::run(all, &mut out)
        .map(|_| String::from_utf8(out).unwrap())
        .map_err(|e| e.to_string())
}

#[test]
fn the_cli_streams_large_files_with_the_same_results_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let data = systems::b1(30_000, 0.1, 31).val;
    let path = write_data(dir.path(), "big.csv", &data);
    let size = std::fs::metadata(&path).unwrap().len();
    assert!(
        size >= STREAM_MIN_BYTES && 30_000 > 3 * CHUNK_ROWS,
        "{size}"
    );
    let model_path = dir.path().join("m.json");
    let model = b1_model(8, delayed_map());
    model.write(&model_path).unwrap();
    let ds = Dataset::read_csv(&path).unwrap();
    let (m, d) = (model_path.to_str().unwrap(), path.to_str().unwrap());
    // validate: the same JSON score
    for (pred, x0) in [(false, "zero"), (true, "estimate"), (false, "estimate")] {
        let mut args = vec!["validate", "--model", m, "--data", d, "--x0", x0, "--json"];
        if pred {
            args.push("--predictor");
        }
        let got: serde_json::Value = serde_json::from_str(&cli(&args).unwrap()).unwrap();
        let mode = if pred { Mode::Predictor } else { Mode::FreeRun };
        let x = if x0 == "zero" {
            X0::Zero
        } else {
            X0::Estimate { samples: 50 }
        };
        let mem = score_from(&model, &ds, mode, x).unwrap();
        let mem = serde_json::to_value(&mem).unwrap();
        // the human summary counts the rows as the in-memory one
        args.pop_if(|a| *a == "--predictor");
        args.pop();
        let text = cli(&args[..]).unwrap();
        let rows_said = format!("scored on the other {}", 30_000 - 50);
        assert_eq!(text.contains(&rows_said), x0 == "estimate", "{text}");
        for key in ["file", "mode", "skipped", "diverged_at"] {
            assert_eq!(got["score"][key], mem[key], "{key}");
        }
        for key in ["vaf", "bfr"] {
            for (a, b) in got["score"][key]
                .as_array()
                .unwrap()
                .iter()
                .zip(mem[key].as_array().unwrap())
            {
                let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
                assert!(rel(a, b) <= 1e-12, "{key} {a} {b}");
            }
        }
    }
    // simulate: the in-memory bytes
    let out = dir.path().join("sim.csv");
    let o = out.to_str().unwrap();
    let said = cli(&["simulate", "--model", m, "--data", d, "--out", o]).unwrap();
    assert!(
        said.starts_with("wrote 30000 rows with 3 simulated outputs"),
        "{said}"
    );
    let yhat = run(&model, &ds, Mode::FreeRun, X0::Zero).unwrap().yhat;
    let mut whole = ds.clone();
    for j in 0..3 {
        whole.names.push(format!("yhat{}", j + 1));
        whole.cols.push(yhat.column(j).iter().copied().collect());
    }
    assert!(std::fs::read(&out).unwrap() == whole.to_csv_bytes(&out).unwrap());
    // a bad value in a late chunk: the in-memory error (file, line, column), nothing written
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<&str> = text.lines().collect();
    let bad_line = lines[25_000].replacen(',', ",x", 2);
    lines[25_000] = &bad_line;
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, lines.join("\n")).unwrap();
    let b = bad.to_str().unwrap();
    let expect = Dataset::read_csv(&bad).unwrap_err().to_string();
    assert!(expect.contains("25001"), "{expect}");
    let err = cli(&["validate", "--model", m, "--data", b]).unwrap_err();
    assert_eq!(err, expect);
    std::fs::write(&out, "keep").unwrap();
    let err = cli(&["simulate", "--model", m, "--data", b, "--out", o]).unwrap_err();
    assert_eq!(err, expect);
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "keep");
    // no output may replace an input
    let err = cli(&["simulate", "--model", m, "--data", d, "--out", d]).unwrap_err();
    assert!(err.contains("refusing to overwrite an input"), "{err}");
    let mut left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["bad.csv", "big.csv", "m.json", "sim.csv"]);
}
