//! The family benchmark of `lpvid diagnose` (issue 14): random plants per planted effect
//! ([`lpvid_host::diagnose::plants`]), each identified with `lpvid pbsid` as a user would and
//! diagnosed with `--fix` (one step); the confusion matrix (for each planted effect, how often
//! each effect was named first) and the error ratio after the fix. Shared by the release test
//! in `diagnose_planted.rs` and `examples/diagnose_family.rs`.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::fmt::Write as _;

use lpvid_host::diagnose::plants::{family_case, FamilyCase};
use lpvid_host::diagnose::{diagnose, Options};
use lpvid_host::model::ModelFile;
use lpvid_host::simulate::{simulate, Mode};

/// One diagnosed family plant.
#[derive(Debug, Clone)]
pub struct FamilyRun {
    /// Planted effect.
    pub planted: String,
    /// Seed.
    pub seed: u64,
    /// Effect named first (above the noise threshold), or "none".
    pub named: String,
    /// Held-out error (free-run MSE; one-step for a noise model) before / after --fix
    /// (1 when nothing was applied).
    pub ratio: f64,
    /// What was drawn.
    pub description: String,
}

fn mse(model: &ModelFile, ds: &lpvid_host::data::Dataset, mode: Mode) -> f64 {
    match simulate(model, ds, mode) {
        Ok((y, yh)) => {
            let e = &y - &yh;
            let v = e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64;
            if v.is_finite() {
                v
            } else {
                f64::INFINITY
            }
        }
        Err(_) => f64::INFINITY,
    }
}

/// The user's model of a family case: `lpvid pbsid` on its training record with the case's
/// options (the command line a user runs), read back from its output file.
fn user_model(case: &FamilyCase) -> Result<ModelFile, String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let tp = dir.path().join("train.csv");
    let mp = dir.path().join("model.json");
    case.train.write_csv(&tp).map_err(|e| e.to_string())?;
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(case.pbsid_args.iter().cloned());
    cli.extend(["--out".to_string(), mp.display().to_string()]);
    lpvid_host::cli::run(cli, &mut Vec::new()).map_err(|e| e.to_string())?;
    ModelFile::read(&mp).map_err(|e| e.to_string())
}

/// Draw the plant of `effect` with `seed` (records of `n` samples), identify it with the
/// user's `lpvid pbsid` options and diagnose it with `--fix` (one step): the user's model and
/// the outcome, for tests that look into the report.
pub fn diagnose_one(
    effect: &str,
    seed: u64,
    n: usize,
) -> (ModelFile, lpvid_host::diagnose::Outcome) {
    let case = family_case(effect, seed, n).unwrap();
    let model = user_model(&case).unwrap();
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 2,
    };
    let out = diagnose(&model, &case.train, &case.val, &opts).unwrap();
    (model, out)
}

/// Draw, identify and diagnose the plant of `effect` with `seed` (records of `n` samples).
pub fn run_one(effect: &str, seed: u64, n: usize) -> FamilyRun {
    run_one_with(effect, seed, n, None)
}

/// [`run_one`] with the validation (held-out) record cut to its first `val_len` samples (a
/// short held-out record, as the cascaded tanks' 205 samples).
pub fn run_one_with(effect: &str, seed: u64, n: usize, val_len: Option<usize>) -> FamilyRun {
    let mut case = family_case(effect, seed, n).unwrap();
    if let Some(v) = val_len {
        for c in case.val.cols.iter_mut() {
            c.truncate(v);
        }
    }
    let fail = |why: String| FamilyRun {
        planted: effect.to_string(),
        seed,
        named: format!("error: {why}"),
        ratio: 1.0,
        description: case.description.clone(),
    };
    let model = match user_model(&case) {
        Ok(m) => m,
        Err(e) => return fail(e),
    };
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 1,
    };
    let out = match diagnose(&model, &case.train, &case.val, &opts) {
        Ok(o) => o,
        Err(e) => return fail(e.to_string()),
    };
    let r = &out.report;
    if std::env::var("LPVID_FAMILY_VERBOSE").is_ok() {
        // per-plant detail: the findings (with the rule that blocked each) and the
        // output-nonlinearity variants, for tracing a miss to its cause
        let mut v = format!("{effect} seed {seed}: {}\n", case.description);
        for f in r.findings.iter().take(4) {
            let _ = writeln!(
                v,
                "    finding {} ({}) explained {:.3} p {:.1e} rep {:?} sig {} blocked {:?}",
                f.effect,
                f.detail,
                f.explained,
                f.p_value,
                f.replication,
                f.significant,
                f.blocked_by
            );
            for e in f
                .evidence
                .iter()
                .filter(|e| e.contains("larger past window"))
            {
                let _ = writeln!(v, "      {e}");
            }
        }
        for s in r.steps.iter().take(1).flat_map(|st| &st.variants_scored) {
            if s.effect == "output-nonlinearity" || s.explained > 0.05 {
                let _ = writeln!(
                    v,
                    "    variant {} {} explained {:.3} p {:.1e} {:?}",
                    s.effect, s.detail, s.explained, s.p_value, s.error
                );
            }
        }
        print!("{v}");
    }
    let named = r
        .findings
        .first()
        .filter(|f| f.significant)
        .map_or("none".to_string(), |f| f.effect.to_string());
    let ratio = match r.applied.first() {
        Some(a) => {
            let mode = if a.residual == "one-step" {
                Mode::Predictor
            } else {
                Mode::FreeRun
            };
            mse(&model, &case.val, mode) / mse(&out.model, &case.val, mode).max(1e-300)
        }
        None => 1.0,
    };
    FamilyRun {
        planted: effect.to_string(),
        seed,
        named,
        ratio,
        description: case.description,
    }
}

