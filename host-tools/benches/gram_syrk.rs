//! The Gram update against a BLAS syrk (issue 16, the flop limit): one batch of
//! [`GRAM_BATCH`] vectors of length L added to a symmetric accumulator, f64, by
//! - `faer syrk` (the comparison): faer's triangular product C(lower) = W W^T into a dense
//!   L x L matrix, single-threaded, what a BLAS user would call;
//! - `host GramBatch`: what the host's statistics run ([`lpvid_host::linalg::GramBatch`]:
//!   the same faer product, packed and added to the core's accumulator);
//! - `core batch`: the core's portable register-tiled [`lpvid::Gram::update_batch`];
//! - `core per-vector`: [`lpvid::Gram::update`] once per vector (the device's path).
//!
//! L = 16, 30 (the device's extended statistics), 126, 425 (B1, p = 3 primal regression).
//! Run: `cargo bench -p lpvid-host --bench gram_syrk`.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use faer::linalg::matmul::triangular::{matmul, BlockStructure};
use faer::{Accum, Mat, Par};
use lpvid::{packed_len, Gram};
use lpvid_host::linalg::{GramBatch, GRAM_BATCH};

fn block(len: usize) -> Vec<f64> {
    (0..GRAM_BATCH * len)
        .map(|t| ((t * 7919 % 1013) as f64 / 1013.0 - 0.5) * 0.1)
        .collect()
}

fn compare(c: &mut Criterion) {
    let mut group = c.benchmark_group("gram_vs_syrk_f64");
    for len in [4usize, 30, 126, 425] {
        group.sample_size(if len > 200 { 20 } else { 40 });
        group.throughput(Throughput::Elements(GRAM_BATCH as u64));
        let rows = block(len);
        let w = faer::MatRef::from_column_major_slice(&rows, len, GRAM_BATCH);
        let mut dense = Mat::<f64>::zeros(len, len);
        group.bench_function(BenchmarkId::new("faer syrk", len), |b| {
            b.iter(|| {
                matmul(
                    dense.as_mut(),
                    BlockStructure::TriangularLower,
                    Accum::Add,
                    w,
                    BlockStructure::Rectangular,
                    w.transpose(),
                    BlockStructure::Rectangular,
                    1.0,
                    Par::Seq,
                );
                black_box(&dense);
            })
        });
        let mut gram = Gram::new(len, vec![0.0; packed_len(len)]).unwrap();
        let mut batch = GramBatch::new(len);
        group.bench_function(BenchmarkId::new("host GramBatch", len), |b| {
            b.iter(|| batch.add(&mut gram, black_box(&rows), GRAM_BATCH).unwrap())
        });
        group.bench_function(BenchmarkId::new("core batch", len), |b| {
            b.iter(|| gram.update_batch(black_box(&rows), GRAM_BATCH).unwrap())
        });
        group.bench_function(BenchmarkId::new("core per-vector", len), |b| {
            b.iter(|| {
                for v in rows.chunks_exact(len) {
                    gram.update(black_box(v)).unwrap();
                }
            })
        });
    }
    group.finish();
}

criterion_group!(gram_syrk, compare);
criterion_main!(gram_syrk);
