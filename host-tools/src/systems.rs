//! Seeded data generators for the benchmark systems of `BENCHMARKS.md` (B1-B6).
//!
//! Every generator is deterministic given its seed. Each random stream (input, scheduling,
//! noise, training or validation) comes from its own `StdRng` derived from `(seed, tag)`, so
//! the input realisation does not change when only the noise level or a length changes
//! (e.g. `b1(1000, 0.0, 7)` and `b1(1000, 0.05, 7)` share input and scheduling; only the
//! noise differs).
//!
//! Conventions common to all generators:
//! - the time index of a formula such as `mu2_k = cos(2 pi k / 10) + 0.2` is the row index,
//!   `k = 0, 1, ..., N-1`, in the training and in the validation set alike;
//! - every simulation starts from `x0 = 0` (`y_o(-1) = 0` for B6), with no burn-in, and input
//!   filters start from a zero state;
//! - the validation set (`Experiment::val`) is noise-free: a fresh input (and, where the
//!   scheduling is random, a fresh scheduling) realisation, outputs from the true system with
//!   zero noise;
//! - noise scaled "to an SNR" is scaled to the *exact* sample variance the SNR asks for
//!   (sample variances with the 1/(N-1) normalisation), so the achieved SNR equals the
//!   requested one on every realisation.

use std::f64::consts::PI;

use nalgebra::{Complex, DMatrix, DVector};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal, Uniform};

use crate::lpvss::{scheduled, LpvSs, Signals};

// ---------------------------------------------------------------------------------------------
// Filters
// ---------------------------------------------------------------------------------------------

/// Digital Butterworth low-pass filter `(b, a)` of the given order, cutoff `wn` as a fraction
/// of the Nyquist frequency (0 < wn < 1), designed like `scipy.signal.butter(order, wn)`:
/// analog prototype, prewarping `4 tan(pi wn / 2)` (fs = 2), bilinear transform. `a[0] = 1`.
/// Panics when `order == 0` or `wn` is outside (0, 1).
pub fn butterworth_lowpass(order: usize, wn: f64) -> (Vec<f64>, Vec<f64>) {
    assert!(order >= 1, "Butterworth order must be at least 1");
    assert!(
        wn > 0.0 && wn < 1.0,
        "Butterworth cutoff must be in (0, 1) x Nyquist"
    );
    let fs = 2.0;
    let fs2 = 2.0 * fs;
    let warped = fs2 * (PI * wn / fs).tan();
    let nf = order as f64;
    let mut poles = Vec::with_capacity(order);
    let mut denom = Complex::new(1.0, 0.0);
    for j in 0..order {
        // analog prototype poles -exp(i pi m / (2N)), m = -N+1, -N+3, ..., N-1, scaled to
        // the prewarped cutoff
        let m = -nf + 1.0 + 2.0 * j as f64;
        let p = -Complex::from_polar(1.0, PI * m / (2.0 * nf)) * warped;
        poles.push((fs2 + p) / (fs2 - p));
        denom *= fs2 - p;
    }
    let gain = warped.powi(order as i32) * (Complex::new(1.0, 0.0) / denom).re;
    // all N zeros of the digital filter sit at z = -1
    let zeros = vec![Complex::new(-1.0, 0.0); order];
    let b = poly(&zeros).into_iter().map(|c| gain * c.re).collect();
    let a = poly(&poles).into_iter().map(|c| c.re).collect();
    (b, a)
}

/// Coefficients (highest power first) of prod_i (z - r_i).
fn poly(roots: &[Complex<f64>]) -> Vec<Complex<f64>> {
    let mut c = vec![Complex::new(1.0, 0.0)];
    for r in roots {
        let mut next = c.clone();
        next.push(Complex::new(0.0, 0.0));
        for i in 1..next.len() {
            next[i] -= r * c[i - 1];
        }
        c = next;
    }
    c
}

/// Direct-form IIR/FIR filter with zero initial state, like `scipy.signal.lfilter(b, a, x)`:
/// `a[0] y[n] = sum_i b[i] x[n-i] - sum_{j>=1} a[j] y[n-j]`. Panics when `a` is empty or
/// `a[0] == 0`.
pub fn lfilter(b: &[f64], a: &[f64], x: &[f64]) -> Vec<f64> {
    assert!(
        !a.is_empty() && a[0] != 0.0,
        "lfilter: a[0] must be nonzero"
    );
    let a0 = a[0];
    let mut y = vec![0.0; x.len()];
    for nidx in 0..x.len() {
        let mut acc = 0.0;
        for (i, bi) in b.iter().enumerate() {
            if i > nidx {
                break;
            }
            acc += bi * x[nidx - i];
        }
        for (j, aj) in a.iter().enumerate().skip(1) {
            if j > nidx {
                break;
            }
            acc -= aj * y[nidx - j];
        }
        y[nidx] = acc / a0;
    }
    y
}

// ---------------------------------------------------------------------------------------------
// Shared helpers
// ---------------------------------------------------------------------------------------------

/// One benchmark data set: training data, a noise-free validation set and the true model.
#[derive(Debug, Clone)]
pub struct Experiment {
    /// Training (identification) data, possibly noisy.
    pub train: Signals,
    /// Noise-free validation: fresh input and scheduling realisation, y from the true system
    /// with zero noise, x0 = 0.
    pub val: Signals,
    /// The true system as an LPV state-space model (see each generator for what its K means).
    pub truth: Option<LpvSs>,
    /// Benchmark name ("B1", ...).
    pub name: &'static str,
}

/// Independent random stream number `tag` of experiment seed `seed`.
fn stream(seed: u64, tag: u64) -> StdRng {
    // splitmix64 finaliser of the pair, so nearby seeds/tags give unrelated streams
    let mut z = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(tag.wrapping_mul(0xD1B5_4A32_D192_ED03))
        .wrapping_add(0x632B_E59B_D9B4_E019);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    StdRng::seed_from_u64(z)
}

const TAG_TRAIN_INPUT: u64 = 1;
const TAG_TRAIN_SCHED: u64 = 2;
const TAG_TRAIN_NOISE: u64 = 3;
const TAG_TRAIN_NOISE2: u64 = 4;
const TAG_VAL_INPUT: u64 = 11;
const TAG_VAL_SCHED: u64 = 12;
const TAG_CAL_INPUT: u64 = 21;
const TAG_CAL_SCHED: u64 = 22;
const TAG_CAL_NOISE: u64 = 23;
const TAG_CAL_NOISE2: u64 = 24;

