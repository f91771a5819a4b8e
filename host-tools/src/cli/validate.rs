//! `lpvid validate` (VAF and BFR per output) and `lpvid simulate` (a model's outputs as CSV).

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use serde_json::json;

use super::diagnose::read_model;
use super::files::{check_paths, Outputs};
use super::{print_json, CliError};
use crate::data::Dataset;
use crate::pipeline::score;
use crate::simulate::{diverged_at, simulate, Mode};

/// A model run on a data file: what `validate` and `simulate` share.
#[derive(Debug, Args)]
pub struct ModelOnData {
    /// Model file (JSON).
    #[arg(long)]
    pub model: PathBuf,
    /// Data file (CSV) with the model's columns.
    #[arg(long)]
    pub data: PathBuf,
    /// The one-step-ahead predictor (measured past outputs) instead of the free run.
    #[arg(long)]
    pub predictor: bool,
}

impl ModelOnData {
    /// Free run or predictor, as asked.
    fn mode(&self) -> Mode {
        if self.predictor {
            Mode::Predictor
        } else {
            Mode::FreeRun
        }
    }
}

/// `lpvid validate` arguments.
#[derive(Debug, Args)]
pub struct ValidateArgs {
    #[command(flatten)]
    pub run: ModelOnData,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

/// `lpvid simulate` arguments.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub run: ModelOnData,
    /// Output CSV: the data columns plus yhat1.. per model output. A simulation that
    /// diverges (a value not finite or beyond 1e100) is an error and writes nothing.
    #[arg(long)]
    pub out: PathBuf,
}

/// Run `lpvid validate`.
pub(super) fn run_validate(a: &ValidateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = read_model(&a.run.model)?;
    let ds = Dataset::read_csv(&a.run.data)?;
    let mode = a.run.mode();
    let sc = score(&model, &ds, mode)?;
    let diverged = sc.diverged_at.map(|k| {
        format!(
            "diverged at sample {k} (line {} of {}): the {} output is not finite or beyond 1e100 \
             from there on, so VAF and BFR say nothing about the fit",
            k + 2,
            sc.file,
            sc.mode
        )
    });
    if a.json {
        print_json(
            out,
            &json!({"command": "validate", "model": a.run.model.display().to_string(), "score": sc,
                "diverged": diverged}),
        )?;
    } else {
        writeln!(
            out,
            "{} on {} ({}):",
            a.run.model.display(),
            sc.file,
            sc.mode
        )?;
        for (i, (v, b)) in sc.vaf.iter().zip(&sc.bfr).enumerate() {
            writeln!(out, "  output {}: VAF {v:.3} %  BFR {b:.2} %", i + 1)?;
        }
        writeln!(
            out,
            "  mean:     VAF {:.3} %  BFR {:.2} %",
            sc.vaf_mean, sc.bfr_mean
        )?;
        if let Some(d) = &diverged {
            writeln!(out, "  {d}")?;
        }
    }
    Ok(())
}

/// Run `lpvid simulate`.
pub(super) fn run_simulate(a: &SimulateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    check_paths(
        &[
            ("--model", a.run.model.as_path()),
            ("--data", a.run.data.as_path()),
        ],
        &[("--out", a.out.as_path())],
    )?;
    let model = read_model(&a.run.model)?;
    let mut ds = Dataset::read_csv(&a.run.data)?;
    let mode = a.run.mode();
    let (_, yhat) = simulate(&model, &ds, mode)?;
    if let Some(k) = diverged_at(&yhat) {
        return Err(CliError::Invalid(format!(
            "{}: the simulation diverged at sample {k} (line {} of {}): the output is not \
             finite or beyond 1e100 from there on; nothing written to {}",
            a.run.model.display(),
            k + 2,
            ds.source,
            a.out.display()
        )));
    }
    for j in 0..yhat.ncols() {
        let mut name = format!("yhat{}", j + 1);
        while ds.names.contains(&name) {
            name.push('_');
        }
        ds.names.push(name);
        ds.cols.push(yhat.column(j).iter().copied().collect());
    }
    let mut outputs = Outputs::default();
    outputs.bytes(&a.out, &ds.to_csv_bytes(&a.out)?)?;
    outputs.commit()?;
    writeln!(
        out,
        "wrote {} rows with {} simulated outputs to {}",
        ds.len(),
        yhat.ncols(),
        a.out.display()
    )?;
    Ok(())
}
