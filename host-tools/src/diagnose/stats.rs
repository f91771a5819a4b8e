//! The statistics the residual tests need and nothing else: distribution tails (normal,
//! chi-square, Student t), sample auto- and cross-correlations, a radix-2 FFT for the
//! periodogram, and least squares through the core's mergeable [`lpvid::Gram`] (one
//! least-squares code path for every fit diagnose makes). The paired tests of one model's
//! held-out loss against another's are in [`crate::significance`].

use nalgebra::DMatrix;

use crate::linalg::{min_norm_from_normal, LinalgError};

/// Why a least-squares fit through the core's Gram failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatsError {
    /// The core's Gram rejected the dimension or a row (e.g. a non-finite value).
    #[error(transparent)]
    Core(#[from] lpvid::Error),
    /// The minimum-norm solve of the normal equations failed.
    #[error(transparent)]
    Linalg(#[from] LinalgError),
}

// ------------------------------------------------------------------------------------------
// Distributions
// ------------------------------------------------------------------------------------------

/// ln Gamma(x), x > 0 (Lanczos, g = 7, 9 terms: ~1e-15 relative).
pub fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma Q(a, x) (series below a + 1, continued fraction above).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut del, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        (1.0 - sum * (-x + a * x.ln() - gln).exp()).clamp(0.0, 1.0)
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        ((-x + a * x.ln() - gln).exp() * h).clamp(0.0, 1.0)
    }
}

/// P(chi^2_k > x).
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    gamma_q(0.5 * k, 0.5 * x)
}

