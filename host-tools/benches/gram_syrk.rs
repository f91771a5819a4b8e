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
//!
//! `normal_equations`: J'J of a refinement's Jacobian (10^4 residuals, P parameters) by
//! nalgebra's dense product of the transposed copy (what `refine` computed before, the
//! comparison) and by [`lpvid_host::linalg::gram_of_columns`] (faer's lower half, mirrored).

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use faer::linalg::matmul::triangular::{matmul, BlockStructure};
use faer::{Accum, Mat, Par};
use lpvid::{packed_len, Gram};
use lpvid_host::linalg::{gram_of_columns, GramBatch, GRAM_BATCH};
use nalgebra::DMatrix;

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

fn normal_equations(c: &mut Criterion) {
    let mut group = c.benchmark_group("normal_equations");
    group.sample_size(20);
    let rows = 10_000;
    for params in [40usize, 112, 200] {
        let jac = DMatrix::from_fn(rows, params, |i, j| {
            (((i * 31 + j * 7919) % 1013) as f64 / 1013.0 - 0.5) * 0.1
        });
        group.bench_function(BenchmarkId::new("nalgebra J'J", params), |b| {
            b.iter(|| {
                let jt = black_box(&jac).transpose();
                black_box(&jt * &jac)
            })
        });
        group.bench_function(BenchmarkId::new("gram_of_columns", params), |b| {
            b.iter(|| black_box(gram_of_columns(black_box(&jac))))
        });
    }
    group.finish();
}

criterion_group!(gram_syrk, compare, normal_equations);
criterion_main!(gram_syrk);
