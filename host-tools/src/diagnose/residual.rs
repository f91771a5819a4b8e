//! The standard tests of a residual (on validation data, free-run or one-step):
//! - whiteness: autocorrelation with the +-z/sqrt(N) band and the Ljung-Box statistic;
//! - cross-correlation with every input, scheduling signal and logged column at leads and
//!   lags, with the plain band +-z/sqrt(N) and Bartlett's band for two autocorrelated series
//!   (var r_xy = (1/N) sum_tau rho_x(tau) rho_y(tau) under independence), which is the honest
//!   one for a coloured free-run residual; significance uses Bartlett's band with a Bonferroni
//!   correction over the lags looked at;
//! - correlation with candidate nonlinear regressors (u^2, |u| u, sign u, |u|, p^2, p^3, p u,
//!   p y(k-1), p yhat, p_a p_b, yhat^2) over lags 0..=10, same bands;
//! - periodogram with significant peaks: an ordinate is a peak when it exceeds the local
//!   spectral level (running median / ln 2 of the periodogram around it; ordinates are
//!   ~ level x Exp(1)) by ln(N / (2 alpha)), the level the largest of N/2 independent Exp(1)
//!   variables exceeds with probability alpha;
//! - residual mean and RMS per scheduling bin (quintiles of each scheduling signal).

use nalgebra::DMatrix;
use serde::Serialize;

use super::stats::{acf, ccf, chi2_sf, mean, normal_quantile, periodogram, refine_peak, t_sf};
use crate::data::Dataset;
use crate::significance::{batch_count, batch_means_t};

/// Family-wise level of every test in this module.
pub const ALPHA: f64 = 0.01;
/// Largest lag of the correlation tests.
pub const MAX_LAG: usize = 40;
/// Lags 0..=NL_LAGS of the nonlinear-regressor correlations.
pub const NL_LAGS: usize = 10;

/// Autocorrelation test of one output's residual.
#[derive(Debug, Clone, Serialize)]
pub struct Whiteness {
    /// Output index (1-based).
    pub output: usize,
    /// r(0..=MAX_LAG).
    pub acf: Vec<f64>,
    /// 95 % band z/sqrt(N).
    pub band: f64,
    /// Lags 1.. outside the band.
    pub excursions: usize,
    /// Ljung-Box Q over lags 1..=h.
    pub ljung_box: f64,
    /// h (degrees of freedom).
    pub dof: usize,
    /// P(chi^2_h > Q).
    pub p_value: f64,
}

/// Cross-correlation of one output's residual with one data column.
#[derive(Debug, Clone, Serialize)]
pub struct CrossCorr {
    /// Output index (1-based).
    pub output: usize,
    /// Column name.
    pub signal: String,
    /// "input", "scheduling" or "logged".
    pub kind: &'static str,
    /// r(tau) = corr(e_k, s_{k-tau}) for tau = -MAX_LAG..=MAX_LAG.
    pub r: Vec<f64>,
    /// 95 % band z/sqrt(N).
    pub band: f64,
    /// Bartlett's 95 % band for two autocorrelated series.
    pub bartlett_band: f64,
    /// Largest |r| and its lag.
    pub max_abs: f64,
    /// Lag of the largest |r| (positive: the signal leads the residual).
    pub at_lag: isize,
    /// |r| beyond Bartlett's band at level ALPHA, Bonferroni over the lags.
    pub significant: bool,
    /// The bound `significant` tests |r| against: Bartlett's band at level ALPHA with a
    /// Bonferroni correction over the lags (wider than the 95 % `bartlett_band`).
    pub bound: f64,
}

/// Correlation of the residual with a nonlinear regressor.
#[derive(Debug, Clone, Serialize)]
pub struct NonlinTest {
    /// Output index (1-based).
    pub output: usize,
    /// The regressor, e.g. `u1^2`, `p1*yhat1`.
    pub regressor: String,
    /// Largest |corr(e_k, g_{k-tau})| over tau = 0..=NL_LAGS (signed).
    pub r: f64,
    /// Lag of it.
    pub lag: usize,
    /// Bartlett's band at level ALPHA, Bonferroni over lags.
    pub bound: f64,
    /// |r| / bound.
    pub ratio: f64,
}

