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

/// Sparse path (sparse paper section 4.2): [C K^p, D] by the group-lasso path of (33) on
/// explicit regressors. BPDN-AIC: the point of rule (34), then Gamma^p K^p Z by eq. (14),
/// the SVD (15) and the state candidates (16) for windows 0..=N-p. BPDN-SV with
/// `BpdnScore::Simulation` (default): the point and the order whose realized model
/// simulates best ([`bpdn::select_by_simulation`]); the chosen order is returned with its
/// reason. BPDN-SV with `BpdnScore::OneStep`: Algorithm 1 of the paper ([`bpdn_paper`]).
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
    ),
    FitError,
> {
    let (p, l) = (dims.p, dims.l);
    let all: Vec<usize> = (0..windows).collect();
    let (g, y) = bpdn::LazyGram::build(dims, slab, &all, opts.feedthrough)?;
    if opts.reg == Reg::BpdnSv && opts.bpdn_score == BpdnScore::OneStep {
        let (sv, x, info, why) = bpdn_paper(dims, f, slab, windows, &g, val_rows, opts)?;
        return Ok((sv, x, info, why, None));
    }
    if opts.reg == Reg::BpdnSv {
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
        let orders: Vec<usize> = match opts.order {
            Order::Fixed(n) => vec![n],
            Order::Auto => (1..=opts.max_order.min(f * l).min(windows / 2).max(1)).collect(),
        };
        let sel = bpdn::select_by_simulation(
            dims,
            f,
            &g,
            &y,
            slab,
            val_slab.as_ref(),
            &orders,
            opts.feedthrough,
        )?;
        let info = RegressionInfo {
            lambda: Some((sel.lambda, 1.0)),
            dof: sel.active as f64,
        };
        let why = match opts.order {
            Order::Fixed(n) => format!("order {n} given"),
            Order::Auto => format!(
                "order {} realizes the model with the best free-run score on the BPDN-SV path",
                sel.order
            ),
        };
        return Ok((
            sel.singular_values,
            sel.states,
            info,
            sel.reason,
            Some((sel.order, why)),
        ));
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
    Ok((sv, x, info, sel.reason, None))
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
