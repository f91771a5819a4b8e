//! The scheduling centre of `lpvid pbsid` measured on plant families: every family plant with
//! a scheduling signal, its p1 moved by an offset in the training and validation records,
//! identified with `--centre zero`, `mean` and `auto` (with 0 away from p1's mean: both fitted
//! and the better free run on the training record kept), and scored by the validation
//! record's normalised free-run error from an estimated initial state (10 when the run
//! diverges or the fit fails). Prints, per offset, the mean log10 error of each centre and how
//! often `auto` is more than 10 % better or worse than each fixed centre. The figures are in
//! docs/bench-diagnose.md ("The scheduling centre chosen by the free run").
//!
//! `cargo run --release -p lpvid-host --example scheduling_offset -- [seeds per effect] [N]
//! [first seed] [offsets, comma-separated]` (defaults 4, 1500, 1000, `0,0.5,1,1.5,2,3,6`);
//! `LPVID_VERBOSE=1` prints every plant's three errors.

#[path = "../tests/centre_support/mod.rs"]
mod centre;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(4);
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1500);
    let first: u64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let offsets: Vec<f64> = args
        .get(4)
        .map(|s| s.split(',').filter_map(|w| w.parse().ok()).collect())
        .unwrap_or_else(|| vec![0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 6.0]);
    let cases = centre::scheduled_cases(seeds, n, first);
    println!("{} scheduled plants, N = {n}", cases.len());
    println!(
        "| offset | mean log10 error, zero | mean | auto | auto better / worse than zero (10 %) | than mean |"
    );
    println!("|---|---|---|---|---|---|");
    let threads = std::thread::available_parallelism().map_or(1, |v| v.get());
    for &offset in &offsets {
        let rows = centre::errors(&cases, offset, threads);
        if std::env::var_os("LPVID_VERBOSE").is_some() {
            for (c, e) in cases.iter().zip(&rows) {
                println!(
                    "  offset {offset} {} {}: zero {:.4} mean {:.4} auto {:.4}",
                    c.effect, c.seed, e[0], e[1], e[2]
                );
            }
        }
        let count = |k: usize| {
            let better = rows.iter().filter(|e| e[2] < 0.9 * e[k]).count();
            let worse = rows.iter().filter(|e| e[2] > 1.1 * e[k]).count();
            format!("{better} / {worse}")
        };
        println!(
            "| {offset} | {:.3} | {:.3} | {:.3} | {} | {} |",
            centre::mean_log10(&rows, 0),
            centre::mean_log10(&rows, 1),
            centre::mean_log10(&rows, 2),
            count(0),
            count(1)
        );
    }
}
