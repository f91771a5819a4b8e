//! LPV-PBSID_opt in constant memory: the primal form of regression (13) (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, Algorithm 1 of section 4.5) from data that
//! arrive in chunks and are never held whole. Two passes over the data:
//!
//! 1. the channel sums (the scaling) and the Gram of the plain statistic vectors
//!    w_k = [z_k^p; u_{k+p}; y_{k+p}] of the raw samples; scaled afterwards (D G D, the
//!    scaling is diagonal), then regression (13), Gamma^p K^p (14), the SVD (15) and the
//!    order as in [`super::fit`];
//! 2. the states x_{k+p} = T z_k^p (16) window by window and the two least-squares problems
//!    of section 4.3 (C, D; then A, B, K) accumulated as normal equations; the innovation
//!    e = y - C x - D u enters through a linear map of the accumulated moments, as in
//!    [`super::realize_from_stats`].
//!
//! Chunks overlap by p samples, so every window is counted once whatever the chunking; the
//! model equals [`super::fit`]'s primal fit of the same samples up to rounding.

use lpvid::window::write_pbsid_regressor;
use lpvid::{
    packed_len, stat_vector_len, write_stat_vector, Gram, PbsidDims, Samples, Slab, StatsLayout,
};
use nalgebra::DMatrix;

use super::error::FitError;
use super::order::choose_order;
use super::primal::{dense, primal_regression_svd};
use super::realize::{output_row, solve_abk, solve_cd, split_gram, state_row};
use super::scaling::{scale_stat_gram, scaled_rows, unscale, ChannelSums, Scaling};
use super::settings::{PbsidFit, PbsidOptions, Reg, Solver};
use crate::kernel_sweep::dot4;
use crate::lpvss::Signals;

/// The last p sample rows of the data seen so far (flat rows [u, y, 1, p]), prepended to the
/// next chunk so that the windows across the boundary are formed.
#[derive(Debug, Clone, Default)]
struct Tail {
    rows: Vec<f64>,
}

impl Tail {
    /// This chunk's rows after the tail; returns the slab data and keeps the new tail.
    fn extend(&mut self, chunk: &[f64], width: usize, p: usize) -> Vec<f64> {
        let mut all = std::mem::take(&mut self.rows);
        all.extend_from_slice(chunk);
        let keep = (all.len() / width).min(p) * width;
        self.rows = all[all.len() - keep..].to_vec();
        all
    }
}

/// Why a streamed fit cannot be made in the primal form: the caller fits in memory instead
/// (which also gives the canonical error for data the fit refuses).
#[derive(Debug)]
pub enum NotStreamed {
    /// The options need the data (kernel form, BPDN, `--refine`).
    Options(&'static str),
    /// The cost model picks the kernel form for this many windows.
    KernelCheaper,
    /// The fit failed; the in-memory fit reports it.
    Fit(FitError),
}

impl From<FitError> for NotStreamed {
    fn from(e: FitError) -> Self {
        NotStreamed::Fit(e)
    }
}

impl From<lpvid::Error> for NotStreamed {
    fn from(e: lpvid::Error) -> Self {
        NotStreamed::Fit(e.into())
    }
}

/// Whether `opts` allow the streamed primal fit at all (before any data are read).
pub fn streamable(opts: &PbsidOptions) -> Result<(), NotStreamed> {
    if opts.refine {
        return Err(NotStreamed::Options(
            "--refine simulates the whole record repeatedly",
        ));
    }
    if matches!(opts.reg, Reg::BpdnAic | Reg::BpdnSv) {
        return Err(NotStreamed::Options("BPDN solves with explicit regressors"));
    }
    if opts.kernel_rows.is_some() || opts.solver == Solver::Dual {
        return Err(NotStreamed::Options("the kernel form needs every window"));
    }
    Ok(())
}

/// Pass 1: channel sums and the raw plain Gram.
pub struct PassOne {
    dims: PbsidDims,
    len: usize,
    sums: ChannelSums,
    gram: Gram<f64, Vec<f64>>,
    /// The second thread's share of the Gram, merged in [`PassOne::finish`].
    gram2: Gram<f64, Vec<f64>>,
    split: bool,
    tail: Tail,
    samples: usize,
    /// The scheduling centre the Gram's vectors are taken about: the first chunk's mean,
    /// so that the centring of [`scale_stat_gram`] moves it by a fraction of the range
    /// (raw vectors of p = 370 +- 1 cancel beyond f64 there).
    centre: Option<Vec<f64>>,
}

impl PassOne {
    /// Start for r inputs, l outputs, s scheduling signals and the options' past window.
    pub fn new(r: usize, l: usize, s: usize, opts: &PbsidOptions) -> Result<PassOne, FitError> {
        let dims = PbsidDims::new(r, l, s, opts.past)?;
        let q = dims.q()?;
        if q > 20_000 {
            return Err(FitError::PrimalTooLarge { q });
        }
        let len = stat_vector_len(&dims, StatsLayout::Plain)?;
        Ok(PassOne {
            dims,
            len,
            sums: ChannelSums::empty(r, l, s),
            gram: Gram::new(len, vec![0.0; packed_len(len)])?,
            gram2: Gram::new(len, vec![0.0; packed_len(len)])?,
            split: false,
            tail: Tail::default(),
            samples: 0,
            centre: None,
        })
    }

