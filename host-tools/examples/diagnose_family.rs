//! The family benchmark of `lpvid diagnose`: random plants per planted effect, the confusion
//! matrix (how often each effect was named first) and the error ratio after `--fix`.
//! `cargo run --release -p lpvid-host --example diagnose_family -- [seeds per effect] [N]
//! [first seed] [held-out samples] [effects, comma-separated]` (defaults 10, 2000, 1000, N,
//! all). `LPVID_FAMILY_SHAPE=INPUTSxOUTPUTS` (e.g. `2x2`, `2x1`: two inputs, one output; default
//! `1x1`) draws multi-input multi-output plants instead (`plants::family_case_shaped`); the
//! printed lines and tables are the same. `LPVID_FAMILY_VERBOSE=1` prints each plant's
//! findings and variants; `LPVID_FAMILY_DUMP=DIR` writes each plant's records and the user's
//! `lpvid pbsid` options (`DIR/EFFECT-SEED.train.csv`, `.val.csv`, `.args`) to trace a miss
//! through the command line; `LPVID_FAMILY_ORDER=auto` lets the user's fit choose its order
//! (`--order auto`) instead of being given the plant's (not for `order-too-low`);
//! `LPVID_FAMILY_PAST=P` gives every plant the user's past window P instead of the one drawn
//! from its slowest pole;
//! `LPVID_FAMILY_SCHEDULING=operating-points` moves a scheduled plant's p1 between held levels
//! (`plants::Profile::OperatingPoints`) instead of the drawn signals, and
//! `LPVID_FAMILY_SCHEDULING=two-signals` gives a scheduled plant a second scheduling signal p2
//! (`plants::Profile::TwoSignals`; the planted effects stay on p1). The figures are in
//! docs/bench-diagnose.md.

#[path = "../tests/diagnose_support/family.rs"]
mod family;

use lpvid_host::diagnose::plants::{Shape, FAMILY_EFFECTS};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(10);
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2000);
    let first: u64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let val_len: Option<usize> = args.get(4).and_then(|s| s.parse().ok());
    let effects: Vec<&str> = match args.get(5) {
        Some(list) => FAMILY_EFFECTS
            .iter()
            .copied()
            .filter(|e| list.split(',').any(|w| w == *e))
            .collect(),
        None => FAMILY_EFFECTS.to_vec(),
    };
    let shape = match std::env::var("LPVID_FAMILY_SHAPE") {
        Ok(text) => Shape::parse(&text).unwrap_or_else(|| {
            eprintln!("LPVID_FAMILY_SHAPE={text:?}: expected INPUTSxOUTPUTS, e.g. 2x2");
            std::process::exit(2)
        }),
        Err(_) => Shape::SISO,
    };
    let threads = std::thread::available_parallelism().map_or(1, |v| v.get());
    let seeds: Vec<u64> = (first..first + seeds).collect();
    let t0 = std::time::Instant::now();
    let runs = family::run_family_shaped(&effects, &seeds, n, threads, val_len, shape);
    for r in &runs {
        println!(
            "{:<24} seed {:>5}: named {:<24} ratio {:>8}  ({})",
            r.planted,
            r.seed,
            r.named,
            family::Ratio(r.ratio),
            r.description
        );
    }
    println!();
    println!("{}", family::matrix(&runs));
    println!(
        "{}; {} plants, N = {n}, {:.0} s",
        family::clean_line(&runs),
        runs.len(),
        t0.elapsed().as_secs_f64()
    );
    // after the matrix (parsed by others, unchanged): the oracle of each plant and the
    // recall among the plants whose planted effect is identifiable (family::identifiable)
    println!();
    println!("Oracles (the user's structure refit with the planted effect's true structure):");
    for r in &runs {
        if let Some(o) = &r.oracle {
            println!(
                "{:<24} seed {:>5}: oracle ratio {:>8} explained {:>7.3} p {:.1e} identifiable {:<5} ({})",
                r.planted, r.seed, family::Ratio(o.ratio), o.explained, o.p_value, o.identifiable, o.detail
            );
        }
    }
    println!();
    println!("{}", family::identifiable_table(&runs));
}
