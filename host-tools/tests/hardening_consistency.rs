//! Issue 15, consistency of what is printed: the summary's numbers are the fit record's,
//! `--refine` and an unstable predictor are mentioned, diagnose warns on data that are not
//! held out, its stop line names the rule that blocked, its evidence does not contradict
//! itself, and the plots say what they show.

mod diagnose_support;

use std::path::Path;

use diagnose_support::{generate, planted, run_case};
use lpvid_host::cli::run;
use serde_json::Value;

fn lpvid(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut full = vec!["lpvid"];
    full.extend_from_slice(args);
    run(full, &mut out).map_err(|e| e.to_string())?;
    Ok(String::from_utf8(out).unwrap())
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `n` rows of a first-order LPV system with input offset `u0`.
fn rows(n: usize, u0: f64) -> String {
    let mut t = String::from("u1,y1,p1\n");
    let mut y = 0.0;
    for k in 0..n {
        let f = k as f64;
        let u = u0 + (0.7 * f).sin() + 0.3 * (2.1 * f).cos();
        let p = 0.5 + 0.4 * (0.1 * f).sin();
        y = 0.5 * y + p * u + 0.01 * ((k * 7919 % 1000) as f64 / 500.0 - 1.0);
        t.push_str(&format!("{u},{y},{p}\n"));
    }
    t
}

fn read_json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

#[test]
fn pbsid_summary_regressors_refine_and_unstable_predictor() {
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("t.csv");
    std::fs::write(&t, rows(400, 0.0)).unwrap();
    let m = dir.path().join("m.json");
    let text = lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "3",
        "--refine",
        "--out",
        s(&m),
    ])
    .unwrap();
    let fit = &read_json(&m)["fit"];
    let q = fit["regressors"].as_u64().unwrap();
    assert!(text.contains(&format!("q = {q} regressors")), "{text}");
    assert_eq!(fit["feedthrough_regressors"], 1);
    assert!(
        text.contains("--refine: output-error Levenberg-Marquardt"),
        "{text}"
    );
    let it = fit["refine"]["iterations"].as_u64().unwrap();
    assert!(text.contains(&format!("in {it} iterations")), "{text}");
    assert_eq!(fit["states"], fit["order"]);
    // a fit with an unstable one-step predictor is flagged
    let t = dir.path().join("s75.csv");
    std::fs::write(&t, rows(75, 0.0)).unwrap();
    let text = lpvid(&["pbsid", "--train", s(&t), "--past", "10", "--out", s(&m)]).unwrap();
    let rho = read_json(&m)["fit"]["stability_region"]["max_spectral_radius_over_box"]
        .as_f64()
        .unwrap();
    assert_eq!(
        rho >= 1.0,
        text.contains("UNSTABLE predictor"),
        "{rho}: {text}"
    );
}

#[test]
#[ignore = "long tier: make test-long"]
fn diagnose_warns_when_val_is_train_or_train_is_not_the_models() {
    let (plant, args) = planted("output-offset");
    let (train, val) = generate(&plant, 3);
    let dir = tempfile::tempdir().unwrap();
    let (tp, vp, mp) = (
        dir.path().join("t.csv"),
        dir.path().join("v.csv"),
        dir.path().join("m.json"),
    );
    train.write_csv(&tp).unwrap();
    val.write_csv(&vp).unwrap();
    let mut a = vec!["pbsid", "--train", s(&tp)];
    a.extend(args.iter());
    a.extend(["--out", s(&mp)]);
    lpvid(&a).unwrap();
    let rp = dir.path().join("r.json");
    let note = lpvid(&[
        "diagnose",
        "--model",
        s(&mp),
        "--train",
        s(&tp),
        "--val",
        s(&tp),
        "--json",
        s(&rp),
    ])
    .unwrap();
    assert!(
        note.contains("warning: --train and --val are the same data"),
        "{note}"
    );
    let notes = read_json(&rp)["notes"].to_string();
    assert!(
        notes.contains("--train and --val are the same data"),
        "{notes}"
    );
    // a copy of the training file is the same data too
    let copy = dir.path().join("copy.csv");
    std::fs::copy(&tp, &copy).unwrap();
    let note = lpvid(&[
        "diagnose",
        "--model",
        s(&mp),
        "--train",
        s(&tp),
        "--val",
        s(&copy),
    ])
    .unwrap();
    assert!(note.contains("identical content"), "{note}");
    // training on the validation file: not the model's training file
    let note = lpvid(&[
        "diagnose",
        "--model",
        s(&mp),
        "--train",
        s(&vp),
        "--val",
        s(&tp),
        "--json",
        s(&rp),
    ])
    .unwrap();
    assert!(
        note.contains("is not the file the model was identified on"),
        "{note}"
    );
    assert!(read_json(&rp)["notes"]
        .to_string()
        .contains("is not the file the model was identified on"));
    // the proper call has no warning
    let note = lpvid(&[
        "diagnose",
        "--model",
        s(&mp),
        "--train",
        s(&tp),
        "--val",
        s(&vp),
    ])
    .unwrap();
    assert!(!note.contains("warning"), "{note}");
}

