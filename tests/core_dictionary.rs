//! The streaming kernel dictionary allocates nothing: with a counting global allocator,
//! admission tests (Algorithm 3), the accumulation of the projected normal equations, the
//! solve and the eq. (25) pieces make zero heap allocations once the storage exists, in f64
//! over `Vec`s and in f32 over arrays.

use lpvid::dictionary::{
    dictionary_gram_len, dictionary_storage_len, realization_vector_len, DictionaryConfig,
    KernelDictionary, KernelDictionaryArrays, Step,
};
use lpvid::stats::packed_len;
use lpvid::{window_storage_len, PbsidDims, Slab, Streaming};

// ---------------------------------------------------------------- counting allocator

mod common;

use common::counting_alloc::{count_allocs, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Rows [u, y1, y2, 1, rho] of a deterministic, rich signal (r = 1, l = 2, s = 1).
fn signal(n: usize) -> Vec<f64> {
    (0..n)
        .flat_map(|k| {
            let f = k as f64;
            [
                (0.7 * f).sin() + 0.3 * (2.9 * f).cos(),
                (1.3 * f).cos() * (0.11 * f).sin(),
                (0.5 * f).sin() - 0.2 * (1.7 * f).cos(),
                1.0,
                0.5 * (0.23 * f).sin() + 0.1 * (3.1 * f).cos(),
            ]
        })
        .collect()
}

#[test]
fn dictionary_updates_allocate_nothing_f64_vec() {
    let (r, l, s, p, cap) = (1, 2, 1, 4, 24);
    let dims = PbsidDims::new(r, l, s, p).unwrap();
    let n = 300;
    let data = signal(n);
    let slab = Slab::new(&data, r, l, s + 1).unwrap();
    let mut dct = KernelDictionary::with_storage(
        dims,
        DictionaryConfig::new(cap, 1e-3, true),
        vec![0.0; window_storage_len(r, l, s, p)],
        vec![0.0; dictionary_storage_len(r, l, s, p, cap)],
        vec![0.0; dictionary_gram_len(l, cap)],
    )
    .unwrap();
    let mut work = vec![0.0; packed_len(cap)];
    let mut alpha = vec![0.0; l * cap];
    let f = p;
    let mut kappa = vec![0.0; f * cap];
    let mut g = vec![0.0; f * l];
    let mut v = vec![0.0; realization_vector_len(r, l, s, f)];

    let ((admitted, accumulated), allocs) = count_allocs(|| {
        let mut admitted = 0;
        for k in 0..n {
            let row = &data[k * 5..(k + 1) * 5];
            if let Step::Admitted { .. } = dct.update(&row[..1], &row[1..3], &row[4..]).unwrap() {
                admitted += 1;
            }
            // a rejected sample on the way costs nothing either
            assert!(dct.update(&[f64::NAN], &row[1..3], &row[4..]).is_err());
        }
        dct.freeze().unwrap();
        dct.break_window();
        let mut accumulated = 0;
        for k in 0..n {
            let row = &data[k * 5..(k + 1) * 5];
            // the same update through the one streaming trait
            let step = Streaming::update(&mut dct, (&row[..1], &row[1..3], &row[4..])).unwrap();
            if matches!(step, Step::Accumulated { .. }) {
                accumulated += 1;
            }
        }
        let m = dct.len();
        dct.solve(1e-6, &mut work[..packed_len(m)], &mut alpha[..l * m])
            .unwrap();
        let rss = dct.residual_sum_of_squares(&alpha[..l * m]).unwrap();
        assert!(rss.is_finite());
        for b in 0..=n - p {
            dct.shifted_kernels(&slab, b, f, &mut kappa[..f * m])
                .unwrap();
            dct.state_candidate(&slab, b, f, &alpha[..l * m], &mut g)
                .unwrap();
        }
        for k in 0..n - p {
            dct.write_realization_vector(&slab, k, f, &alpha[..l * m], &mut v)
                .unwrap();
        }
        (admitted, accumulated)
    });
    assert_eq!(allocs, 0, "the dictionary allocated {allocs} times");
    assert!(admitted > 5, "{admitted}");
    assert_eq!(admitted, dct.len());
    assert_eq!(accumulated, n - p);
    assert!(g.iter().any(|x| *x != 0.0));
}

#[test]
fn dictionary_updates_allocate_nothing_f32_arrays() {
    const R: usize = 1;
    const L: usize = 2;
    const S: usize = 1;
    const P: usize = 3;
    const M: usize = 16;
    const W: usize = window_storage_len(R, L, S, P);
    const D: usize = dictionary_storage_len(R, L, S, P, M);
    const G: usize = dictionary_gram_len(L, M);
    let dims = PbsidDims::new(R, L, S, P).unwrap();
    let data: Vec<f32> = signal(200).iter().map(|x| *x as f32).collect();
    let (res, allocs) = count_allocs(|| {
        let mut dct =
            KernelDictionaryArrays::<f32, W, D, G>::new(dims, DictionaryConfig::new(M, 1e-2, true))
                .unwrap();
        for k in 0..200 {
            let row = &data[k * 5..(k + 1) * 5];
            if k == 100 {
                dct.freeze().unwrap();
            }
            dct.update(&row[..1], &row[1..3], &row[4..]).unwrap();
        }
        let m = dct.len();
        let mut work = [0.0f32; packed_len(M)];
        let mut alpha = [0.0f32; L * M];
        dct.solve(1e-3, &mut work[..packed_len(m)], &mut alpha[..L * m])
            .map(|_| (m, dct.normal_equations().map(|g| g.count())))
    });
    assert_eq!(allocs, 0, "the dictionary allocated {allocs} times");
    let (m, count) = res.unwrap();
    assert!(m > 3);
    assert_eq!(count, Some(100));
}
