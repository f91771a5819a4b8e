//! The 10^9-sample form of the `f32_long_run` acceptance test (issue 18): compensated f32
//! statistics against a compensated f64 reference, and the VAF of the models fitted from
//! them. `cargo run --release -p lpvid-host --example f32_long_run [samples]`.

#[path = "../tests/long_run/mod.rs"]
mod long_run;

fn main() {
    let n = std::env::args()
        .nth(1)
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000_000u64);
    let t = std::time::Instant::now();
    let r = long_run::run(n, 18);
    println!("{r:?}");
    println!(
        "{} samples in {:.1} s; plain f32 relative error {:.2e}; VAF loss: compensated f32 {:.2e}, plain f32 {:?} points \
         (plain normed error {:.2e})",
        r.samples,
        t.elapsed().as_secs_f64(),
        r.rel_plain,
        r.vaf_f64 - r.vaf_f32,
        r.vaf_plain.as_ref().map(|v| r.vaf_f64 - v),
        r.normed_plain
    );
    let ok = r.rel_compensated < 1e-5
        && r.normed_compensated < 1e-5
        && (r.vaf_f64 - r.vaf_f32).abs() <= 0.5;
    println!("{}", if ok { "PASS" } else { "FAIL" });
    if !ok {
        std::process::exit(1);
    }
}
