//! `lpvid pbsid --stats A --stats B ...`: one fit from the mergeable statistics of several
//! experiments or devices ([`crate::statistics::Statistics`], the byte encoding of
//! `docs/wire.md` section 7), through [`crate::pipeline::identify_from_stats`].

use std::io::Write;

use serde_json::json;

use super::files::{check_paths, Outputs};
use super::pbsid::{pbsid_options, PbsidArgs};
use super::{fmt_list, print_json, CliError, Ui};
use crate::data::{read_input, DataError};
use crate::statistics::Statistics;

/// Read, check and merge the statistics files, fit, write the model, print the summary.
pub(super) fn run_pbsid(a: &PbsidArgs, _ui: Ui, out: &mut dyn Write) -> Result<(), CliError> {
    let inputs: Vec<(&str, &std::path::Path)> =
        a.stats.iter().map(|p| ("--stats", p.as_path())).collect();
    check_paths(&inputs, &[("--out", a.out.as_path())])?;
    let mut merged: Option<Statistics> = None;
    for path in &a.stats {
        let shown = path.display().to_string();
        let bytes = read_input(path)?;
        let st = Statistics::from_bytes(&bytes)
            .map_err(|e| DataError::new(&shown, None, None, e.to_string()))?;
        match &mut merged {
            None => merged = Some(st),
            Some(m) => m.merge(&st).map_err(|e| {
                DataError::new(
                    &shown,
                    None,
                    None,
                    format!("cannot be merged with {}: {e}", a.stats[0].display()),
                )
            })?,
        }
    }
    let st = merged.ok_or_else(|| CliError::Invalid("--stats needs at least one file".into()))?;
    let dims = st.dims();
    if let Some(p) = a.past {
        if p != dims.p {
            return Err(CliError::Invalid(format!(
                "--past {p}, but the statistics were accumulated with past window {}",
                dims.p
            )));
        }
    }
    let opts = pbsid_options(a, dims.p);
    let (model, fit) = st.identify(&opts)?;
    let mut outputs = Outputs::default();
    outputs.model(&model, &a.out)?;
    outputs.commit()?;
    if a.json {
        return print_json(
            out,
            &json!({
                "command": "pbsid",
                "stats": a.stats.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
                "experiments": st.experiments(),
                "windows": st.windows(),
                "order": fit.order,
                "order_reason": fit.order_reason,
                "singular_values": fit.singular_values,
                "solver": fit.solver.name(),
                "lambda": fit.lambda,
                "out": a.out.display().to_string(),
                "fit": model.fit,
            }),
        );
    }
    writeln!(
        out,
        "LPV-PBSID_opt from statistics: {} file{}, {} experiment{}, {} windows; {} inputs, {} outputs, {} scheduling signals, past window p = {}",
        a.stats.len(),
        if a.stats.len() == 1 { "" } else { "s" },
        st.experiments(),
        if st.experiments() == 1 { "" } else { "s" },
        st.windows(),
        dims.r,
        dims.l,
        dims.s,
        dims.p
    )?;
    writeln!(out, "  solver: {}", fit.solver_reason)?;
    writeln!(
        out,
        "  singular values of Gamma K Z: {}",
        fmt_list(&fit.singular_values, 4)
    )?;
    writeln!(out, "  order n = {}: {}", fit.order, fit.order_reason)?;
    writeln!(
        out,
        "  (no data: no free-run score; validate the model with `lpvid validate`)"
    )?;
    writeln!(out, "  model written to {}", a.out.display())?;
    Ok(())
}