#[test]
fn diagnose_report_agrees_with_itself() {
    // an input of one sign: sign(u1) would be the offset's regressor
    let dir = tempfile::tempdir().unwrap();
    let (tp, vp, mp) = (
        dir.path().join("t.csv"),
        dir.path().join("v.csv"),
        dir.path().join("m.json"),
    );
    std::fs::write(&tp, rows(600, 3.0)).unwrap();
    let val = rows(1200, 3.0);
    let val_rows: Vec<&str> = val.lines().collect();
    std::fs::write(&vp, format!("u1,y1,p1\n{}\n", val_rows[601..].join("\n"))).unwrap();
    lpvid(&["pbsid", "--train", s(&tp), "--past", "2", "--out", s(&mp)]).unwrap();
    let (rp, plots) = (dir.path().join("r.json"), dir.path().join("plots"));
    let note = lpvid(&[
        "diagnose",
        "--model",
        s(&mp),
        "--train",
        s(&tp),
        "--val",
        s(&vp),
        "--json",
        s(&rp),
        "--plots",
        s(&plots),
    ])
    .unwrap();
    let r = read_json(&rp);
    // the stop line is the JSON's
    let stopped = r["stopped"].as_str().unwrap();
    assert!(note.contains(&format!("Stopped: {stopped}.")), "{note}");
    if stopped.starts_with("nothing explains") {
        assert!(stopped.contains("not a finding because"), "{stopped}");
    }
    // sign(u1) is not tried as a separate regressor, and the report says why
    let step = &r["steps"][0];
    assert!(
        step["not_applicable"].to_string().contains("sign(u1)"),
        "{step}"
    );
    assert!(!step["variants_scored"].to_string().contains("sign(u1)"));
    // every cross-correlation's verdict is against the bound it prints
    for c in r["residual"]["free_run"]["cross"].as_array().unwrap() {
        let (m, b) = (c["max_abs"].as_f64().unwrap(), c["bound"].as_f64().unwrap());
        assert_eq!(c["significant"].as_bool().unwrap(), m > b, "{c}");
    }
    for f in r["findings"].as_array().unwrap() {
        for e in f["evidence"].as_array().unwrap() {
            let e = e.as_str().unwrap();
            if e.contains("largest |r|") {
                assert!(e.contains("significance bound"), "{e}");
            }
        }
    }
    // plots: the fit window is named, the bands have a legend, one panel is one panel wide
    let fit = std::fs::read_to_string(plots.join("fit.svg")).unwrap();
    assert!(fit.contains("last 300 of 600 samples"), "{}", &fit[..300]);
    let spec = std::fs::read_to_string(plots.join("spectrum.svg")).unwrap();
    assert!(spec.contains(r#"width="520""#));
    let acf = std::fs::read_to_string(plots.join("autocorrelation.svg")).unwrap();
    assert!(acf.contains("95 % band"));
    if let Ok(cc) = std::fs::read_to_string(plots.join("cross-correlation.svg")) {
        assert!(cc.contains("Bartlett 95 % band") && cc.contains("significance bound"));
    }
    for name in ["fit.svg", "autocorrelation.svg", "spectrum.svg"] {
        let text = std::fs::read_to_string(plots.join(name)).unwrap();
        let panels = text.matches("font-weight").count().max(1);
        if panels == 1 {
            assert!(text.contains(r#"width="520""#), "{name}");
        }
    }
}

#[test]
fn coloured_noise_fix_records_the_state_dimension() {
    let case = run_case("coloured-noise", 11);
    let fit = &case.outcome.model.fit;
    assert_eq!(case.outcome.report.applied[0].effect, "coloured-noise");
    let lpvid_host::model::ModelKind::Ss(ss) = &case.outcome.model.kind else {
        panic!("an lpv-ss model");
    };
    // "order" is the plant order the refits use, "states" the model's state dimension
    assert_eq!(fit["states"].as_u64().unwrap() as usize, ss.n(), "{fit}");
    let order = fit["order"].as_u64().unwrap() as usize;
    if fit["noise_model"].is_null() {
        assert_eq!(ss.n(), order, "{fit}");
    } else {
        assert!(ss.n() > order, "{fit}");
    }
}

#[test]
fn a_sparse_fit_is_recorded_as_sparse() {
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("t.csv");
    std::fs::write(&t, rows(300, 0.0)).unwrap();
    let m = dir.path().join("m.json");
    let json = lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "2",
        "--reg",
        "bpdn-aic",
        "--out",
        s(&m),
        "--json",
    ])
    .unwrap();
    let fit = &read_json(&m)["fit"];
    assert_eq!(fit["solver"], "sparse", "{fit}");
    assert!(fit["solver_reason"].as_str().unwrap().contains("sparse"));
    let v: Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v["solver"], "sparse");
}

#[test]
fn diagnose_reports_its_candidate_progress() {
    use lpvid_host::diagnose::{diagnose_with_progress, Options};
    use std::sync::atomic::{AtomicUsize, Ordering};
    let (plant, args) = planted("output-offset");
    let (train, val) = generate(&plant, 5);
    let dir = tempfile::tempdir().unwrap();
    let (tp, mp) = (dir.path().join("t.csv"), dir.path().join("m.json"));
    train.write_csv(&tp).unwrap();
    let mut a = vec!["pbsid", "--train", s(&tp)];
    a.extend(args.iter());
    a.extend(["--out", s(&mp)]);
    lpvid(&a).unwrap();
    let model = lpvid_host::model::ModelFile::read(&mp).unwrap();
    let (calls, last, total) = (
        AtomicUsize::new(0),
        AtomicUsize::new(0),
        AtomicUsize::new(0),
    );
    let progress = |done: usize, of: usize| {
        calls.fetch_add(1, Ordering::Relaxed);
        last.fetch_max(done, Ordering::Relaxed);
        total.store(of, Ordering::Relaxed);
        assert!(done >= 1 && done <= of);
    };
    let out =
        diagnose_with_progress(&model, &train, &val, &Options::default(), Some(&progress)).unwrap();
    let variants = out.report.steps[0].variants;
    assert_eq!(calls.load(Ordering::Relaxed), variants);
    assert_eq!(last.load(Ordering::Relaxed), variants);
    assert_eq!(total.load(Ordering::Relaxed), variants);
}

#[test]
fn progress_stays_off_the_output_and_quiet_is_global() {
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("t.csv");
    std::fs::write(&t, rows(300, 0.0)).unwrap();
    let m = dir.path().join("m.json");
    for args in [
        vec![
            "--quiet",
            "pbsid",
            "--train",
            s(&t),
            "--past",
            "2",
            "--out",
            s(&m),
        ],
        vec![
            "pbsid",
            "--train",
            s(&t),
            "--past",
            "2",
            "--out",
            s(&m),
            "--quiet",
        ],
        vec!["pbsid", "--train", s(&t), "--past", "2", "--out", s(&m)],
    ] {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_lpvid"))
            .args(&args)
            .output()
            .unwrap();
        assert!(o.status.success());
        // stderr is a pipe here: no bar, no spinner, no carriage returns
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains('\r') && !err.contains("fitting"), "{err}");
        assert!(String::from_utf8_lossy(&o.stdout).contains("model written to"));
    }
}
