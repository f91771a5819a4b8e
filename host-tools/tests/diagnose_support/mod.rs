//! Plants with one planted effect each (DESIGN.md section 6 catalogue) for the diagnose
//! acceptance tests, the model identified without it through `lpvid pbsid`, and the
//! diagnosis with `--fix`. Nothing here is visible to the tool: it sees two CSV files and a
//! model file.
#![allow(dead_code)]

pub mod family;

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use lpvid_host::data::Dataset;
use lpvid_host::diagnose::{diagnose, Options, Outcome};
use lpvid_host::model::ModelFile;
use lpvid_host::simulate::{simulate, Mode};
use nalgebra::{DMatrix, DVector};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

/// Samples in the training and in the validation record.
pub const N: usize = 2000;

/// A plant: x+ = A(p) x + B(p) v + Bw(p) w, y = C(p) x + D(p) v + disturbances, with
/// A(p) = A0 + p A1 + p^2 A2 (B, C, D alike, missing terms zero), v = the (possibly
/// nonlinear, delayed) input, w a logged signal.
#[derive(Clone)]
pub struct Plant {
    pub a: Vec<DMatrix<f64>>,
    pub b: Vec<DMatrix<f64>>,
    pub c: Vec<DMatrix<f64>>,
    pub d: Vec<DMatrix<f64>>,
    /// Static input nonlinearity v = f(u).
    pub input_nl: Option<fn(f64) -> f64>,
    /// Dead time on the input (samples).
    pub delay: usize,
    /// Output offset (times std y).
    pub offset: f64,
    /// Sinusoid (amplitude x std y, rad/sample, phase) locked to absolute time.
    pub sine: Option<(f64, f64, f64)>,
    /// AR(1) output noise (pole, std x std y).
    pub coloured: Option<(f64, f64)>,
    /// White noise e std (x std y of the noise-free output): y += e, and x+ += K e when
    /// the plant has an innovation gain K (innovation form), else output error.
    pub white: f64,
    /// Innovation gain K.
    pub k: Option<DMatrix<f64>>,
    /// Noise std on the measured scheduling signal (training record only).
    pub sched_noise: f64,
    /// Logged signal w entering through this B column.
    pub bw: Option<DMatrix<f64>>,
    /// Scheduling signal kind: smooth (0) or B6-like sin(0.1 k) + 0.2 delta (1).
    pub sched_kind: u8,
}

fn m(r: usize, c: usize, v: &[f64]) -> DMatrix<f64> {
    DMatrix::from_row_slice(r, c, v)
}

/// The base plant: second order, one input, one output, affine in p1.
pub fn base() -> Plant {
    Plant {
        a: vec![
            m(2, 2, &[0.5, 0.5, -0.5, 0.5]),
            m(2, 2, &[0.2, 0.0, 0.0, 0.2]),
        ],
        b: vec![m(2, 1, &[1.0, 0.0]), m(2, 1, &[0.5, 0.5])],
        c: vec![m(1, 2, &[1.0, 0.0])],
        d: vec![m(1, 1, &[0.0])],
        input_nl: None,
        delay: 0,
        offset: 0.0,
        sine: None,
        coloured: None,
        white: 0.05,
        // A0 - K C has a double eigenvalue at 0.2: a fast predictor, so that past = 3 is an
        // adequate window for the clean plant
        k: Some(m(2, 1, &[0.6, -0.32])),
        sched_noise: 0.0,
        bw: None,
        sched_kind: 0,
    }
}

fn poly(mats: &[DMatrix<f64>], p: f64) -> DMatrix<f64> {
    let mut out = mats[0].clone();
    let mut pk = 1.0;
    for mm in &mats[1..] {
        pk *= p;
        out += mm * pk;
    }
    out
}

fn gauss(rng: &mut StdRng, n: usize) -> Vec<f64> {
    (0..n).map(|_| StandardNormal.sample(rng)).collect()
}

fn std_of(v: &[f64]) -> f64 {
    let n = v.len() as f64;
    let mu = v.iter().sum::<f64>() / n;
    (v.iter().map(|x| (x - mu) * (x - mu)).sum::<f64>() / n).sqrt()
}

