//! What a caller chooses for an LPV-PBSID_opt fit and what the fit returns: the
//! regularisation of problem (13) (kernel paper, `papers/lpv-pbsid-kernel-automatica2009.md`,
//! eq. (18) and section 5.3; the sparse paper, `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md`,
//! section 4.2), the order rule (section 4.3), the form of (13) solved (section 5).

use nalgebra::DMatrix;

use super::scaling::Scaling;
use crate::lpvss::LpvSs;

/// Regularisation of problem (13).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reg {
    /// Minimum-norm least squares (eq. (18)).
    None,
    /// Tikhonov (ridge) with the parameter chosen by generalised cross-validation.
    TikhonovGcv,
    /// Tikhonov with a given parameter (relative to the largest eigenvalue of the Gram).
    Tikhonov(f64),
    /// Sparse BPDN (33) with the AIC rule (34) (sparse paper section 4.2.1).
    BpdnAic,
    /// Sparse BPDN (33) with the validation-error rule of Algorithm 1 (section 4.2.2).
    BpdnSv,
}

/// A setting given as text (command line, model file) that does not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingError {
    /// `tikhonov=X` with an X that is not a number.
    #[error("bad Tikhonov parameter in '{text}': {error}")]
    TikhonovParameter {
        /// The whole setting.
        text: String,
        /// Why X is not a number.
        error: std::num::ParseFloatError,
    },
    /// Not a regularisation name.
    #[error("unknown regularisation '{0}' (expected none, tikhonov-gcv, bpdn-aic or bpdn-sv)")]
    UnknownReg(String),
    /// Not a BPDN-SV score name.
    #[error("unknown BPDN-SV score '{0}' (expected simulation or paper)")]
    UnknownBpdnScore(String),
    /// Not a positive integer or `auto`.
    #[error("order must be a positive integer or 'auto', got '{0}'")]
    Order(String),
    /// Not a scheduling centre name.
    #[error("unknown scheduling centre '{0}' (expected auto, zero or mean)")]
    UnknownCentre(String),
}

impl std::str::FromStr for Reg {
    type Err = SettingError;
    fn from_str(s: &str) -> Result<Self, SettingError> {
        match s {
            "none" => Ok(Reg::None),
            "tikhonov-gcv" => Ok(Reg::TikhonovGcv),
            "bpdn-aic" => Ok(Reg::BpdnAic),
            "bpdn-sv" => Ok(Reg::BpdnSv),
            t if t.starts_with("tikhonov=") => {
                t[9..].parse::<f64>().map(Reg::Tikhonov).map_err(|error| {
                    SettingError::TikhonovParameter {
                        text: t.to_string(),
                        error,
                    }
                })
            }
            other => Err(SettingError::UnknownReg(other.to_string())),
        }
    }
}

/// How BPDN-SV (`Reg::BpdnSv`) scores the points of its group-lasso path (see the module
/// documentation of [`super::bpdn`] for the evidence behind the default).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BpdnScore {
    /// Ours (the default): the free-run simulation of each point's realized model, on the
    /// `--val` data or on the whole training record with an AIC order penalty; the point
    /// and the order come out together ([`super::bpdn::select_by_simulation`]).
    #[default]
    Simulation,
    /// The sparse paper's Algorithm 1: the path on the identification windows, each point
    /// scored by its one-step prediction error on the validation windows (from their
    /// statistics; the last quarter of the training record when no validation data are
    /// given), the order then by the singular-value rule ([`super::bpdn::select`] with
    /// [`super::bpdn::Rule::Sv`]).
    OneStep,
}

impl BpdnScore {
    /// Name used on the command line and in the model file's `fit` record.
    pub fn name(&self) -> &'static str {
        match self {
            BpdnScore::Simulation => "simulation",
            BpdnScore::OneStep => "paper",
        }
    }
}

impl std::str::FromStr for BpdnScore {
    type Err = SettingError;
    fn from_str(s: &str) -> Result<Self, SettingError> {
        match s {
            "simulation" => Ok(BpdnScore::Simulation),
            "paper" => Ok(BpdnScore::OneStep),
            other => Err(SettingError::UnknownBpdnScore(other.to_string())),
        }
    }
}

/// Model order: given, or chosen from the singular-value gap.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Order {
    /// Largest gap in the singular values of Gamma^p K^p Z.
    Auto,
    /// Given n.
    Fixed(usize),
}

impl std::str::FromStr for Order {
    type Err = SettingError;
    fn from_str(s: &str) -> Result<Self, SettingError> {
        if s == "auto" {
            return Ok(Order::Auto);
        }
        match s.parse::<usize>() {
            Ok(n) if n > 0 => Ok(Order::Fixed(n)),
            _ => Err(SettingError::Order(s.to_string())),
        }
    }
}

/// Which exact form of problem (13) to solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solver {
    /// The cheaper of the two, by an operation count.
    Auto,
    /// Normal equations from the core's second-moment statistics (q x q).
    Primal,
    /// Dual (kernel) form with the kernels of Theorem 10 (N x N), never forming Z.
    Dual,
}

impl Solver {
    /// Name used in reports.
    pub fn name(&self) -> &'static str {
        match self {
            Solver::Auto => "auto",
            Solver::Primal => "primal",
            Solver::Dual => "kernel",
        }
    }
}

