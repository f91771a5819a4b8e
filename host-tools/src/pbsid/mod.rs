//! LPV-PBSID_opt (kernel paper, `papers/lpv-pbsid-kernel-automatica2009.md`, Algorithms 1
//! and 2, sections 4-6; the sparse paper, `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md`,
//! section 4.2 for the sparse forms): regression (13) from the core's statistics (primal)
//! or in the dual/kernel form (19)-(22) when the regressor outgrows the data,
//! Gamma^p K^p Z by eq. (14) or eq. (25), SVD (15), state (16), then the system matrices by
//! least squares (section 4.3).
//!
//! Signals are scaled internally (inputs and outputs by their standard deviation, each
//! scheduling signal centred and scaled — an exact affine re-parametrisation of mu) and the
//! model is returned in original units.
//!
//! Where each step lives:
//! - [`settings`]: what a caller chooses ([`PbsidOptions`], [`Reg`], [`Order`], [`Solver`],
//!   [`BpdnScore`]) and what a fit returns ([`PbsidFit`]);
//! - [`scaling`]: the channel scaling, the scaled sample rows, the statistics' scale vector
//!   and the way back to original units ([`unscale`]);
//! - [`ridge`]: the ridge step shared by every form of (13), with GCV (section 5.3);
//! - [`primal`]: regression (13) from the statistics (Algorithm 1);
//! - [`dual`]: the kernel form (19)-(22), eq. (25) and the row selection of Algorithm 3
//!   (section 6);
//! - [`bpdn`] and [`sparse`]: BPDN (33) with rule (34) or Algorithm 1 of the sparse paper;
//! - [`order`]: the order from the singular values of Gamma K Z;
//! - [`realize`]: eq. (14), the SVD (15), the states (16) and the system matrices
//!   (section 4.3);
//! - [`error`]: why a fit could not be made ([`FitError`]).
//!
//! This file holds the three entry points: [`fit`], [`fit_with_validation`] and
//! [`fit_from_stats`].

pub mod bpdn;
pub mod dual;
pub mod error;
pub mod memo;
pub mod order;
pub mod primal;
pub mod realize;
pub mod ridge;
pub mod sample_cd;
pub mod scaling;
pub mod settings;
pub mod sparse;
pub mod stream;

use lpvid::{stat_vector_len, Gram, PbsidDims, Slab, StatsLayout};

use crate::lpvss::Signals;

pub use dual::{
    detect_period, dual_gamma_kz_matrix, dual_gamma_kz_matrix_with, dual_kernel_matrix,
    dual_kernel_matrix_with, select_kernel_rows, sweep_workers, SWEEP_SPLIT_MIN_WORK,
};
pub use error::FitError;
pub use order::{
    far_worse, free_run_order, paired_p, select_order, FreeRunScore, OrderCheck, FAR_WORSE_FACTOR,
    FAR_WORSE_GAP, FAR_WORSE_RATIO, FLOOR_FACTOR, ORDER_ALPHA, ORDER_MIN_BATCHES,
    ORDER_MIN_BATCH_LEN,
};
pub use realize::{gamma_k, realize_from_states, realize_from_stats};
pub use scaling::{centre_in_doubt, unscale, Scaling, P_ZERO_EDGE, P_ZERO_INSIDE};
pub use settings::{
    BpdnScore, Centre, Order, PbsidFit, PbsidOptions, Reg, SettingError, Solver,
    DEFAULT_SCHED_WEIGHT,
};

use order::choose_order;
use primal::{dense, primal_regression_svd};
use scaling::{scale_stat_gram, scaled_rows, ChannelSums};

/// Check the options against the data size; returns the future window.
fn check_options(dims: &PbsidDims, windows: usize, opts: &PbsidOptions) -> Result<usize, FitError> {
    if !(opts.sched_weight > 0.0 && opts.sched_weight.is_finite()) {
        return Err(FitError::SchedulingWeight(opts.sched_weight));
    }
    if windows < 2 {
        return Err(FitError::TooFewWindows {
            windows,
            past: dims.p,
        });
    }
    future(dims, opts)
}

