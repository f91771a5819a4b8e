//! LPV-PBSID_opt (kernel paper, Algorithms 1 and 2): regression (13) from the core's
//! statistics (primal) or in the dual/kernel form (19)-(22) when the regressor outgrows the
//! data, Gamma^p K^p Z by eq. (14) or eq. (25), SVD (15), state (16), then the system
//! matrices by least squares (section 4.3).
//!
//! Signals are scaled internally (inputs and outputs by their standard deviation, each
//! scheduling signal centred and scaled — an exact affine re-parametrisation of mu) and the
//! model is returned in original units.

use lpvid::dictionary::{
    dictionary_gram_len, dictionary_storage_len, DictionaryConfig, KernelDictionary, Step,
};
use lpvid::kernel::dual_kernel;
use lpvid::window::write_pbsid_regressor;
use lpvid::{
    packed_len, stat_vector_len, write_stat_vector, Gram, PbsidDims, Samples, Slab, StatsLayout,
};
use nalgebra::{DMatrix, DVector};

use crate::bpdn;
use crate::kernel_sweep::{dot4, KernelSweep};
use crate::linalg::{min_norm_from_normal, sym_eig, Tridiagonal};
use crate::lpvss::{LpvSs, Signals};

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

impl std::str::FromStr for Reg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(Reg::None),
            "tikhonov-gcv" => Ok(Reg::TikhonovGcv),
            "bpdn-aic" => Ok(Reg::BpdnAic),
            "bpdn-sv" => Ok(Reg::BpdnSv),
            t if t.starts_with("tikhonov=") => t[9..]
                .parse::<f64>()
                .map(Reg::Tikhonov)
                .map_err(|e| format!("bad Tikhonov parameter in '{t}': {e}")),
            other => Err(format!(
                "unknown regularisation '{other}' (expected none, tikhonov-gcv, bpdn-aic or bpdn-sv)"
            )),
        }
    }
}

/// How BPDN-SV (`Reg::BpdnSv`) scores the points of its group-lasso path (see the module
/// documentation of [`crate::bpdn`] for the evidence behind the default).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BpdnScore {
    /// Ours (the default): the free-run simulation of each point's realized model, on the
    /// `--val` data or on the whole training record with an AIC order penalty; the point
    /// and the order come out together ([`bpdn::select_by_simulation`]).
    #[default]
    Simulation,
    /// The sparse paper's Algorithm 1: the path on the identification windows, each point
    /// scored by its one-step prediction error on the validation windows (from their
    /// statistics; the last quarter of the training record when no validation data are
    /// given), the order then by the singular-value rule ([`bpdn::select`] with
    /// [`bpdn::Rule::Sv`]).
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
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "simulation" => Ok(BpdnScore::Simulation),
            "paper" => Ok(BpdnScore::OneStep),
            other => Err(format!(
                "unknown BPDN-SV score '{other}' (expected simulation or paper)"
            )),
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
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Order::Auto);
        }
        match s.parse::<usize>() {
            Ok(n) if n > 0 => Ok(Order::Fixed(n)),
            _ => Err(format!(
                "order must be a positive integer or 'auto', got '{s}'"
            )),
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
        }
    }
}

/// Default scheduling weight kappa (see [`PbsidOptions::sched_weight`]).
pub const DEFAULT_SCHED_WEIGHT: f64 = 0.05;

/// Internal scaling: u' = u / su, y' = y / sy, p' = (p - pc) / ps.
#[derive(Debug, Clone, PartialEq)]
pub struct Scaling {
    /// Input scales.
    pub u: Vec<f64>,
    /// Output scales.
    pub y: Vec<f64>,
    /// Scheduling centres (zero: centring would move the first local model A^(1), whose
    /// powers build Gamma^p in eq. (14), away from p = 0 and break its structure).
    pub p_center: Vec<f64>,
    /// Scheduling scales.
    pub p_scale: Vec<f64>,
}

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

/// Sums of the channels over the windows' target samples (samples p..N-1): exactly what
/// the channel block of the core's statistic vector accumulates, so a file fit and a fit
/// from a device's statistics scale identically.
#[derive(Debug, Clone)]
struct ChannelSums {
    count: f64,
    u: Vec<(f64, f64)>,
    y: Vec<(f64, f64)>,
    p: Vec<(f64, f64)>,
}

impl ChannelSums {
    fn from_signals(sig: &Signals, start: usize) -> ChannelSums {
        let col = |m: &DMatrix<f64>, j: usize| {
            m.column(j)
                .iter()
                .skip(start)
                .fold((0.0, 0.0), |(a, b), v| (a + v, b + v * v))
        };
        ChannelSums {
            count: (sig.len() - start) as f64,
            u: (0..sig.u.ncols()).map(|j| col(&sig.u, j)).collect(),
            y: (0..sig.y.ncols()).map(|j| col(&sig.y, j)).collect(),
            p: (0..sig.p.ncols()).map(|j| col(&sig.p, j)).collect(),
        }
    }

    /// Read the sums from statistics of `layout` (channel block after the core part).
    fn from_stats<S: AsRef<[f64]> + AsMut<[f64]>>(
        g: &Gram<f64, S>,
        dims: &PbsidDims,
        layout: StatsLayout,
    ) -> Result<ChannelSums, FitError> {
        let len = stat_vector_len(dims, layout)?;
        let one = len - 1 - dims.s;
        let q = dims.q()?;
        Ok(ChannelSums {
            count: g.get(one, one),
            u: (0..dims.r)
                .map(|j| (g.get(one, q + j), g.get(q + j, q + j)))
                .collect(),
            y: (0..dims.l)
                .map(|j| {
                    let i = q + dims.r + j;
                    (g.get(one, i), g.get(i, i))
                })
                .collect(),
            p: (0..dims.s)
                .map(|j| (g.get(one, one + 1 + j), g.get(one + 1 + j, one + 1 + j)))
                .collect(),
        })
    }

