//! Cost of compensated summation in the core's [`lpvid::Gram`] (src/stats.rs module doc):
//! f32, dimension 30 (the extended statistic vector of r = l = s = 1, p = 2), per vector:
//! - `single/plain` vs `single/compensated`: one `update` per vector (the device's path);
//! - `batch64/plain` vs `batch64/compensated`: `update_batch` of 64 vectors (blocked: the
//!   block is summed in registers, then flushed plainly or compensated).
//!
//! Run: `cargo bench -p lpvid-host --bench summation`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lpvid::{gram_storage_len, packed_len, Gram};

const DIM: usize = 30;
const N: usize = 1024;

fn rows() -> Vec<f32> {
    let mut x = 0x1234_5678u32;
    (0..N * DIM)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x as f32 / u32::MAX as f32) * 2.0 - 0.5
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let rows = rows();
    let mut g = c.benchmark_group("gram_f32_dim30");
    g.throughput(Throughput::Elements(N as u64));
    for (name, storage) in [
        ("plain", packed_len(DIM)),
        ("compensated", gram_storage_len(DIM)),
    ] {
        let mut gram = Gram::new(DIM, vec![0.0f32; storage]).unwrap();
        g.bench_function(format!("single/{name}"), |b| {
            b.iter(|| {
                for w in rows.chunks_exact(DIM) {
                    gram.update(w).unwrap();
                }
            })
        });
        g.bench_function(format!("batch64/{name}"), |b| {
            b.iter(|| {
                for blk in rows.chunks_exact(DIM * 64) {
                    gram.update_batch(blk, 64).unwrap();
                }
            })
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(2));
    targets = bench
}
criterion_main!(benches);
