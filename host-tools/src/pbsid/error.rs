//! Why an LPV-PBSID_opt fit could not be made: one variant per cause a caller can act on.
//! The text of each variant is the message `lpvid pbsid` prints.

use super::bpdn::BpdnError;
use crate::linalg::LinalgError;

/// A fit that could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// Fewer samples than the past window needs (p + 3).
    #[error("{samples} samples, but a past window of {past} needs at least {needed} (and many more for a useful fit)")]
    TooFewSamples {
        /// Samples in the training data.
        samples: usize,
        /// Past window p.
        past: usize,
        /// The least number of samples p needs.
        needed: usize,
    },
    /// Fewer than two regression windows (rows of (13)).
    #[error("{windows} regression windows: a past window of {past} needs more samples")]
    TooFewWindows {
        /// Regression windows N - p.
        windows: usize,
        /// Past window p.
        past: usize,
    },
    /// BPDN-SV with the paper's score has too few identification or validation windows.
    #[error("{identification} identification and {validation} validation windows: too few samples for BPDN-SV (paper score) with a past window of {past}")]
    TooFewBpdnWindows {
        /// Identification windows.
        identification: usize,
        /// Validation windows.
        validation: usize,
        /// Past window p.
        past: usize,
    },
    /// A given order above the number of singular values f l.
    #[error(
        "order {order} exceeds the f*l = {available} singular values: increase the (future) window"
    )]
    OrderTooLarge {
        /// The order asked for.
        order: usize,
        /// The number of singular values of Gamma^f K^p Z.
        available: usize,
    },
    /// A future window outside 1..=p.
    #[error("future window {future} must be between 1 and the past window {past}")]
    FutureWindow {
        /// The future window asked for.
        future: usize,
        /// Past window p.
        past: usize,
    },
    /// A scheduling weight kappa that is not positive and finite.
    #[error("scheduling weight must be positive, got {0}")]
    SchedulingWeight(f64),
    /// Kernel row selection asked for no row.
    #[error("--kernel-rows must be at least 1")]
    NoKernelRows,
    /// An input with no variation: the regression is rank deficient (1-based index).
    #[error(
        "input u{0} is constant: it carries no information and makes the regression rank deficient"
    )]
    ConstantInput(usize),
    /// An output with no variation (1-based index).
    #[error("output y{0} is constant")]
    ConstantOutput(usize),
    /// A scheduling signal with no variation: it duplicates the affine term (1-based index).
    #[error("scheduling p{0} is constant: it is indistinguishable from the affine term")]
    ConstantScheduling(usize),
    /// The primal form's Gram matrix would be too large.
    #[error("the primal form needs a {q} x {q} Gram matrix; use the kernel form (--kernel) or a smaller past window")]
    PrimalTooLarge {
        /// Regressor length q.
        q: usize,
    },
    /// The kernel form's kernel matrix would be too large.
    #[error("the kernel form needs a {windows} x {windows} kernel matrix; use the primal form or fewer samples")]
    KernelTooLarge {
        /// Regression windows N - p.
        windows: usize,
    },
    /// The validation data's channels differ from the training data's.
    #[error("the validation data have other signals than the training data")]
    ValidationSignals,
    /// The validation data are shorter than one window.
    #[error("the validation data are shorter than the window")]
    ValidationTooShort,
    /// Statistics whose dimension is not the extended layout of the given dimensions.
    #[error("statistics of dimension {got} do not match the extended layout for r={r}, l={l}, s={s}, p={p} (expected {expected})")]
    StatisticsDimension {
        /// The statistics' dimension.
        got: usize,
        /// The extended layout's dimension.
        expected: usize,
        /// Inputs r.
        r: usize,
        /// Outputs l.
        l: usize,
        /// Scheduling signals s.
        s: usize,
        /// Past window p.
        p: usize,
    },
    /// The statistic vector's layout has an entry that is not a product of distinct
    /// channel values, so the centring of the scheduling signals cannot be mapped onto it
    /// (an internal error: the layout and `pbsid::scaling` disagree).
    #[error("internal: entry {0} of the statistic vector is not a product of distinct channel values; the scheduling centring cannot map it")]
    CentringLayout(usize),
    /// Statistics accumulated with another past window than the one asked for.
    #[error("the statistics were accumulated with past window {statistics}, not {asked}")]
    StatisticsPastWindow {
        /// The statistics' past window.
        statistics: usize,
        /// The options' past window.
        asked: usize,
    },
    /// The core rejected the data or dimensions (non-finite samples, sizes, capacities).
    #[error(transparent)]
    Core(#[from] lpvid::Error),
    /// An eigendecomposition of the regression or of the SVD (15) failed.
    #[error(transparent)]
    Linalg(#[from] LinalgError),
    /// The sparse (BPDN) estimation failed.
    #[error(transparent)]
    Sparse(#[from] BpdnError),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pbsid::{fit, Order, PbsidOptions, Reg, SettingError};
    use crate::systems;

    /// Callers branch on the variant; the text stays the message the CLI prints.
    #[test]
    fn fit_errors_are_variants_with_the_printed_text() {
        let e = systems::b2(75, 25.0, 3);
        let mut o = PbsidOptions::new(2);
        o.order = Order::Fixed(50);
        let err = fit(&e.train, &o).unwrap_err();
        assert_eq!(
            err,
            FitError::OrderTooLarge {
                order: 50,
                available: 2
            }
        );
        assert_eq!(
            err.to_string(),
            "order 50 exceeds the f*l = 2 singular values: increase the (future) window"
        );
        let err = fit(&e.train.slice(0, 4), &PbsidOptions::new(2)).unwrap_err();
        assert!(matches!(
            err,
            FitError::TooFewSamples {
                samples: 4,
                past: 2,
                needed: 5
            }
        ));
        let mut o = PbsidOptions::new(2);
        o.future = Some(3);
        assert!(matches!(
            fit(&e.train, &o),
            Err(FitError::FutureWindow { future: 3, past: 2 })
        ));
        let mut o = PbsidOptions::new(2);
        o.sched_weight = 0.0;
        assert!(matches!(
            fit(&e.train, &o),
            Err(FitError::SchedulingWeight(_))
        ));
        let mut flat = e.train.clone();
        flat.u.fill(1.0);
        assert_eq!(
            fit(&flat, &PbsidOptions::new(2)).unwrap_err(),
            FitError::ConstantInput(1)
        );
        assert!(matches!(
            "tikhonov=x".parse::<Reg>(),
            Err(SettingError::TikhonovParameter { .. })
        ));
        assert_eq!("0".parse::<Order>(), Err(SettingError::Order("0".into())));
    }
}
