//! The internal scaling of an LPV-PBSID_opt fit (ours, not the papers'): u' = u / su,
//! y' = y / sy, mu' = (p - pc) / ps, from the channel sums a file or a device's statistics
//! provide alike; the scaled sample rows, the same map applied to the Gram of raw statistic
//! vectors ([`scale_stat_gram`]: the centring, then a diagonal), and [`unscale`], the exact
//! way back to the model in original units.

use lpvid::{stat_vector_len, write_stat_vector, Gram, PbsidDims, Slab, StatsLayout};
use nalgebra::{DMatrix, DVector};

use super::error::FitError;
use super::settings::Centre;
use crate::lpvss::{LpvSs, Signals};

/// Internal scaling: u' = u / su, y' = y / sy, p' = (p - pc) / ps.
#[derive(Debug, Clone, PartialEq)]
pub struct Scaling {
    /// Input scales.
    pub u: Vec<f64>,
    /// Output scales.
    pub y: Vec<f64>,
    /// Scheduling centres: 0 while p = 0 lies within [`P_ZERO_INSIDE`] standard deviations
    /// of the mean, else the mean (see [`ChannelSums::scaling`]).
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

    /// Internal scaling: inputs and outputs by their standard deviation; each scheduling
    /// signal centred at c ([`Scaling::p_center`], by `centre`; the rule below for
    /// [`Centre::Auto`]) and scaled by the RMS of p - c times
    /// sqrt(s / kappa), so that the mean of |mu'|^2 over the s signals is kappa.
    ///
    /// The centre is where the first local model A^(1) of the fit sits, whose powers build
    /// Gamma^p in eq. (14) of the kernel paper, and the point the regularisation of (13)
    /// shrinks the p-dependence towards. It stays at p = 0 while 0 is within the data's
    /// range (the mean +- [`P_ZERO_INSIDE`] standard deviations; a uniform signal spans
    /// +- 1.73): B1's predictor is most contractive at p = 0 (spectral radius of A~(mu) 0.92
    /// there, 1.11 at its mean), and the centre at the mean loses its exact finite-window
    /// predictor (noise-free VAF 100 -> 99.80). Beyond that range the centre is the mean,
    /// so the fit no longer depends on where the units put p = 0 (a rotor speed of 370 rpm):
    /// before, B2 with p + 370 had validation VAF 56.9 % against 95.3 % at p + 0, and 43
    /// scheduled family plants at p + 20 a held-out error 9x theirs at p + 0
    /// (docs/bench-diagnose.md, "A scheduling signal far from 0").
    /// The mean and standard deviation of one channel's (sum, sum of squares).
    fn mean_sd(&self, (s1, s2): (f64, f64)) -> (f64, f64) {
        let mean = s1 / self.count;
        let var = (s2 / self.count - mean * mean).max(0.0);
        (mean, var.sqrt())
    }

    /// [`centre_in_doubt`] from the channel sums: the one criterion of the in-memory fit and
    /// the streamed one ([`crate::pbsid::stream::PassOne::centre_in_doubt`]).
    pub(crate) fn centre_in_doubt(&self) -> bool {
        self.p.iter().any(|&sums| {
            let (mean, sd) = self.mean_sd(sums);
            mean.abs() > P_ZERO_EDGE * sd
        })
    }

    pub(crate) fn scaling(&self, kappa: f64, centre: Centre) -> Result<Scaling, FitError> {
        let stats = |sums| self.mean_sd(sums);
        let constant = |mean: f64, sd: f64| sd <= 1e-12 * mean.abs().max(1e-300) || sd == 0.0;
        let mut sc = Scaling {
            u: vec![],
            y: vec![],
            p_center: vec![0.0; self.p.len()],
            p_scale: vec![],
        };
        for (j, &m) in self.u.iter().enumerate() {
            let (mean, sd) = stats(m);
            if constant(mean, sd) {
                return Err(FitError::ConstantInput(j + 1));
            }
            sc.u.push(sd);
        }
        for (j, &m) in self.y.iter().enumerate() {
            let (mean, sd) = stats(m);
            if constant(mean, sd) {
                return Err(FitError::ConstantOutput(j + 1));
            }
            sc.y.push(sd);
        }
        let s = self.p.len() as f64;
        for (j, &m) in self.p.iter().enumerate() {
            let (mean, sd) = stats(m);
            if constant(mean, sd) {
                return Err(FitError::ConstantScheduling(j + 1));
            }
            let c = match centre {
                Centre::Zero => 0.0,
                Centre::Mean => mean,
                // 0 inside the data's range: the centre stays there; else the data's mean
                Centre::Auto if mean.abs() <= P_ZERO_INSIDE * sd => 0.0,
                Centre::Auto => mean,
            };
            sc.p_center[j] = c;
            // the RMS of p - c
            sc.p_scale
                .push(((mean - c) * (mean - c) + sd * sd).sqrt() / (kappa / s).sqrt());
        }
        Ok(sc)
    }
}

/// How many standard deviations from its mean p = 0 may lie and still be taken as inside the
/// scheduling range ([`ChannelSums::scaling`]).
pub const P_ZERO_INSIDE: f64 = 2.0;