    /// Internal scaling: inputs and outputs by their standard deviation, scheduling by
    /// its RMS times sqrt(s / kappa) (no centring: see [`Scaling::p_center`]).
    fn scaling(&self, kappa: f64) -> Result<Scaling, FitError> {
        let n = self.count;
        let stats = |(s1, s2): (f64, f64)| {
            let mean = s1 / n;
            let var = (s2 / n - mean * mean).max(0.0);
            (mean, var.sqrt(), (s2 / n).sqrt())
        };
        let constant = |mean: f64, sd: f64| sd <= 1e-12 * mean.abs().max(1e-300) || sd == 0.0;
        let mut sc = Scaling {
            u: vec![],
            y: vec![],
            p_center: vec![0.0; self.p.len()],
            p_scale: vec![],
        };
        for (j, &m) in self.u.iter().enumerate() {
            let (mean, sd, _) = stats(m);
            if constant(mean, sd) {
                return Err(FitError(format!(
                    "input u{} is constant: it carries no information and makes the regression rank deficient",
                    j + 1
                )));
            }
            sc.u.push(sd);
        }
        for (j, &m) in self.y.iter().enumerate() {
            let (mean, sd, _) = stats(m);
            if constant(mean, sd) {
                return Err(FitError(format!("output y{} is constant", j + 1)));
            }
            sc.y.push(sd);
        }
        let s = self.p.len() as f64;
        for (j, &m) in self.p.iter().enumerate() {
            let (mean, sd, rms) = stats(m);
            if constant(mean, sd) {
                return Err(FitError(format!(
                    "scheduling p{} is constant: it is indistinguishable from the affine term",
                    j + 1
                )));
            }
            sc.p_scale.push(rms / (kappa / s).sqrt());
        }
        Ok(sc)
    }
}

/// The signals in scaled units laid out as the core's sample rows [u', y', mu'].
fn scaled_rows(sig: &Signals, sc: &Scaling) -> Vec<f64> {
    let (n, r, l, s) = (sig.len(), sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
    let w = r + l + s + 1;
    let mut rows = vec![0.0; n * w];
    for k in 0..n {
        let row = &mut rows[k * w..(k + 1) * w];
        for (j, v) in row[..r].iter_mut().enumerate() {
            *v = sig.u[(k, j)] / sc.u[j];
        }
        for (j, v) in row[r..r + l].iter_mut().enumerate() {
            *v = sig.y[(k, j)] / sc.y[j];
        }
        row[r + l] = 1.0;
        for (j, v) in row[r + l + 1..].iter_mut().enumerate() {
            *v = (sig.p[(k, j)] - sc.p_center[j]) / sc.p_scale[j];
        }
    }
    rows
}

/// The diagonal D with s' = D s for statistic vectors of scaled signals: every entry of s
/// is a product of one value per channel factor, so D is the statistic vector of a
/// constant "sample" holding the reciprocal scales (the same core code writes both).
fn stat_scale_vector(
    dims: &PbsidDims,
    layout: StatsLayout,
    sc: &Scaling,
) -> Result<Vec<f64>, FitError> {
    let mut row = Vec::with_capacity(dims.sample_len());
    row.extend(sc.u.iter().map(|v| 1.0 / v));
    row.extend(sc.y.iter().map(|v| 1.0 / v));
    row.push(1.0);
    row.extend(sc.p_scale.iter().map(|v| 1.0 / v));
    let rows: Vec<f64> = (0..=dims.p).flat_map(|_| row.iter().copied()).collect();
    let slab = Slab::new(&rows, dims.r, dims.l, dims.m())?;
    let mut out = vec![0.0; stat_vector_len(dims, layout)?];
    write_stat_vector(dims, layout, &slab, 0, &mut out);
    Ok(out)
}

/// Spectrum of a ridge problem in the form shared by the primal and the dual: eigenvalues
/// lambda_i of the Gram (equal nonzero eigenvalues either way), the energy c_i of the
/// targets along each (dual coordinates), the total target energy and the row count. GCV
/// computed from this is the same number whichever form was solved.
struct Spectrum {
    vals: Vec<f64>,
    energy: Vec<f64>,
    total: f64,
    rows: f64,
}

impl Spectrum {
    /// Residual sum of squares and effective degrees of freedom at ridge parameter `lam`
    /// (lam = 0: minimum norm with eigenvalues below `cut` dropped).
    fn rss_dof(&self, lam: f64, cut: f64) -> (f64, f64) {
        let (rss, deficit) = self.rss_deficit(lam, cut);
        (rss, self.rows - deficit)
    }

    /// RSS and rows - dof, each computed without cancellation: the residual factor of
    /// component i is lam / (lambda_i + lam), and dropped components count fully.
    fn rss_deficit(&self, lam: f64, cut: f64) -> (f64, f64) {
        // energy outside the Gram's range (zero in the dual); clamp the cancellation error
        let mut rss = (self.total - self.energy.iter().sum::<f64>()).max(0.0);
        let mut deficit = self.rows;
        for (&v, &c) in self.vals.iter().zip(&self.energy) {
            if v <= cut {
                rss += c;
                continue;
            }
            let g = residual_factor(v, lam);
            rss += c * g * g;
            deficit -= 1.0 - g;
        }
        (rss.max(0.0), deficit.max(0.0))
    }

    /// GCV(lam) = rows * RSS / (rows - dof)^2.
    fn gcv(&self, lam: f64, cut: f64) -> f64 {
        let (rss, deficit) = self.rss_deficit(lam, cut);
        if deficit <= 0.0 {
            return f64::INFINITY;
        }
        self.rows * rss / (deficit * deficit)
    }

    /// Ridge parameter minimising GCV (see [`gcv_minimiser`]).
    fn gcv_lambda(&self, cut: f64) -> f64 {
        let vmax = self.vals.iter().copied().fold(0.0, f64::max);
        gcv_minimiser(vmax, |lam| self.gcv(lam, cut))
    }
}

/// Ridge parameter minimising `gcv(lam)`: a log grid over 14 decades below the largest
/// eigenvalue `vmax`, refined by golden-section search in log(lam).
fn gcv_minimiser(vmax: f64, gcv: impl Fn(f64) -> f64) -> f64 {
    let vmax = vmax.max(1e-300);
    let f = |e: f64| gcv(vmax * 10f64.powf(e));
    let (lo, hi, step) = (-14.0, 1.0, 0.25);
    let mut best = (lo, f(lo));
    let mut e = lo;
    while e <= hi {
        let g = f(e);
        if g < best.1 {
            best = (e, g);
        }
        e += step;
    }
    let (mut a, mut b) = (best.0 - step, best.0 + step);
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let mut c = b - phi * (b - a);
    let mut d = a + phi * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..40 {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - phi * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + phi * (b - a);
            fd = f(d);
        }
    }
    let e = 0.5 * (a + b);
    let e = if f(e) <= best.1 { e } else { best.0 };
    vmax * 10f64.powf(e)
}

