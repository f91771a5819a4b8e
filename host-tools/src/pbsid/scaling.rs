//! The internal scaling of an LPV-PBSID_opt fit (ours, not the papers'): u' = u / su,
//! y' = y / sy, mu' = (p - pc) / ps, from the channel sums a file or a device's statistics
//! provide alike; the scaled sample rows, the diagonal that scales statistic vectors, and
//! [`unscale`], the exact way back to the model in original units.

use lpvid::{stat_vector_len, write_stat_vector, Gram, PbsidDims, Slab, StatsLayout};
use nalgebra::{DMatrix, DVector};

use super::error::FitError;
use crate::lpvss::{LpvSs, Signals};

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

/// Sums of the channels over the windows' target samples (samples p..N-1): exactly what
/// the channel block of the core's statistic vector accumulates, so a file fit and a fit
/// from a device's statistics scale identically.
#[derive(Debug, Clone)]
pub(crate) struct ChannelSums {
    pub(crate) count: f64,
    u: Vec<(f64, f64)>,
    y: Vec<(f64, f64)>,
    p: Vec<(f64, f64)>,
}

impl ChannelSums {
    pub(crate) fn from_signals(sig: &Signals, start: usize) -> ChannelSums {
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
    /// No samples yet (for [`ChannelSums::add`]).
    pub(crate) fn empty(r: usize, l: usize, s: usize) -> ChannelSums {
        ChannelSums {
            count: 0.0,
            u: vec![(0.0, 0.0); r],
            y: vec![(0.0, 0.0); l],
            p: vec![(0.0, 0.0); s],
        }
    }

    /// Add the samples of `sig` after its first `skip` (a chunk of a record streamed in
    /// order: summed in the same order as [`ChannelSums::from_signals`] of the whole).
    pub(crate) fn add(&mut self, sig: &Signals, skip: usize) {
        let add = |acc: &mut [(f64, f64)], m: &DMatrix<f64>| {
            for (j, (a, b)) in acc.iter_mut().enumerate() {
                for v in m.column(j).iter().skip(skip) {
                    *a += v;
                    *b += v * v;
                }
            }
        };
        add(&mut self.u, &sig.u);
        add(&mut self.y, &sig.y);
        add(&mut self.p, &sig.p);
        self.count += sig.len().saturating_sub(skip) as f64;
    }

    pub(crate) fn from_stats<S: AsRef<[f64]> + AsMut<[f64]>>(
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
    pub(crate) fn scaling(&self, kappa: f64) -> Result<Scaling, FitError> {
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
                return Err(FitError::ConstantInput(j + 1));
            }
            sc.u.push(sd);
        }
        for (j, &m) in self.y.iter().enumerate() {
            let (mean, sd, _) = stats(m);
            if constant(mean, sd) {
                return Err(FitError::ConstantOutput(j + 1));
            }
            sc.y.push(sd);
        }
        let s = self.p.len() as f64;
        for (j, &m) in self.p.iter().enumerate() {
            let (mean, sd, rms) = stats(m);
            if constant(mean, sd) {
                return Err(FitError::ConstantScheduling(j + 1));
            }
            sc.p_scale.push(rms / (kappa / s).sqrt());
        }
        Ok(sc)
    }
}

/// The signals in scaled units laid out as the core's sample rows [u', y', mu'].
impl Scaling {
    /// No scaling (every factor 1, no centre): [`scaled_rows`] then gives the raw rows.
    pub(crate) fn unit(dims: &PbsidDims) -> Scaling {
        Scaling {
            u: vec![1.0; dims.r],
            y: vec![1.0; dims.l],
            p_center: vec![0.0; dims.s],
            p_scale: vec![1.0; dims.s],
        }
    }
}

pub(crate) fn scaled_rows(sig: &Signals, sc: &Scaling) -> Vec<f64> {
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
pub(crate) fn stat_scale_vector(
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