fn gaussian(rng: &mut StdRng, n: usize) -> Vec<f64> {
    (0..n).map(|_| StandardNormal.sample(rng)).collect()
}

fn gaussian_matrix(rng: &mut StdRng, rows: usize, cols: usize, std: f64) -> DMatrix<f64> {
    // column-major fill: column by column, so a column is one contiguous stretch of the stream
    let mut m = DMatrix::zeros(rows, cols);
    for j in 0..cols {
        for i in 0..rows {
            let z: f64 = StandardNormal.sample(rng);
            m[(i, j)] = std * z;
        }
    }
    m
}

/// Sample variance with the 1/(N-1) normalisation (0 for fewer than two samples).
fn sample_var<'a>(x: impl IntoIterator<Item = &'a f64>) -> f64 {
    let v: Vec<f64> = x.into_iter().copied().collect();
    if v.len() < 2 {
        return 0.0;
    }
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    v.iter().map(|a| (a - mean) * (a - mean)).sum::<f64>() / (v.len() as f64 - 1.0)
}

/// Standard Gaussian N x cols noise, each column rescaled to sample variance exactly `var`.
fn noise_with_variance(rng: &mut StdRng, rows: usize, cols: usize, var: f64) -> DMatrix<f64> {
    let mut m = gaussian_matrix(rng, rows, cols, 1.0);
    for j in 0..cols {
        let v = sample_var(m.column(j).iter());
        let f = if v > 0.0 { (var / v).sqrt() } else { 0.0 };
        m.column_mut(j).scale_mut(f);
    }
    m
}

fn rm(rows: usize, cols: usize, data: &[f64]) -> DMatrix<f64> {
    DMatrix::from_row_slice(rows, cols, data)
}

fn col(v: &[f64]) -> DMatrix<f64> {
    DMatrix::from_column_slice(v.len(), 1, v)
}

/// Simulation of the deterministic-stochastic form of the sparse paper, eq. (1)-(2):
/// `x_{k+1} = sum_i mu_k^(i) (A^(i) x_k + B^(i) u_k) + w_k`, `y_k = C x_k + D u_k + v_k`,
/// from `x0 = 0`, with process noise `w` (N x n) and measurement noise `v` (N x l), each
/// optional. `K` of the model is ignored. The outputs of `sig` are ignored. Returns N x l.
pub fn simulate_wv(
    model: &LpvSs,
    sig: &Signals,
    w: Option<&DMatrix<f64>>,
    v: Option<&DMatrix<f64>>,
) -> DMatrix<f64> {
    let (n, l) = (model.n(), model.l());
    let mut x = DVector::<f64>::zeros(n);
    let mut out = DMatrix::<f64>::zeros(sig.len(), l);
    for k in 0..sig.len() {
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        let mut yk = scheduled(&model.c, &mu) * &x + scheduled(&model.d, &mu) * &u;
        if let Some(v) = v {
            yk += v.row(k).transpose();
        }
        out.set_row(k, &yk.transpose());
        let mut xn = scheduled(&model.a, &mu) * &x + scheduled(&model.b, &mu) * &u;
        if let Some(w) = w {
            xn += w.row(k).transpose();
        }
        x = xn;
    }
    out
}

pub use crate::linalg::spectral_radius;

/// Eigenvalues of each local matrix A^(i) of a model (what the kernel paper's Fig. 2 plots).
pub fn local_eigenvalues(model: &LpvSs) -> Vec<Vec<Complex<f64>>> {
    model
        .a
        .iter()
        .map(|a| a.clone().complex_eigenvalues().iter().copied().collect())
        .collect()
}

fn zeros_like(count: usize, rows: usize, cols: usize) -> Vec<DMatrix<f64>> {
    vec![DMatrix::zeros(rows, cols); count]
}

// ---------------------------------------------------------------------------------------------
// B1: Verdult-Verhaegen MIMO benchmark
// ---------------------------------------------------------------------------------------------

/// The true B1 model (kernel paper section 7.1; Verdult & Verhaegen 2002/2005), innovation
/// form with the constant K stored as K^(1) (K^(2..4) = 0), C = [I3 0], D = 0.
pub fn b1_truth() -> LpvSs {
    let a1 = rm(
        4,
        4,
        &[
            -1.3, -0.6325, -0.1115, 0.0596, //
            1.0, 0.0, 0.0, 0.0, //
            0.0, 1.0, 0.0, 0.0, //
            0.0, 0.0, 1.0, 0.0,
        ],
    );
    let a2 = rm(
        4,
        4,
        &[
            -0.51, -0.1075, -0.007275, -0.0000625, //
            1.0, 0.0, 0.0, 0.0, //
            0.0, 1.0, 0.0, 0.0, //
            0.0, 0.0, 1.0, 0.0,
        ],
    );
    let a3 = DMatrix::from_diagonal(&DVector::from_vec(vec![0.2, 0.4, 0.0, 0.0]));
    let a4 = DMatrix::from_diagonal(&DVector::from_vec(vec![0.0, 0.0, 0.3, 0.3]));
    let b1 = rm(4, 2, &[0.0, 1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 1.0]);
    let bi = rm(4, 2, &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.3, 0.3]);
    let c = rm(
        3,
        4,
        &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
    );
    let k = rm(
        4,
        3,
        &[
            0.16, 0.0, 0.0, //
            0.0, 0.16, 0.0, //
            0.0, 0.0, 0.16, //
            0.16, 0.0, 0.0,
        ],
    );
    let mut ks = zeros_like(4, 4, 3);
    ks[0] = k;
    LpvSs {
        a: vec![a1, a2, a3, a4],
        b: vec![b1, bi.clone(), bi.clone(), bi],
        k: ks,
        c: vec![c],
        d: vec![DMatrix::zeros(3, 2)],
    }
}

/// B1 inputs (N x 2) and scheduling (N x 3) from two random streams.
fn b1_signals(
    n: usize,
    in_rng: &mut StdRng,
    sched_rng: &mut StdRng,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let eta = gaussian(in_rng, n);
    let nu = gaussian(in_rng, n);
    let xi = gaussian(in_rng, n);
    let (gb, ga) = butterworth_lowpass(2, 0.2);
    let fir = lfilter(&[0.75, 1.05, 0.15], &[1.0], &eta);
    let g = lfilter(&gb, &ga, &nu);
    let mut u = DMatrix::zeros(n, 2);
    for k in 0..n {
        u[(k, 0)] = fir[k] + g[k];
        u[(k, 1)] = xi[k];
    }
    let unif = Uniform::new(0.0, 1.0);
    let mut p = DMatrix::zeros(n, 3);
    for k in 0..n {
        let rho: f64 = unif.sample(sched_rng);
        let th = 2.0 * PI * k as f64 / 100.0;
        p[(k, 0)] = rho;
        p[(k, 1)] = 0.5 * th.sin() * rho;
        p[(k, 2)] = 0.5 * th.cos() * rho;
    }
    (u, p)
}

