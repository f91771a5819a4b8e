//! `lpvid demo`: the main job on the bundled fixture (B1, the Verdult-Verhaegen benchmark).

use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use super::pbsid::{pbsid_json, print_pbsid};
use super::{print_json, CliError};
use crate::data::Dataset;
use crate::pbsid::Reg;
use crate::pipeline::{self, DataFile, PbsidSettings};

/// `lpvid demo` arguments.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Also write the identified model here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    pub json: bool,
}

/// The bundled default fixture: B1 (Verdult-Verhaegen benchmark), N = 1000, 40 dB.
const DEMO_TRAIN: &[u8] = include_bytes!("../../../fixtures/b1-train.csv");
const DEMO_VAL: &[u8] = include_bytes!("../../../fixtures/b1-val.csv");

/// Run `lpvid demo`.
pub(super) fn run(a: &DemoArgs, out: &mut dyn Write) -> Result<(), CliError> {
    if let Some(p) = &a.out {
        super::files::check_paths(&[], &[("--out", p.as_path())])?;
    }
    let train = DataFile::from_bytes("fixtures/b1-train.csv", DEMO_TRAIN)?;
    let val = Dataset::parse("fixtures/b1-val.csv", DEMO_VAL)?;
    let mut settings = PbsidSettings::new(3);
    settings.fit.reg = Reg::TikhonovGcv;
    let run = pipeline::identify(&train, Some(&val), &settings)?;
    if let Some(p) = &a.out {
        let mut outputs = super::files::Outputs::default();
        outputs.model(&run.model, p)?;
        outputs.commit()?;
    }
    super::print_warnings(&run.warnings);
    if a.json {
        return print_json(out, &pbsid_json(&run, a.out.as_deref()));
    }
    writeln!(
        out,
        "lpvid demo: the Verdult-Verhaegen LPV benchmark (4 states, 2 inputs, 3 outputs, 4 local models),\n\
         1000 samples at 40 dB, identified with LPV-PBSID_opt (p = 3, Tikhonov + GCV, order from the data),\n\
         validated by free-run simulation on a fresh noise-free data set.\n"
    )
    ?;
    print_pbsid(&run, &settings.fit, out)?;
    if let Some(p) = &a.out {
        writeln!(out, "  model written to {}", p.display())?;
    }
    Ok(())
}