    /// Add the next chunk of samples.
    pub fn update(&mut self, chunk: &Signals) -> Result<(), FitError> {
        let p = self.dims.p;
        // the channel sums skip the first p samples, as [`ChannelSums::from_signals`] does
        self.sums.add(chunk, p.saturating_sub(self.samples));
        self.samples += chunk.len();
        let width = self.dims.sample_len();
        if chunk.is_empty() {
            return Ok(());
        }
        let centre = self.centre.get_or_insert_with(|| {
            (0..chunk.p.ncols())
                .map(|j| chunk.p.column(j).mean())
                .collect()
        });
        let raw = scaled_rows(
            chunk,
            &Scaling {
                p_center: centre.clone(),
                ..Scaling::unit(&self.dims)
            },
        );
        let all = self.tail.extend(&raw, width, p);
        let rows = all.len() / width;
        if rows <= p {
            return Ok(());
        }
        let slab = Slab::new(&all, self.dims.r, self.dims.l, self.dims.m())?;
        let windows = rows - p;
        let dims = self.dims;
        let row = |k: usize, dst: &mut [f64]| {
            write_stat_vector(&dims, StatsLayout::Plain, &slab, k, dst);
        };
        // the chunk's two halves on two threads when large enough to gain; the second
        // thread's sums are merged at the end (the statistics are sums)
        let split = crate::linalg::split_pays(self.len, windows);
        self.split |= split;
        crate::linalg::gram_add_rows_split(
            &mut self.gram,
            &mut self.gram2,
            0..windows,
            &row,
            split,
        )?;
        Ok(())
    }

    /// Samples seen.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// Whether the scheduling centre is in doubt ([`super::centre_in_doubt`], from the same
    /// channel sums): with [`super::Centre::Auto`] the caller then finishes at `Zero` and at
    /// `Mean` and keeps the better free run, as [`crate::pipeline::identify`] does.
    pub fn centre_in_doubt(&self) -> bool {
        self.sums.centre_in_doubt()
    }

