//! Why an LPV-PBSID_opt fit could not be made.

/// A fit that could not be made, with the reason in words.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct FitError(pub String);

impl From<lpvid::Error> for FitError {
    fn from(e: lpvid::Error) -> Self {
        FitError(e.to_string())
    }
}

impl From<String> for FitError {
    fn from(e: String) -> Self {
        FitError(e)
    }
}