/// The future window f (default p), checked.
fn future(dims: &PbsidDims, opts: &PbsidOptions) -> Result<usize, FitError> {
    let f = opts.future.unwrap_or(dims.p);
    if f == 0 || f > dims.p {
        return Err(FitError::FutureWindow {
            future: f,
            past: dims.p,
        });
    }
    Ok(f)
}

/// The cheaper exact form of regression (13) for `qf` regressors (with the feedthrough
/// columns), `windows` windows and past window `p`: operation counts of building and
/// decomposing the primal statistics against the kernel matrix.
pub(crate) fn primal_is_cheaper(qf: usize, windows: usize, p: usize) -> bool {
    let qf = qf as f64;
    let nb = windows as f64;
    let primal_cost = nb * qf * qf / 2.0 + 10.0 * qf * qf * qf;
    let dual_cost = nb * nb * (p * p) as f64 + 10.0 * nb * nb * nb;
    primal_cost <= dual_cost
}

/// Identify an LPV state-space model with LPV-PBSID_opt from data (Algorithm 1 with the
/// primal statistics, or Algorithm 2 in the kernel form, whichever is cheaper).
pub fn fit(sig: &Signals, opts: &PbsidOptions) -> Result<PbsidFit, FitError> {
    fit_with_validation(sig, None, opts)
}

/// As [`fit`]; `val` is the validation data BPDN-SV scores its path on. Without it,
/// `BpdnScore::Simulation` (the default) scores on the whole of `sig` with an AIC order
/// penalty and `BpdnScore::OneStep` on the last quarter of `sig`, as the sparse paper does.
/// Other regularisations ignore it.
pub fn fit_with_validation(
    sig: &Signals,
    val: Option<&Signals>,
    opts: &PbsidOptions,
) -> Result<PbsidFit, FitError> {
    state_candidates(sig, val, opts)?.realize(sig, opts, None)
}

/// The first stage of a fit, shared by every order: the regression, the singular values
/// (15) and the state candidates of (16) for all orders (or the sparse path's states and
/// order). [`StateCandidates::realize`] finishes a model at one order, so that comparing
/// orders (`--order auto`'s free-run check) costs one regression, not one per order.
#[derive(Clone)]
pub struct StateCandidates {
    scaling: Scaling,
    sv: Vec<f64>,
    x: nalgebra::DMatrix<f64>,
    reg: ridge::RegressionInfo,
    solver: Solver,
    solver_reason: String,
    sparse_order: Option<(usize, String)>,
    q: usize,
    windows: usize,
    past: usize,
    /// State time of the first column of `x`: the past window p, or earlier for a sparse
    /// estimate of shallower depth (see `bpdn::depth`).
    start: usize,
}

/// The regression and state candidates of [`fit_with_validation`] (all but the order choice
/// and the realization).
/// Inside a [`memo::Scope`] the candidates of the same signals and regression settings are
/// computed once.
pub fn state_candidates(
    sig: &Signals,
    val: Option<&Signals>,
    opts: &PbsidOptions,
) -> Result<StateCandidates, FitError> {
    memo::state_candidates(sig, val, opts, || compute_state_candidates(sig, val, opts))
}