/// Run every (effect, seed) on `threads` threads.
pub fn run_family(effects: &[&str], seeds: &[u64], n: usize, threads: usize) -> Vec<FamilyRun> {
    run_family_with(effects, seeds, n, threads, None)
}

/// [`run_family`] with held-out records of `val_len` samples ([`run_one_with`]).
pub fn run_family_with(
    effects: &[&str],
    seeds: &[u64],
    n: usize,
    threads: usize,
    val_len: Option<usize>,
) -> Vec<FamilyRun> {
    let jobs: Vec<(String, u64)> = effects
        .iter()
        .flat_map(|e| seeds.iter().map(move |s| (e.to_string(), *s)))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let out = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..threads.max(1) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((e, seed)) = jobs.get(i) else { break };
                let r = run_one_with(e, *seed, n, val_len);
                out.lock().unwrap().push(r);
            });
        }
    });
    let mut v = out.into_inner().unwrap();
    v.sort_by(|a, b| (&a.planted, a.seed).cmp(&(&b.planted, b.seed)));
    v
}

/// Per planted effect: (recall = named first correctly, or "none" for clean; median error
/// ratio; min; max; runs).
pub fn summary(runs: &[FamilyRun]) -> BTreeMap<String, (f64, f64, f64, f64, usize)> {
    let mut by: BTreeMap<String, Vec<&FamilyRun>> = BTreeMap::new();
    for r in runs {
        by.entry(r.planted.clone()).or_default().push(r);
    }
    by.into_iter()
        .map(|(e, rs)| {
            let want = if e == "clean" { "none" } else { e.as_str() };
            let hits = rs.iter().filter(|r| r.named == want).count();
            let mut ratios: Vec<f64> = rs.iter().map(|r| r.ratio).collect();
            ratios.sort_by(f64::total_cmp);
            let med = ratios[ratios.len() / 2];
            (
                e.clone(),
                (
                    hits as f64 / rs.len() as f64,
                    med,
                    ratios[0],
                    ratios[ratios.len() - 1],
                    rs.len(),
                ),
            )
        })
        .collect()
}

/// The confusion matrix as a markdown table (rows: planted; columns: named first), then
/// recall and the error ratio after --fix (median [min, max]).
pub fn matrix(runs: &[FamilyRun]) -> String {
    let mut named: Vec<String> = runs.iter().map(|r| r.named.clone()).collect();
    named.sort();
    named.dedup();
    let mut planted: Vec<String> = runs.iter().map(|r| r.planted.clone()).collect();
    planted.sort();
    planted.dedup();
    let sum = summary(runs);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| planted \\ named first | {} | recall | error ratio median [min, max] |",
        named.join(" | ")
    );
    let _ = writeln!(s, "|---|{}---|---|", "---|".repeat(named.len()));
    for p in &planted {
        let cells: Vec<String> = named
            .iter()
            .map(|n| {
                let c = runs
                    .iter()
                    .filter(|r| &r.planted == p && &r.named == n)
                    .count();
                if c == 0 {
                    ".".to_string()
                } else {
                    c.to_string()
                }
            })
            .collect();
        let (rec, med, lo, hi, _) = sum[p];
        let _ = writeln!(
            s,
            "| {p} | {} | {rec:.2} | {med:.2} [{lo:.2}, {hi:.2}] |",
            cells.join(" | ")
        );
    }
    s
}
