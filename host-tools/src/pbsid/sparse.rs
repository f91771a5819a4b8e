//! The sparse forms of regression (13) (sparse paper,
//! `papers/lpv-pbsid-sparse-bpdn-hinf-observer.md`, section 4.2): BPDN-AIC (problem (33)
//! with rule (34)) and BPDN-SV (Algorithm 1, or our simulation score), glued to the
//! realization: the regressors, the path of [`super::bpdn`], Gamma^p K^p Z (14), the SVD
//! (15) and the state candidates (16).

use lpvid::kernel::dual_kernel;
use lpvid::window::write_pbsid_regressor;
use lpvid::{PbsidDims, Samples, Slab};
use nalgebra::DMatrix;

use super::bpdn;
use super::error::FitError;
use super::realize::states_from_gkz;
use super::ridge::{RegressionInfo, Spectrum, RANK_TOL};
use super::settings::{BpdnScore, Order, PbsidOptions, Reg};
use crate::linalg::sym_eig;

/// Our BPDN-SV over the past windows d = 1..=p: the path, realization and score of
/// [`bpdn::select_by_simulation`] on the regressors z^d (eq. (13) with past window d) of
/// windows 0..N-d, the best score over all (d, lambda, order) wins. The columns of z^d are
/// the lag <= d columns of z^p for the same target, so depth d is problem (33) with the
/// left part of [C K^p, D] beyond lag d set to zero (the sparsity the paper's section 4.2
/// expects of a stable predictor), fitted on the N - d windows that exist for it instead of
/// the N - p of the full regressor. Depths are fitted on up to two threads (deepest, the
/// costliest, first); ties go to the shallower depth. Returns the selection and its depth.
pub fn sv_over_depths(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    val: Option<&Slab<'_, f64>>,
    opts: &PbsidOptions,
) -> Result<(bpdn::SimSelection, usize), FitError> {
    let workers = std::thread::available_parallelism().map_or(1, |v| v.get());
    sv_over_depths_with(dims, slab, val, opts, workers.min(2))
}

/// [`sv_over_depths`] on `workers` threads (1: in the calling thread); the result does not
/// depend on it (`benches/bpdn.rs` times 1 against 2).
pub fn sv_over_depths_with(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    val: Option<&Slab<'_, f64>>,
    opts: &PbsidOptions,
    workers: usize,
) -> Result<(bpdn::SimSelection, usize), FitError> {
    let p = dims.p;
    let one = |d: usize| -> Result<Option<bpdn::SimSelection>, FitError> {
        let l = dims.l;
        let dims_d = PbsidDims::new(dims.r, l, dims.s, d)?;
        let f_d = opts.future.map_or(d, |f| f.min(d));
        let w_d = slab.len().saturating_sub(d);
        let orders: Vec<usize> = match opts.order {
            Order::Fixed(n) if n <= f_d * l => vec![n],
            Order::Fixed(_) => return Ok(None),
            Order::Auto => (1..=opts.max_order.min(f_d * l).min(w_d / 2).max(1)).collect(),
        };
        let all: Vec<usize> = (0..w_d).collect();
        let (g, y) = bpdn::LazyGram::build(&dims_d, slab, &all, opts.feedthrough)?;
        let sel =
            bpdn::select_by_simulation(&dims_d, f_d, &g, &y, slab, val, &orders, opts.feedthrough)?;
        Ok(Some(sel))
    };
    let next = std::sync::atomic::AtomicUsize::new(0);
    let workers = workers.clamp(1, p.max(1));
    let work = || {
        let mut out = Vec::new();
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if i >= p {
                return out;
            }
            let d = p - i;
            out.push((d, one(d)));
        }
    };
    let mut results: Vec<(usize, Result<Option<bpdn::SimSelection>, FitError>)> = if workers <= 1 {
        work()
    } else {
        std::thread::scope(|sc| {
            let handles: Vec<_> = (0..workers).map(|_| sc.spawn(work)).collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().expect("BPDN-SV depth worker panicked"))
                .collect()
        })
    };
    results.sort_by_key(|r| r.0);
    let mut best: Option<(bpdn::SimSelection, usize)> = None;
    let mut first_err = None;
    for (d, r) in results {
        match r {
            Ok(Some(sel)) => {
                if best.as_ref().is_none_or(|(b, _)| sel.score < b.score) {
                    best = Some((sel, d));
                }
            }
            Ok(None) => {}
            Err(e) => {
                first_err.get_or_insert(e);
            }
        }
    }
    match (best, first_err) {
        (Some(b), _) => Ok(b),
        (None, Some(e)) => Err(e),
        (None, None) => Err(bpdn::BpdnError::NoCandidateOrder.into()),
    }
}

