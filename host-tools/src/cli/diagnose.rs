//! `lpvid diagnose`: residual tests, missing effects, the fix ([`crate::diagnose`]).

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;

use super::files::{check_dir, check_paths, refuse_inputs, Outputs};
use super::{print_warnings, CliError, Ui};
use crate::data::{read_input, same_file, DataError, Dataset};
use crate::diagnose::{diagnose_with_progress, plots, refit_on_all, report, Options};
use crate::model::ModelFile;
use crate::pipeline::{fingerprint, DataFile};

/// `lpvid diagnose` arguments.
#[derive(Debug, Args)]
pub struct DiagnoseArgs {
    /// Model file (JSON) to diagnose.
    #[arg(long)]
    pub model: PathBuf,
    /// Training data (CSV) the model was (and candidates are) identified on.
    #[arg(long)]
    pub train: PathBuf,
    /// Validation data (CSV): the held-out data every candidate is scored on.
    #[arg(long, required_unless_present = "hold_out")]
    pub val: Option<PathBuf>,
    /// Instead of --val: hold out this fraction of the --train rows at their end (0 < F <
    /// 0.5; the candidates are refit on the rows before). With --fix, the chosen structure is
    /// then refit on all the --train rows (select on the held-out rows, then refit on
    /// everything); its score on the held-out rows is in-sample and reported as such.
    #[arg(long, conflicts_with = "val")]
    pub hold_out: Option<f64>,
    /// Add the best effect to the model and refit it with the model's own settings.
    #[arg(long)]
    pub fix: bool,
    /// With --fix: repeat while an effect explains the residual above the noise threshold.
    #[arg(long, default_value_t = 1, requires = "fix")]
    pub max_steps: usize,
    /// With --fix: where to write the fixed model (JSON).
    #[arg(long, requires = "fix")]
    pub out: Option<PathBuf>,
    /// Write the JSON report here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write SVG pictures here (fit before/after, residual correlations, spectrum, singular
    /// values).
    #[arg(long)]
    pub plots: Option<PathBuf>,
    /// Worker threads for the candidate refits (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// Run `lpvid diagnose`.
pub(super) fn run(a: &DiagnoseArgs, ui: Ui, out: &mut dyn Write) -> Result<(), CliError> {
    let mut inputs = vec![
        ("--model", a.model.as_path()),
        ("--train", a.train.as_path()),
    ];
    if let Some(v) = &a.val {
        inputs.push(("--val", v.as_path()));
    }
    let mut outs = Vec::new();
    if let Some(p) = &a.out {
        outs.push(("--out", p.as_path()));
    }
    if let Some(p) = &a.json {
        outs.push(("--json", p.as_path()));
    }
    check_paths(&inputs, &outs)?;
    if let Some(dir) = &a.plots {
        check_dir("--plots", dir, &inputs)?;
    }
    let model = read_model(&a.model)?;
    let train_file = DataFile::read(&a.train)?;
    let mut warnings = Vec::new();
    let train_fp = fingerprint(&train_file.bytes);
    // the rows the candidates are refit on and the held-out rows they are scored on
    let (fit_rows, val) = match (&a.val, a.hold_out) {
        (Some(vp), _) => {
            let val_bytes = read_input(vp)?;
            let val = Dataset::parse(&vp.display().to_string(), &val_bytes[..])?;
            if same_file(&a.train, vp) || train_fp == fingerprint(&val_bytes) {
                warnings.push(format!(
                    "--train and --val are the same data ({}): the scores are not held-out, and a \
                     candidate that fits the noise looks like a finding",
                    if same_file(&a.train, vp) {
                        "the same file".to_string()
                    } else {
                        format!("identical content, FNV-1a {train_fp}")
                    }
                ));
            }
            (None, val)
        }
        (None, Some(f)) => {
            let n = train_file.data.len();
            let held = (f * n as f64).round() as usize;
            if !(f > 0.0 && f < 0.5) || held < 20 {
                return Err(CliError::Invalid(format!(
                    "--hold-out {f}: the fraction must be in (0, 0.5) and leave at least 20 held-out rows ({n} rows in --train)"
                )));
            }
            let cut = |lo: usize, hi: usize, tag: &str| Dataset {
                source: format!("{} rows {}..{} ({tag})", a.train.display(), lo + 1, hi),
                names: train_file.data.names.clone(),
                cols: train_file
                    .data
                    .cols
                    .iter()
                    .map(|c| c[lo..hi].to_vec())
                    .collect(),
            };
            (Some(cut(0, n - held, "fit")), cut(n - held, n, "held out"))
        }
        (None, None) => {
            return Err(CliError::Invalid(
                "give --val or --hold-out: the held-out data the candidates are scored on".into(),
            ))
        }
    };
    let train = fit_rows.as_ref().unwrap_or(&train_file.data);
    if let Some(rec) = model
        .fit
        .get("train")
        .and_then(|t| t.get("fnv1a64"))
        .and_then(|v| v.as_str())
    {
        if rec == train_fp && fit_rows.is_some() {
            warnings.push(format!(
                "the model was identified on all of --train {}, the held-out rows of --hold-out \
                 included: its \"before\" score is in-sample; the candidates are compared with \
                 the null structure refit on the rows before the hold-out",
                a.train.display()
            ));
        }
        if rec != train_fp {
            warnings.push(format!(
                "--train {} (FNV-1a {train_fp}) is not the file the model was identified on \
                 (its fit record says {}, FNV-1a {rec}): the refits and the model differ in \
                 their data",
                a.train.display(),
                model.fit["train"]["file"].as_str().unwrap_or("?")
            ));
        }
    }
    let opts = Options {
        fix: a.fix,
        max_steps: a.max_steps,
        threads: a.threads,
    };
    let bar = ui.bar(0, "candidate refits");
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let res = diagnose_with_progress(&model, train, &val, &opts, Some(&progress));
    bar.finish_and_clear();
    let mut res = res.map_err(crate::Error::from)?;
    if let (true, Some(fit_rows)) = (a.fix, &fit_rows) {
        // the held-out rows are the tail of --train: refit the chosen structure on all of it
        refit_on_all(&mut res, fit_rows, &val).map_err(crate::Error::from)?;
    }
    res.report.model = a.model.display().to_string();
    for w in warnings.iter().rev() {
        res.report.notes.insert(0, format!("warning: {w}"));
    }
    if res.report.changed() {
        if let serde_json::Value::Object(m) = &mut res.model.fit {
            m.insert("train".into(), train_file.record());
        }
    }
    let mut outputs = Outputs::default();
    if let Some(p) = &a.out {
        if !res.report.changed() {
            // nothing to add: the model is written unchanged so that scripts find the file
            outputs.model(&model, p)?;
        } else {
            outputs.model(&res.model, p)?;
        }
        res.report.out = Some(p.display().to_string());
    }
    if let Some(p) = &a.json {
        let text = serde_json::to_string_pretty(&res.report)
            .map_err(|e| CliError::Invalid(format!("cannot encode the report: {e}")))?;
        outputs.bytes(p, text.as_bytes())?;
    }
    let mut written = Vec::new();
    if let Some(dir) = &a.plots {
        let figs = plots::render_all(dir, &res);
        let figure_paths: Vec<(&str, &Path)> =
            figs.iter().map(|(p, _)| ("--plots", p.as_path())).collect();
        refuse_inputs(&inputs, &figure_paths)?;
        outputs.figures(dir, &figs)?;
        written = figs.into_iter().map(|f| f.0).collect();
    }
    outputs.commit()?;
    print_warnings(&warnings);
    let text = report::summary(&res.report, &written);
    out.write_all(text.as_bytes())?;
    Ok(())
}

/// Read a model file, refusing inputs that never end ([`read_input`]).
pub(super) fn read_model(path: &Path) -> Result<ModelFile, CliError> {
    let bytes = read_input(path)?;
    let source = path.display().to_string();
    let text = String::from_utf8(bytes).map_err(|e| {
        let at = e.utf8_error().valid_up_to();
        let line = e.as_bytes()[..at].iter().filter(|&&b| b == b'\n').count() + 1;
        DataError::new(&source, Some(line), None, "invalid UTF-8 text")
    })?;
    Ok(ModelFile::from_json_str(&source, &text)?)
}