fn b1_parts(n: usize, sigma: f64, seed: u64) -> (Experiment, DMatrix<f64>) {
    let truth = b1_truth();
    let (u, p) = b1_signals(
        n,
        &mut stream(seed, TAG_TRAIN_INPUT),
        &mut stream(seed, TAG_TRAIN_SCHED),
    );
    let e = gaussian_matrix(&mut stream(seed, TAG_TRAIN_NOISE), n, 3, sigma);
    let mut train = Signals {
        u,
        y: DMatrix::zeros(n, 3),
        p,
    };
    train.y = truth.simulate(&train, Some(&e));
    let (vu, vp) = b1_signals(
        n,
        &mut stream(seed, TAG_VAL_INPUT),
        &mut stream(seed, TAG_VAL_SCHED),
    );
    let mut val = Signals {
        u: vu,
        y: DMatrix::zeros(n, 3),
        p: vp,
    };
    val.y = truth.simulate(&val, None);
    (
        Experiment {
            train,
            val,
            truth: Some(truth),
            name: "B1",
        },
        e,
    )
}

/// B1, the Verdult-Verhaegen MIMO benchmark (kernel paper section 7.1, Table 2;
/// BENCHMARKS.md B1): n = 4, r = 2, l = 3, m = 4, innovation form with constant K, D = 0.
///
/// Scheduling columns `p = [rho_k, 0.5 sin(2 pi k/100) rho_k, 0.5 cos(2 pi k/100) rho_k]`,
/// `rho_k ~ U[0,1)` i.i.d.; inputs `u1 = (0.75 + 1.05 q^-1 + 0.15 q^-2) eta + G(q) nu`
/// (G = `butterworth_lowpass(2, 0.2)`, both filters from zero state), `u2 = xi`, with
/// `eta, nu, xi ~ N(0,1)`; innovation `e_k = sigma N(0, I3)` (sigma = 0.05 is the 40 dB case,
/// sigma = 0 noise-free). Validation: same recipe, fresh input and rho, length `n`, no noise.
/// `truth` is exact: `truth.simulate(&train, Some(&e))` reproduces `train.y`.
pub fn b1(n: usize, sigma: f64, seed: u64) -> Experiment {
    b1_parts(n, sigma, seed).0
}

// ---------------------------------------------------------------------------------------------
// B2: sparse paper Example I (rotor-blade model, deterministic-stochastic form)
// ---------------------------------------------------------------------------------------------

/// The B2 system (sparse paper section 5.1), K = 0: the noise of B2 is process noise w plus
/// measurement noise v, which has no constant-K innovation form.
pub fn b2_truth() -> LpvSs {
    LpvSs {
        a: vec![
            rm(2, 2, &[0.0, 0.073, -6.52, -0.50]),
            rm(2, 2, &[-0.0021, 0.0, -0.014, 0.52]),
        ],
        b: vec![rm(2, 1, &[-0.72, -9.63]), DMatrix::zeros(2, 1)],
        k: zeros_like(2, 2, 1),
        c: vec![rm(1, 2, &[1.0, 0.0])],
        d: vec![DMatrix::zeros(1, 1)],
    }
}

/// `mu2_k = cos(2 pi k / 10) + 0.2`, k = 0..n-1, as an n x 1 scheduling matrix.
fn periodic_sched(n: usize) -> DMatrix<f64> {
    DMatrix::from_fn(n, 1, |k, _| (2.0 * PI * k as f64 / 10.0).cos() + 0.2)
}

/// B2 validation length for training length `n`.
fn b2_val_len(n: usize) -> usize {
    n.max(500)
}

fn b2_parts(n: usize, snr_db: f64, seed: u64) -> (Experiment, DMatrix<f64>, DMatrix<f64>) {
    let truth = b2_truth();
    let u = gaussian_matrix(&mut stream(seed, TAG_TRAIN_INPUT), n, 1, 1.0);
    let mut train = Signals {
        u,
        y: DMatrix::zeros(n, 1),
        p: periodic_sched(n),
    };
    let y0 = simulate_wv(&truth, &train, None, None);
    // SNR(y, s) = 20 log10(var(y) / var(s))  =>  var(s) = var(y) 10^(-SNR/20)
    let var_s = sample_var(y0.iter()) * 10f64.powf(-snr_db / 20.0);
    let w = noise_with_variance(&mut stream(seed, TAG_TRAIN_NOISE), n, 2, var_s);
    let v = noise_with_variance(&mut stream(seed, TAG_TRAIN_NOISE2), n, 1, var_s);
    train.y = simulate_wv(&truth, &train, Some(&w), Some(&v));
    let nv = b2_val_len(n);
    let mut val = Signals {
        u: gaussian_matrix(&mut stream(seed, TAG_VAL_INPUT), nv, 1, 1.0),
        y: DMatrix::zeros(nv, 1),
        p: periodic_sched(nv),
    };
    val.y = simulate_wv(&truth, &val, None, None);
    (
        Experiment {
            train,
            val,
            truth: Some(truth),
            name: "B2",
        },
        w,
        v,
    )
}

/// B2, sparse paper Example I (lpv-pbsid-sparse-bpdn-hinf-observer.md section 5.1;
/// BENCHMARKS.md B2): second-order blade model, r = l = 1, m = 2, N = 75 standard.
///
/// `mu2_k = cos(2 pi k/10) + 0.2`, `u_k ~ N(0,1)`. As in the paper's model (1)-(2), the
/// noise is white Gaussian process noise `w_k` (2 channels) added to the state equation
/// *outside* the scheduling sum, `x_{k+1} = sum_i mu^(i)(A^(i) x + B^(i) u) + w_k`, and
/// white Gaussian measurement noise `v_k` added to the output, `y = C x + v`. The paper sets
/// `SNR(y, w) = SNR(y, v) = snr_db` with `SNR(y, s) = 20 log10(var(y)/var(s))` (variances, as
/// printed in the paper, not amplitudes), y the noise-free output of the same input: so every
/// channel of w and of v is scaled to the sample variance `var(y) 10^(-snr_db/20)` exactly.
/// `snr_db = f64::INFINITY` gives noise-free data.
///
/// Validation: noise-free, fresh N(0,1) input, same scheduling formula (k = 0..), length
/// `max(n, 500)`. `truth` has K = 0 (see [`b2_truth`]).
pub fn b2(n: usize, snr_db: f64, seed: u64) -> Experiment {
    b2_parts(n, snr_db, seed).0
}