/// Where a scheduling signal is centred for the fit: the point of the first local model
/// A^(1) whose powers build Gamma^p in eq. (14) of the kernel paper, and the point the
/// regularisation of (13) shrinks the p-dependence towards ([`crate::pbsid::Scaling`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Centre {
    /// p = 0 while 0 lies within the data's range (the mean +-
    /// [`crate::pbsid::P_ZERO_INSIDE`] standard deviations), else the mean; where the centre is
    /// in doubt ([`crate::pbsid::centre_in_doubt`]), [`crate::pipeline::identify`] and the
    /// streamed fit fit at both and keep the one whose model runs better in free run (the
    /// choice is then recorded as `Zero` or `Mean`).
    #[default]
    Auto,
    /// Always p = 0 (the papers' choice).
    Zero,
    /// Always the mean of each scheduling signal over the training record.
    Mean,
}

impl Centre {
    /// Name used on the command line and in the fit record.
    pub fn name(&self) -> &'static str {
        match self {
            Centre::Auto => "auto",
            Centre::Zero => "zero",
            Centre::Mean => "mean",
        }
    }
}

impl std::str::FromStr for Centre {
    type Err = SettingError;
    fn from_str(s: &str) -> Result<Self, SettingError> {
        match s {
            "auto" => Ok(Centre::Auto),
            "zero" => Ok(Centre::Zero),
            "mean" => Ok(Centre::Mean),
            other => Err(SettingError::UnknownCentre(other.to_string())),
        }
    }
}

/// Settings of an LPV-PBSID_opt fit.
#[derive(Debug, Clone)]
pub struct PbsidOptions {
    /// Past window p.
    pub past: usize,
    /// Model order.
    pub order: Order,
    /// Regularisation.
    pub reg: Reg,
    /// Estimate the feedthrough D (otherwise D = 0).
    pub feedthrough: bool,
    /// Primal, dual or automatic.
    pub solver: Solver,
    /// Largest order `Order::Auto` may choose.
    pub max_order: usize,
    /// Future window f <= p: the number of row blocks of Gamma^f K^p Z used for the SVD
    /// (the paper uses f = p; a shorter future drops the most truncated rows).
    pub future: Option<usize>,
    /// Scheduling weight kappa: the scheduling signals are scaled so that the mean of
    /// |p'|^2 is kappa. Each regressor block carries one mu factor per step of depth, so
    /// kappa sets how strongly the regularisation (and the minimum-norm choice) favours
    /// short-memory over deep Kronecker terms; it does not change an unregularised
    /// full-rank fit.
    pub sched_weight: f64,
    /// Kernel row selection (Algorithm 3): at most this many rows of Z^T Z (dictionary
    /// windows) in the kernel form; None uses every row.
    pub kernel_rows: Option<usize>,
    /// Admission tolerance of Algorithm 3, relative to the mean kernel diagonal k(w, w);
    /// 0 keeps exactly the rows that span (section 6.1 for periodic scheduling).
    pub kernel_tol: f64,
    /// Refine the subspace estimate by output-error Levenberg-Marquardt ([`crate::refine`]):
    /// removes the finite-window truncation bias on open-loop data.
    pub refine: bool,
    /// How BPDN-SV scores its path (only read with `Reg::BpdnSv`).
    pub bpdn_score: BpdnScore,
    /// Where the scheduling signals are centred.
    pub centre: Centre,
}

impl PbsidOptions {
    /// Defaults for past window `p`: automatic order, no regularisation, D estimated.
    pub fn new(past: usize) -> Self {
        PbsidOptions {
            past,
            order: Order::Auto,
            reg: Reg::None,
            feedthrough: true,
            solver: Solver::Auto,
            max_order: 20,
            future: None,
            sched_weight: DEFAULT_SCHED_WEIGHT,
            kernel_rows: None,
            kernel_tol: 0.0,
            refine: false,
            bpdn_score: BpdnScore::Simulation,
            centre: Centre::Auto,
        }
    }
}

/// Default scheduling weight kappa (see [`PbsidOptions::sched_weight`]).
pub const DEFAULT_SCHED_WEIGHT: f64 = 0.05;

/// The result of a fit, with what a user needs to judge it.
#[derive(Debug, Clone)]
pub struct PbsidFit {
    /// The identified model, original units.
    pub model: LpvSs,
    /// Singular values of Gamma^p K^p Z (eq. (15)), scaled units, descending.
    pub singular_values: Vec<f64>,
    /// The chosen order.
    pub order: usize,
    /// Why that order.
    pub order_reason: String,
    /// The Tikhonov parameter used (relative to the largest Gram eigenvalue), if any.
    pub lambda: Option<f64>,
    /// Effective number of parameters per output at that lambda.
    pub dof: f64,
    /// Which form of (13) was solved.
    pub solver: Solver,
    /// Why that form.
    pub solver_reason: String,
    /// Regressor length q.
    pub q: usize,
    /// Number of windows (regression rows) N - p.
    pub windows: usize,
    /// The scaling used.
    pub scaling: Scaling,
    /// The estimated state sequence in the model's basis (the scaling does not change the
    /// state): column k is x_{p+k}, k = 0..=N-p. `None` for a fit from statistics. The
    /// observer design (eq. (24)-(25) of the sparse paper) takes its residuals from it.
    pub states: Option<DMatrix<f64>>,
    /// Output-error refinement, when asked: (MSE before, MSE after, iterations).
    pub refinement: Option<(f64, f64, usize)>,
}