/// Simulate 2N samples of `plant` and split into training and validation records (columns
/// t, u1, y1, p1 and w when the plant has a logged signal).
pub fn generate(plant: &Plant, seed: u64) -> (Dataset, Dataset) {
    let total = 2 * N;
    let mut rng = StdRng::seed_from_u64(seed.wrapping_mul(7919).wrapping_add(17));
    let u = gauss(&mut rng, total);
    // scheduling
    let p: Vec<f64> = if plant.sched_kind == 1 {
        let d = gauss(&mut rng, total);
        (0..total)
            .map(|k| (0.8 * (0.1 * k as f64).sin() + 0.15 * d[k]).clamp(-1.0, 1.0))
            .collect()
    } else {
        let ph: f64 = rng.gen::<f64>() * 2.0 * PI;
        let ph2: f64 = rng.gen::<f64>() * 2.0 * PI;
        let z = gauss(&mut rng, total);
        let mut lp = 0.0;
        let mut f = vec![0.0; total];
        for k in 0..total {
            lp = 0.98 * lp + 0.02 * z[k];
            f[k] = lp;
        }
        let sf = std_of(&f).max(1e-12);
        (0..total)
            .map(|k| {
                let v = 0.55 * (2.0 * PI * k as f64 / 250.0 + ph).sin()
                    + 0.25 * (2.0 * PI * k as f64 / 61.0 + ph2).sin()
                    + 0.2 * f[k] / sf;
                v.clamp(-1.0, 1.0)
            })
            .collect()
    };
    let w: Vec<f64> = {
        let z = gauss(&mut rng, total);
        let mut lp = 0.0;
        z.iter()
            .map(|v| {
                lp = 0.8 * lp + v;
                lp
            })
            .collect()
    };
    let n = plant.a[0].nrows();
    let white = gauss(&mut rng, total);
    let run = |e_scale: f64| {
        let mut x = DVector::zeros(n);
        let mut y = vec![0.0; total];
        for k in 0..total {
            let uk = if k >= plant.delay {
                u[k - plant.delay]
            } else {
                0.0
            };
            let v = plant.input_nl.map_or(uk, |f| f(uk));
            let pk = p[k];
            let vv = DVector::from_element(1, v);
            let e = e_scale * white[k];
            y[k] = (poly(&plant.c, pk) * &x + poly(&plant.d, pk) * &vv)[0] + e;
            let mut xn = poly(&plant.a, pk) * &x + poly(&plant.b, pk) * &vv;
            if let Some(bw) = &plant.bw {
                xn += bw * w[k];
            }
            if let Some(kk) = &plant.k {
                xn += kk * e;
            }
            x = xn;
        }
        y
    };
    let sy = std_of(&run(0.0));
    let mut y = run(plant.white * sy);
    let cz = gauss(&mut rng, total);
    let mut cn = 0.0;
    let eta = gauss(&mut rng, total);
    for k in 0..total {
        y[k] += plant.offset * sy;
        if let Some((amp, om, ph)) = plant.sine {
            y[k] += amp * sy * (om * k as f64 + ph).sin();
        }
        if let Some((pole, s)) = plant.coloured {
            cn = pole * cn + cz[k];
            y[k] += s * sy * (1.0 - pole * pole).sqrt() * cn;
        }
    }
    let split = |lo: usize, hi: usize, noisy_p: bool| {
        let mut names = vec!["t".to_string(), "u1".into(), "y1".into(), "p1".into()];
        let mut cols = vec![
            (lo..hi).map(|k| k as f64 * 0.01).collect::<Vec<_>>(),
            u[lo..hi].to_vec(),
            y[lo..hi].to_vec(),
            (lo..hi)
                .map(|k| {
                    p[k] + if noisy_p {
                        plant.sched_noise * eta[k]
                    } else {
                        0.0
                    }
                })
                .collect(),
        ];
        if plant.bw.is_some() {
            names.push("w".into());
            cols.push(w[lo..hi].to_vec());
        }
        Dataset {
            source: if lo == 0 {
                "train.csv".into()
            } else {
                "val.csv".into()
            },
            names,
            cols,
        }
    };
    (split(0, N, true), split(N, total, false))
}