// ---------------------------------------------------------------------------------------------
// B3: sparse paper Example II
// ---------------------------------------------------------------------------------------------

/// The B3 system (sparse paper section 5.2), innovation form, n = 4, r = l = m = 2,
/// B^(2) = K^(2) = 0, D = 0.
pub fn b3_truth() -> LpvSs {
    let a1 = rm(
        4,
        4,
        &[
            0.67, 0.67, 0.0, 0.0, //
            -0.67, 0.67, 0.0, 0.0, //
            0.0, 0.0, -0.67, -0.67, //
            0.0, 0.0, 0.67, -0.67,
        ],
    );
    let a2 = rm(
        4,
        4,
        &[
            -0.2, -0.2, 0.0, 0.0, //
            0.2, -0.2, 0.0, 0.0, //
            0.0, 0.0, 0.2, 0.2, //
            0.0, 0.0, -0.2, 0.2,
        ],
    );
    // B^(1) and K^(1) are printed transposed in the paper
    let b1 = rm(2, 4, &[0.66, 1.97, 4.32, -2.64, -0.53, 0.48, -0.49, -0.34]).transpose();
    let k1 = rm(2, 4, &[-0.70, 0.17, 0.65, -0.94, -0.15, 0.56, -0.47, 0.10]).transpose();
    let c = rm(2, 4, &[-0.37, 0.075, -0.52, 0.58, -0.90, 0.75, 0.12, 0.098]);
    LpvSs {
        a: vec![a1, a2],
        b: vec![b1, DMatrix::zeros(4, 2)],
        k: vec![k1, DMatrix::zeros(4, 2)],
        c: vec![c],
        d: vec![DMatrix::zeros(2, 2)],
    }
}

fn b3_val_len(n: usize) -> usize {
    n.max(500)
}

fn b3_parts(n: usize, seed: u64) -> (Experiment, DMatrix<f64>) {
    let truth = b3_truth();
    let sched = |len: usize| DMatrix::from_fn(len, 1, |k, _| 0.5 + (k as f64).sin());
    let e = gaussian_matrix(&mut stream(seed, TAG_TRAIN_NOISE), n, 2, 0.5);
    let mut train = Signals {
        u: gaussian_matrix(&mut stream(seed, TAG_TRAIN_INPUT), n, 2, 1.0),
        y: DMatrix::zeros(n, 2),
        p: sched(n),
    };
    train.y = truth.simulate(&train, Some(&e));
    let nv = b3_val_len(n);
    let mut val = Signals {
        u: gaussian_matrix(&mut stream(seed, TAG_VAL_INPUT), nv, 2, 1.0),
        y: DMatrix::zeros(nv, 2),
        p: sched(nv),
    };
    val.y = truth.simulate(&val, None);
    (
        Experiment {
            train,
            val,
            truth: Some(truth),
            name: "B3",
        },
        e,
    )
}

/// B3, sparse paper Example II (lpv-pbsid-sparse-bpdn-hinf-observer.md section 5.2;
/// BENCHMARKS.md B3): fourth-order system in innovation form, r = l = m = 2, N = 250
/// standard.
///
/// `mu2_k = 0.5 + sin(k)` (k = 0.., radians), `u_k ~ N(0, I2)`, innovation
/// `e_k ~ N(0, 0.25 I2)`. Validation: noise-free, fresh input, same scheduling formula from
/// k = 0 (so its first `n` scheduling samples equal the training ones; the paper changes
/// only the input realisation), length `max(n, 500)`. `truth` is exact.
pub fn b3(n: usize, seed: u64) -> Experiment {
    b3_parts(n, seed).0
}

// ---------------------------------------------------------------------------------------------
// B4: bilinear example
// ---------------------------------------------------------------------------------------------

/// The B4 bilinear system (kernel paper section 7.3): `mu = [1, u]`, B^(2) = 0, K = 0.
pub fn b4_truth() -> LpvSs {
    LpvSs {
        a: vec![
            rm(2, 2, &[0.5, 0.5, -0.5, 0.5]),
            rm(2, 2, &[0.2, 0.2, -0.2, 0.2]),
        ],
        b: vec![rm(2, 1, &[1.0, 0.0]), DMatrix::zeros(2, 1)],
        k: zeros_like(2, 2, 1),
        c: vec![rm(1, 2, &[1.0, 1.0])],
        d: vec![DMatrix::zeros(1, 1)],
    }
}

fn b4_input(n: usize, rng: &mut StdRng) -> DMatrix<f64> {
    let (b, a) = butterworth_lowpass(4, 0.8);
    col(&lfilter(&b, &a, &gaussian(rng, n)))
}

fn b4_parts(n: usize, snr_db: Option<f64>, seed: u64) -> (Experiment, DMatrix<f64>) {
    let truth = b4_truth();
    let u = b4_input(n, &mut stream(seed, TAG_TRAIN_INPUT));
    let mut train = Signals {
        p: u.clone(),
        u,
        y: DMatrix::zeros(n, 1),
    };
    let y0 = truth.simulate(&train, None);
    let v = match snr_db {
        Some(snr) => {
            let var_v = sample_var(y0.iter()) * 10f64.powf(-snr / 10.0);
            noise_with_variance(&mut stream(seed, TAG_TRAIN_NOISE), n, 1, var_v)
        }
        None => DMatrix::zeros(n, 1),
    };
    train.y = &y0 + &v;
    let vu = b4_input(n, &mut stream(seed, TAG_VAL_INPUT));
    let mut val = Signals {
        p: vu.clone(),
        u: vu,
        y: DMatrix::zeros(n, 1),
    };
    val.y = truth.simulate(&val, None);
    (
        Experiment {
            train,
            val,
            truth: Some(truth),
            name: "B4",
        },
        v,
    )
}

