//! What a model file records about its fit (DESIGN.md section 5, `"fit"`): the data files
//! it was identified on (name, rows, FNV-1a fingerprint), the settings and what the fit
//! chose, written by one function per method so that every front end writes the same
//! record and `diagnose` can read it back to refit.

use std::path::Path;

use serde_json::{json, Value};

use crate::data::{DataError, Dataset};
use crate::lpvss::Signals;
use crate::model::SignalMap;
use crate::pbsid::{Order, PbsidFit, PbsidOptions, Reg};

/// FNV-1a 64-bit fingerprint of a file's bytes (recorded in the model's `fit`, so a later
/// refit can tell whether it is given the same training file).
pub fn fingerprint(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf29ce484222325;
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    format!("{h:016x}")
}

/// A data file read whole, with its bytes kept for the fingerprint.
#[derive(Debug, Clone)]
pub struct DataFile {
    /// The path as the user gave it.
    pub path: std::path::PathBuf,
    /// The parsed file.
    pub data: Dataset,
    /// The file's bytes.
    pub bytes: Vec<u8>,
}

impl DataFile {
    /// Read and parse `path` (errors name the file, line and column).
    pub fn read(path: &Path) -> Result<DataFile, DataError> {
        // refuses devices that never end and bounds pipes and line lengths
        Self::from_read_input(path, crate::data::read_input(path)?)
    }

    /// [`DataFile::read`] of the bytes [`crate::data::read_input`] read from `path` (a
    /// caller that looks at the bytes before parsing them).
    pub fn from_read_input(path: &Path, bytes: Vec<u8>) -> Result<DataFile, DataError> {
        let data = Dataset::parse_read_input(&path.display().to_string(), &bytes)?;
        Ok(DataFile {
            path: path.to_path_buf(),
            data,
            bytes,
        })
    }

    /// Wrap data already in memory (`name` is the file name the record shows).
    pub fn from_bytes(name: &str, bytes: &[u8]) -> Result<DataFile, DataError> {
        Ok(DataFile {
            path: name.into(),
            data: Dataset::parse(name, bytes)?,
            bytes: bytes.to_vec(),
        })
    }

    /// `{"file", "rows", "fnv1a64"}` as the model's `fit` records a data file.
    pub fn record(&self) -> Value {
        json!({
            "file": self.path.display().to_string(),
            "rows": self.data.len(),
            "fnv1a64": fingerprint(&self.bytes),
        })
    }
}

/// The name of a regularisation as the command line and the `fit` record write it.
pub fn reg_name(r: Reg) -> String {
    match r {
        Reg::None => "none".into(),
        Reg::TikhonovGcv => "tikhonov-gcv".into(),
        Reg::Tikhonov(v) => format!("tikhonov={v}"),
        Reg::BpdnAic => "bpdn-aic".into(),
        Reg::BpdnSv => "bpdn-sv".into(),
    }
}

/// The order rule as the `fit` record writes it (`auto` or the number).
pub fn order_rule(o: Order) -> String {
    match o {
        Order::Auto => "auto".into(),
        Order::Fixed(n) => n.to_string(),
    }
}

/// The solver as the `fit` record and the summaries name it: `primal` or `kernel`, and
/// `sparse` for BPDN (which always solves with explicit regressors, whatever the cost model
/// chose for the dense forms; its `solver_reason` says so).
pub fn solver_name(opts: &PbsidOptions, fit: &PbsidFit) -> &'static str {
    if matches!(opts.reg, Reg::BpdnAic | Reg::BpdnSv) {
        "sparse"
    } else {
        fit.solver.name()
    }
}

/// The training data as the fit sees it, checked: every used column present and not
/// constant, enough rows for the window.
pub fn training_signals(ds: &Dataset, past: usize) -> Result<(SignalMap, Signals), DataError> {
    let map = SignalMap::default_for(ds)?;
    for prefix in ['u', 'y', 'p'] {
        for name in ds.channels(prefix) {
            ds.check_scale(&name)?;
        }
    }
    for name in ds.channels('u').iter().chain(ds.channels('p').iter()) {
        ds.check_not_constant(name)?;
    }
    let needed = past + 3;
    if ds.len() < needed {
        return Err(DataError::new(
            &ds.source,
            Some(ds.len() + 1),
            None,
            format!(
                "{} data rows, but a past window of {past} needs at least {needed} (and many more for a useful fit)",
                ds.len()
            ),
        ));
    }
    let sig = map.evaluate(ds)?;
    Ok((map, sig))
}

/// The `fit` record of an LPV-PBSID_opt model: the settings and what the fit chose, enough
/// to refit (`diagnose` reads it back). `train` is the training file's record (see
/// [`DataFile::record`]).
pub fn pbsid_fit_record(opts: &PbsidOptions, fit: &PbsidFit, train: Value) -> Value {
    json!({
        "method": "lpv-pbsid-opt",
        "past": opts.past,
        "future": opts.future.unwrap_or(opts.past),
        "order": fit.order,
        "states": fit.model.n(),
        "order_rule": order_rule(opts.order),
        "order_reason": fit.order_reason,
        "max_order": opts.max_order,
        "reg": reg_name(opts.reg),
        "bpdn_score": (opts.reg == Reg::BpdnSv).then(|| opts.bpdn_score.name()),
        "lambda": fit.lambda,
        "effective_parameters": fit.dof,
        "solver": solver_name(opts, fit),
        "solver_reason": fit.solver_reason,
        "feedthrough": opts.feedthrough,
        "observer": "ls",
        "sched_weight": opts.sched_weight,
        "kernel_rows": opts.kernel_rows,
        "kernel_tol": opts.kernel_tol,
        "refine": fit.refinement.map(|(before, after, it)| json!({
            "method": "output-error Levenberg-Marquardt",
            "mse_before": before, "mse_after": after, "iterations": it,
        })),
        "regressors": fit.q,
        "feedthrough_regressors": if opts.feedthrough { fit.model.r() } else { 0 },
        "windows": fit.windows,
        "singular_values": fit.singular_values,
        "centre": opts.centre.name(),
        "scaling": {
            "u": fit.scaling.u, "y": fit.scaling.y,
            "p_center": fit.scaling.p_center, "p_scale": fit.scaling.p_scale,
        },
        "train": train,
        "lpvid_version": env!("CARGO_PKG_VERSION"),
    })
}
