//! Monte-Carlo of the sparse estimate (sparse paper section 5): mean, minimum and fit time
//! of the free-run VAF on the noise-free validation data over seeded runs, per past window.
//!
//! ```text
//! cargo run --release -p lpvid-host --example bpdn_montecarlo -- [b2|b3] [sv|sv-paper|aic|tik|none] [RUNS] [P,P,...]
//! ```
//!
//! b2: Example I (N = 75, 25 dB), b3: Example II (N = 250); defaults b2 sv 20 3..14.
//! `sv-paper` is BPDN-SV with the paper's one-step score (`--bpdn-score paper`); `ORDER=n`
//! fixes the order (default: automatic).
//! `REFINE=1` adds the output-error refinement (`--refine`). `SEED0=k` starts the seeds at k
//! (seeds k..k+RUNS), so a figure can be checked on seeds that were not looked at. `FUTURE=f`
//! sets the future window (min(f, p)); `SKIP=k` drops the first k training samples (to
//! compare past windows on the same number of regression windows). The acceptance test
//! `tests/acceptance_bpdn.rs` runs the smaller version of this (B2 20 runs, B3 10 runs).

use std::time::Instant;

use lpvid_host::lpvss::Signals;
use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::pbsid::{fit, BpdnScore, Order, PbsidOptions, Reg};
use lpvid_host::systems;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let sys = args.get(1).map(String::as_str).unwrap_or("b2");
    let rule = args.get(2).map(String::as_str).unwrap_or("sv");
    let score = if rule == "sv-paper" {
        BpdnScore::OneStep
    } else {
        BpdnScore::Simulation
    };
    let order = match std::env::var("ORDER").ok().and_then(|v| v.parse().ok()) {
        Some(n) => Order::Fixed(n),
        None => Order::Auto,
    };
    let reg = match rule {
        "sv" | "sv-paper" => Reg::BpdnSv,
        "aic" => Reg::BpdnAic,
        "tik" => Reg::TikhonovGcv,
        _ => Reg::None,
    };
    let runs: u64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(20);
    let ps: Vec<usize> = args
        .get(4)
        .map(|s| s.split(',').filter_map(|v| v.parse().ok()).collect())
        .unwrap_or_else(|| (3..=14).collect());
    let refine = std::env::var("REFINE").is_ok();
    let future: Option<usize> = std::env::var("FUTURE").ok().and_then(|v| v.parse().ok());
    let skip: usize = std::env::var("SKIP")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let seed0: u64 = std::env::var("SEED0")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    println!(
        "{sys}, {reg:?} ({score:?} score), order {order:?}, {runs} runs (seeds {seed0}..{}){}",
        seed0 + runs,
        if refine { ", refined" } else { "" }
    );
    println!("   p   mean VAF   min VAF   std VAF   fit ms   orders");
    for p in ps {
        let mut vafs = Vec::new();
        let mut orders = Vec::new();
        let t = Instant::now();
        for seed in seed0..seed0 + runs {
            let mut e = if sys == "b3" {
                systems::b3(250, seed)
            } else {
                systems::b2(75, 25.0, seed)
            };
            if skip > 0 {
                let t = &e.train;
                let n = t.len() - skip;
                e.train = Signals {
                    u: t.u.rows(skip, n).into_owned(),
                    y: t.y.rows(skip, n).into_owned(),
                    p: t.p.rows(skip, n).into_owned(),
                };
            }
            let mut o = PbsidOptions::new(p);
            o.reg = reg;
            o.refine = refine;
            o.bpdn_score = score;
            o.order = order;
            o.future = future.map(|f| f.min(p));
            match fit(&e.train, &o) {
                Ok(f) => {
                    orders.push(f.order);
                    let yh = f.model.simulate(&e.val, None);
                    vafs.push(mean(&vaf_per_output(&e.val.y, &yh, 0)));
                }
                Err(err) => {
                    eprintln!("p = {p}, seed {seed}: {err}");
                    vafs.push(0.0);
                }
            }
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / runs as f64;
        let min = vafs.iter().copied().fold(f64::INFINITY, f64::min);
        let avg = mean(&vafs);
        let std = (vafs.iter().map(|v| (v - avg) * (v - avg)).sum::<f64>()
            / (vafs.len().max(2) - 1) as f64)
            .sqrt();
        println!("  {p:2}   {avg:8.2}   {min:7.2}   {std:7.2}   {ms:6.1}   {orders:?}");
    }
}