/// Sparse path (sparse paper section 4.2): [C K^p, D] by the group-lasso path of (33) on
/// explicit regressors. BPDN-AIC: the point of rule (34), then Gamma^p K^p Z by eq. (14),
/// the SVD (15) and the state candidates (16) for windows 0..=N-p. BPDN-SV with
/// `BpdnScore::Simulation` (default): the depth, point and order whose realized model
/// simulates best ([`sv_over_depths`]); the chosen order is returned with its reason. BPDN-SV
/// with `BpdnScore::OneStep`: Algorithm 1 of the paper ([`bpdn_paper`]). The last value is
/// the past window of the returned states (column k is the state of time depth + k): the
/// chosen depth for our BPDN-SV, p otherwise.
#[allow(clippy::type_complexity)]
pub(crate) fn bpdn_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    val_rows: Option<&[f64]>,
    opts: &PbsidOptions,
) -> Result<
    (
        Vec<f64>,
        DMatrix<f64>,
        RegressionInfo,
        String,
        Option<(usize, String)>,
        usize,
    ),
    FitError,
> {
    let (p, l) = (dims.p, dims.l);
    if opts.reg == Reg::BpdnSv && opts.bpdn_score == BpdnScore::Simulation {
        let val_slab = match val_rows {
            Some(rows) => {
                let vs = Slab::new(rows, dims.r, dims.l, dims.m())?;
                if vs.len() < p + 2 {
                    return Err(FitError::ValidationTooShort);
                }
                Some(vs)
            }
            None => None,
        };
        let (sel, depth) = sv_over_depths(dims, slab, val_slab.as_ref(), opts)?;
        let info = RegressionInfo {
            lambda: Some((sel.lambda, 1.0)),
            dof: sel.active as f64,
        };
        let why = match opts.order {
            Order::Fixed(n) => format!("order {n} given"),
            Order::Auto => format!(
                "order {} realizes the model with the best free-run score on the BPDN-SV paths",
                sel.order
            ),
        };
        let reason = format!(
            "{}; past windows 1..={p} scored, depth {depth} chosen",
            sel.reason
        );
        return Ok((
            sel.singular_values,
            sel.states,
            info,
            reason,
            Some((sel.order, why)),
            depth,
        ));
    }
    let all: Vec<usize> = (0..windows).collect();
    let (g, y) = bpdn::LazyGram::build(dims, slab, &all, opts.feedthrough)?;
    if opts.reg == Reg::BpdnSv {
        // BpdnScore::OneStep
        let (sv, x, info, why) = bpdn_paper(dims, f, slab, windows, &g, val_rows, opts)?;
        return Ok((sv, x, info, why, None, p));
    }
    // residual of the unregularised (minimum-norm) solution, for rule (34), from the kernel
    let rss_unreg = {
        let g = DMatrix::from_fn(windows, windows, |a, b| {
            dual_kernel(slab, a, slab, b, p, opts.feedthrough)
        });
        let (vals, vecs) = sym_eig(&g)?;
        let yv = DMatrix::from_row_slice(l, windows, &y);
        let bd = vecs.transpose() * yv.transpose();
        let spec = Spectrum {
            energy: (0..windows).map(|i| bd.row(i).norm_squared()).collect(),
            vals,
            total: yv.norm_squared(),
            rows: windows as f64,
        };
        let vmax = spec.vals.iter().copied().fold(0.0, f64::max);
        spec.rss_dof(0.0, vmax * RANK_TOL).0
    };
    let sel = bpdn::select(&g, &y, l, bpdn::Rule::Aic, None, rss_unreg)?;
    let mut z_last = vec![0.0; dims.q()?];
    write_pbsid_regressor(dims, slab, windows, &mut z_last);
    let gkz = bpdn::gamma_kz(dims, f, &sel.theta, &g, &z_last);
    let (sv, x) = states_from_gkz(&gkz, windows)?;
    let info = RegressionInfo {
        lambda: Some((sel.lambda, 1.0)),
        dof: sel.active as f64,
    };
    Ok((sv, x, info, sel.reason, None, p))
}