/// The plant with effect `name` planted, and the `lpvid pbsid` options the model is
/// identified with (what a user who does not know the effect would choose).
pub fn planted(name: &str) -> (Plant, Vec<&'static str>) {
    let mut p = base();
    let mut args: Vec<&'static str> = vec!["--past", "3"];
    match name {
        // the model a careful user makes: a past window long enough for the predictor
        "clean" => args = vec!["--past", "5"],
        "output-offset" => p.offset = 1.0,
        "feedthrough" => {
            p.d = vec![m(1, 1, &[1.2])];
            args.push("--no-feedthrough");
        }
        "scheduled-output" => {
            // C(p) = [1 + 0.8 p, 0]; a fast-varying scheduling signal (with a slowly varying
            // one, C(p) x is nearly a state transformation of a model with p^2 in B)
            p.c = vec![m(1, 2, &[1.0, 0.0]), m(1, 2, &[0.8, 0.0])];
            p.white = 0.02;
            p.sched_kind = 1;
        }
        "scheduling-nonlinearity" => {
            p.a.push(m(2, 2, &[-0.25, 0.0, 0.0, -0.25]));
            p.b.push(m(2, 1, &[1.5, 0.0]));
        }
        "input-nonlinearity" => p.input_nl = Some(|u: f64| u + 0.7 * u.abs() * u),
        "input-delay" => p.delay = 5,
        "scheduling-noise" => {
            // first order, strong scheduling dependence, B6-like scheduling; the sensor
            // noise is on the training record only (the validation record is clean)
            p.a = vec![m(1, 1, &[0.3]), m(1, 1, &[0.5])];
            p.b = vec![m(1, 1, &[0.5]), m(1, 1, &[1.0])];
            p.c = vec![m(1, 1, &[1.0])];
            p.d = vec![m(1, 1, &[0.0])];
            p.k = None;
            p.sched_noise = 0.3;
            p.white = 0.02;
            args = vec!["--past", "4"];
        }
        "periodic-disturbance" => p.sine = Some((0.6, 0.37, 0.3)),
        "order-too-low" => {
            p.a = vec![
                m(
                    4,
                    4,
                    &[
                        0.7, 0.5, 0.0, 0.0, //
                        -0.5, 0.7, 0.0, 0.0, //
                        0.0, 0.0, 0.2, 0.8, //
                        0.0, 0.0, -0.8, 0.2,
                    ],
                ),
                DMatrix::identity(4, 4) * 0.1,
            ];
            p.b = vec![
                m(4, 1, &[1.0, 0.0, 1.0, 0.0]),
                m(4, 1, &[0.3, 0.0, 0.0, 0.0]),
            ];
            p.c = vec![m(1, 4, &[1.0, 0.0, 1.0, 0.0])];
            p.k = None;
            args = vec!["--past", "4", "--order", "2"];
        }
        "coloured-noise" => {
            p.white = 0.02;
            p.k = None;
            p.coloured = Some((0.99, 0.3));
            args = vec!["--past", "3", "--order", "2"];
        }
        "unused-signal" => {
            p.bw = Some(m(2, 1, &[0.8, 0.0]));
        }
        other => panic!("no plant for {other}"),
    }
    (p, args)
}

/// A diagnosis of a planted case.
pub struct Case {
    pub outcome: Outcome,
    pub before: ModelFile,
    pub val: Dataset,
    pub dir: tempfile::TempDir,
}

/// Identify with `lpvid pbsid` (the CLI, which calls pbsid::fit) and diagnose with --fix.
pub fn run_case(name: &str, seed: u64) -> Case {
    let (plant, args) = planted(name);
    let (train, val) = generate(&plant, seed);
    let dir = tempfile::tempdir().unwrap();
    let tp = dir.path().join("train.csv");
    let vp = dir.path().join("val.csv");
    train.write_csv(&tp).unwrap();
    val.write_csv(&vp).unwrap();
    let mp = dir.path().join("model.json");
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(args.iter().map(|s| s.to_string()));
    cli.push("--out".into());
    cli.push(mp.display().to_string());
    let mut sink = Vec::new();
    lpvid_host::cli::run(cli, &mut sink).unwrap();
    let model = ModelFile::read(&mp).unwrap();
    let train = Dataset::read_csv(&tp).unwrap();
    let val = Dataset::read_csv(&vp).unwrap();
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 0,
    };
    let outcome = diagnose(&model, &train, &val, &opts).unwrap();
    Case {
        outcome,
        before: model,
        val,
        dir,
    }
}

