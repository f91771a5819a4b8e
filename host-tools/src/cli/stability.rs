//! `lpvid stability`: the frozen-scheduling stability region of a model's one-step predictor
//! (sparse paper, section 5: A(mu) - K(mu) C over the scheduling box).

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use serde_json::Value;

use super::{print_json, CliError};
use crate::data::Dataset;
use crate::model::ModelKind;
use crate::observer;

/// `lpvid stability` arguments.
#[derive(Debug, Args)]
pub struct StabilityArgs {
    /// Model file (JSON, type lpv-ss).
    #[arg(long)]
    pub model: PathBuf,
    /// Data file whose scheduling range is the operating box and whose means hold the other
    /// signals (default: the training range and means recorded in the model's `fit`).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Operating range NAME=LO:HI overriding the data's (repeat or comma-separate).
    #[arg(long, value_name = "NAME=LO:HI", allow_hyphen_values = true)]
    pub range: Vec<String>,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

/// `lpvid stability`: for each scheduling signal (the others at their mean) the interval
/// around its mean where the frozen predictor A(mu) - K(mu) C(mu) has spectral radius < 1,
/// and the largest spectral radius over the operating box.
pub(super) fn run(a: &StabilityArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let model = super::diagnose::read_model(&a.model)?;
    let ss = match &model.kind {
        ModelKind::Ss(m) => m,
        _ => {
            return Err(CliError::Invalid(format!(
                "{}: the stability region is defined for lpv-ss models (A, K, C); this is an lpv-arx model",
                a.model.display()
            )))
        }
    };
    let names = model.signals.scheduling_names();
    let sig = match &a.data {
        Some(p) => Some(model.signals.evaluate(&Dataset::read_csv(p)?)?),
        None => None,
    };
    let rep = observer::stability_report(ss, &names, &model.fit, sig.as_ref(), &a.range)
        .map_err(|e| CliError::Invalid(format!("{}: {e}", a.model.display())))?;
    // signals on the model's own output read the measured one in the predictor
    let own: Vec<String> = model
        .signals
        .scheduling
        .iter()
        .skip(1)
        .filter(|p| p.iter().any(|f| model.signals.own_output(f).is_some()))
        .map(|p| crate::model::describe(p))
        .collect();
    let own_note = (!own.is_empty()).then(|| {
        format!(
            "{} read the model's own output: the predictor reads the measured one, so the region is the predictor's; the free run closes a loop through them that a frozen-scheduling test does not cover",
            own.join(", ")
        )
    });
    if a.json {
        let mut v = rep.to_json();
        if let Value::Object(o) = &mut v {
            if let Some(n) = &own_note {
                o.insert("own_output_note".into(), n.clone().into());
            }
            o.insert("command".into(), "stability".into());
            o.insert("model".into(), a.model.display().to_string().into());
            o.insert(
                "observer".into(),
                model.fit.get("observer").cloned().unwrap_or(Value::Null),
            );
        }
        return print_json(out, &v);
    }
    let gamma = model
        .fit
        .get("observer")
        .and_then(|o| o.get("gamma"))
        .and_then(Value::as_f64);
    writeln!(
        out,
        "{}: predictor A(mu) - K(mu) C, frozen scheduling (others at the {}){}",
        a.model.display(),
        rep.reference_source,
        gamma
            .map(|g| format!(", H-infinity gain with gamma = {g:.4e}"))
            .unwrap_or_default()
    )?;
    for r in &rep.regions {
        writeln!(out, "  {}", r.describe())?;
    }
    writeln!(
        out,
        "  max spectral radius over the box: {:.4} ({})",
        rep.max_rho,
        if rep.max_rho < 1.0 {
            "stable at every frozen point of the box"
        } else {
            "UNSTABLE somewhere in the box"
        }
    )?;
    if let Some(n) = &own_note {
        writeln!(out, "  note: {n}")?;
    }
    Ok(())
}
