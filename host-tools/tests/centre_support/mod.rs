//! The scheduling centre of `lpvid pbsid` on plant families (used by the release test
//! `scheduling_centre` and the example `scheduling_offset`): every family plant with a
//! scheduling signal, its p1 moved by an offset in the training and validation records,
//! identified with `--centre zero`, `mean` and `auto`, and scored by the validation record's
//! normalised free-run error from an estimated initial state (`pipeline::held_out_error`).

use lpvid_host::data::Dataset;
use lpvid_host::diagnose::plants::{family_case, FamilyCase, FAMILY_EFFECTS};
use lpvid_host::model::ModelFile;
use lpvid_host::pipeline::held_out_error;

/// The error scored when a fit fails or its free run diverges.
pub const FAILED: f64 = 10.0;

/// The centres compared, in the order of [`errors`]' entries.
pub const CENTRES: [&str; 3] = ["zero", "mean", "auto"];

/// The family plants with a scheduling signal among seeds `first..first + seeds` of every
/// effect (records of `n` samples).
pub fn scheduled_cases(seeds: u64, n: usize, first: u64) -> Vec<FamilyCase> {
    let mut cases = Vec::new();
    for effect in FAMILY_EFFECTS {
        for seed in first..first + seeds {
            match family_case(effect, seed, n) {
                Ok(c) if c.train.names.iter().any(|n| n == "p1") => cases.push(c),
                _ => {}
            }
        }
    }
    cases
}

fn shifted(ds: &Dataset, offset: f64) -> Dataset {
    let mut d = ds.clone();
    if let Some(j) = d.names.iter().position(|n| n == "p1") {
        for v in &mut d.cols[j] {
            *v += offset;
        }
    }
    d
}

/// Validation error of the model `lpvid pbsid` fits to `train` with `args` and `--centre`.
fn error(train: &Dataset, val: &Dataset, args: &[String], centre: &str) -> f64 {
    let Ok(dir) = tempfile::tempdir() else {
        return FAILED;
    };
    let tp = dir.path().join("train.csv");
    let mp = dir.path().join("model.json");
    if train.write_csv(&tp).is_err() {
        return FAILED;
    }
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(args.iter().cloned());
    cli.extend(["--centre".into(), centre.into()]);
    cli.extend(["--out".to_string(), mp.display().to_string()]);
    if lpvid_host::cli::run(cli, &mut Vec::new()).is_err() {
        return FAILED;
    }
    let Ok(model) = ModelFile::read(&mp) else {
        return FAILED;
    };
    match held_out_error(&model, val) {
        Ok(e) if e.is_finite() => e.min(FAILED),
        _ => FAILED,
    }
}

/// The validation errors of each case at [`CENTRES`] with p1 moved by `offset`, on `threads`
/// threads (in the order of `cases`).
pub fn errors(cases: &[FamilyCase], offset: f64, threads: usize) -> Vec<[f64; 3]> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let rows = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|sc| {
        for _ in 0..threads.max(1) {
            sc.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(c) = cases.get(i) else { break };
                let (t, v) = (shifted(&c.train, offset), shifted(&c.val, offset));
                let mut e = [0.0; 3];
                for (k, centre) in CENTRES.iter().enumerate() {
                    e[k] = error(&t, &v, &c.pbsid_args, centre);
                }
                rows.lock().unwrap_or_else(|p| p.into_inner()).push((i, e));
            });
        }
    });
    let mut rows = rows.into_inner().unwrap_or_else(|p| p.into_inner());
    rows.sort_by_key(|r| r.0);
    rows.into_iter().map(|r| r.1).collect()
}

/// The mean over cases of log10 of the error at centre `k` of [`CENTRES`].
pub fn mean_log10(rows: &[[f64; 3]], k: usize) -> f64 {
    rows.iter().map(|e| e[k].max(1e-12).log10()).sum::<f64>() / rows.len().max(1) as f64
}