/// A spectral peak of the residual.
#[derive(Debug, Clone, Serialize)]
pub struct Peak {
    /// Frequency, rad/sample.
    pub omega: f64,
    /// Period in samples.
    pub period: f64,
    /// Periodogram ordinate / local level.
    pub ratio: f64,
}

/// Periodogram of one output's residual.
#[derive(Debug, Clone, Serialize)]
pub struct Spectrum {
    /// Output index (1-based).
    pub output: usize,
    /// Threshold on ordinate / local level.
    pub threshold: f64,
    /// Significant peaks, strongest first (at most 5).
    pub peaks: Vec<Peak>,
    /// The largest ordinate / local level anywhere (significant or not).
    pub top: Peak,
    /// Frequencies (rad/sample) of the plotted periodogram (not in the JSON report).
    #[serde(skip)]
    pub omega: Vec<f64>,
    /// Periodogram (not in the JSON report).
    #[serde(skip)]
    pub power: Vec<f64>,
    /// Local level (not in the JSON report).
    #[serde(skip)]
    pub level: Vec<f64>,
}

/// Residual in one bin of a scheduling signal.
#[derive(Debug, Clone, Serialize)]
pub struct Bin {
    /// Bin edges.
    pub lo: f64,
    /// Upper edge.
    pub hi: f64,
    /// Samples.
    pub count: usize,
    /// Mean residual.
    pub mean: f64,
    /// RMS residual.
    pub rms: f64,
}

/// Residual statistics per bin of one scheduling signal.
#[derive(Debug, Clone, Serialize)]
pub struct BinStats {
    /// Output index (1-based).
    pub output: usize,
    /// Scheduling column.
    pub signal: String,
    /// Quintile bins.
    pub bins: Vec<Bin>,
    /// Largest / smallest bin RMS.
    pub rms_ratio: f64,
}

/// All tests of one residual.
#[derive(Debug, Clone, Serialize)]
pub struct ResidualReport {
    /// "free-run" or "one-step".
    pub kind: &'static str,
    /// Samples.
    pub samples: usize,
    /// Mean per output.
    pub mean: Vec<f64>,
    /// RMS per output.
    pub rms: Vec<f64>,
    /// Batch-means t statistic of the mean per output.
    pub mean_t: Vec<f64>,
    /// Two-sided p-value of the mean per output.
    pub mean_p: Vec<f64>,
    /// Autocorrelation tests.
    pub whiteness: Vec<Whiteness>,
    /// Cross-correlations.
    pub cross: Vec<CrossCorr>,
    /// Nonlinear-regressor correlations, largest ratio first.
    pub nonlinear: Vec<NonlinTest>,
    /// Periodograms.
    pub spectrum: Vec<Spectrum>,
    /// Per scheduling bin.
    pub bins: Vec<BinStats>,
}

/// Columns of a data set by role: inputs u1.., scheduling p1.., logged (anything else but
/// outputs y1.. and the time column `t`).
pub fn column_roles(ds: &Dataset) -> Vec<(String, &'static str)> {
    let inputs = ds.channels('u');
    let sched = ds.channels('p');
    let outputs = ds.channels('y');
    let mut out = Vec::new();
    for name in &ds.names {
        let kind = if inputs.contains(name) {
            "input"
        } else if sched.contains(name) {
            "scheduling"
        } else if outputs.contains(name) || name == "t" || name == "k" {
            continue;
        } else {
            "logged"
        };
        out.push((name.clone(), kind));
    }
    out
}

/// Bartlett's standard deviation of the sample cross-correlation of two independent series
/// with autocorrelations `ra`, `rb` (lags 0..): sqrt((1/N) sum_{|tau| <= L} ra rb).
fn bartlett_sd(ra: &[f64], rb: &[f64], n: usize) -> f64 {
    let s: f64 = 1.0 + 2.0 * ra.iter().zip(rb).skip(1).map(|(a, b)| a * b).sum::<f64>();
    (s.max(1.0) / n as f64).sqrt()
}

fn ljung_box(r: &[f64], n: usize, h: usize) -> f64 {
    let nf = n as f64;
    nf * (nf + 2.0)
        * (1..=h.min(r.len() - 1))
            .map(|k| r[k] * r[k] / (nf - k as f64))
            .sum::<f64>()
}