/// [`state_candidates`] computed.
fn compute_state_candidates(
    sig: &Signals,
    val: Option<&Signals>,
    opts: &PbsidOptions,
) -> Result<StateCandidates, FitError> {
    let (n_samples, r, l, s) = (sig.len(), sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
    let dims = PbsidDims::new(r, l, s, opts.past)?;
    let p = dims.p;
    let m = dims.m();
    let min_samples = p + 3;
    if n_samples < min_samples {
        return Err(FitError::TooFewSamples {
            samples: n_samples,
            past: p,
            needed: min_samples,
        });
    }
    let windows = n_samples - p;
    let q = dims.q()?;
    let r_ft = if opts.feedthrough { r } else { 0 };
    let f = check_options(&dims, windows, opts)?;
    let scaling = ChannelSums::from_signals(sig, p).scaling(opts.sched_weight, opts.centre)?;
    let rows = scaled_rows(sig, &scaling);
    let slab = Slab::new(&rows, r, l, m)?;

    let primal_cheaper = primal_is_cheaper(q + r_ft, windows, p);
    let (solver, solver_reason) = match opts.solver {
        _ if opts.kernel_rows.is_some() => (
            Solver::Dual,
            "kernel form with row selection (Algorithm 3)".to_string(),
        ),
        Solver::Primal => (Solver::Primal, "primal form requested".to_string()),
        Solver::Dual => (Solver::Dual, "kernel form requested".to_string()),
        Solver::Auto => {
            if primal_cheaper {
                (
                    Solver::Primal,
                    format!(
                        "primal: q = {q} regressors (+ {r_ft} feedthrough) for {windows} windows"
                    ),
                )
            } else {
                (
                    Solver::Dual,
                    format!(
                        "kernel: q = {q} regressors (+ {r_ft} feedthrough) exceed what {windows} windows make cheaper in the dual"
                    ),
                )
            }
        }
    };
    if solver == Solver::Primal && q > 20_000 {
        return Err(FitError::PrimalTooLarge { q });
    }
    if solver == Solver::Dual && windows > 20_000 {
        return Err(FitError::KernelTooLarge { windows });
    }

    // Candidate states for windows 0..=N-p (the last one only as the successor state).
    let sparse = matches!(opts.reg, Reg::BpdnAic | Reg::BpdnSv);
    let val_rows = match (opts.reg, val) {
        (Reg::BpdnSv, Some(v)) => {
            if v.u.ncols() != r || v.y.ncols() != l || v.p.ncols() != s {
                return Err(FitError::ValidationSignals);
            }
            Some(scaled_rows(v, &scaling))
        }
        _ => None,
    };
    let mut solver_reason = solver_reason;
    let mut sparse_order = None;
    // state time of the first column of x (p, or earlier for a sparse estimate of
    // shallower depth, see bpdn::depth)
    let mut start = p;
    let (sv, x, reg) = match solver {
        _ if sparse => {
            let (sv, x, reg, why, order, first) =
                sparse::bpdn_states(&dims, f, &slab, windows, val_rows.as_deref(), opts)?;
            solver_reason = format!("sparse form with explicit regressors ({why})");
            sparse_order = order;
            start = first;
            (sv, x, reg)
        }
        Solver::Dual => dual::dual_states(&dims, f, &slab, windows, opts)?,
        _ => primal::primal_states(&dims, f, &slab, windows, opts)?,
    };
    Ok(StateCandidates {
        scaling,
        sv,
        x,
        reg,
        solver,
        solver_reason,
        sparse_order,
        q,
        windows,
        past: p,
        start,
    })
}

impl StateCandidates {
    /// The singular values of (15), largest first.
    pub fn singular_values(&self) -> &[f64] {
        &self.sv
    }

    /// The model at `order` (None: the order rule of `opts`, or the sparse path's choice),
    /// realized from the first `order` state candidates on the same data `sig` (eqs. (17)-(18):
    /// least squares for the system matrices given the states), then refined if `opts` asks.
    pub fn realize(
        &self,
        sig: &Signals,
        opts: &PbsidOptions,
        order: Option<usize>,
    ) -> Result<PbsidFit, FitError> {
        let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
        let dims = PbsidDims::new(r, l, s, self.past)?;
        let (order, order_reason) = match (order, &self.sparse_order) {
            (Some(o), _) => {
                if o == 0 || o > self.x.nrows() {
                    return Err(FitError::OrderTooLarge {
                        order: o,
                        available: self.x.nrows(),
                    });
                }
                (o, format!("order {o} given"))
            }
            (None, Some(chosen)) => chosen.clone(),
            (None, None) => choose_order(&self.sv, self.windows, opts)?,
        };
        let rows = scaled_rows(sig, &self.scaling);
        let slab = Slab::new(&rows, r, l, dims.m())?;
        let scaling = self.scaling.clone();
        let (sv, reg, solver, solver_reason, q, windows) = (
            self.sv.clone(),
            &self.reg,
            self.solver,
            self.solver_reason.clone(),
            self.q,
            self.windows,
        );
        let states = self.x.rows(0, order).into_owned();
        let scaled = realize_from_states(
            &PbsidDims::new(r, l, s, self.start)?,
            &slab,
            &states,
            opts.feedthrough,
        )?;
        // the fit reports the states of times p..=N (what the observer step aligns with)
        let skip = self.past - self.start;
        let states = states.columns(skip, states.ncols() - skip).into_owned();
        let mut model = unscale(&scaled, &scaling);
        let mut refinement = None;
        if opts.refine {
            let r = crate::refine::refine_output_error(&model, sig, opts.feedthrough, 50);
            if r.mse_after < r.mse_before {
                model = r.model;
            }
            refinement = Some((r.mse_before, r.mse_after.min(r.mse_before), r.iterations));
        }
        Ok(PbsidFit {
            model,
            singular_values: sv,
            order,
            order_reason,
            lambda: reg.lambda_rel(),
            dof: reg.dof,
            solver,
            solver_reason,
            q,
            windows,
            scaling,
            states: Some(states),
            refinement,
        })
    }
}

/// Identify from statistics alone (a device's pull, or merged experiments): the Gram of the
/// `Extended` statistic vectors of raw (unscaled) samples. Scaling is applied to the
/// statistics (D G D), regression (13) and the SVD are the primal ones of [`fit`], and the
/// realization's least squares use moments that are linear maps of the statistics, so the
/// model equals the file-based primal fit of the same samples up to rounding.
pub fn fit_from_stats<S: AsRef<[f64]> + AsMut<[f64]>>(
    gram: &Gram<f64, S>,
    dims: &PbsidDims,
    opts: &PbsidOptions,
) -> Result<PbsidFit, FitError> {
    let layout = StatsLayout::Extended;
    let len = stat_vector_len(dims, layout)?;
    if gram.dim() != len {
        return Err(FitError::StatisticsDimension {
            got: gram.dim(),
            expected: len,
            r: dims.r,
            l: dims.l,
            s: dims.s,
            p: dims.p,
        });
    }
    let sums = ChannelSums::from_stats(gram, dims, layout)?;
    let windows = sums.count.round() as usize;
    if opts.past != dims.p {
        return Err(FitError::StatisticsPastWindow {
            statistics: dims.p,
            asked: opts.past,
        });
    }
    let f = check_options(dims, windows, opts)?;
    let scaling = sums.scaling(opts.sched_weight, opts.centre)?;
    let mut g = dense(gram, len);
    scale_stat_gram(dims, layout, &scaling, &vec![0.0; dims.s], &mut g)?;
    let d = dims.stat_len()?;
    let plain = g.view((0, 0), (d, d)).into_owned();
    let (reg, sv, t) = primal_regression_svd(dims, f, &plain, windows, opts)?;
    let (order, order_reason) = choose_order(&sv, windows, opts)?;
    let t = t.rows(0, order).into_owned();
    let gv = g.view((0, 0), (d * dims.m(), d * dims.m())).into_owned();
    let scaled = realize_from_stats(dims, &t, &gv, opts.feedthrough)?;
    let model = unscale(&scaled, &scaling);
    Ok(PbsidFit {
        model,
        singular_values: sv,
        order,
        order_reason,
        lambda: reg.lambda_rel(),
        dof: reg.dof,
        solver: Solver::Primal,
        solver_reason: "from statistics (primal form)".into(),
        q: dims.q()?,
        windows,
        scaling,
        states: None,
        refinement: None,
    })
}