    /// Regression (13), the SVD and the order from the accumulated statistics: what pass 2
    /// needs. `Err(KernelCheaper)` when the options' automatic choice is the kernel form.
    /// The statistics stay, so the same pass 1 can be finished with other options (another
    /// centre).
    pub fn finish(&mut self, opts: &PbsidOptions) -> Result<PassTwo, NotStreamed> {
        if self.split {
            // merged once: the second thread's share then starts again from zero
            self.gram.merge(&self.gram2)?;
            self.gram2.reset();
            self.split = false;
        }
        let dims = self.dims;
        let p = dims.p;
        let min_samples = p + 3;
        if self.samples < min_samples {
            return Err(NotStreamed::Fit(FitError::TooFewSamples {
                samples: self.samples,
                past: p,
                needed: min_samples,
            }));
        }
        let windows = self.samples - p;
        let q = dims.q()?;
        let r_ft = if opts.feedthrough { dims.r } else { 0 };
        let f = super::check_options(&dims, windows, opts)?;
        if opts.solver == Solver::Auto && !super::primal_is_cheaper(q + r_ft, windows, p) {
            return Err(NotStreamed::KernelCheaper);
        }
        let scaling = self.sums.scaling(opts.sched_weight, opts.centre)?;
        let mut g = dense(&self.gram, self.len);
        let centre = self.centre.clone().unwrap_or_else(|| vec![0.0; dims.s]);
        scale_stat_gram(&dims, StatsLayout::Plain, &scaling, &centre, &mut g)?;
        let (reg, sv, t) = primal_regression_svd(&dims, f, &g, windows, opts)?;
        let (order, order_reason) = choose_order(&sv, windows, opts)?;
        let t_rows = t.rows(0, order).transpose();
        let reason = match opts.solver {
            Solver::Primal => "primal form requested".to_string(),
            _ => format!("primal: q = {q} regressors (+ {r_ft} feedthrough) for {windows} windows"),
        };
        let (n, r, l, m) = (order, dims.r, dims.l, dims.m());
        let nxi = n + r + l;
        let d1 = n + r_ft + l;
        let d2 = m * nxi + n;
        Ok(PassTwo {
            dims,
            q,
            feedthrough: opts.feedthrough,
            t_rows,
            scaling,
            sv,
            order,
            order_reason,
            lambda: reg.lambda_rel(),
            dof: reg.dof,
            solver_reason: format!("{reason}; streamed in chunks (constant memory)"),
            windows,
            g1: Gram::new(d1, vec![0.0; packed_len(d1)])?,
            g2: Gram::new(d2, vec![0.0; packed_len(d2)])?,
            tail: Tail::default(),
        })
    }
}

/// Windows whose rows pass 2 adds to the realization's Grams as one batch (as the in-memory
/// realization adds 64 rows per batch).
const STATE_BLOCK: usize = 64;

/// Pass 2: the states and the normal equations of the realization.
pub struct PassTwo {
    dims: PbsidDims,
    q: usize,
    feedthrough: bool,
    /// The first `order` rows of T (x = T z), as columns: each state is one contiguous dot
    /// product with the regressor.
    t_rows: DMatrix<f64>,
    scaling: Scaling,
    sv: Vec<f64>,
    order: usize,
    order_reason: String,
    lambda: Option<f64>,
    dof: f64,
    solver_reason: String,
    windows: usize,
    g1: Gram<f64, Vec<f64>>,
    g2: Gram<f64, Vec<f64>>,
    tail: Tail,
}

impl PassTwo {
    /// Add the next chunk of samples (the same chunks as pass 1, in order).
    pub fn update(&mut self, chunk: &Signals) -> Result<(), FitError> {
        let dims = self.dims;
        let (p, r, l, m) = (dims.p, dims.r, dims.l, dims.m());
        let n = self.order;
        let r_ft = if self.feedthrough { r } else { 0 };
        let width = dims.sample_len();
        let rows_scaled = scaled_rows(chunk, &self.scaling);
        let all = self.tail.extend(&rows_scaled, width, p);
        let rows = all.len() / width;
        if rows <= p {
            return Ok(());
        }
        let slab = Slab::new(&all, r, l, m)?;
        let (q, nxi) = (self.q, n + r + l);
        let (d1, d2) = (n + r_ft + l, m * nxi + n);
        let windows = rows - p;
        // blocks of windows: the states of the block and of the window after it, each a
        // contiguous dot product per row of T (the one after is the next block's first),
        // then the rows of both Grams added as one batch
        let state = |k: usize, x: &mut [f64], z: &mut [f64]| {
            write_pbsid_regressor(&dims, &slab, k, z);
            for (xi, ti) in x.iter_mut().zip(self.t_rows.column_iter()) {
                *xi = dot4(ti.as_slice(), z);
            }
        };
        let mut z = vec![0.0; q];
        let mut xb = vec![0.0; n * (STATE_BLOCK + 1)];
        let mut xi = vec![0.0; nxi];
        let mut rows1 = vec![0.0; STATE_BLOCK * d1];
        let mut rows2 = vec![0.0; STATE_BLOCK * d2];
        state(0, &mut xb[..n], &mut z);
        let mut k0 = 0;
        while k0 < windows {
            let c = STATE_BLOCK.min(windows - k0);
            for (j, x) in xb.chunks_exact_mut(n).take(c + 1).enumerate().skip(1) {
                state(k0 + j, x, &mut z);
            }
            for j in 0..c {
                let k = k0 + j;
                let (x, x_next) = (&xb[j * n..(j + 1) * n], &xb[(j + 1) * n..(j + 2) * n]);
                let (u, y, mu) = (slab.u(k + p), slab.y(k + p), slab.mu(k + p));
                output_row(&mut rows1[j * d1..(j + 1) * d1], x, u, y, r_ft);
                xi[..n].copy_from_slice(x);
                xi[n..n + r].copy_from_slice(u);
                xi[n + r..].copy_from_slice(y);
                state_row(&mut rows2[j * d2..(j + 1) * d2], mu, &xi, x_next);
            }
            self.g1.update_batch(&rows1[..c * d1], c)?;
            self.g2.update_batch(&rows2[..c * d2], c)?;
            xb.copy_within(c * n..(c + 1) * n, 0);
            k0 += c;
        }
        Ok(())
    }

    /// The system matrices (section 4.3) and the fit, in original units.
    pub fn finish(self) -> Result<PbsidFit, FitError> {
        let dims = self.dims;
        let (r, l, m) = (dims.r, dims.l, dims.m());
        let n = self.order;
        let r_ft = if self.feedthrough { r } else { 0 };
        let (s1_ff, s1_fy) = split_gram(&self.g1, n + r_ft);
        let (c, d) = solve_cd(&s1_ff, &s1_fy, n, r, self.feedthrough)?;
        // [x; u; e] = P [x; u; y] with e = y - C x - D u, per local model
        let nxi = n + r + l;
        let mut pm = DMatrix::<f64>::identity(nxi, nxi);
        pm.view_mut((n + r, 0), (l, n)).copy_from(&(-&c));
        pm.view_mut((n + r, n), (l, r)).copy_from(&(-&d));
        let mut phi = DMatrix::zeros(m * nxi, m * nxi);
        for i in 0..m {
            phi.view_mut((i * nxi, i * nxi), (nxi, nxi)).copy_from(&pm);
        }
        let (g_ff, g_fy) = split_gram(&self.g2, m * nxi);
        let s2_ff = &phi * g_ff * phi.transpose();
        let s2_fy = &phi * g_fy;
        let scaled = solve_abk(&s2_ff, &s2_fy, c, d, m)?;
        Ok(PbsidFit {
            model: unscale(&scaled, &self.scaling),
            singular_values: self.sv,
            order: self.order,
            order_reason: self.order_reason,
            lambda: self.lambda,
            dof: self.dof,
            solver: Solver::Primal,
            solver_reason: self.solver_reason,
            q: self.q,
            windows: self.windows,
            scaling: self.scaling,
            states: None,
            refinement: None,
        })
    }
}