/// Whiteness test of one residual series.
pub fn whiteness(output: usize, e: &[f64]) -> Whiteness {
    let n = e.len();
    let maxlag = MAX_LAG.min(n / 4).max(1);
    let r = acf(e, maxlag);
    let band = 1.959_963_984_540_054 / (n as f64).sqrt();
    let h = 20.min(n / 5).max(1).min(maxlag);
    let q = ljung_box(&r, n, h);
    Whiteness {
        output,
        excursions: r.iter().skip(1).filter(|v| v.abs() > band).count(),
        acf: r,
        band,
        ljung_box: q,
        dof: h,
        p_value: chi2_sf(q, h as f64),
    }
}

/// The spectrum test of one residual series.
pub fn spectrum(output: usize, e: &[f64]) -> Spectrum {
    let n = e.len();
    let pad = 4;
    let (w, p) = periodogram(e, pad);
    // local level on the unpadded grid (every pad-th ordinate), running median over
    // +-HALF bins, / ln 2 (median of Exp(1) is ln 2)
    let coarse: Vec<f64> = p.iter().step_by(pad).copied().collect();
    const HALF: usize = 12;
    let mut lvl_coarse = vec![0.0; coarse.len()];
    let mut win: Vec<f64> = Vec::with_capacity(2 * HALF + 1);
    for (i, l) in lvl_coarse.iter_mut().enumerate() {
        let lo = i.saturating_sub(HALF);
        let hi = (i + HALF + 1).min(coarse.len());
        win.clear();
        win.extend_from_slice(&coarse[lo..hi]);
        win.sort_by(f64::total_cmp);
        *l = (win[win.len() / 2] / std::f64::consts::LN_2).max(1e-300);
    }
    let level: Vec<f64> = (0..p.len())
        .map(|k| lvl_coarse[((k + pad / 2) / pad).min(lvl_coarse.len() - 1)])
        .collect();
    let threshold = ((n as f64 / 2.0) / ALPHA).ln();
    // local maxima, away from DC (the first two unpadded bins are trends)
    let mut cands: Vec<(usize, f64)> = (1..p.len().saturating_sub(1))
        .filter(|&k| k >= 2 * pad && p[k] >= p[k - 1] && p[k] >= p[k + 1])
        .map(|k| (k, p[k] / level[k]))
        .collect();
    cands.sort_by(|a, b| b.1.total_cmp(&a.1));
    let dw = 2.0 * std::f64::consts::PI / (p.len() as f64 - 1.0) / 2.0;
    let mk = |k: usize, ratio: f64| {
        let lo = (w[k] - dw).max(0.0);
        let hi = (w[k] + dw).min(std::f64::consts::PI);
        let om = refine_peak(e, lo, hi);
        Peak {
            omega: om,
            period: 2.0 * std::f64::consts::PI / om,
            ratio,
        }
    };
    let top = cands.first().map(|&(k, rr)| mk(k, rr)).unwrap_or(Peak {
        omega: 0.0,
        period: f64::INFINITY,
        ratio: 0.0,
    });
    let mut peaks: Vec<Peak> = Vec::new();
    let sep = 3.0 * 2.0 * std::f64::consts::PI / n as f64;
    for &(k, rr) in &cands {
        if rr < threshold || peaks.len() >= 5 {
            break;
        }
        if peaks.iter().any(|q| (q.omega - w[k]).abs() < sep) {
            continue;
        }
        peaks.push(mk(k, rr));
    }
    Spectrum {
        output,
        threshold,
        peaks,
        top,
        omega: w,
        power: p,
        level,
    }
}

fn quantiles(x: &[f64], q: usize) -> Vec<f64> {
    let mut s = x.to_vec();
    s.sort_by(f64::total_cmp);
    (0..=q)
        .map(|i| s[((i * (s.len() - 1)) as f64 / q as f64).round() as usize])
        .collect()
}