/// B4, the bilinear example (kernel paper section 7.3; BENCHMARKS.md B4), N = 500 standard.
///
/// `x_{k+1} = A^(1) x_k + u_k A^(2) x_k + B u_k`, `y_k = [1 1] x_k (+ v_k)`; the scheduling
/// column p1 equals the input u1 (mu = [1, u]). `u` = N(0,1) white noise through
/// `butterworth_lowpass(4, 0.8)` (zero initial state). `None`: noise-free; `Some(snr)`:
/// white Gaussian output noise v with `SNR = 10 log10(var(y)/var(v))` (power ratio; y the
/// noise-free output), scaled to that sample variance exactly. Since K = 0, this is the
/// innovation form with e = v: `truth` is exact. Validation: noise-free, fresh input, length
/// `n`.
pub fn b4(n: usize, snr_db: Option<f64>, seed: u64) -> Experiment {
    b4_parts(n, snr_db, seed).0
}

// ---------------------------------------------------------------------------------------------
// B5: blade flapping in closed loop
// ---------------------------------------------------------------------------------------------

/// Period of the B5 scheduling `mu2_k = cos(2 pi k/10) + 0.2`.
pub const B5_PERIOD: usize = 10;

fn b5_a() -> [DMatrix<f64>; 2] {
    [
        rm(2, 2, &[0.0, 0.0734, -6.5229, -0.4997]),
        rm(2, 2, &[-0.0021, 0.0, -0.0138, 0.5196]),
    ]
}

fn b5_b() -> DMatrix<f64> {
    rm(2, 1, &[-0.7221, -9.6277])
}

/// The B5 system (kernel paper section 7.2) in innovation form. With `C = I2` and only
/// process noise, `x_{k+1} = A(mu_k) x_k + B u_k + w_k`, `y_k = x_k` equals the innovation
/// form with `K^(i) = A^(i)`, `e_k = w_{k-1}` (`e_0 = 0`) and state `x_k - w_{k-1}`; so
/// `truth.k` holds copies of `truth.a`. D = 0.
pub fn b5_truth() -> LpvSs {
    let a = b5_a().to_vec();
    LpvSs {
        k: a.clone(),
        a,
        b: vec![b5_b(), DMatrix::zeros(2, 1)],
        c: vec![DMatrix::identity(2, 2)],
        d: vec![DMatrix::zeros(2, 1)],
    }
}

/// True eigenvalues of the B5 local matrices A^(1) and A^(2) (the crosses of the kernel
/// paper's Fig. 2): A^(1): -0.24985 +- 0.64526i; A^(2): -0.0021 and 0.5196.
pub fn b5_true_eigenvalues() -> Vec<Vec<Complex<f64>>> {
    local_eigenvalues(&b5_truth())
}

/// The periodic state-feedback gains F_0..F_9 of B5 (u_k = -F_{k mod 10} x_k + r_k), from the
/// discrete periodic Riccati equation with Q = I2, R = 1 for `A_k = A^(1) + mu2_k A^(2)`,
/// `B = B^(1)`: the backward recursion
/// `P_j = Q + A_j' P_{j+1} A_j - A_j' P_{j+1} B (R + B' P_{j+1} B)^-1 B' P_{j+1} A_j`
/// is iterated over whole periods from `P = Q` until P at phase 0 changes by less than 1e-13
/// (relative), then `F_j = (R + B' P_{j+1} B)^-1 B' P_{j+1} A_j` with `P_10 = P_0`.
pub fn b5_controller() -> Vec<DMatrix<f64>> {
    let [a1, a2] = b5_a();
    let b = b5_b();
    let sched = periodic_sched(B5_PERIOD);
    let a: Vec<DMatrix<f64>> = (0..B5_PERIOD).map(|j| &a1 + &a2 * sched[(j, 0)]).collect();
    let q = DMatrix::<f64>::identity(2, 2);
    let r = 1.0;
    // P at phase j+1 -> P at phase j, and the gain F_j
    let step = |pn: &DMatrix<f64>, aj: &DMatrix<f64>| -> (DMatrix<f64>, DMatrix<f64>) {
        let s = r + (b.transpose() * pn * &b)[(0, 0)];
        let f = (b.transpose() * pn * aj) / s;
        let p = &q + aj.transpose() * pn * aj - aj.transpose() * pn * &b * &f;
        let p = (&p + p.transpose()) * 0.5;
        (p, f)
    };
    let mut p0 = q.clone();
    for _ in 0..100_000 {
        let mut p = p0.clone();
        for j in (0..B5_PERIOD).rev() {
            p = step(&p, &a[j]).0;
        }
        let change = (&p - &p0).amax() / p.amax().max(1.0);
        p0 = p;
        if change < 1e-13 {
            break;
        }
    }
    // one more backward sweep from the periodic P_10 = P_0 gives all P_{j+1} and F_j
    let mut f = vec![DMatrix::zeros(1, 2); B5_PERIOD];
    let mut p = p0;
    for j in (0..B5_PERIOD).rev() {
        let (pj, fj) = step(&p, &a[j]);
        f[j] = fj;
        p = pj;
    }
    f
}

/// Closed-loop run: returns (u, y) for reference r and process noise w (N x 2, optional).
fn b5_closed_loop(
    truth: &LpvSs,
    gains: &[DMatrix<f64>],
    r: &[f64],
    w: Option<&DMatrix<f64>>,
) -> (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>) {
    let n = r.len();
    let p = periodic_sched(n);
    let mut u = DMatrix::zeros(n, 1);
    let mut y = DMatrix::zeros(n, 2);
    let mut x = DVector::<f64>::zeros(2);
    for k in 0..n {
        let uk = -(&gains[k % B5_PERIOD] * &x)[(0, 0)] + r[k];
        u[(k, 0)] = uk;
        y.set_row(k, &x.transpose());
        let mu = DVector::from_vec(vec![1.0, p[(k, 0)]]);
        let mut xn = truth.a_at(&mu) * &x + scheduled(&truth.b, &mu) * uk;
        if let Some(w) = w {
            xn += w.row(k).transpose();
        }
        x = xn;
    }
    (u, y, p)
}

fn b5_parts(n: usize, seed: u64) -> (Experiment, DMatrix<f64>) {
    let truth = b5_truth();
    let gains = b5_controller();
    let r = gaussian(&mut stream(seed, TAG_TRAIN_INPUT), n);
    let w = gaussian_matrix(&mut stream(seed, TAG_TRAIN_NOISE), n, 2, 0.1f64.sqrt());
    let (u, y, p) = b5_closed_loop(&truth, &gains, &r, Some(&w));
    let rv = gaussian(&mut stream(seed, TAG_VAL_INPUT), n);
    let (vu, vy, vp) = b5_closed_loop(&truth, &gains, &rv, None);
    (
        Experiment {
            train: Signals { u, y, p },
            val: Signals {
                u: vu,
                y: vy,
                p: vp,
            },
            truth: Some(truth),
            name: "B5",
        },
        w,
    )
}

