//! The host library's error: one variant per module's typed error, so a caller (the
//! command line, the Python package, a test) can branch on what failed; the message a
//! user sees is built from it at the edge (`Display`).

use crate::arx::ArxError;
use crate::data::DataError;
use crate::diagnose::DiagnoseError;
use crate::link::{CompareError, LinkError};
use crate::observer::ObserverError;
use crate::pbsid::FitError;

/// Anything the host library can fail with.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A data or model file problem (names file, line, column).
    #[error(transparent)]
    Data(#[from] DataError),
    /// LPV-PBSID_opt could not fit the data of `file`.
    #[error("{file}: {source}")]
    Fit {
        /// The training file (or "statistics").
        file: String,
        /// What the fit reported.
        source: FitError,
    },
    /// The observer step (H-infinity design, operating box) failed.
    #[error(transparent)]
    Observer(#[from] ObserverError),
    /// LPV-ARX settings or data rejected before fitting.
    #[error(transparent)]
    Arx(#[from] ArxError),
    /// LPV-ARX could not fit the data of `file`.
    #[error("{file}: {source}")]
    ArxFit {
        /// The training file.
        file: String,
        /// What the fit reported.
        source: ArxError,
    },
    /// The device link failed.
    #[error("device: {0}")]
    Link(#[from] LinkError),
    /// Device statistics could not be compared with a file or fitted.
    #[error(transparent)]
    Compare(#[from] CompareError),
    /// The diagnosis failed.
    #[error("diagnose: {0}")]
    Diagnose(#[from] DiagnoseError),
    /// A core (statistics) error: dimensions, capacities, non-finite samples.
    #[error(transparent)]
    Core(#[from] lpvid::Error),
}

impl Error {
    /// The observer step's error (for `map_err`).
    pub fn observer(e: ObserverError) -> Error {
        Error::Observer(e)
    }
}