/// Relative eigenvalue cut-off defining the numerical rank of a Gram matrix.
const RANK_TOL: f64 = 1e-11;

/// Pick lambda for the chosen regularisation; returns (lambda, dof, cut).
fn choose_lambda(reg: Reg, spec: &Spectrum) -> (f64, f64, f64) {
    let vmax = spec.vals.iter().copied().fold(0.0, f64::max);
    let cut = vmax * RANK_TOL;
    let lam = match reg {
        Reg::None | Reg::BpdnAic | Reg::BpdnSv => 0.0,
        Reg::TikhonovGcv => spec.gcv_lambda(cut),
        Reg::Tikhonov(rel) => rel * vmax,
    };
    let (_, dof) = spec.rss_dof(lam, cut);
    (lam, dof, cut)
}

/// Filter factor applied to component i: 1/(v + lam), or 0 below the rank cut-off.
fn filter(v: f64, lam: f64, cut: f64) -> f64 {
    if v <= cut {
        0.0
    } else {
        (1.0 - residual_factor(v, lam)) / v
    }
}

/// 1 - phi_i, the part of component i the regularised fit leaves in the residual.
fn residual_factor(v: f64, lam: f64) -> f64 {
    lam / (v + lam)
}

/// Which normal equations a ridge step solves: primal (A = Phi Phi^T, B = Phi Y^T) or dual
/// (A = Phi^T Phi, B = Y^T). The target energy along eigenvector i of A is (V^T B)_i^2 /
/// lambda_i in the primal and (V^T B)_i^2 in the dual.
#[derive(Clone, Copy, PartialEq)]
enum NormalForm {
    Primal,
    Dual,
}

/// Below this fraction of the largest eigenvalue a Tikhonov parameter is solved through the
/// eigendecomposition (with the rank cut-off) rather than the shifted tridiagonal system.
const SHIFTED_SOLVE_MIN: f64 = 1e-10;

/// The ridge step shared by every form of regression (13): X = (A + lam I)^{-1} B, lam
/// chosen by `reg` on the common [`Spectrum`] (so GCV is the same number in the primal and
/// the dual), lam = 0 the minimum-norm solution (eq. (18)). Tikhonov reduces A to
/// tridiagonal form once: eigenvalues and target energies without eigenvectors, then one
/// tridiagonal solve, O(n^2) after the reduction instead of a full eigendecomposition.
fn ridge_solve(
    a: &DMatrix<f64>,
    b: &DMatrix<f64>,
    form: NormalForm,
    total: f64,
    rows: f64,
    reg: Reg,
) -> Result<(DMatrix<f64>, RegressionInfo), FitError> {
    let spectrum = |vals: &[f64], proj: &DMatrix<f64>| Spectrum {
        energy: vals
            .iter()
            .enumerate()
            .map(|(i, &v)| {
                let e = proj.row(i).norm_squared();
                match form {
                    NormalForm::Dual => e,
                    NormalForm::Primal if v > 0.0 => e / v,
                    NormalForm::Primal => 0.0,
                }
            })
            .collect(),
        vals: vals.to_vec(),
        total,
        rows,
    };
    let tikhonov = matches!(reg, Reg::TikhonovGcv | Reg::Tikhonov(_));
    if tikhonov {
        let tri = Tridiagonal::new(a);
        let bt = tri.to_tridiagonal(b);
        let (lam, dof, vmax) = match form {
            NormalForm::Primal => {
                // the primal residual needs the energies b_i^2 / lambda_i: eigen-coordinates
                let (vals, proj) = tri.eigen_projection(&bt)?;
                let (lam, dof, _) = choose_lambda(reg, &spectrum(&vals, &proj));
                (lam, dof, vals.first().copied().unwrap_or(0.0).max(0.0))
            }
            NormalForm::Dual => {
                // RSS = lam^2 ||(T + lam I)^{-1} Q^T y||^2 and rows - dof =
                // lam tr((T + lam I)^{-1}): O(n) per lambda, no eigenvalues needed
                let vmax = tri.largest_eigenvalue().max(0.0);
                let curve = |lam: f64| {
                    tri.shifted_norm_trace(lam, &bt)
                        .map(|(xx, tr)| (lam * lam * xx, lam * tr))
                };
                let lam = match reg {
                    Reg::Tikhonov(rel) => rel * vmax,
                    _ => gcv_minimiser(vmax, |lam| match curve(lam) {
                        Some((rss, deficit)) if deficit > 0.0 => rows * rss / (deficit * deficit),
                        _ => f64::INFINITY,
                    }),
                };
                let dof = curve(lam).map_or(f64::NAN, |(_, deficit)| rows - deficit);
                (lam, dof, vmax)
            }
        };
        if lam > SHIFTED_SOLVE_MIN * vmax && dof.is_finite() {
            if let Some(w) = tri.solve_shifted(lam, &bt) {
                let lambda = Some((lam, vmax));
                return Ok((tri.from_tridiagonal(&w), RegressionInfo { lambda, dof }));
            }
        }
    }
    let (vals, vecs) = sym_eig(a)?;
    let mut proj = vecs.transpose() * b;
    let (lam, dof, cut) = choose_lambda(reg, &spectrum(&vals, &proj));
    for (i, &v) in vals.iter().enumerate() {
        proj.row_mut(i).scale_mut(filter(v, lam, cut));
    }
    let vmax = vals.first().copied().unwrap_or(0.0);
    let lambda = tikhonov.then_some((lam, vmax));
    Ok((vecs * proj, RegressionInfo { lambda, dof }))
}

/// Gamma^p K^p of eq. (14) from the estimate of C K^p (l x q): row block i, column block j
/// (j >= i) is C (A~^(1))^{i-1} L_{p-j+1}, the leading m^{p-j+1}(r+l) columns of block
/// (j - i + 1) of C K^p (Definitions 2 and 4); blocks with j < i are zero.
pub fn gamma_k(dims: &PbsidDims, f: usize, ck: &DMatrix<f64>) -> DMatrix<f64> {
    let (p, l) = (dims.p, dims.l);
    let q = ck.ncols();
    let mut m = DMatrix::zeros(f * l, q);
    for i in 1..=f {
        for j in i..=p {
            let len = dims.block_len(j);
            let dst = dims.block_offset(j);
            let src = dims.block_offset(j - i + 1);
            m.view_mut(((i - 1) * l, dst), (l, len))
                .copy_from(&ck.view((0, src), (l, len)));
        }
    }
    m
}

