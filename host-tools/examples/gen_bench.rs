//! Writes one benchmark data file of any length from the seeded generators of
//! `lpvid_host::systems` (for the scale measurements of `docs/scale.md` and
//! `scripts/compare-toolbox.sh`):
//!
//! ```text
//! cargo run --release -p lpvid-host --example gen_bench -- SYSTEM N SEED OUT.csv [VAL.csv]
//! ```
//!
//! SYSTEM is `b1` (sigma 0.05, about 40 dB), `b2` (25 dB) or `b3`; the columns are
//! `u1..ur, y1..yl, p1..ps` in Rust's shortest round-trip form, as `make_fixtures` writes
//! them. With VAL.csv the generator's noise-free validation record is written too.

use std::io::Write;

use lpvid_host::lpvss::Signals;
use lpvid_host::systems::{b1, b2, b3};

fn num(x: f64) -> String {
    let a = x.abs();
    if x == 0.0 || (1e-4..1e15).contains(&a) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

fn write(path: &str, sig: &Signals) {
    let file = std::fs::File::create(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
    let mut header = Vec::new();
    for (name, m) in [("u", &sig.u), ("y", &sig.y), ("p", &sig.p)] {
        for j in 0..m.ncols() {
            header.push(format!("{name}{}", j + 1));
        }
    }
    writeln!(out, "{}", header.join(",")).unwrap();
    for k in 0..sig.len() {
        let row: Vec<String> = [&sig.u, &sig.y, &sig.p]
            .iter()
            .flat_map(|m| m.row(k).iter().map(|&v| num(v)).collect::<Vec<_>>())
            .collect();
        writeln!(out, "{}", row.join(",")).unwrap();
    }
    out.flush().unwrap();
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 4 {
        eprintln!("usage: gen_bench b1|b2|b3 N SEED OUT.csv [VAL.csv]");
        std::process::exit(2);
    }
    let n: usize = args[1].parse::<f64>().expect("N") as usize;
    let seed: u64 = args[2].parse().expect("SEED");
    let exp = match args[0].as_str() {
        "b1" => b1(n, 0.05, seed),
        "b2" => b2(n, 25.0, seed),
        "b3" => b3(n, seed),
        other => panic!("unknown system {other}"),
    };
    write(&args[3], &exp.train);
    if let Some(v) = args.get(4) {
        write(v, &exp.val);
    }
}