/// The columns `t, u1, y1, p1, w` cut into a training record (rows before `cut`, source
/// `train.csv`) and a validation record (the rest, `val.csv`).
pub fn train_val(cols: [&[f64]; 5], cut: usize) -> (Dataset, Dataset) {
    let names: Vec<String> = ["t", "u1", "y1", "p1", "w"].map(String::from).to_vec();
    let part = |r: std::ops::Range<usize>, source: &str| Dataset {
        source: source.into(),
        names: names.clone(),
        cols: cols.iter().map(|c| c[r.clone()].to_vec()).collect(),
    };
    let n = cols[0].len();
    (part(0..cut, "train.csv"), part(cut..n, "val.csv"))
}

/// `lpvid pbsid --past PAST --order ORDER` on `train` (the command line, on a temporary
/// file), then `diagnose --fix` (one step, two threads) with `val` held out: the user's steps
/// on the plants of the generators of other shapes (`diagnose_logged`, `diagnose_tank_chain`).
pub fn identify_and_diagnose(
    train: &Dataset,
    val: &Dataset,
    past: usize,
    order: usize,
) -> (ModelFile, Outcome) {
    identify_with_order_and_diagnose(train, val, past, &order.to_string())
}

/// [`identify_and_diagnose`] with `--order ORDER` as the user types it (`auto`, or a number).
pub fn identify_with_order_and_diagnose(
    train: &Dataset,
    val: &Dataset,
    past: usize,
    order: &str,
) -> (ModelFile, Outcome) {
    let dir = tempfile::tempdir().unwrap();
    let tp = dir.path().join("train.csv");
    let mp = dir.path().join("model.json");
    train.write_csv(&tp).unwrap();
    let cli: Vec<String> = [
        "lpvid",
        "pbsid",
        "--train",
        tp.to_str().unwrap(),
        "--past",
        &past.to_string(),
        "--order",
        order,
        "--out",
        mp.to_str().unwrap(),
    ]
    .map(String::from)
    .to_vec();
    lpvid_host::cli::run(cli, &mut Vec::new()).unwrap();
    let model = ModelFile::read(&mp).unwrap();
    let opts = Options {
        fix: true,
        max_steps: 1,
        threads: 2,
    };
    let out = diagnose(&model, train, val, &opts).unwrap();
    (model, out)
}

/// Mean square error of a model on data (free run or one-step), mean over outputs.
pub fn mse(model: &ModelFile, ds: &Dataset, mode: Mode) -> f64 {
    let (y, yh) = simulate(model, ds, mode).unwrap();
    let e = &y - &yh;
    e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64
}

/// Where the measured data live (../shared/data from the workspace root), if present.
pub fn shared_data() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let d = root.join("../shared/data");
    d.is_dir().then(|| d.canonicalize().unwrap_or(d))
}

/// A standard normal draw.
pub fn normal(rng: &mut StdRng) -> f64 {
    StandardNormal.sample(rng)
}

/// A random stable A0 of order `n`: real poles in [-0.5, 0.85), complex pairs of radius
/// 0.3-0.85, in a random basis.
pub fn stable(rng: &mut StdRng, n: usize) -> DMatrix<f64> {
    let mut a = DMatrix::zeros(n, n);
    let mut i = 0;
    while i < n {
        if i + 1 < n && rng.gen_bool(0.5) {
            let (r, th): (f64, f64) = (rng.gen_range(0.3..0.85), rng.gen_range(0.2..2.5));
            a[(i, i)] = r * th.cos();
            a[(i, i + 1)] = r * th.sin();
            a[(i + 1, i)] = -r * th.sin();
            a[(i + 1, i + 1)] = r * th.cos();
            i += 2;
        } else {
            a[(i, i)] = rng.gen_range(-0.5..0.85);
            i += 1;
        }
    }
    let t = DMatrix::from_fn(n, n, |r, c| normal(rng) + if r == c { 3.0 } else { 0.0 });
    let ti = t
        .clone()
        .try_inverse()
        .expect("a diagonally dominant basis");
    &t * a * &ti
}

/// The seeds of a long-tier generator run, `FIRST,COUNT` from the environment variable `var`
/// (to measure the spread on other seeds; the assertions judge those), else `default`.
pub fn env_seeds(var: &str, default: (u64, u64)) -> (u64, u64) {
    std::env::var(var)
        .ok()
        .and_then(|s| {
            let (a, b) = s.split_once(',')?;
            Some((a.trim().parse().ok()?, b.trim().parse().ok()?))
        })
        .unwrap_or(default)
}
