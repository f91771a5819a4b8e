//! The public benchmarks of ../shared/data on their splits (docs/benchmarks-measured.md):
//! identify as a user would (`lpvid pbsid --past 10`), diagnose with `--fix --max-steps 3`
//! holding out the last fifth of the training data, and print the test RMSE (data units)
//! before and after, from x0 = 0 and with the initial state estimated from the first 50 test
//! samples (those then not scored).
//!
//! `cargo run --release -p lpvid-host --example benchmarks_measured [-- NAME...]` (names:
//! silverbox, tanks, disk, emps, rotor), from host-tools/.

#[path = "../tests/benchmarks_support/mod.rs"]
mod benchmarks_support;

use benchmarks_support::{benches, describe, run_bench, shared_data};

fn main() {
    let Some(dir) = shared_data() else {
        eprintln!("../shared/data not found (run from host-tools/)");
        return;
    };
    let want: Vec<String> = std::env::args().skip(1).collect();
    for b in benches() {
        if !want.is_empty() && !want.iter().any(|w| w == b.name) {
            continue;
        }
        let r = run_bench(&dir, &b);
        print!("{}", describe(&b, &r));
    }
}