/// Order from the singular values of Gamma K Z (the gap of section 4.3). Gaps are
/// d_n = log(sigma_n / sigma_{n+1}). The noise floor is the median of the smaller half of
/// the singular values; an order is a candidate when sigma_n stands at least
/// [`FLOOR_FACTOR`] times above that floor. Among candidates the order is the LARGEST n
/// whose gap is at least half the largest candidate gap, so a big drop after the first
/// singular value (one mode dominating the output energy) does not hide the drop into the
/// noise floor, while gaps inside the floor are never chosen.
pub fn select_order(sv: &[f64], max_n: usize) -> (usize, String) {
    let tiny = sv.first().copied().unwrap_or(0.0) * 1e-13;
    let mut sorted: Vec<f64> = sv.to_vec();
    sorted.sort_by(f64::total_cmp);
    let half = &sorted[..(sorted.len() / 2).max(1)];
    let floor = half[half.len() / 2].max(tiny);
    let upto = max_n.min(sv.len().saturating_sub(1));
    let gaps: Vec<(usize, f64)> = (1..=upto)
        .filter(|&n| n == 1 || sv[n - 1] >= FLOOR_FACTOR * floor)
        .map(|n| (n, (sv[n - 1].max(tiny) / sv[n].max(tiny)).ln()))
        .collect();
    if gaps.is_empty() {
        return (1, "only one singular value".into());
    }
    let (nbig, dmax) = gaps
        .iter()
        .copied()
        .fold((0, f64::MIN), |a, g| if g.1 > a.1 { g } else { a });
    let &(n, d) = gaps
        .iter()
        .rev()
        .find(|g| g.1 >= ALPHA_GAP * dmax)
        .unwrap_or(&gaps[0]);
    let mut reason = format!(
        "singular-value gap after sigma_{n}: sigma_{n}/sigma_{} = {:.1}, sigma_{n} is {:.0}x the noise floor {:.3e}",
        n + 1,
        d.exp(),
        sv[n - 1] / floor,
        floor
    );
    if nbig != n {
        reason.push_str(&format!(
            "; the larger gap {:.1} after sigma_{nbig} is followed by this one",
            dmax.exp()
        ));
    }
    (n, reason)
}

/// Fraction of the largest log-gap a later gap needs to be chosen (see [`select_order`]).
const ALPHA_GAP: f64 = 0.65;
/// How far above the noise floor a singular value must stand to count as signal.
pub const FLOOR_FACTOR: f64 = 4.0;

/// Check the options against the data size; returns the future window.
fn check_options(dims: &PbsidDims, windows: usize, opts: &PbsidOptions) -> Result<usize, FitError> {
    if !(opts.sched_weight > 0.0 && opts.sched_weight.is_finite()) {
        return Err(FitError(format!(
            "scheduling weight must be positive, got {}",
            opts.sched_weight
        )));
    }
    if windows < 2 {
        return Err(FitError(format!(
            "{windows} regression windows: a past window of {} needs more samples",
            dims.p
        )));
    }
    future(dims, opts)
}

