//! `lpvid diagnose`: residual tests, missing effects, the fix ([`crate::diagnose`]).

use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use super::CliError;
use crate::data::{DataError, Dataset};
use crate::diagnose::{diagnose, plots, report, Options};
use crate::model::ModelFile;
use crate::pipeline::fingerprint;

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
    #[arg(long)]
    pub val: PathBuf,
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
pub(super) fn run(a: &DiagnoseArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let train = Dataset::read_csv(&a.train)?;
    let val = Dataset::read_csv(&a.val)?;
    let opts = Options {
        fix: a.fix,
        max_steps: a.max_steps,
        threads: a.threads,
    };
    let mut res = diagnose(&model, &train, &val, &opts).map_err(crate::Error::from)?;
    res.report.model = a.model.display().to_string();
    if !res.report.applied.is_empty() {
        if let (Ok(bytes), serde_json::Value::Object(m)) =
            (std::fs::read(&a.train), &mut res.model.fit)
        {
            m.insert(
                "train".into(),
                serde_json::json!({
                    "file": a.train.display().to_string(),
                    "rows": train.len(),
                    "fnv1a64": fingerprint(&bytes),
                }),
            );
        }
    }
    if let Some(p) = &a.out {
        if res.report.applied.is_empty() {
            // nothing to add: the model is written unchanged so that scripts find the file
            model.write(p)?;
        } else {
            res.model.write(p)?;
        }
        res.report.out = Some(p.display().to_string());
    }
    if let Some(p) = &a.json {
        let text = serde_json::to_string_pretty(&res.report)
            .map_err(|e| CliError::Invalid(format!("cannot encode the report: {e}")))?;
        crate::data::write_atomic(p, text.as_bytes())?;
    }
    let mut written = Vec::new();
    if let Some(dir) = &a.plots {
        std::fs::create_dir_all(dir).map_err(|e| {
            DataError::new(
                dir.display().to_string(),
                None,
                None,
                format!("cannot create: {e}"),
            )
        })?;
        written = plots::write_all(dir, &res)?;
    }
    let text = report::summary(&res.report, &written);
    out.write_all(text.as_bytes())?;
    Ok(())
}
