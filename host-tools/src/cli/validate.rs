//! `lpvid validate` (VAF and BFR per output) and `lpvid simulate` (a model's outputs as CSV).

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use serde_json::json;

use super::{print_json, CliError};
use crate::data::Dataset;
use crate::model::ModelFile;
use crate::pipeline::score;
use crate::simulate::{simulate, Mode};

#[derive(Debug, Args)]
pub struct ValidateArgs {
    /// Model file (JSON).
    #[arg(long)]
    pub model: PathBuf,
    /// Data file (CSV) with the model's columns.
    #[arg(long)]
    pub data: PathBuf,
    /// Score the one-step-ahead predictor instead of the free-run simulation.
    #[arg(long)]
    pub predictor: bool,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Model file (JSON).
    #[arg(long)]
    pub model: PathBuf,
    /// Data file (CSV) with the model's columns.
    #[arg(long)]
    pub data: PathBuf,
    /// One-step-ahead predictor instead of free run.
    #[arg(long)]
    pub predictor: bool,
    /// Output CSV: the data columns plus yhat1.. per model output.
    #[arg(long)]
    pub out: PathBuf,
}

/// Run `lpvid validate`.
pub(super) fn run_validate(a: &ValidateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let ds = Dataset::read_csv(&a.data)?;
    let mode = if a.predictor {
        Mode::Predictor
    } else {
        Mode::FreeRun
    };
    let sc = score(&model, &ds, mode)?;
    if a.json {
        print_json(
            out,
            &json!({"command": "validate", "model": a.model.display().to_string(), "score": sc}),
        )?;
    } else {
        writeln!(out, "{} on {} ({}):", a.model.display(), sc.file, sc.mode)?;
        for (i, (v, b)) in sc.vaf.iter().zip(&sc.bfr).enumerate() {
            writeln!(out, "  output {}: VAF {v:.3} %  BFR {b:.2} %", i + 1)?;
        }
        writeln!(
            out,
            "  mean:     VAF {:.3} %  BFR {:.2} %",
            sc.vaf_mean, sc.bfr_mean
        )?;
    }
    Ok(())
}

/// Run `lpvid simulate`.
pub(super) fn run_simulate(a: &SimulateArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = ModelFile::read(&a.model)?;
    let mut ds = Dataset::read_csv(&a.data)?;
    let mode = if a.predictor {
        Mode::Predictor
    } else {
        Mode::FreeRun
    };
    let (_, yhat) = simulate(&model, &ds, mode)?;
    for j in 0..yhat.ncols() {
        let mut name = format!("yhat{}", j + 1);
        while ds.names.contains(&name) {
            name.push('_');
        }
        ds.names.push(name);
        ds.cols.push(yhat.column(j).iter().copied().collect());
    }
    ds.write_csv(&a.out)?;
    writeln!(
        out,
        "wrote {} rows with {} simulated outputs to {}",
        ds.len(),
        yhat.ncols(),
        a.out.display()
    )?;
    Ok(())
}