/// How many standard deviations from its mean p = 0 must lie before the centre is in doubt:
/// from there on [`crate::pipeline::identify`] fits at both ([`centre_in_doubt`]).
pub const P_ZERO_EDGE: f64 = 0.5;

/// Whether the fit's centre of a scheduling signal of `sig` (samples `start`.., as the fit's
/// scaling sums them) is in doubt: 0 lies more than [`P_ZERO_EDGE`] standard deviations from
/// its mean, so 0 and the mean are different points of the range (or 0 lies outside it).
/// B1's p1 = rho ~ U[0, 1] (1.74) and B3's p1 (0.71) are such signals; B2's (0.30) and B6's
/// (0.02) are not.
pub fn centre_in_doubt(sig: &Signals, start: usize) -> bool {
    ChannelSums::from_signals(sig, start).centre_in_doubt()
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

/// The Gram G = sum_k s_k s_k^T of statistic vectors of `layout` of the raw signals with
/// the scheduling signals taken about `accumulated` (a device's statistics: 0) mapped to the
/// Gram of the scaled signals' vectors ([`scaled_rows`]): G' = D C G C^T D, C the centring
/// by sc.p_center - accumulated ([`centring_map`]) and D the diagonal of
/// [`stat_scale_vector`]. A file fit scales its rows before the Gram; a fit from
/// statistics (a device's, or a file streamed in chunks) maps the Gram, to the same matrix
/// up to rounding. The products of centred factors cancel in that map: statistics of p far
/// from `accumulated` (by 10^2 of its spread or more) lose their precision, so a device
/// should send p about its nominal operating point.
pub(crate) fn scale_stat_gram(
    dims: &PbsidDims,
    layout: StatsLayout,
    sc: &Scaling,
    accumulated: &[f64],
    g: &mut DMatrix<f64>,
) -> Result<(), FitError> {
    let len = g.nrows();
    let shift: Vec<f64> = sc
        .p_center
        .iter()
        .zip(accumulated)
        .map(|(c, a)| c - a)
        .collect();
    if shift.iter().any(|&c| c != 0.0) {
        let c = centring_map(dims, layout, &shift)?;
        // K = G C^T (columns of the symmetric G combined), then C K, again by columns of K^T
        let combine = |src: &DMatrix<f64>| {
            let mut out = DMatrix::zeros(len, len);
            for (a, row) in c.iter().enumerate() {
                let mut col = out.column_mut(a);
                for &(i, w) in row {
                    col.axpy(w, &src.column(i), 1.0);
                }
            }
            out
        };
        let k = combine(g).transpose();
        *g = combine(&k);
    }
    let dvec = stat_scale_vector(dims, layout, sc)?;
    for j in 0..len {
        for i in 0..len {
            g[(i, j)] *= dvec[i] * dvec[j];
        }
    }
    Ok(())
}

/// The centring mu_j -> mu_j - c_j mu_1 (mu_1 = 1) of the scheduling signals as a linear map
/// of statistic vectors, as sparse rows (entry, weight). Every entry of s is a product of one
/// value per factor (a channel at a step of the window), linear in each: an entry with d
/// factors of centred signals becomes the sum over the 2^d ways of keeping each such factor
/// or replacing it by -c_j times the constant mu_1 at the same step, which is the entry with
/// that factor left out. The factors of each entry are found by writing the vector of a
/// window of ones with one value set to 2 ([`write_stat_vector`], the one definition of the
/// layout), so this map follows the layout wherever it changes.
fn centring_map(
    dims: &PbsidDims,
    layout: StatsLayout,
    centre: &[f64],
) -> Result<Vec<Vec<(usize, f64)>>, FitError> {
    let (r, l, m, p) = (dims.r, dims.l, dims.m(), dims.p);
    let w = r + l + m;
    let len = stat_vector_len(dims, layout)?;
    let mut rows = vec![1.0; (p + 1) * w];
    let mut out = vec![0.0; len];
    // the factors of every entry: (step, column), the constant column mu_1 left out
    let mut factors: Vec<Vec<(usize, usize)>> = vec![vec![]; len];
    for t in 0..=p {
        for col in (0..w).filter(|&c| c != r + l) {
            rows[t * w + col] = 2.0;
            write_stat_vector(dims, layout, &Slab::new(&rows, r, l, m)?, 0, &mut out);
            rows[t * w + col] = 1.0;
            for (i, &v) in out.iter().enumerate() {
                if v == 2.0 {
                    factors[i].push((t, col));
                } else if v != 1.0 {
                    return Err(FitError::CentringLayout(i));
                }
            }
        }
    }
    let index: std::collections::HashMap<&[(usize, usize)], usize> = factors
        .iter()
        .enumerate()
        .map(|(i, f)| (f.as_slice(), i))
        .collect();
    let mut map = Vec::with_capacity(len);
    for f in &factors {
        // the factors of centred scheduling signals, and their centres
        let centred: Vec<(usize, f64)> = f
            .iter()
            .enumerate()
            .filter(|(_, &(_, col))| col > r + l && centre[col - r - l - 1] != 0.0)
            .map(|(a, &(_, col))| (a, -centre[col - r - l - 1]))
            .collect();
        let mut row = Vec::with_capacity(1 << centred.len());
        for subset in 0..1usize << centred.len() {
            let mut weight = 1.0;
            let mut kept: Vec<(usize, usize)> = Vec::with_capacity(f.len());
            let mut skip = centred
                .iter()
                .enumerate()
                .filter(|(b, _)| subset >> b & 1 == 1);
            let mut next = skip.next();
            for (a, &fa) in f.iter().enumerate() {
                match next {
                    Some((_, &(ai, c))) if ai == a => {
                        weight *= c;
                        next = skip.next();
                    }
                    _ => kept.push(fa),
                }
            }
            let &i = index
                .get(kept.as_slice())
                .ok_or(FitError::CentringLayout(map.len()))?;
            row.push((i, weight));
        }
        map.push(row);
    }
    Ok(map)
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pbsid::primal::dense;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// The Gram of the statistic vectors of `sig`'s rows scaled by `sc`.
    fn gram_of(sig: &Signals, dims: &PbsidDims, layout: StatsLayout, sc: &Scaling) -> DMatrix<f64> {
        let rows = scaled_rows(sig, sc);
        let slab = Slab::new(&rows, dims.r, dims.l, dims.m()).unwrap();
        let len = stat_vector_len(dims, layout).unwrap();
        let g = crate::linalg::gram_from_rows(len, sig.len() - dims.p, |k, dst| {
            write_stat_vector(dims, layout, &slab, k, dst)
        })
        .unwrap();
        dense(&g, len)
    }

    #[test]
    fn the_centring_map_gives_the_gram_of_centred_signals() {
        let mut rng = StdRng::seed_from_u64(5);
        for (r, l, s, p, layout) in [
            (1, 1, 1, 3, StatsLayout::Plain),
            (2, 3, 3, 3, StatsLayout::Plain),
            (2, 1, 2, 2, StatsLayout::Extended),
        ] {
            let n = 60;
            let sig = Signals {
                u: DMatrix::from_fn(n, r, |_, _| rng.gen_range(-1.0..1.0)),
                y: DMatrix::from_fn(n, l, |_, _| rng.gen_range(-1.0..1.0)),
                p: DMatrix::from_fn(n, s, |_, j| 0.3 * j as f64 + rng.gen_range(-1.0..1.0)),
            };
            let dims = PbsidDims::new(r, l, s, p).unwrap();
            let acc: Vec<f64> = (0..s).map(|j| 0.1 - 0.2 * j as f64).collect();
            let sc = Scaling {
                u: vec![0.5; r],
                y: vec![2.0; l],
                p_center: (0..s).map(|j| 0.7 + 0.4 * j as f64).collect(),
                p_scale: vec![1.5; s],
            };
            let want = gram_of(&sig, &dims, layout, &sc);
            let mut got = gram_of(
                &sig,
                &dims,
                layout,
                &Scaling {
                    p_center: acc.clone(),
                    ..Scaling::unit(&dims)
                },
            );
            scale_stat_gram(&dims, layout, &sc, &acc, &mut got).unwrap();
            let err = (&got - &want).amax() / want.amax();
            assert!(err < 1e-12, "{r} {l} {s} {p} {layout:?}: {err}");
        }
    }

    #[test]
    fn the_centre_follows_the_rule_or_the_option_and_the_doubt_starts_at_half_a_deviation() {
        // p1 = 1 + sin: mean 1, sd 0.707 (0 at 1.41 sd: inside, in doubt); p2 = 5 + sin (7.1
        // sd: outside); p3 = 0.2 + sin (0.28 sd: not in doubt)
        let n = 400;
        let wave = |c: f64| DMatrix::from_fn(n, 1, |k, _| c + (0.1 * k as f64).sin());
        let sig = |c: f64| Signals {
            u: DMatrix::from_fn(n, 1, |k, _| (0.37 * k as f64).cos()),
            y: DMatrix::from_fn(n, 1, |k, _| (0.23 * k as f64).sin()),
            p: wave(c),
        };
        let centre = |c: f64, how: Centre| {
            ChannelSums::from_signals(&sig(c), 0)
                .scaling(0.05, how)
                .unwrap()
                .p_center[0]
        };
        // the mean of sin(0.1 k) over these 400 samples is 0.0407
        assert_eq!(centre(1.0, Centre::Auto), 0.0);
        assert!((centre(5.0, Centre::Auto) - 5.0407).abs() < 1e-3);
        assert!((centre(1.0, Centre::Mean) - 1.0407).abs() < 1e-3);
        assert_eq!(centre(5.0, Centre::Zero), 0.0);
        assert!(centre_in_doubt(&sig(1.0), 0));
        assert!(centre_in_doubt(&sig(5.0), 0));
        assert!(!centre_in_doubt(&sig(0.2), 0));
        assert!(!centre_in_doubt(&sig(-0.2), 0));
        assert!(centre_in_doubt(&sig(-1.0), 0));
    }
}