/// B5, blade flapping in closed loop with periodic scheduling (kernel paper section 7.2;
/// BENCHMARKS.md B5), N = 2000 standard.
///
/// `x_{k+1} = (A^(1) + mu2_k A^(2)) x_k + B^(1) u_k + w_k`, `y_k = x_k` (C = I2, no
/// measurement noise), `mu2_k = cos(2 pi k/10) + 0.2`, process noise `w_k ~ N(0, 0.1 I2)`,
/// state feedback `u_k = -F_{k mod 10} x_k + r_k` with the periodic Riccati gains of
/// [`b5_controller`] and reference/excitation `r_k ~ N(0,1)` white. The recorded `u` is the
/// plant input (after the controller). Validation: the same closed loop with a fresh `r`, no
/// noise, length `n`. `truth` is the exact innovation form of [`b5_truth`] (K^(i) = A^(i));
/// the true local eigenvalues are [`b5_true_eigenvalues`].
pub fn b5(n: usize, seed: u64) -> Experiment {
    b5_parts(n, seed).0
}

// ---------------------------------------------------------------------------------------------
// B6: BC-IV example (noisy scheduling)
// ---------------------------------------------------------------------------------------------

/// The noise-free B6 signals: (u, p_o, y_o) of length n from one input and one scheduling
/// stream. `y_o(k) = -0.8 p_o(k)^2 y_o(k-1) + 0.4 p_o(k)^2 u(k)`, `y_o(-1) = 0`.
fn b6_clean(
    n: usize,
    in_rng: &mut StdRng,
    sched_rng: &mut StdRng,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let u: Vec<f64> = (0..n).map(|_| in_rng.gen_range(0.0..1.0)).collect();
    let po: Vec<f64> = (0..n)
        .map(|k| {
            let d: f64 = StandardNormal.sample(sched_rng);
            (0.1 * k as f64).sin() + 0.2 * d
        })
        .collect();
    let mut yo = vec![0.0; n];
    let mut prev = 0.0;
    for k in 0..n {
        let p2 = po[k] * po[k];
        yo[k] = -0.8 * p2 * prev + 0.4 * p2 * u[k];
        prev = yo[k];
    }
    (u, po, yo)
}

fn b6_noisy(
    n: usize,
    sigma_eta: f64,
    sigma_nu: f64,
    seed: u64,
    tags: [u64; 4],
) -> (Signals, Vec<f64>, Vec<f64>) {
    let (u, po, yo) = b6_clean(n, &mut stream(seed, tags[0]), &mut stream(seed, tags[1]));
    let eta = gaussian(&mut stream(seed, tags[2]), n);
    let nu = gaussian(&mut stream(seed, tags[3]), n);
    let p: Vec<f64> = po
        .iter()
        .zip(&eta)
        .map(|(a, e)| a + sigma_eta * e)
        .collect();
    let y: Vec<f64> = yo.iter().zip(&nu).map(|(a, e)| a + sigma_nu * e).collect();
    (
        Signals {
            u: col(&u),
            y: col(&y),
            p: col(&p),
        },
        po,
        yo,
    )
}

/// B6 with explicit lengths and noise levels; see [`b6`]. Training and calibration sets are
/// noisy in both p (std `sigma_eta`) and y (std `sigma_nu`); the validation set is noise-free
/// in both (`p = p_o`, `y = y_o`). Each set starts at k = 0 with `y_o(-1) = 0` and has its own
/// input, delta and noise realisations.
pub fn b6_with(
    n_train: usize,
    n_cal: usize,
    n_val: usize,
    sigma_eta: f64,
    sigma_nu: f64,
    seed: u64,
) -> (Signals, Signals, Signals) {
    let train = b6_noisy(
        n_train,
        sigma_eta,
        sigma_nu,
        seed,
        [
            TAG_TRAIN_INPUT,
            TAG_TRAIN_SCHED,
            TAG_TRAIN_NOISE,
            TAG_TRAIN_NOISE2,
        ],
    )
    .0;
    let cal = b6_noisy(
        n_cal,
        sigma_eta,
        sigma_nu,
        seed,
        [TAG_CAL_INPUT, TAG_CAL_SCHED, TAG_CAL_NOISE, TAG_CAL_NOISE2],
    )
    .0;
    let (u, po, yo) = b6_clean(
        n_val,
        &mut stream(seed, TAG_VAL_INPUT),
        &mut stream(seed, TAG_VAL_SCHED),
    );
    let val = Signals {
        u: col(&u),
        y: col(&yo),
        p: col(&po),
    };
    (train, cal, val)
}