/// BPDN-SV as the sparse paper does it (Algorithm 1, section 5.1): the group-lasso path on
/// the identification windows, each point scored by the one-step prediction error
/// ||Y_val - [C K^p, D] Z_val||_F of the validation windows, computed from their statistics
/// (Gram, cross products, ||Y_val||^2). With `val_rows` (a validation file) every training
/// window identifies and every window of the file validates; without it the first three
/// quarters of the training record identify (windows whose target y_{k+p} lies in them)
/// and the windows lying wholly in the last quarter validate. The chosen [C K^p, D] is not
/// refit; Gamma^p K^p Z (14), the SVD (15) and the state candidates (16) are then formed on
/// all training windows (`g`) and the order is left to the singular-value rule.
#[allow(clippy::too_many_arguments)]
pub(crate) fn bpdn_paper(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    g: &bpdn::LazyGram,
    val_rows: Option<&[f64]>,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo, String), FitError> {
    let (p, l) = (dims.p, dims.l);
    let val_slab = match val_rows {
        Some(rows) => Some(Slab::new(rows, dims.r, dims.l, dims.m())?),
        None => None,
    };
    let (id_windows, val_windows, split): (Vec<usize>, Vec<usize>, String) = match &val_slab {
        Some(vs) => (
            (0..windows).collect(),
            (0..vs.len().saturating_sub(p)).collect(),
            "validation file".to_string(),
        ),
        None => {
            let n_id = (3 * slab.len()) / 4;
            (
                (0..windows).filter(|k| k + p < n_id).collect(),
                (0..windows).filter(|&k| k >= n_id).collect(),
                format!("samples {n_id}.. of the training record"),
            )
        }
    };
    if id_windows.len() < 2 || val_windows.len() < 2 {
        return Err(FitError::TooFewBpdnWindows {
            identification: id_windows.len(),
            validation: val_windows.len(),
            past: p,
        });
    }
    let (id, y_id) = bpdn::LazyGram::build(dims, slab, &id_windows, opts.feedthrough)?;
    let (val, y_val) = bpdn::LazyGram::build(
        dims,
        val_slab.as_ref().unwrap_or(slab),
        &val_windows,
        opts.feedthrough,
    )?;
    let sel = bpdn::select(&id, &y_id, l, bpdn::Rule::Sv, Some((&val, &y_val)), 0.0)?;
    let mut z_last = vec![0.0; dims.q()?];
    write_pbsid_regressor(dims, slab, windows, &mut z_last);
    let gkz = bpdn::gamma_kz(dims, f, &sel.theta, g, &z_last);
    let (sv, x) = states_from_gkz(&gkz, windows)?;
    let info = RegressionInfo {
        lambda: Some((sel.lambda, 1.0)),
        dof: sel.active as f64,
    };
    let why = format!(
        "{} (Algorithm 1: path on {} identification windows, one-step error on {} validation windows, {split})",
        sel.reason,
        id_windows.len(),
        val_windows.len()
    );
    Ok((sv, x, info, why))
}