/// All tests of a residual `e` (N x l) on data `ds`, with the model's free-run output `yhat`.
pub fn analyse(
    kind: &'static str,
    e: &DMatrix<f64>,
    yhat: &DMatrix<f64>,
    ds: &Dataset,
) -> ResidualReport {
    let (n, l) = (e.nrows(), e.ncols());
    let cols: Vec<Vec<f64>> = (0..l)
        .map(|j| e.column(j).iter().copied().collect())
        .collect();
    let roles = column_roles(ds);
    let maxlag = MAX_LAG.min(n / 4).max(1);
    let band = 1.959_963_984_540_054 / (n as f64).sqrt();
    let mut rep = ResidualReport {
        kind,
        samples: n,
        mean: vec![],
        rms: vec![],
        mean_t: vec![],
        mean_p: vec![],
        whiteness: vec![],
        cross: vec![],
        nonlinear: vec![],
        spectrum: vec![],
        bins: vec![],
    };
    let nb = batch_count(n);
    // nonlinear regressors: built once
    let mut regs: Vec<(String, Vec<f64>)> = Vec::new();
    let inputs: Vec<(String, &[f64])> = roles
        .iter()
        .filter(|r| r.1 == "input")
        .filter_map(|r| ds.column(&r.0).map(|c| (r.0.clone(), c)))
        .collect();
    let sched: Vec<(String, &[f64])> = roles
        .iter()
        .filter(|r| r.1 == "scheduling")
        .filter_map(|r| ds.column(&r.0).map(|c| (r.0.clone(), c)))
        .collect();
    for (name, u) in &inputs {
        regs.push((format!("{name}^2"), u.iter().map(|v| v * v).collect()));
        regs.push((
            format!("abs({name})*{name}"),
            u.iter().map(|v| v.abs() * v).collect(),
        ));
        regs.push((
            format!("sign({name})"),
            u.iter().map(|v| v.signum()).collect(),
        ));
        regs.push((format!("abs({name})"), u.iter().map(|v| v.abs()).collect()));
    }
    for (a, (pa, p)) in sched.iter().enumerate() {
        regs.push((format!("{pa}^2"), p.iter().map(|v| v * v).collect()));
        regs.push((format!("{pa}^3"), p.iter().map(|v| v * v * v).collect()));
        for (name, u) in &inputs {
            regs.push((
                format!("{pa}*{name}"),
                p.iter().zip(*u).map(|(x, y)| x * y).collect(),
            ));
        }
        for yname in ds.channels('y') {
            if let Some(y) = ds.column(&yname) {
                let v = (0..p.len())
                    .map(|k| if k > 0 { p[k] * y[k - 1] } else { 0.0 })
                    .collect();
                regs.push((format!("{pa}*{yname}(k-1)"), v));
            }
        }
        for j in 0..yhat.ncols() {
            regs.push((
                format!("{pa}*yhat{}", j + 1),
                p.iter()
                    .zip(yhat.column(j).iter())
                    .map(|(x, y)| x * y)
                    .collect(),
            ));
        }
        for (pb, q) in sched.iter().skip(a + 1) {
            regs.push((
                format!("{pa}*{pb}"),
                p.iter().zip(*q).map(|(x, y)| x * y).collect(),
            ));
        }
    }
    for j in 0..yhat.ncols() {
        regs.push((
            format!("yhat{}^2", j + 1),
            yhat.column(j).iter().map(|v| v * v).collect(),
        ));
    }
    let z_cc = normal_quantile(1.0 - ALPHA / (2.0 * (2 * maxlag + 1) as f64));
    for (j, ej) in cols.iter().enumerate() {
        let m = mean(ej);
        let rms = (ej.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        let (t, nu) = batch_means_t(ej, nb);
        rep.mean.push(m);
        rep.rms.push(rms);
        rep.mean_t.push(t);
        rep.mean_p.push((2.0 * t_sf(t.abs(), nu)).min(1.0));
        let wt = whiteness(j + 1, ej);
        let re = wt.acf.clone();
        rep.whiteness.push(wt);
        for (name, kind) in &roles {
            let Some(s) = ds.column(name) else { continue };
            let r = ccf(ej, s, maxlag, maxlag);
            let rs = acf(s, maxlag);
            let bsd = bartlett_sd(&re, &rs, n);
            let (imax, &rmax) = r
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .unwrap_or((maxlag, &0.0));
            rep.cross.push(CrossCorr {
                output: j + 1,
                signal: name.clone(),
                kind,
                band,
                bartlett_band: 1.959_963_984_540_054 * bsd,
                max_abs: rmax.abs(),
                at_lag: imax as isize - maxlag as isize,
                significant: rmax.abs() > z_cc * bsd,
                bound: z_cc * bsd,
                r,
            });
        }
        let z_nl = normal_quantile(1.0 - ALPHA / (2.0 * (NL_LAGS + 1) as f64));
        for (name, g) in &regs {
            let r = ccf(ej, g, 0, NL_LAGS.min(n / 4));
            let rg = acf(g, maxlag);
            let bound = z_nl * bartlett_sd(&re, &rg, n);
            let (lag, &rv) = r
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .unwrap_or((0, &0.0));
            rep.nonlinear.push(NonlinTest {
                output: j + 1,
                regressor: name.clone(),
                r: rv,
                lag,
                bound,
                ratio: rv.abs() / bound.max(1e-300),
            });
        }
        rep.spectrum.push(spectrum(j + 1, ej));
        for (pname, p) in &sched {
            let edges = quantiles(p, 5);
            let mut bins = Vec::new();
            for b in 0..5 {
                let (lo, hi) = (edges[b], edges[b + 1]);
                let sel: Vec<f64> = p
                    .iter()
                    .zip(ej)
                    .filter(|(v, _)| **v >= lo && (**v < hi || (b == 4 && **v <= hi)))
                    .map(|(_, e)| *e)
                    .collect();
                if sel.is_empty() {
                    continue;
                }
                let cnt = sel.len();
                bins.push(Bin {
                    lo,
                    hi,
                    count: cnt,
                    mean: mean(&sel),
                    rms: (sel.iter().map(|v| v * v).sum::<f64>() / cnt as f64).sqrt(),
                });
            }
            let mx = bins.iter().map(|b| b.rms).fold(0.0, f64::max);
            let mn = bins.iter().map(|b| b.rms).fold(f64::INFINITY, f64::min);
            rep.bins.push(BinStats {
                output: j + 1,
                signal: pname.clone(),
                rms_ratio: if mn > 0.0 { mx / mn } else { f64::INFINITY },
                bins,
            });
        }
    }
    rep.nonlinear.sort_by(|a, b| b.ratio.total_cmp(&a.ratio));
    rep
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: u64, n: usize) -> Vec<f64> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                let mut acc = 0.0;
                for _ in 0..12 {
                    s = s
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    acc += (s >> 11) as f64 / (1u64 << 53) as f64;
                }
                acc - 6.0
            })
            .collect()
    }

    #[test]
    fn white_noise_passes_and_a_sinusoid_is_found() {
        let n = 4000;
        let e = lcg(3, n);
        let w = whiteness(1, &e);
        assert!(w.p_value > 0.001, "LB p {}", w.p_value);
        let s = spectrum(1, &e);
        assert!(s.peaks.is_empty(), "{:?}", s.peaks);
        let x: Vec<f64> = e
            .iter()
            .enumerate()
            .map(|(k, v)| v + 0.3 * (0.9 * k as f64 + 0.4).sin())
            .collect();
        let s = spectrum(1, &x);
        assert!(!s.peaks.is_empty());
        assert!((s.peaks[0].omega - 0.9).abs() < 1e-3, "{:?}", s.peaks);
        // AR(1) residual fails whiteness
        let mut v = 0.0;
        let ar: Vec<f64> = e
            .iter()
            .map(|x| {
                v = 0.5 * v + x;
                v
            })
            .collect();
        assert!(whiteness(1, &ar).p_value < 1e-6);
    }

    #[test]
    fn cross_correlation_finds_a_lagged_input() {
        let n = 3000;
        let u = lcg(5, n);
        let noise = lcg(9, n);
        let e: Vec<f64> = (0..n)
            .map(|k| noise[k] + if k >= 7 { 0.3 * u[k - 7] } else { 0.0 })
            .collect();
        let ds = Dataset {
            source: "x".into(),
            names: vec!["u1".into(), "y1".into(), "w".into()],
            cols: vec![u.clone(), vec![0.0; n], lcg(11, n)],
        };
        let em = DMatrix::from_column_slice(n, 1, &e);
        let rep = analyse("free-run", &em, &DMatrix::zeros(n, 1), &ds);
        let cu = rep.cross.iter().find(|c| c.signal == "u1").unwrap();
        assert!(
            cu.significant && cu.at_lag == 7,
            "{:?}",
            (cu.at_lag, cu.max_abs)
        );
        let cw = rep.cross.iter().find(|c| c.signal == "w").unwrap();
        assert_eq!(cw.kind, "logged");
        assert!(!cw.significant);
    }
}
