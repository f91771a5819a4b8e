//! The one streaming interface: for every accumulator of the core, a block update through
//! `Streaming::update_block` gives bit for bit the state of the same samples fed one by one
//! through the inherent methods, allocates nothing, and `Merge` of two halves equals the whole.

use lpvid::arx::{ArxDims, ArxWindow};
use lpvid::bciv::{BcivDims, BcivStats};
use lpvid::dictionary::{
    dictionary_gram_len, dictionary_storage_len, DictionaryConfig, KernelDictionary,
};
use lpvid::{
    packed_len, stat_vector_len, window_storage_len, Error, Gram, Merge, PbsidDims, PbsidStats,
    StatsLayout, Streaming,
};

mod common;

use common::counting_alloc::{count_allocs, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

/// n samples [u, y, p] of a small closed-form signal (r = l = s = 1).
fn rows(n: usize) -> Vec<f64> {
    (0..n)
        .flat_map(|k| {
            let f = k as f64;
            [
                (0.7 * f).sin(),
                (1.3 * f).cos() + 0.1 * f,
                0.5 * (0.2 * f).sin(),
            ]
        })
        .collect()
}

type Stats = PbsidStats<f64, Vec<f64>, Vec<f64>, Vec<f64>>;

fn stats(dims: PbsidDims) -> Stats {
    let len = stat_vector_len(&dims, StatsLayout::Extended).unwrap();
    PbsidStats::with_storage(
        dims,
        StatsLayout::Extended,
        vec![0.0; window_storage_len(dims.r, dims.l, dims.s, dims.p)],
        vec![0.0; packed_len(len)],
        vec![0.0; len],
    )
    .unwrap()
}

#[test]
fn pbsid_stats_block_equals_samples_and_merges() {
    let dims = PbsidDims::new(1, 1, 1, 2).unwrap();
    let data = rows(40);
    let mut one = stats(dims);
    for row in data.chunks_exact(3) {
        one.update(&row[..1], &row[1..2], &row[2..]).unwrap();
    }
    let mut block = stats(dims);
    let (res, allocs) = count_allocs(|| block.update_block(&data));
    res.unwrap();
    assert_eq!(allocs, 0);
    assert_eq!(block.gram().packed(), one.gram().packed());
    assert_eq!(block.gram().count(), one.gram().count());
    // a ragged block is rejected before anything changes
    assert!(matches!(
        block.update_block(&data[..4]),
        Err(Error::Dimension { .. })
    ));
    assert_eq!(block.gram().packed(), one.gram().packed());
    // merge of two halves (windows do not straddle the cut: each half breaks its window)
    let (mut a, mut b) = (stats(dims), stats(dims));
    a.update_block(&data[..60]).unwrap();
    b.update_block(&data[60..]).unwrap();
    Merge::merge(&mut a, &b).unwrap();
    let mut whole = stats(dims);
    whole.update_block(&data[..60]).unwrap();
    whole.break_window();
    whole.update_block(&data[60..]).unwrap();
    assert_eq!(a.gram().count(), whole.gram().count());
    for (x, y) in a.gram().packed().iter().zip(whole.gram().packed()) {
        assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()));
    }
    let other = stats(PbsidDims::new(1, 1, 1, 1).unwrap());
    assert_eq!(Merge::merge(&mut a, &other), Err(Error::Mismatch));
}

#[test]
fn gram_block_is_the_batch_update() {
    let data = rows(25);
    let mut one = Gram::new(3, vec![0.0; 6]).unwrap();
    for w in data.chunks_exact(3) {
        one.update(w).unwrap();
    }
    let mut block = Gram::new(3, vec![0.0; 6]).unwrap();
    let (res, allocs) = count_allocs(|| Streaming::update_block(&mut block, &data));
    res.unwrap();
    assert_eq!(allocs, 0);
    let mut batch = Gram::new(3, vec![0.0; 6]).unwrap();
    batch.update_batch(&data, 25).unwrap();
    assert_eq!(block.packed(), batch.packed());
    for (x, y) in block.packed().iter().zip(one.packed()) {
        assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()));
    }
    // atomic: one bad row and nothing changes
    let mut bad = data.clone();
    bad[40] = f64::NAN;
    let before = block.packed().to_vec();
    assert!(Streaming::update_block(&mut block, &bad).is_err());
    assert_eq!(block.packed(), &before[..]);
    let mut half = Gram::new(3, [0.0; 6]).unwrap();
    half.update_batch(&data[..30], 10).unwrap();
    let mut rest = Gram::new(3, vec![0.0; 6]).unwrap();
    rest.update_batch(&data[30..], 15).unwrap();
    Merge::merge(&mut half, &rest).unwrap();
    assert_eq!(half.count(), 25);
}