/// B6, the BC-IV-LASSO example (lpv-bias-corrected-iv-lasso.md section 6.1; BENCHMARKS.md
/// B6): returns (training 8000, calibration 1000, validation 1000), columns u1, y1, p1.
///
/// `y_o(k) = -0.8 p_o(k)^2 y_o(k-1) + 0.4 p_o(k)^2 u(k)` (the paper's
/// `y_o = a_{1,2} p_o^2 y_o(k-1) + b_{0,2} p_o^2 u(k)` with a_{1,2} = -0.8, b_{0,2} = 0.4, i.e.
/// a_{1,2} = +0.8 in the lpv-arx JSON convention `y = -sum a_i y(k-i) + ...`),
/// `y = y_o + nu`, `p = p_o + eta`, `u ~ U[0,1)`, `p_o(k) = sin(0.1 k) + 0.2 delta(k)`,
/// `delta ~ N(0,1)`, `sigma_eta = 0.25`, `sigma_nu = 0.06`. The validation set is noise-free
/// in p and y (the paper compares with "the true output"; BENCHMARKS.md says noise-free).
pub fn b6(seed: u64) -> (Signals, Signals, Signals) {
    b6_with(8000, 1000, 1000, 0.25, 0.06, seed)
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64], tol: f64) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < tol, "{a:?} vs {b:?}");
        }
    }

    fn finite_bounded(m: &DMatrix<f64>, bound: f64) {
        assert!(
            m.iter().all(|v| v.is_finite() && v.abs() < bound),
            "max {}",
            m.amax()
        );
    }

    #[test]
    fn systems_butterworth_matches_scipy() {
        let (b, a) = butterworth_lowpass(2, 0.2);
        close(&b, &[0.06745527, 0.13491055, 0.06745527], 1e-8);
        close(&a, &[1.0, -1.1429805, 0.4128016], 1e-7);
        // butter(4, 0.8). The brief quoted b = [0.43826514, 1.75306056, 2.62959085, ...], which
        // is not a unit-DC-gain low-pass with this a (16 x 0.43826514 = 7.012 != sum(a) = 6.930);
        // the bilinear transform (checked independently by substituting s = 4 (z-1)/(z+1) in
        // the analog prototype) gives b = 0.43284664 [1 4 6 4 1].
        let (b, a) = butterworth_lowpass(4, 0.8);
        close(
            &b,
            &[0.43284664, 1.73138658, 2.59707987, 1.73138658, 0.43284664],
            1e-7,
        );
        close(&a, &[1.0, 2.3695130, 2.3139884, 1.0546654, 0.1873795], 1e-6);
        // unit DC gain for any order
        for order in 1..8 {
            let (b, a) = butterworth_lowpass(order, 0.37);
            let g = b.iter().sum::<f64>() / a.iter().sum::<f64>();
            assert!((g - 1.0).abs() < 1e-10, "order {order}: {g}");
        }
    }

    #[test]
    fn systems_lfilter_impulse_and_recursion() {
        let x = [1.0, 0.0, 0.0, 0.0];
        // FIR
        close(
            &lfilter(&[0.75, 1.05, 0.15], &[1.0], &x),
            &[0.75, 1.05, 0.15, 0.0],
            1e-15,
        );
        // y[n] = x[n] + 0.5 y[n-1], with a0 = 2 normalisation
        close(
            &lfilter(&[2.0], &[2.0, -1.0], &x),
            &[1.0, 0.5, 0.25, 0.125],
            1e-15,
        );
    }

    #[test]
    fn systems_deterministic_for_a_seed() {
        let a = b1(300, 0.05, 5);
        let b = b1(300, 0.05, 5);
        assert_eq!(a.train, b.train);
        assert_eq!(a.val, b.val);
        let c = b1(300, 0.05, 6);
        assert_ne!(a.train, c.train);
        // the noise level does not change the input realisation
        let d = b1(300, 0.0, 5);
        assert_eq!(a.train.u, d.train.u);
        assert_eq!(a.train.p, d.train.p);
        assert_ne!(a.train.y, d.train.y);
        assert_eq!(b2(75, 25.0, 3).train, b2(75, 25.0, 3).train);
        assert_eq!(b3(250, 3).train, b3(250, 3).train);
        assert_eq!(b4(500, Some(15.0), 3).train, b4(500, Some(15.0), 3).train);
        assert_eq!(b5(300, 3).train, b5(300, 3).train);
        let (t1, c1, v1) = b6_with(500, 100, 100, 0.25, 0.06, 3);
        let (t2, c2, v2) = b6_with(500, 100, 100, 0.25, 0.06, 3);
        assert_eq!((t1, c1, v1), (t2, c2, v2));
    }

    #[test]
    fn systems_shapes() {
        let e = b1(200, 0.05, 1);
        assert_eq!(
            (e.train.u.shape(), e.train.y.shape(), e.train.p.shape()),
            ((200, 2), (200, 3), (200, 3))
        );
        assert_eq!(e.val.len(), 200);
        let e = b2(75, 25.0, 1);
        assert_eq!((e.train.len(), e.val.len()), (75, 500));
        assert_eq!(e.train.p.ncols(), 1);
        let e = b3(250, 1);
        assert_eq!(
            (e.train.u.ncols(), e.train.y.ncols(), e.val.len()),
            (2, 2, 500)
        );
        let e = b4(500, None, 1);
        assert_eq!(e.train.u, e.train.p);
        assert_eq!(e.val.u, e.val.p);
        let e = b5(400, 1);
        assert_eq!(
            (e.train.u.ncols(), e.train.y.ncols(), e.train.p.ncols()),
            (1, 2, 1)
        );
        for e in [
            b1(100, 0.05, 2),
            b2(75, 25.0, 2),
            b3(100, 2),
            b4(100, Some(15.0), 2),
            b5(100, 2),
        ] {
            e.truth.as_ref().unwrap().validate().unwrap();
        }
        let (t, c, v) = b6(1);
        assert_eq!((t.len(), c.len(), v.len()), (8000, 1000, 1000));
    }

    #[test]
    fn systems_b1_noise_level_and_truth_consistency() {
        let sigma = 0.05;
        let (ex, e) = b1_parts(2000, sigma, 11);
        for j in 0..3 {
            let s = sample_var(e.column(j).iter()).sqrt();
            assert!((s - sigma).abs() < 0.1 * sigma, "std of e{j}: {s}");
        }
        let truth = ex.truth.unwrap();
        // the innovation form with the recorded e reproduces the data (the true predictor
        // A(mu) - K C is not stable for every rho, so predict() is not used here)
        assert!((truth.simulate(&ex.train, Some(&e)) - &ex.train.y).amax() < 1e-12);
        // the validation set is the noise-free response
        assert_eq!(truth.simulate(&ex.val, None), ex.val.y);
    }

    #[test]
    fn systems_b1_spectral_radius_reaches_1_28_yet_bounded() {
        let truth = b1_truth();
        let mut max_rho = 0.0f64;
        for i in 0..=100 {
            let rho = i as f64 / 100.0;
            for k in 0..100 {
                let th = 2.0 * PI * k as f64 / 100.0;
                let mu =
                    DVector::from_vec(vec![1.0, rho, 0.5 * th.sin() * rho, 0.5 * th.cos() * rho]);
                max_rho = max_rho.max(spectral_radius(&truth.a_at(&mu)));
            }
        }
        assert!(
            (max_rho - 1.28).abs() < 0.02,
            "max spectral radius {max_rho}"
        );
        let ex = b1(5000, 0.05, 1);
        finite_bounded(&ex.train.y, 1e3);
        finite_bounded(&ex.val.y, 1e3);
    }

    #[test]
    fn systems_b2_snr_achieved() {
        for snr in [15.0, 25.0, 50.0] {
            let (ex, w, v) = b2_parts(75, snr, 4);
            let truth = ex.truth.as_ref().unwrap();
            let y0 = simulate_wv(truth, &ex.train, None, None);
            let vy = sample_var(y0.iter());
            for s in [w.column(0), w.column(1), v.column(0)] {
                let got = 20.0 * (vy / sample_var(s.iter())).log10();
                assert!((got - snr).abs() < 1e-9, "snr {got} vs {snr}");
            }
            // the noise-free simulation with the recorded noise reproduces the data
            let y = simulate_wv(truth, &ex.train, Some(&w), Some(&v));
            assert!((&y - &ex.train.y).amax() < 1e-12);
            finite_bounded(&ex.train.y, 1e3);
        }
        let clean = b2(75, f64::INFINITY, 4);
        let truth = clean.truth.as_ref().unwrap();
        assert!((simulate_wv(truth, &clean.train, None, None) - &clean.train.y).amax() < 1e-12);
    }

    #[test]
    fn systems_b3_innovation_and_bounded() {
        let (ex, e) = b3_parts(250, 9);
        for j in 0..2 {
            let s = sample_var(e.column(j).iter()).sqrt();
            assert!((s - 0.5).abs() < 0.1, "std e{j} {s}");
        }
        let truth = ex.truth.as_ref().unwrap();
        assert!((truth.simulate(&ex.train, Some(&e)) - &ex.train.y).amax() < 1e-12);
        let long = b3(5000, 9);
        finite_bounded(&long.train.y, 1e4);
        finite_bounded(&long.val.y, 1e4);
        assert!((long.train.p[(3, 0)] - (0.5 + 3f64.sin())).abs() < 1e-15);
    }

    #[test]
    fn systems_b4_noise_and_bilinear_structure() {
        let (ex, v) = b4_parts(500, Some(15.0), 2);
        let truth = ex.truth.as_ref().unwrap();
        let y0 = truth.simulate(&ex.train, None);
        let got = 10.0 * (sample_var(y0.iter()) / sample_var(v.iter())).log10();
        assert!((got - 15.0).abs() < 1e-9);
        assert!((&y0 + &v - &ex.train.y).amax() < 1e-12);
        let clean = b4(500, None, 2);
        assert_eq!(clean.train.u, ex.train.u);
        assert!((&clean.train.y - &y0).amax() < 1e-12);
        finite_bounded(&clean.train.y, 1e3);
        // bilinear by hand for a few steps
        let u = &clean.train.u;
        let mut x = [0.0f64; 2];
        for k in 0..20 {
            assert!((clean.train.y[(k, 0)] - (x[0] + x[1])).abs() < 1e-12);
            let s = 0.5 + 0.2 * u[(k, 0)];
            x = [s * (x[0] + x[1]) + u[(k, 0)], s * (-x[0] + x[1])];
        }
    }

    #[test]
    fn systems_b5_closed_loop() {
        let gains = b5_controller();
        assert_eq!(gains.len(), B5_PERIOD);
        let [a1, a2] = b5_a();
        let b = b5_b();
        let sched = periodic_sched(B5_PERIOD);
        // closed-loop monodromy matrix is stable, and better damped than open loop
        let mut mono = DMatrix::<f64>::identity(2, 2);
        let mut open = DMatrix::<f64>::identity(2, 2);
        for j in 0..B5_PERIOD {
            let aj = &a1 + &a2 * sched[(j, 0)];
            mono = (&aj - &b * &gains[j]) * mono;
            open = &aj * open;
        }
        let rc = spectral_radius(&mono);
        assert!(rc < 1.0 && rc < spectral_radius(&open), "closed {rc}");
        // true local eigenvalues
        let ev = b5_true_eigenvalues();
        let mut e1: Vec<_> = ev[0].clone();
        e1.sort_by(|x, y| x.im.partial_cmp(&y.im).unwrap());
        assert!(
            (e1[0].re + 0.24985).abs() < 1e-9
                && (e1[1].im - (0.4788 - 0.24985f64.powi(2)).sqrt()).abs() < 1e-3
        );
        let mut e2: Vec<f64> = ev[1].iter().map(|c| c.re).collect();
        e2.sort_by(|x, y| x.partial_cmp(y).unwrap());
        close(&e2, &[-0.0021, 0.5196], 1e-12);
        // data: innovation form with K = A, e_k = w_{k-1}
        let (ex, w) = b5_parts(2000, 8);
        let truth = ex.truth.as_ref().unwrap();
        let mut e = DMatrix::zeros(2000, 2);
        for k in 1..2000 {
            e.set_row(k, &w.row(k - 1));
        }
        assert!((truth.simulate(&ex.train, Some(&e)) - &ex.train.y).amax() < 1e-9);
        assert!((truth.simulate(&ex.val, None) - &ex.val.y).amax() < 1e-9);
        finite_bounded(&ex.train.y, 1e3);
        let s = sample_var(w.column(0).iter());
        assert!((s - 0.1).abs() < 0.015, "var w {s}");
    }

    #[test]
    fn systems_b6_recursion() {
        let (train, cal, val) = b6(21);
        // validation is noise-free: the recursion holds exactly
        for k in 1..50 {
            let p2 = val.p[(k, 0)].powi(2);
            let want = -0.8 * p2 * val.y[(k - 1, 0)] + 0.4 * p2 * val.u[(k, 0)];
            assert!((val.y[(k, 0)] - want).abs() < 1e-15);
        }
        let p2 = val.p[(0, 0)].powi(2);
        assert!((val.y[(0, 0)] - 0.4 * p2 * val.u[(0, 0)]).abs() < 1e-15);
        // without noise the training set obeys it too, and sin(0.1 k) is the mean of p
        let (clean, _, _) = b6_with(300, 10, 10, 0.0, 0.0, 21);
        for k in 1..300 {
            let p2 = clean.p[(k, 0)].powi(2);
            let want = -0.8 * p2 * clean.y[(k - 1, 0)] + 0.4 * p2 * clean.u[(k, 0)];
            assert!((clean.y[(k, 0)] - want).abs() < 1e-15);
        }
        // the noisy training set: same clean part, noise of the stated size
        let (noisy, _, _) = b6_with(8000, 10, 10, 0.25, 0.06, 21);
        let (clean, _, _) = b6_with(8000, 10, 10, 0.0, 0.0, 21);
        assert_eq!(noisy.u, clean.u);
        let eta = &noisy.p - &clean.p;
        let nu = &noisy.y - &clean.y;
        assert!((sample_var(eta.iter()).sqrt() - 0.25).abs() < 0.01);
        assert!((sample_var(nu.iter()).sqrt() - 0.06).abs() < 0.003);
        assert!(noisy.u.iter().all(|&x| (0.0..1.0).contains(&x)));
        for s in [&train, &cal, &val] {
            finite_bounded(&s.y, 1e3);
        }
        assert_eq!(noisy, train);
        assert_ne!(cal.u.rows(0, 10), train.u.rows(0, 10));
    }
}