/// Order: given, or from the singular values.
fn choose_order(
    sv: &[f64],
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(usize, String), FitError> {
    let max_n = opts.max_order.min(sv.len()).min(windows / 2).max(1);
    match opts.order {
        Order::Fixed(n) => {
            if n > sv.len() {
                return Err(FitError(format!(
                    "order {n} exceeds the f*l = {} singular values: increase the (future) window",
                    sv.len()
                )));
            }
            Ok((n, format!("order {n} given")))
        }
        Order::Auto => Ok(select_order(sv, max_n)),
    }
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
    let (n_samples, r, l, s) = (sig.len(), sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
    let dims = PbsidDims::new(r, l, s, opts.past)?;
    let p = dims.p;
    let m = dims.m();
    let min_samples = p + 3;
    if n_samples < min_samples {
        return Err(FitError(format!(
            "{n_samples} samples, but a past window of {p} needs at least {min_samples} (and many more for a useful fit)"
        )));
    }
    let windows = n_samples - p;
    let q = dims.q()?;
    let r_ft = if opts.feedthrough { r } else { 0 };
    let f = check_options(&dims, windows, opts)?;
    let scaling = ChannelSums::from_signals(sig, p).scaling(opts.sched_weight)?;
    let rows = scaled_rows(sig, &scaling);
    let slab = Slab::new(&rows, r, l, m)?;

    // The cheaper exact form: operation counts of building + decomposing each.
    let qf = (q + r_ft) as f64;
    let nb = windows as f64;
    let primal_cost = nb * qf * qf / 2.0 + 10.0 * qf * qf * qf;
    let dual_cost = nb * nb * (p * p) as f64 + 10.0 * nb * nb * nb;
    let (solver, solver_reason) = match opts.solver {
        _ if opts.kernel_rows.is_some() => (
            Solver::Dual,
            "kernel form with row selection (Algorithm 3)".to_string(),
        ),
        Solver::Primal => (Solver::Primal, "primal form requested".to_string()),
        Solver::Dual => (Solver::Dual, "kernel form requested".to_string()),
        Solver::Auto => {
            if primal_cost <= dual_cost {
                (
                    Solver::Primal,
                    format!("primal: q = {} regressors for {windows} windows", q + r_ft),
                )
            } else {
                (
                    Solver::Dual,
                    format!(
                        "kernel: q = {} regressors exceed what {windows} windows make cheaper in the dual",
                        q + r_ft
                    ),
                )
            }
        }
    };
    if solver == Solver::Primal && q > 20_000 {
        return Err(FitError(format!(
            "the primal form needs a {q} x {q} Gram matrix; use the kernel form (--kernel) or a smaller past window"
        )));
    }
    if solver == Solver::Dual && windows > 20_000 {
        return Err(FitError(format!(
            "the kernel form needs a {windows} x {windows} kernel matrix; use the primal form or fewer samples"
        )));
    }

    // Candidate states for windows 0..=N-p (the last one only as the successor state).
    let sparse = matches!(opts.reg, Reg::BpdnAic | Reg::BpdnSv);
    let val_rows = match (opts.reg, val) {
        (Reg::BpdnSv, Some(v)) => {
            if v.u.ncols() != r || v.y.ncols() != l || v.p.ncols() != s {
                return Err(FitError(
                    "the validation data have other signals than the training data".into(),
                ));
            }
            Some(scaled_rows(v, &scaling))
        }
        _ => None,
    };
    let mut solver_reason = solver_reason;
    let mut sparse_order = None;
    let (sv, x, reg) = match solver {
        _ if sparse => {
            let (sv, x, reg, why, order) =
                bpdn_states(&dims, f, &slab, windows, val_rows.as_deref(), opts)?;
            solver_reason = format!("sparse form with explicit regressors ({why})");
            sparse_order = order;
            (sv, x, reg)
        }
        Solver::Dual => dual_states(&dims, f, &slab, windows, opts)?,
        _ => {
            let len = stat_vector_len(&dims, StatsLayout::Plain)?;
            let mut gram = Gram::new(len, vec![0.0; packed_len(len)])?;
            const BATCH: usize = crate::linalg::GRAM_BATCH;
            let mut buf = vec![0.0; BATCH * len];
            let mut k = 0;
            while k < windows {
                let nb = BATCH.min(windows - k);
                for b in 0..nb {
                    let row = &mut buf[b * len..(b + 1) * len];
                    write_stat_vector(&dims, StatsLayout::Plain, &slab, k + b, row);
                }
                crate::linalg::gram_update_batch(&mut gram, &buf[..nb * len], nb)?;
                k += nb;
            }
            let stats = dense(&gram, len);
            let (reg, sv, t) = primal_regression_svd(&dims, f, &stats, windows, opts)?;
            let mut x = DMatrix::zeros(t.nrows(), windows + 1);
            let mut z = vec![0.0; q];
            for k in 0..=windows {
                write_pbsid_regressor(&dims, &slab, k, &mut z);
                x.set_column(k, &(&t * DVector::from_column_slice(&z)));
            }
            (sv, x, reg)
        }
    };
    let (order, order_reason) = match sparse_order {
        Some(chosen) => chosen,
        None => choose_order(&sv, windows, opts)?,
    };
    let states = x.rows(0, order).into_owned();
    let scaled = realize_from_states(&dims, &slab, &states, opts.feedthrough)?;
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
        return Err(FitError(format!(
            "statistics of dimension {} do not match the extended layout for r={}, l={}, s={}, p={} (expected {len})",
            gram.dim(),
            dims.r,
            dims.l,
            dims.s,
            dims.p
        )));
    }
    let sums = ChannelSums::from_stats(gram, dims, layout)?;
    let windows = sums.count.round() as usize;
    if opts.past != dims.p {
        return Err(FitError(format!(
            "the statistics were accumulated with past window {}, not {}",
            dims.p, opts.past
        )));
    }
    let f = check_options(dims, windows, opts)?;
    let scaling = sums.scaling(opts.sched_weight)?;
    let dvec = stat_scale_vector(dims, layout, &scaling)?;
    let mut g = dense(gram, len);
    for i in 0..len {
        for j in 0..len {
            g[(i, j)] *= dvec[i] * dvec[j];
        }
    }
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

/// The dense symmetric matrix of a Gram's leading `len` rows and columns.
fn dense<S: AsRef<[f64]> + AsMut<[f64]>>(g: &Gram<f64, S>, len: usize) -> DMatrix<f64> {
    DMatrix::from_fn(len, len, |i, j| g.get(i, j))
}

/// Outcome of the regularised regression.
struct RegressionInfo {
    /// (lambda, largest Gram eigenvalue), None for the minimum-norm solution.
    lambda: Option<(f64, f64)>,
    /// Effective number of parameters per output.
    dof: f64,
}

impl RegressionInfo {
    fn lambda_rel(&self) -> Option<f64> {
        self.lambda
            .map(|(lam, vmax)| if vmax > 0.0 { lam / vmax } else { 0.0 })
    }
}

/// SVD of Gamma^p K^p Z (eq. (15)) through the eigendecomposition of its Gram
/// (Gamma K Z)(Gamma K Z)^T, which both forms can build. Returns the singular values and
/// the left singular vectors.
fn svd_left(w: &DMatrix<f64>) -> Result<(Vec<f64>, DMatrix<f64>), FitError> {
    let (vals, vecs) = sym_eig(w)?;
    let sv = vals.iter().map(|v| v.max(0.0).sqrt()).collect();
    Ok((sv, vecs))
}

/// Eq. (15)-(16) on an explicit Gamma K Z (windows 0..=N-p): the SVD from its first
/// `windows` columns (the regression windows), state candidates U^T Gamma K Z for all.
fn states_from_gkz(
    gkz: &DMatrix<f64>,
    windows: usize,
) -> Result<(Vec<f64>, DMatrix<f64>), FitError> {
    let reg_cols = gkz.columns(0, windows);
    let (sv, u) = svd_left(&(reg_cols * reg_cols.transpose()))?;
    Ok((sv, u.transpose() * gkz))
}

/// Primal path on the (scaled) plain statistics `stats` of w_k = [z_k^p; u_{k+p}; y_{k+p}]:
/// regression (13) from them, Gamma^p K^p by eq. (14), the SVD of Gamma K Z from
/// Gamma K S_zz (Gamma K)^T, and T = U^T Gamma^p K^p so that the state candidates are
/// x_{k+p} = T z_k^p (eq. (16): Sigma_n V = U_n^T Gamma K Z).
fn primal_regression_svd(
    dims: &PbsidDims,
    f: usize,
    stats: &DMatrix<f64>,
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(RegressionInfo, Vec<f64>, DMatrix<f64>), FitError> {
    let (r, l) = (dims.r, dims.l);
    let q = dims.q()?;
    let r_ft = if opts.feedthrough { r } else { 0 };
    let qf = q + r_ft;
    let s_ff = stats.view((0, 0), (qf, qf)).into_owned();
    let s_fy = stats.view((0, q + r), (qf, l)).into_owned();
    let syy: f64 = (0..l).map(|j| stats[(q + r + j, q + r + j)]).sum();
    let (x, info) = ridge_solve(
        &s_ff,
        &s_fy,
        NormalForm::Primal,
        syy,
        windows as f64,
        opts.reg,
    )?;
    let theta = x.transpose(); // l x qf
    let ck = theta.columns(0, q).into_owned();
    let gk = gamma_k(dims, f, &ck);
    let s_zz = stats.view((0, 0), (q, q));
    let w = &gk * s_zz * gk.transpose();
    let (sv, u) = svd_left(&w)?;
    let t = u.transpose() * &gk;
    Ok((info, sv, t))
}

/// The future window f (default p), checked.
fn future(dims: &PbsidDims, opts: &PbsidOptions) -> Result<usize, FitError> {
    let f = opts.future.unwrap_or(dims.p);
    if f == 0 || f > dims.p {
        return Err(FitError(format!(
            "future window {f} must be between 1 and the past window {}",
            dims.p
        )));
    }
    Ok(f)
}

/// Dual path (Algorithm 2): kernel Z^T Z + U^T U by Theorem 10, alpha from (19)-(21)
/// (Tikhonov-regularised if asked), Gamma^p K^p Z by eq. (25), and the state candidates
/// U^T Gamma K Z for windows 0..=N-p (the SVD uses the N-p regression windows).
fn dual_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo), FitError> {
    let (p, l) = (dims.p, dims.l);
    let nb = windows;
    if let Some(rows) = opts.kernel_rows {
        return selected_rows_states(dims, f, slab, windows, rows, opts);
    }
    let g = dual_kernel_matrix(slab, p, nb, opts.feedthrough);
    let y = DMatrix::from_fn(l, nb, |j, k| slab.y(k + p)[j]);
    let (x, info) = ridge_solve(
        &g,
        &y.transpose(),
        NormalForm::Dual,
        y.norm_squared(),
        nb as f64,
        opts.reg,
    )?;
    let alpha = x.transpose(); // l x nb
    let gkz = dual_gamma_kz_matrix(dims, f, slab, &alpha, nb + 1);
    let (sv, x) = states_from_gkz(&gkz, nb)?;
    Ok((sv, x, info))
}

/// Sparse path (sparse paper section 4.2): [C K^p, D] by the group-lasso path of (33) on
/// explicit regressors. BPDN-AIC: the point of rule (34), then Gamma^p K^p Z by eq. (14),
/// the SVD (15) and the state candidates (16) for windows 0..=N-p. BPDN-SV with
/// `BpdnScore::Simulation` (default): the point and the order whose realized model
/// simulates best ([`bpdn::select_by_simulation`]); the chosen order is returned with its
/// reason. BPDN-SV with `BpdnScore::OneStep`: Algorithm 1 of the paper ([`bpdn_paper`]).
#[allow(clippy::type_complexity)]
fn bpdn_states(
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
                    return Err(FitError(
                        "the validation data are shorter than the window".into(),
                    ));
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
fn bpdn_paper(
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
        return Err(FitError(format!(
            "{} identification and {} validation windows: too few samples for BPDN-SV (paper score) with a past window of {p}",
            id_windows.len(),
            val_windows.len()
        )));
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

/// Algorithm 3 (kernel selection): the dictionary of windows the core admits by its
/// linear-dependence test (at most `max_rows`, tolerance relative to the mean k(w, w)).
pub fn select_kernel_rows(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    max_rows: usize,
    tol: f64,
    feedthrough: bool,
) -> Result<(Vec<usize>, String), FitError> {
    let n = slab.len();
    if max_rows == 0 {
        return Err(FitError("--kernel-rows must be at least 1".into()));
    }
    let windows = n - dims.p;
    let mean_diag = (0..windows)
        .map(|k| dual_kernel(slab, k, slab, k, dims.p, feedthrough))
        .sum::<f64>()
        / windows as f64;
    let config = DictionaryConfig::new(max_rows, tol * mean_diag, feedthrough);
    let (r, l, s, p) = (dims.r, dims.l, dims.s, dims.p);
    let mut dict = KernelDictionary::with_storage(
        *dims,
        config,
        vec![0.0; lpvid::window_storage_len(r, l, s, p)],
        vec![0.0; dictionary_storage_len(r, l, s, p, max_rows)],
        vec![0.0; dictionary_gram_len(l, max_rows)],
    )?;
    let mut rows = Vec::new();
    for k in 0..n {
        let step = dict.update(slab.u(k), slab.y(k), &slab.mu(k)[1..])?;
        if let Step::Admitted { window, .. } = step {
            if (window as usize) < windows {
                rows.push(window as usize);
            }
        }
    }
    let mut why = format!(
        "{} of {windows} rows kept by the linear-dependence test (tolerance {tol:.1e} x mean k(w,w))",
        rows.len()
    );
    if dict.rejected_full() > 0 {
        why.push_str(&format!(
            "; {} more independent rows did not fit in --kernel-rows {max_rows}",
            dict.rejected_full()
        ));
    }
    if let Some(period) = detect_period(slab, dims.s) {
        why.push_str(&format!(
            "; the scheduling is periodic with period {period} (section 6.1)"
        ));
    }
    Ok((rows, why))
}

/// The smallest period P <= N/3 with p_{k+P} = p_k for every k (to 1e-9 relative), if any.
pub fn detect_period(slab: &Slab<'_, f64>, s: usize) -> Option<usize> {
    let n = slab.len();
    if s == 0 {
        return None;
    }
    let scale = (0..n)
        .flat_map(|k| slab.mu(k)[1..].iter().map(|v| v.abs()))
        .fold(0.0, f64::max)
        .max(1e-300);
    (1..=n / 3).find(|&per| {
        (0..n - per).all(|k| {
            slab.mu(k)[1..]
                .iter()
                .zip(&slab.mu(k + per)[1..])
                .all(|(a, b)| (a - b).abs() <= 1e-9 * scale)
        })
    })
}

/// Kernel form restricted to the rows D of Algorithm 3: min ||Y - alpha_D K_{D,:}||^2
/// (+ Tikhonov with GCV, the same spectrum formula as the other forms), then eq. (25)
/// with alpha zero outside D.
fn selected_rows_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    max_rows: usize,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo), FitError> {
    let (p, l) = (dims.p, dims.l);
    let nb = windows;
    let (rows, _) = select_kernel_rows(dims, slab, max_rows, opts.kernel_tol, opts.feedthrough)?;
    let m = rows.len();
    let kd = DMatrix::from_fn(m, nb, |a, b| {
        dual_kernel(slab, rows[a], slab, b, p, opts.feedthrough)
    });
    let y = DMatrix::from_fn(l, nb, |j, k| slab.y(k + p)[j]);
    let s_ff = &kd * kd.transpose();
    let s_fy = &kd * y.transpose();
    let (x, info) = ridge_solve(
        &s_ff,
        &s_fy,
        NormalForm::Primal,
        y.norm_squared(),
        nb as f64,
        opts.reg,
    )?;
    let alpha_d = x.transpose(); // l x m
    let mut alpha = DMatrix::zeros(l, nb);
    for (a, &w) in rows.iter().enumerate() {
        alpha.set_column(w, &alpha_d.column(a));
    }
    let gkz = dual_gamma_kz_matrix(dims, f, slab, &alpha, nb + 1);
    let (sv, x) = states_from_gkz(&gkz, nb)?;
    Ok((sv, x, info))
}

/// Eq. (25): row block i of Gamma^p K^p Z is alpha sum_{j >= i} (Z^{i,j})^T Z^{1,j}. Entry
/// (a, b) of that kernel is Theorem 10 between the window starting at a - i + 1 and window
/// b, summed over t0 >= i - 1; one backward pass over t gives it for every i at once.
/// Columns are windows b = 0..cols (a window needs only its p samples, not a target).
pub fn dual_gamma_kz_matrix(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    alpha: &DMatrix<f64>,
    cols: usize,
) -> DMatrix<f64> {
    let (p, l) = (dims.p, dims.l);
    let nb = alpha.ncols();
    // alpha row by row, contiguous
    let alpha_rows: Vec<Vec<f64>> = (0..l)
        .map(|j| alpha.row(j).iter().copied().collect())
        .collect();
    let mut out = DMatrix::zeros(f * l, cols);
    let mut sweep = KernelSweep::new(slab, p);
    // window starts s = -(p-1) .. nb-1; row block i = t + 1 pairs window a with s = a - t
    let s0 = -(p as isize - 1);
    for b in 0..cols {
        sweep.window(b, s0, nb + p - 1, |t, ks| {
            if t < f {
                let k = &ks[p - 1 - t..p - 1 - t + nb];
                for (j, ar) in alpha_rows.iter().enumerate() {
                    out[(t * l + j, b)] = dot4(ar, k);
                }
            }
        });
    }
    out
}

/// The dual kernel of (19), [Z^T Z + U^T U] over windows 0..nb (the U^T U term only with
/// feedthrough), by Theorem 10 for all pairs ([`KernelSweep`]).
pub fn dual_kernel_matrix(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
) -> DMatrix<f64> {
    let mut g = DMatrix::<f64>::zeros(nb, nb);
    let mut sweep = KernelSweep::new(slab, p);
    for b in 0..nb {
        sweep.window(b, 0, b + 1, |t, ks| {
            if t == 0 {
                g.view_mut((0, b), (b + 1, 1)).copy_from_slice(ks);
            }
        });
        if feedthrough {
            let ub = slab.u(b + p);
            for a in 0..=b {
                g[(a, b)] += lpvid::real::dot(slab.u(a + p), ub);
            }
        }
    }
    for b in 0..nb {
        for a in 0..b {
            g[(b, a)] = g[(a, b)];
        }
    }
    g
}

/// Section 4.3, output equation: C and D from the normal equations of
/// y_k = C x_k + D u_k + e_k (regressors [x; u] or [x] without feedthrough).
fn solve_cd(
    s_ff: &DMatrix<f64>,
    s_fy: &DMatrix<f64>,
    n: usize,
    r: usize,
    feedthrough: bool,
) -> Result<(DMatrix<f64>, DMatrix<f64>), FitError> {
    let (cd, _) = min_norm_from_normal(s_ff, &s_fy.transpose(), 1e-12)?;
    let l = cd.nrows();
    let c = cd.columns(0, n).into_owned();
    let d = if feedthrough {
        cd.columns(n, r).into_owned()
    } else {
        DMatrix::zeros(l, r)
    };
    Ok((c, d))
}

/// Section 4.3, state equation: A^(i), B^(i), K^(i) from the normal equations of
/// x_{k+1} = [A^(1) B^(1) K^(1) | ... | A^(m) B^(m) K^(m)] (mu_k (x) [x_k; u_k; e_k]).
fn solve_abk(
    s_ff: &DMatrix<f64>,
    s_fy: &DMatrix<f64>,
    c: DMatrix<f64>,
    d: DMatrix<f64>,
    m: usize,
) -> Result<LpvSs, FitError> {
    let (l, n) = (c.nrows(), c.ncols());
    let r = d.ncols();
    let nxi = n + r + l;
    let (abk, _) = min_norm_from_normal(s_ff, &s_fy.transpose(), 1e-12)?;
    let mut model = LpvSs {
        a: vec![],
        b: vec![],
        k: vec![],
        c: vec![c],
        d: vec![d],
    };
    for i in 0..m {
        let o = i * nxi;
        model.a.push(abk.columns(o, n).into_owned());
        model.b.push(abk.columns(o + n, r).into_owned());
        model.k.push(abk.columns(o + n + r, l).into_owned());
    }
    Ok(model)
}

/// Section 4.3 with the states at hand: `states` column k is x_{k+p} of window k, for
/// windows 0..=N-p (the last one only as a successor). The normal equations are accumulated
/// with the core's Gram.
pub fn realize_from_states(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    states: &DMatrix<f64>,
    feedthrough: bool,
) -> Result<LpvSs, FitError> {
    let (p, r, l, m) = (dims.p, dims.r, dims.l, dims.m());
    let n = states.nrows();
    let nb = states.ncols() - 1;
    let r_ft = if feedthrough { r } else { 0 };
    let dcd = n + r_ft + l;
    let mut g1 = Gram::new(dcd, vec![0.0; packed_len(dcd)])?;
    let mut row = vec![0.0; dcd];
    for k in 0..nb {
        row[..n].copy_from_slice(states.column(k).as_slice());
        row[n..n + r_ft].copy_from_slice(&slab.u(k + p)[..r_ft]);
        row[n + r_ft..].copy_from_slice(slab.y(k + p));
        g1.update(&row)?;
    }
    let (s1_ff, s1_fy) = split_gram(&g1, n + r_ft);
    let (c, d) = solve_cd(&s1_ff, &s1_fy, n, r, feedthrough)?;
    let nxi = n + r + l;
    let dst = m * nxi + n;
    let mut g2 = Gram::new(dst, vec![0.0; packed_len(dst)])?;
    let mut row = vec![0.0; dst];
    let mut xi = vec![0.0; nxi];
    for k in 0..nb {
        let x = states.column(k);
        let u = slab.u(k + p);
        let y = slab.y(k + p);
        let e = DVector::from_column_slice(y) - &c * x - &d * DVector::from_column_slice(u);
        xi[..n].copy_from_slice(x.as_slice());
        xi[n..n + r].copy_from_slice(u);
        xi[n + r..].copy_from_slice(e.as_slice());
        let mu = slab.mu(k + p);
        for i in 0..m {
            for (dstv, v) in row[i * nxi..(i + 1) * nxi].iter_mut().zip(&xi) {
                *dstv = mu[i] * v;
            }
        }
        row[m * nxi..].copy_from_slice(states.column(k + 1).as_slice());
        g2.update(&row)?;
    }
    let (s2_ff, s2_fy) = split_gram(&g2, m * nxi);
    solve_abk(&s2_ff, &s2_fy, c, d, m)
}

/// Section 4.3 from statistics: with x_{k+p} = T z_k^p, every regressor and target of the
/// two least-squares problems is a linear map of v_k = mu_{k+p} (x) w_k (block 0 is w_k;
/// z_{k+1}^p is a selection of v_k), so their normal equations are L G_v L^T.
pub fn realize_from_stats(
    dims: &PbsidDims,
    t: &DMatrix<f64>,
    gv: &DMatrix<f64>,
    feedthrough: bool,
) -> Result<LpvSs, FitError> {
    let (r, l, m) = (dims.r, dims.l, dims.m());
    let q = dims.q()?;
    let d = q + r + l;
    let n = t.nrows();
    let r_ft = if feedthrough { r } else { 0 };
    let sww = gv.view((0, 0), (d, d));
    // output equation: [x; u] = L1 w, y = Ly w
    let mut l1 = DMatrix::zeros(n + r_ft, d);
    l1.view_mut((0, 0), (n, q)).copy_from(t);
    for j in 0..r_ft {
        l1[(n + j, q + j)] = 1.0;
    }
    let mut ly = DMatrix::zeros(l, d);
    for j in 0..l {
        ly[(j, q + r + j)] = 1.0;
    }
    let s1_ff = &l1 * sww * l1.transpose();
    let s1_fy = &l1 * sww * ly.transpose();
    let (c, dm) = solve_cd(&s1_ff, &s1_fy, n, r, feedthrough)?;
    // xi = [x; u; e] = Xi w with e = y - C x - D u
    let nxi = n + r + l;
    let mut xi = DMatrix::zeros(nxi, d);
    xi.view_mut((0, 0), (n, q)).copy_from(t);
    for j in 0..r {
        xi[(n + j, q + j)] = 1.0;
    }
    let ct = &c * t;
    for j in 0..l {
        for i in 0..q {
            xi[(n + r + j, i)] = -ct[(j, i)];
        }
        for i in 0..r {
            xi[(n + r + j, q + i)] = -dm[(j, i)];
        }
        xi[(n + r + j, q + r + j)] = 1.0;
    }
    // regressors: block i of mu (x) xi = Xi (block i of v)
    let vlen = d * m;
    let mut phi = DMatrix::zeros(m * nxi, vlen);
    for i in 0..m {
        phi.view_mut((i * nxi, i * d), (nxi, d)).copy_from(&xi);
    }
    // target: x_{k+p+1} = T z_{k+1}^p, z_{k+1}^p a selection of v
    let mut x2 = DMatrix::zeros(n, vlen);
    let nz = dims.nz();
    for j in 1..=dims.p {
        let dst0 = dims.block_offset(j);
        let (src_off, inner) = if j < dims.p {
            (dims.block_offset(j + 1), dims.block_len(j + 1))
        } else {
            (q, nz)
        };
        for i in 0..m {
            for tt in 0..inner {
                let dst = dst0 + i * inner + tt;
                let src = i * d + src_off + tt;
                for row in 0..n {
                    x2[(row, src)] += t[(row, dst)];
                }
            }
        }
    }
    let s2_ff = &phi * gv * phi.transpose();
    let s2_fy = &phi * gv * x2.transpose();
    solve_abk(&s2_ff, &s2_fy, c, dm, m)
}

/// Split a Gram of [phi; target] into (S_phiphi, S_phitarget).
fn split_gram(g: &Gram<f64, Vec<f64>>, nphi: usize) -> (DMatrix<f64>, DMatrix<f64>) {
    let d = g.dim();
    let s_ff = DMatrix::from_fn(nphi, nphi, |i, j| g.get(i, j));
    let s_fy = DMatrix::from_fn(nphi, d - nphi, |i, j| g.get(i, nphi + j));
    (s_ff, s_fy)
}

/// Undo the internal scaling: with mu'_{j+1} = (p_j - c_j)/s_j, a scheduled matrix
/// M(mu') = M'_1 + sum_j mu'_{j+1} M'_{j+1} equals M_1 + sum_j p_j M_{j+1} with
/// M_{j+1} = M'_{j+1}/s_j and M_1 = M'_1 - sum_j (c_j/s_j) M'_{j+1}; inputs and outputs
/// rescale B, K, C, D.
pub fn unscale(model: &LpvSs, sc: &Scaling) -> LpvSs {
    let su = DMatrix::from_diagonal(&DVector::from_iterator(
        sc.u.len(),
        sc.u.iter().map(|v| 1.0 / v),
    ));
    let sy_inv = DMatrix::from_diagonal(&DVector::from_iterator(
        sc.y.len(),
        sc.y.iter().map(|v| 1.0 / v),
    ));
    let sy = DMatrix::from_diagonal(&DVector::from_column_slice(&sc.y));
    let resched = |mats: &[DMatrix<f64>]| -> Vec<DMatrix<f64>> {
        if mats.len() == 1 {
            return mats.to_vec();
        }
        let mut out = mats.to_vec();
        for j in 0..sc.p_scale.len() {
            out[j + 1] = &mats[j + 1] / sc.p_scale[j];
            out[0] -= &mats[j + 1] * (sc.p_center[j] / sc.p_scale[j]);
        }
        out
    };
    let a = resched(&model.a);
    let b: Vec<_> = resched(&model.b).iter().map(|x| x * &su).collect();
    let k: Vec<_> = resched(&model.k).iter().map(|x| x * &sy_inv).collect();
    let c: Vec<_> = resched(&model.c).iter().map(|x| &sy * x).collect();
    let d: Vec<_> = resched(&model.d).iter().map(|x| &sy * x * &su).collect();
    LpvSs { a, b, k, c, d }
}