/// Regularised incomplete beta I_x(a, b) (continued fraction, Lentz).
pub fn beta_inc(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let front =
        (ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln()).exp();
    if x > (a + 1.0) / (a + b + 2.0) {
        return 1.0 - beta_inc(b, a, 1.0 - x);
    }
    let tiny = 1e-300;
    let (mut c, mut d) = (1.0, 1.0 - (a + b) * x / (a + 1.0));
    if d.abs() < tiny {
        d = tiny;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..1000 {
        let m = m as f64;
        let num = m * (b - m) * x / ((a + 2.0 * m - 1.0) * (a + 2.0 * m));
        d = 1.0 + num * d;
        d = if d.abs() < tiny { 1.0 / tiny } else { 1.0 / d };
        c = 1.0 + num / c;
        if c.abs() < tiny {
            c = tiny;
        }
        h *= d * c;
        let num = -(a + m) * (a + b + m) * x / ((a + 2.0 * m) * (a + 2.0 * m + 1.0));
        d = 1.0 + num * d;
        d = if d.abs() < tiny { 1.0 / tiny } else { 1.0 / d };
        c = 1.0 + num / c;
        if c.abs() < tiny {
            c = tiny;
        }
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-15 {
            break;
        }
    }
    (front * h / a).clamp(0.0, 1.0)
}

/// One-sided tail P(T_nu > t) of Student's t.
pub fn t_sf(t: f64, nu: f64) -> f64 {
    let tail = 0.5 * beta_inc(0.5 * nu, 0.5, nu / (nu + t * t));
    if t >= 0.0 {
        tail
    } else {
        1.0 - tail
    }
}

/// P(Z > z) for a standard normal Z.
pub fn normal_sf(z: f64) -> f64 {
    // erfc(x) = Q(1/2, x^2) for x >= 0
    let half = 0.5 * gamma_q(0.5, 0.5 * z * z);
    if z >= 0.0 {
        half
    } else {
        1.0 - half
    }
}

/// The standard normal quantile z with P(Z <= z) = p (Acklam's rational approximation
/// refined by one Newton step on [`normal_sf`]).
pub fn normal_quantile(p: f64) -> f64 {
    let p = p.clamp(1e-300, 1.0 - 1e-16);
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let plow = 0.02425;
    let x = if p < plow {
        let q = (-2.0 * p.ln()).sqrt();
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    } else if p <= 1.0 - plow {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    } else {
        let q = (-2.0 * (1.0 - p).ln()).sqrt();
        -(((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    // one Newton step: f(x) = P(Z <= x) - p
    let e = (1.0 - normal_sf(x)) - p;
    let pdf = (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    if pdf > 0.0 {
        x - e / pdf
    } else {
        x
    }
}

// ------------------------------------------------------------------------------------------
// Correlations and spectra
// ------------------------------------------------------------------------------------------

/// Mean of a slice (0 when empty).
pub fn mean(x: &[f64]) -> f64 {
    if x.is_empty() {
        0.0
    } else {
        x.iter().sum::<f64>() / x.len() as f64
    }
}

/// Population variance.
pub fn var(x: &[f64]) -> f64 {
    let m = mean(x);
    if x.is_empty() {
        0.0
    } else {
        x.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / x.len() as f64
    }
}

/// Normalised sample autocorrelation r(0..=maxlag) (biased estimator, r(0) = 1).
pub fn acf(x: &[f64], maxlag: usize) -> Vec<f64> {
    ccf(x, x, 0, maxlag)
}

/// Normalised sample cross-correlation r(tau) = corr(x_k, y_{k-tau}) for tau = -lead..=lag
/// (index tau + lead), biased estimator (divided by N). Through the FFT: O(N log N).
pub fn ccf(x: &[f64], y: &[f64], lead: usize, lag: usize) -> Vec<f64> {
    let n = x.len().min(y.len());
    let (mx, my) = (mean(&x[..n]), mean(&y[..n]));
    let sx = (x[..n].iter().map(|v| (v - mx) * (v - mx)).sum::<f64>()).sqrt();
    let sy = (y[..n].iter().map(|v| (v - my) * (v - my)).sum::<f64>()).sqrt();
    if sx <= 0.0 || sy <= 0.0 || n == 0 {
        return vec![0.0; lead + lag + 1];
    }
    let len = (2 * n).next_power_of_two();
    let mut ar: Vec<f64> = x[..n].iter().map(|v| v - mx).collect();
    ar.resize(len, 0.0);
    let mut ai = vec![0.0; len];
    let mut br: Vec<f64> = y[..n].iter().map(|v| v - my).collect();
    br.resize(len, 0.0);
    let mut bi = vec![0.0; len];
    fft(&mut ar, &mut ai, false);
    fft(&mut br, &mut bi, false);
    // X(w) conj(Y(w)) -> sum_k x_k y_{k - tau} at index tau (mod len)
    for k in 0..len {
        let (xr, xi, yr, yi) = (ar[k], ai[k], br[k], bi[k]);
        ar[k] = xr * yr + xi * yi;
        ai[k] = xi * yr - xr * yi;
    }
    fft(&mut ar, &mut ai, true);
    let norm = sx * sy;
    (0..=lead + lag)
        .map(|i| {
            let tau = i as isize - lead as isize;
            if tau.unsigned_abs() >= n {
                return 0.0;
            }
            let idx = if tau >= 0 {
                tau as usize
            } else {
                len - tau.unsigned_abs()
            };
            ar[idx] / norm
        })
        .collect()
}

/// In-place iterative radix-2 FFT (length a power of two); `inverse` divides by the length.
pub fn fft(re: &mut [f64], im: &mut [f64], inverse: bool) {
    let n = re.len();
    debug_assert!(n.is_power_of_two() && im.len() == n);
    if n <= 1 {
        return;
    }
    let mut j = 0;
    for i in 1..n {
        let mut bit = n >> 1;
        while j & bit != 0 {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if i < j {
            re.swap(i, j);
            im.swap(i, j);
        }
    }
    let sign = if inverse { 1.0 } else { -1.0 };
    let mut len = 2;
    while len <= n {
        let ang = sign * 2.0 * std::f64::consts::PI / len as f64;
        let (wr, wi) = (ang.cos(), ang.sin());
        for start in (0..n).step_by(len) {
            let (mut cr, mut ci) = (1.0, 0.0);
            for k in 0..len / 2 {
                let a = start + k;
                let b = a + len / 2;
                let tr = re[b] * cr - im[b] * ci;
                let ti = re[b] * ci + im[b] * cr;
                re[b] = re[a] - tr;
                im[b] = im[a] - ti;
                re[a] += tr;
                im[a] += ti;
                let nc = cr * wr - ci * wi;
                ci = cr * wi + ci * wr;
                cr = nc;
            }
        }
        len <<= 1;
    }
    if inverse {
        let s = 1.0 / n as f64;
        re.iter_mut().for_each(|v| *v *= s);
        im.iter_mut().for_each(|v| *v *= s);
    }
}

/// Periodogram of the mean-removed series, zero-padded to `pad` x the next power of two:
/// (omega in rad/sample on [0, pi], |X(omega)|^2 / N).
pub fn periodogram(x: &[f64], pad: usize) -> (Vec<f64>, Vec<f64>) {
    let n = x.len();
    let m = mean(x);
    let len = (n.next_power_of_two() * pad.max(1)).max(2);
    let mut re: Vec<f64> = x.iter().map(|v| v - m).collect();
    re.resize(len, 0.0);
    let mut im = vec![0.0; len];
    fft(&mut re, &mut im, false);
    let half = len / 2;
    let w = (0..=half)
        .map(|k| 2.0 * std::f64::consts::PI * k as f64 / len as f64)
        .collect();
    let p = (0..=half)
        .map(|k| (re[k] * re[k] + im[k] * im[k]) / n.max(1) as f64)
        .collect();
    (w, p)
}

/// |sum_k x_k e^{-i omega k}|^2 / N at one frequency (mean removed).
pub fn dtft_power(x: &[f64], omega: f64) -> f64 {
    let m = mean(x);
    let (mut cr, mut ci) = (0.0, 0.0);
    let (wr, wi) = (omega.cos(), -omega.sin());
    let (mut zr, mut zi) = (1.0, 0.0);
    for (k, v) in x.iter().enumerate() {
        cr += (v - m) * zr;
        ci += (v - m) * zi;
        let nr = zr * wr - zi * wi;
        zi = zr * wi + zi * wr;
        zr = nr;
        if k % 1024 == 1023 {
            // renormalise the rotating phasor against rounding drift
            let a = (zr * zr + zi * zi).sqrt();
            zr /= a;
            zi /= a;
        }
    }
    (cr * cr + ci * ci) / x.len().max(1) as f64
}

/// The frequency in [lo, hi] maximising [`dtft_power`] (golden-section search).
pub fn refine_peak(x: &[f64], lo: f64, hi: f64) -> f64 {
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (lo, hi);
    let mut c = b - phi * (b - a);
    let mut d = a + phi * (b - a);
    let (mut fc, mut fd) = (dtft_power(x, c), dtft_power(x, d));
    for _ in 0..60 {
        if fc > fd {
            b = d;
            d = c;
            fd = fc;
            c = b - phi * (b - a);
            fc = dtft_power(x, c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + phi * (b - a);
            fd = dtft_power(x, d);
        }
        if b - a < 1e-12 {
            break;
        }
    }
    0.5 * (a + b)
}

/// Regressors a harmonic fit is made beside ([`harmonic_rss`]): X (N x m) and the Cholesky
/// factor of X^T X, formed once, so that each trial frequency costs only the products of its
/// own sin/cos columns.
#[derive(Debug, Clone)]
pub struct Nuisance {
    x: DMatrix<f64>,
    xtx: nalgebra::Cholesky<f64, nalgebra::Dyn>,
}

impl Nuisance {
    /// The constant alone: the series' mean removed.
    pub fn constant(n: usize) -> Nuisance {
        Nuisance::new(DMatrix::from_element(n.max(1), 1, 1.0)).expect("a nonzero column")
    }

    /// The columns of `x`, each scaled to unit norm (the span is what counts; signals of very
    /// different sizes would otherwise cost X^T X its conditioning), with a ridge of 1e-10
    /// against collinear columns (a product with a constant scheduling signal). Zero
    /// columns are dropped. None when no column is left or an entry is not finite.
    pub fn new(x: DMatrix<f64>) -> Option<Nuisance> {
        if x.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let kept: Vec<nalgebra::DVector<f64>> = x
            .column_iter()
            .filter_map(|c| {
                let norm = c.norm();
                (norm > 0.0).then(|| c / norm)
            })
            .collect();
        if kept.is_empty() {
            return None;
        }
        let x = DMatrix::from_columns(&kept);
        let mut xtx = x.tr_mul(&x);
        for i in 0..x.ncols() {
            xtx[(i, i)] += 1e-10;
        }
        let xtx = xtx.cholesky()?;
        Some(Nuisance { x, xtx })
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.x.nrows()
    }

    /// True when there is no row.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Number of regressors.
    pub fn width(&self) -> usize {
        self.x.ncols()
    }

    /// The series `v` less its least-squares fit on the regressors (None when its length
    /// is not the number of rows).
    pub fn residual(&self, v: &[f64]) -> Option<Vec<f64>> {
        if v.len() != self.len() {
            return None;
        }
        let xv = nalgebra::DVector::from_column_slice(v);
        let fit = &self.x * self.xtx.solve(&self.x.tr_mul(&xv));
        Some(v.iter().zip(fit.iter()).map(|(a, b)| a - b).collect())
    }
}

/// Residual sum of squares of the series `x` after least squares on the regressors of
/// `beside` and sin(h omega k), cos(h omega k), h = 1..=`harmonics` (a harmonic series of one
/// fundamental `omega` in rad/sample), by the Schur complement of the nuisance block: the
/// sinusoids' normal equations are 2H x 2H. With [`Nuisance::constant`] this is the
/// mean-removed series' fit. Non-finite results, and a series whose length is not the
/// nuisance's, count as the series' own sum of squares (nothing explained).
pub fn harmonic_rss(x: &[f64], omega: f64, harmonics: usize, beside: &Nuisance) -> f64 {
    let raw: f64 = x.iter().map(|v| v * v).sum();
    if x.len() != beside.len() {
        return raw;
    }
    let xv = nalgebra::DVector::from_column_slice(x);
    let bx = beside.x.tr_mul(&xv);
    let kx = beside.xtx.solve(&bx);
    let tot = (raw - bx.dot(&kx)).max(0.0);
    if harmonics == 0 || !tot.is_finite() {
        return if tot.is_finite() { tot } else { raw };
    }
    let w = 2 * harmonics;
    let s = DMatrix::<f64>::from_fn(x.len(), w, |k, j| {
        let a = (j / 2 + 1) as f64 * omega * k as f64;
        if j % 2 == 0 {
            a.sin()
        } else {
            a.cos()
        }
    });
    let xs = beside.x.tr_mul(&s);
    let ks = beside.xtx.solve(&xs);
    let g = s.tr_mul(&s) - xs.tr_mul(&ks);
    let b = s.tr_mul(&xv) - ks.tr_mul(&bx);
    match g.cholesky() {
        Some(c) => {
            let th = c.solve(&b);
            let r = tot - th.dot(&b);
            if r.is_finite() {
                r.max(0.0)
            } else {
                tot
            }
        }
        None => tot,
    }
}

/// The fundamental in [lo, hi] (rad/sample) minimising the summed [`harmonic_rss`] of the
/// series `xs` with `harmonics` harmonics beside the regressors `beside`: least squares on
/// the frequency, beyond the periodogram's bin (a grid of 41 points, then golden-section
/// search around the best one).
pub fn refine_harmonic(
    xs: &[Vec<f64>],
    lo: f64,
    hi: f64,
    harmonics: usize,
    beside: &Nuisance,
) -> f64 {
    let f = |w: f64| {
        xs.iter()
            .map(|x| harmonic_rss(x, w, harmonics, beside))
            .sum::<f64>()
    };
    let steps = 40;
    let dw = (hi - lo) / steps as f64;
    let best = (0..=steps)
        .map(|i| lo + dw * i as f64)
        .map(|w| (f(w), w))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map_or(0.5 * (lo + hi), |v| v.1);
    crate::linalg::golden_section(f, (best - dw).max(lo), (best + dw).min(hi), 40, 1e-12)
}

// ------------------------------------------------------------------------------------------
// Least squares through the core's Gram
// ------------------------------------------------------------------------------------------

/// Second moments of rows [phi_k; t_k] (`row(k, buf)` writes one) accumulated by the core's
/// [`lpvid::Gram`] on columns scaled to unit RMS (a first pass measures them, so badly scaled
/// physical units do not spoil the conditioning). Returns the dense scaled moment matrix and
/// the scale factors (scaled column = raw column x factor).
pub fn moments(
    rows: usize,
    d: usize,
    mut row: impl FnMut(usize, &mut [f64]),
) -> Result<(DMatrix<f64>, Vec<f64>), StatsError> {
    let mut buf = vec![0.0; d];
    let mut ss = vec![0.0; d];
    for k in 0..rows {
        row(k, &mut buf);
        for (s, v) in ss.iter_mut().zip(&buf) {
            *s += v * v;
        }
    }
    let scale: Vec<f64> = ss
        .iter()
        .map(|s| {
            let r = (s / rows.max(1) as f64).sqrt();
            if r > 0.0 && r.is_finite() {
                1.0 / r
            } else {
                1.0
            }
        })
        .collect();
    let g = crate::linalg::gram_from_rows(d, rows, |k, dst| {
        row(k, dst);
        for (v, s) in dst.iter_mut().zip(&scale) {
            *v *= s;
        }
    })?;
    Ok((DMatrix::from_fn(d, d, |i, j| g.get(i, j)), scale))
}

/// Least squares of targets `tgts` on regressors `regs` (indices into the columns of
/// [`moments`]): X (tgts x regs, raw units) by minimum-norm least squares, and the residual
/// sum of squares per target (raw units).
pub fn solve_moments(
    s: &DMatrix<f64>,
    scale: &[f64],
    regs: &[usize],
    tgts: &[usize],
) -> Result<(DMatrix<f64>, Vec<f64>), StatsError> {
    let s_ff = DMatrix::from_fn(regs.len(), regs.len(), |i, j| s[(regs[i], regs[j])]);
    let s_ft = DMatrix::from_fn(tgts.len(), regs.len(), |i, j| s[(tgts[i], regs[j])]);
    let xs = if regs.is_empty() {
        DMatrix::zeros(tgts.len(), 0)
    } else {
        min_norm_from_normal(&s_ff, &s_ft, 1e-12)?.0
    };
    let mut rss = Vec::with_capacity(tgts.len());
    for (i, &t) in tgts.iter().enumerate() {
        let xi = xs.row(i);
        let v = if regs.is_empty() {
            s[(t, t)]
        } else {
            s[(t, t)] - 2.0 * (xi * s_ft.row(i).transpose())[(0, 0)]
                + (xi * &s_ff * xi.transpose())[(0, 0)]
        };
        rss.push(v.max(0.0) / (scale[t] * scale[t]));
    }
    let x = DMatrix::from_fn(tgts.len(), regs.len(), |i, j| {
        xs[(i, j)] * scale[regs[j]] / scale[tgts[i]]
    });
    Ok((x, rss))
}

/// Least squares X = argmin sum_k |t_k - X phi_k|^2 for `rows` samples: `row(k, buf)` writes
/// [phi_k (nreg); t_k (ntgt)]. Returns (X, ntgt x nreg; residual sum of squares per target).
pub fn lstsq(
    rows: usize,
    nreg: usize,
    ntgt: usize,
    row: impl FnMut(usize, &mut [f64]),
) -> Result<(DMatrix<f64>, Vec<f64>), StatsError> {
    let (s, scale) = moments(rows, nreg + ntgt, row)?;
    let regs: Vec<usize> = (0..nreg).collect();
    let tgts: Vec<usize> = (nreg..nreg + ntgt).collect();
    solve_moments(&s, &scale, &regs, &tgts)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform numbers in [-0.5, 0.5) from a 64-bit linear congruential generator (Knuth's
    /// MMIX constants): a fixed, dependency-free noise for these tests.
    fn uniform(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed;
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        }
    }

    #[test]
    fn distributions() {
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-9);
        assert!((chi2_sf(31.410_432_844_230_918, 20.0) - 0.05).abs() < 1e-9);
        assert!((t_sf(2.093_024_054_408_263, 19.0) - 0.025).abs() < 1e-9);
        assert!((t_sf(-2.093_024_054_408_263, 19.0) - 0.975).abs() < 1e-9);
        assert!((normal_sf(1.959_963_984_540_054) - 0.025).abs() < 1e-9);
        assert!((normal_sf(-1.0) - 0.841_344_746_068_542_9).abs() < 1e-9);
        assert!((normal_quantile(0.975) - 1.959_963_984_540_054).abs() < 1e-9);
        assert!((normal_quantile(1e-6) + 4.753_424_308_822_899).abs() < 1e-7);
        assert!((ln_gamma(10.0) - 362_880f64.ln()).abs() < 1e-12);
    }

    #[test]
    fn correlations_match_direct_sums() {
        let x: Vec<f64> = (0..200).map(|k| ((k * 7919) % 101) as f64 - 50.0).collect();
        let y: Vec<f64> = (0..200).map(|k| ((k * 104_729) % 97) as f64).collect();
        let r = ccf(&x, &y, 3, 4);
        let (mx, my) = (mean(&x), mean(&y));
        let norm = (x.iter().map(|v| (v - mx).powi(2)).sum::<f64>()
            * y.iter().map(|v| (v - my).powi(2)).sum::<f64>())
        .sqrt();
        for tau in -3isize..=4 {
            let mut s = 0.0;
            for k in 0..200isize {
                let j = k - tau;
                if (0..200).contains(&j) {
                    s += (x[k as usize] - mx) * (y[j as usize] - my);
                }
            }
            assert!(
                (r[(tau + 3) as usize] - s / norm).abs() < 1e-10,
                "tau {tau}"
            );
        }
        assert!((acf(&x, 2)[0] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn harmonic_series_frequency_beyond_the_bin() {
        // 1P and 3P of a fundamental between two periodogram bins, in white noise
        let n = 4000;
        let w0 = 0.3871234;
        let mut noise = uniform(12345);
        let x: Vec<f64> = (0..n)
            .map(|k| {
                let e = noise();
                let a = w0 * k as f64;
                (a + 0.3).sin() + 0.5 * (3.0 * a).cos() + e
            })
            .collect();
        let bin = 2.0 * std::f64::consts::PI / n as f64;
        let mean = Nuisance::constant(n);
        let w = refine_harmonic(std::slice::from_ref(&x), w0 - bin, w0 + bin, 3, &mean);
        assert!((w - w0).abs() < 0.02 * bin, "{w} vs {w0}");
        let r3 = harmonic_rss(&x, w, 3, &mean);
        let r1 = harmonic_rss(&x, w, 1, &mean);
        let tot = harmonic_rss(&x, w, 0, &mean);
        assert!(r3 < r1 && r1 < tot);
        // what is left is the noise: n / 12 within 10 %
        assert!((r3 / (n as f64 / 12.0) - 1.0).abs() < 0.1, "{r3}");
    }

    #[test]
    fn harmonic_rss_beside_regressors_is_the_joint_least_squares() {
        // the Schur complement of the nuisance block against one least squares on [X, S],
        // with regressors of very different sizes (the columns are scaled inside)
        let (n, w, h) = (300, 0.61, 2);
        let mut next = uniform(99);
        let x = DMatrix::<f64>::from_fn(n, 4, |k, j| match j {
            0 => 1.0,
            1 => 300.0 * next(),
            2 => k as f64 * 0.01,
            _ => 1e-3 * next(),
        });
        let y: Vec<f64> = (0..n)
            .map(|k| 2.0 * x[(k, 1)] / 300.0 + (w * k as f64).sin() + 0.3 * next())
            .collect();
        let joint = DMatrix::<f64>::from_fn(n, 4 + 2 * h, |k, j| {
            if j < 4 {
                x[(k, j)]
            } else {
                let a = ((j - 4) / 2 + 1) as f64 * w * k as f64;
                if (j - 4) % 2 == 0 {
                    a.sin()
                } else {
                    a.cos()
                }
            }
        });
        let yv = nalgebra::DVector::from_vec(y.clone());
        let direct = |m: &DMatrix<f64>| {
            let th = m.clone().svd(true, true).solve(&yv, 1e-14).unwrap();
            (&yv - m * th).norm_squared()
        };
        let beside = Nuisance::new(x.clone()).unwrap();
        let (rh, r0) = (
            harmonic_rss(&y, w, h, &beside),
            harmonic_rss(&y, w, 0, &beside),
        );
        let (dh, d0) = (direct(&joint), direct(&x));
        assert!((rh / dh - 1.0).abs() < 1e-8, "{rh} vs {dh}");
        assert!((r0 / d0 - 1.0).abs() < 1e-8, "{r0} vs {d0}");
        // a series of another length explains nothing
        assert_eq!(
            harmonic_rss(&y[1..], w, h, &beside),
            y[1..].iter().map(|v| v * v).sum::<f64>()
        );
    }

    #[test]
    fn fft_round_trip_and_peak() {
        let n = 256;
        let x: Vec<f64> = (0..n).map(|k| (0.7 * k as f64).sin()).collect();
        let mut re = x.clone();
        let mut im = vec![0.0; n];
        fft(&mut re, &mut im, false);
        fft(&mut re, &mut im, true);
        assert!(re.iter().zip(&x).all(|(a, b)| (a - b).abs() < 1e-12));
        let (w, p) = periodogram(&x, 4);
        let k = (0..p.len()).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
        let f = refine_peak(&x, w[k - 1], w[k + 1]);
        assert!((f - 0.7).abs() < 1e-3, "{f}");
    }

    #[test]
    fn least_squares_recovers_coefficients() {
        let n = 500;
        let (x, rss) = lstsq(n, 2, 1, |k, b| {
            let a = (k as f64 * 0.37).sin() * 1e3;
            let c = (k as f64 * 0.11).cos();
            b[0] = a;
            b[1] = c;
            b[2] = 2e-3 * a - 5.0 * c;
        })
        .unwrap();
        assert!((x[(0, 0)] - 2e-3).abs() < 1e-12 && (x[(0, 1)] + 5.0).abs() < 1e-9);
        assert!(rss[0] < 1e-12);
    }

    #[test]
    fn batch_means_detects_a_shift_in_coloured_noise() {
        use crate::significance::batch_means_t;
        // AR(1) noise with pole 0.9: mean zero
        let mut v = 0.0;
        let mut noise = uniform(12345);
        let d: Vec<f64> = (0..4000)
            .map(|_| {
                v = 0.9 * v + noise();
                v
            })
            .collect();
        let (t, nu) = batch_means_t(&d, 20);
        assert!(t_sf(t.abs(), nu) > 0.001, "t = {t}");
        let shifted: Vec<f64> = d.iter().map(|x| x + 0.5).collect();
        let (t, nu) = batch_means_t(&shifted, 20);
        assert!(t_sf(t, nu) < 1e-6, "t = {t}");
    }
}
