//! `lpvid validate` (VAF and BFR per output) and `lpvid simulate` (a model's outputs as CSV).
//! A data file of at least [`crate::stream::STREAM_MIN_BYTES`] is read in chunks (constant
//! memory, [`crate::stream`]) when the model allows; the same output either way.

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;
use serde_json::json;

use super::diagnose::read_model;
use super::files::{check_paths, Outputs};
use super::{print_json, CliError};
use crate::data::Dataset;
use crate::simulate::{diverged_at, run, score_from, Mode, X0, X0_SAMPLES};
use crate::stream::{score_streaming, should_stream_data, simulate_streaming, SimulateFailure};

/// The initial state of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum X0Choice {
    /// The zero state; every sample is scored.
    Zero,
    /// Estimated by least squares from the first --x0-samples samples, which are not scored.
    Estimate,
}

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
    /// Initial state: zero, or estimated from the first --x0-samples samples (which are then
    /// left out of the score), as the public benchmarks allow.
    #[arg(long, value_enum, default_value = "zero")]
    pub x0: X0Choice,
    /// Samples used to estimate the initial state with --x0 estimate.
    #[arg(long, default_value_t = X0_SAMPLES as u64, value_parser = clap::value_parser!(u64).range(1..))]
    pub x0_samples: u64,
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

    /// The initial state, as asked.
    fn x0(&self) -> X0 {
        match self.x0 {
            X0Choice::Zero => X0::Zero,
            X0Choice::Estimate => X0::Estimate {
                samples: usize::try_from(self.x0_samples).unwrap_or(usize::MAX),
            },
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
    let mode = a.run.mode();
    // a large file in chunks (constant memory), when the model allows; the same score
    let streamed = if should_stream_data(&a.run.data) {
        score_streaming(&model, &a.run.data, mode, a.run.x0())
    } else {
        None
    };
    let (sc, rows) = match streamed {
        Some(s) => s,
        None => {
            let ds = Dataset::read_csv(&a.run.data)?;
            (score_from(&model, &ds, mode, a.run.x0())?, ds.len())
        }
    };
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
        let start = if sc.skipped > 0 {
            format!(
                ", initial state estimated from the first {} samples, scored on the other {}",
                sc.skipped,
                rows - sc.skipped
            )
        } else {
            String::new()
        };
        writeln!(
            out,
            "{} on {} ({}{start}):",
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
    let mode = a.run.mode();
    let diverged = |k: usize, source: &str| {
        CliError::Invalid(format!(
            "{}: the simulation diverged at sample {k} (line {} of {}): the output is not \
             finite or beyond 1e100 from there on; nothing written to {}",
            a.run.model.display(),
            k + 2,
            source,
            a.out.display()
        ))
    };
    let mut outputs = Outputs::default();
    // a large file in chunks, its output written chunk by chunk into the staged file
    if should_stream_data(&a.run.data) {
        match simulate_streaming(&model, &a.run.data, mode, a.run.x0(), &a.out) {
            Some(Ok(s)) => {
                outputs.staged(s.staged);
                outputs.commit()?;
                return wrote(out, s.rows, s.outputs, &a.out);
            }
            Some(Err(SimulateFailure::Diverged(k))) => {
                return Err(diverged(k, &a.run.data.display().to_string()))
            }
            Some(Err(SimulateFailure::Write(e))) => return Err(e.into()),
            None => {}
        }
    }
    let mut ds = Dataset::read_csv(&a.run.data)?;
    let yhat = run(&model, &ds, mode, a.run.x0())?.yhat;
    if let Some(k) = diverged_at(&yhat) {
        return Err(diverged(k, &ds.source));
    }
    for j in 0..yhat.ncols() {
        let mut name = format!("yhat{}", j + 1);
        while ds.names.contains(&name) {
            name.push('_');
        }
        ds.names.push(name);
        ds.cols.push(yhat.column(j).iter().copied().collect());
    }
    outputs.bytes(&a.out, &ds.to_csv_bytes(&a.out)?)?;
    outputs.commit()?;
    wrote(out, ds.len(), yhat.ncols(), &a.out)
}

/// What `lpvid simulate` says when it has written its output.
fn wrote(out: &mut dyn Write, rows: usize, outputs: usize, path: &Path) -> Result<(), CliError> {
    writeln!(
        out,
        "wrote {rows} rows with {outputs} simulated outputs to {}",
        path.display()
    )?;
    Ok(())
}
