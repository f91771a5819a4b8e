//! Writes the committed benchmark fixtures into `fixtures/` (or the directory given as the
//! first argument) from the seeded generators of `lpvid_host::systems`:
//!
//! ```text
//! cargo run -p lpvid-host --example make_fixtures [-- OUT_DIR]
//! ```
//!
//! Columns `u1..ur, y1..yl, p1..ps`, one header line, one row per sample, every number in
//! Rust's shortest round-trip form (parsing it back gives the identical f64). The settings of
//! each file are listed in `fixtures/README.md`; keep the two in step.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use lpvid_host::lpvss::Signals;
use lpvid_host::systems::{b1, b2, b3, b6};
use nalgebra::DVector;

/// B1 whose local input matrices drift (issue 18, the device's forgetting check): the
/// signals of `b1(n, sigma, seed)` (inputs, scheduling, innovation) re-simulated with every
/// B^(i) scaled by g(k) = 0.8 + 0.4 k / (n - 1), a gain rising from 0.8 to 1.2 over the
/// record (A, K, C untouched: the plant stays stable and keeps its innovation form).
/// The innovation is recovered from the seeded record as e = y - (one-step prediction of
/// the true model), so it is the generator's e up to rounding.
fn b1_drift(n: usize, sigma: f64, seed: u64) -> Signals {
    let e1 = b1(n, sigma, seed);
    let truth = e1.truth.expect("b1 has its true model");
    let mut sig = e1.train;
    let e = &sig.y - truth.predict(&sig);
    let nx = truth.a[0].nrows();
    let mut x = DVector::<f64>::zeros(nx);
    for k in 0..n {
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        let ek = e.row(k).transpose();
        // D = 0, C constant
        let y = &truth.c[0] * &x + &ek;
        sig.y.set_row(k, &y.transpose());
        let g = 0.8 + 0.4 * k as f64 / (n - 1).max(1) as f64;
        let mut xn = DVector::<f64>::zeros(nx);
        for i in 0..truth.a.len() {
            xn += (&truth.a[i] * &x + &truth.b[i] * &u * g + &truth.k[i] * &ek) * mu[i];
        }
        x = xn;
    }
    sig
}

/// Shortest round-trip text of an f64: plain decimal for moderate magnitudes, exponent form
/// otherwise (both parse back exactly with `str::parse::<f64>`).
fn num(x: f64) -> String {
    let a = x.abs();
    if x == 0.0 || (1e-4..1e15).contains(&a) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// A tiny CSV writer: header `u1..,y1..,p1..`, then one line per sample.
fn to_csv(sig: &Signals) -> String {
    let mut header = Vec::new();
    for (name, m) in [("u", &sig.u), ("y", &sig.y), ("p", &sig.p)] {
        for j in 0..m.ncols() {
            header.push(format!("{name}{}", j + 1));
        }
    }
    let mut out = header.join(",");
    out.push('\n');
    for k in 0..sig.len() {
        let row: Vec<String> = [&sig.u, &sig.y, &sig.p]
            .iter()
            .flat_map(|m| m.row(k).iter().map(|&v| num(v)).collect::<Vec<_>>())
            .collect();
        let _ = writeln!(out, "{}", row.join(","));
    }
    out
}

fn write(dir: &Path, name: &str, sig: &Signals) -> u64 {
    assert!(
        sig.u
            .iter()
            .chain(sig.y.iter())
            .chain(sig.p.iter())
            .all(|v| v.is_finite()),
        "{name}: non-finite sample"
    );
    let path = dir.join(name);
    let text = to_csv(sig);
    std::fs::write(&path, &text).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
    println!(
        "{:>10} bytes  {:>5} rows  {}",
        text.len(),
        sig.len(),
        path.display()
    );
    text.len() as u64
}

fn main() {
    let dir: PathBuf = std::env::args_os()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures"));
    std::fs::create_dir_all(&dir).expect("creating the fixtures directory");
    let mut total = 0;

    // B1: Verdult-Verhaegen benchmark, N = 1000, sigma = 0.05 (40 dB), seed 1
    let e = b1(1000, 0.05, 1);
    total += write(&dir, "b1-train.csv", &e.train);
    total += write(&dir, "b1-val.csv", &e.val);

    // B2: sparse paper Example I, N = 75, SNR 25 dB (process and measurement noise), seed 1
    let e = b2(75, 25.0, 1);
    total += write(&dir, "b2-train.csv", &e.train);
    total += write(&dir, "b2-val.csv", &e.val);

    // B3: sparse paper Example II, N = 250, e ~ N(0, 0.25 I), seed 1
    let e = b3(250, 1);
    total += write(&dir, "b3-train.csv", &e.train);
    total += write(&dir, "b3-val.csv", &e.val);

    // B6: BC-IV example, 8000 / 1000 / 1000, sigma_eta = 0.25, sigma_nu = 0.06, seed 1
    let (train, calib, val) = b6(1);
    total += write(&dir, "b6-train.csv", &train);
    total += write(&dir, "b6-calib.csv", &calib);
    total += write(&dir, "b6-val.csv", &val);

    // B1 with input matrices drifting 0.8 -> 1.2, N = 4000, sigma = 0.05, seed 2 (the
    // device's forgetting and sliding-window check in `make device-test`)
    total += write(&dir, "b1-drift.csv", &b1_drift(4000, 0.05, 2));

    println!("{total:>10} bytes in total");
}