#[test]
fn arx_window_and_bciv_blocks() {
    let arx = ArxDims::new(1, 1, 2, 1, 2).unwrap();
    let data = rows(30);
    let mut one = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    let mut block = ArxWindow::new(arx, vec![0.0; arx.window_len()]).unwrap();
    for row in data.chunks_exact(3) {
        one.push(&row[..1], row[1], &row[2..]).unwrap();
    }
    let (res, allocs) = count_allocs(|| block.update_block(&data));
    res.unwrap();
    assert_eq!(allocs, 0);
    let nt = arx.n_theta().unwrap();
    let (mut ra, mut rb) = (vec![0.0; nt], vec![0.0; nt]);
    one.write_regressor(&mut ra).unwrap();
    block.write_regressor(&mut rb).unwrap();
    assert_eq!(ra, rb);

    // BC-IV: rows [zeta (nzeta), u, y, p] with a fixed instrument part
    let dims = BcivDims::new(arx, 2, 1).unwrap();
    let new = || {
        BcivStats::new(
            dims,
            vec![0.0; dims.storage_len()],
            vec![0.0; dims.window_len()],
        )
        .unwrap()
    };
    let brows: Vec<f64> = data
        .chunks_exact(3)
        .enumerate()
        .flat_map(|(k, r)| [(0.3 * k as f64).cos(), r[0] - 0.5, r[0], r[1], r[2]])
        .collect();
    let mut one = new();
    for r in brows.chunks_exact(5) {
        one.update(&r[..2], &r[2..3], r[3], &r[4..]).unwrap();
    }
    let mut block = new();
    let (res, allocs) = count_allocs(|| block.update_block(&brows));
    res.unwrap();
    assert_eq!(allocs, 0);
    assert_eq!(block.values(), one.values());
    assert_eq!(block.count(), one.count());
    let mut a = new();
    a.update_block(&brows[..50]).unwrap();
    let mut b = new();
    b.update_block(&brows[50..]).unwrap();
    Merge::merge(&mut a, &b).unwrap();
    assert_eq!(a.count() + 2, one.count()); // each half fills its own window
}

#[test]
fn dictionary_block_equals_samples() {
    let dims = PbsidDims::new(1, 1, 1, 2).unwrap();
    let cfg = DictionaryConfig::new(8, 1e-6, true);
    let new = || {
        KernelDictionary::with_storage(
            dims,
            cfg,
            vec![0.0; window_storage_len(1, 1, 1, 2)],
            vec![0.0; dictionary_storage_len(1, 1, 1, 2, 8)],
            vec![0.0; dictionary_gram_len(1, 8)],
        )
        .unwrap()
    };
    let data = rows(40);
    let mut one = new();
    for row in data.chunks_exact(3) {
        one.update(&row[..1], &row[1..2], &row[2..]).unwrap();
    }
    let mut block = new();
    let (res, allocs) = count_allocs(|| block.update_block(&data));
    res.unwrap();
    assert_eq!(allocs, 0);
    assert_eq!(block.len(), one.len());
    assert_eq!(block.cholesky(), one.cholesky());
    one.freeze().unwrap();
    block.freeze().unwrap();
    for row in data.chunks_exact(3) {
        one.update(&row[..1], &row[1..2], &row[2..]).unwrap();
    }
    block.update_block(&data).unwrap();
    assert_eq!(
        block.normal_equations().unwrap().packed(),
        one.normal_equations().unwrap().packed()
    );
}
