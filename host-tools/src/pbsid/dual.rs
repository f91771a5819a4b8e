//! The dual (kernel) form of regression (13) (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, section 5, Algorithm 2): the kernel
//! Z^T Z + U^T U of (19) by Theorem 10, alpha from (19)-(22), Gamma^p K^p Z by eq. (25) —
//! both through the batched sweep of [`crate::kernel_sweep`] — and the kernel selection of
//! Algorithm 3 (section 6.2) with the periodic-scheduling check of section 6.1.

use lpvid::dictionary::{
    dictionary_gram_len, dictionary_storage_len, DictionaryConfig, KernelDictionary, Step,
};
use lpvid::kernel::dual_kernel;
use lpvid::{PbsidDims, Samples, Slab};
use nalgebra::DMatrix;

use super::error::FitError;
use super::realize::states_from_gkz;
use super::ridge::{ridge_solve, ridge_tridiagonal, NormalForm, RegressionInfo};
use super::settings::PbsidOptions;
use crate::kernel_sweep::{dot4, KernelSweep};
use crate::linalg::Tridiagonal;

/// Dual path (Algorithm 2): kernel Z^T Z + U^T U by Theorem 10, alpha from (19)-(21)
/// (Tikhonov-regularised if asked), Gamma^p K^p Z by eq. (25), and the state candidates
/// U^T Gamma K Z for windows 0..=N-p (the SVD uses the N-p regression windows).
pub(crate) fn dual_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo), FitError> {
    let (p, l) = (dims.p, dims.l);
    let nb = windows;
    if let Some(rows) = opts.kernel_rows {
        return selected_rows_states(dims, f, slab, windows, rows, opts);
    }
    let y = DMatrix::from_fn(l, nb, |j, k| slab.y(k + p)[j]);
    let (yt, total, rows) = (y.transpose(), y.norm_squared(), nb as f64);
    // only the kernel's lower triangle, reduced in its own storage
    let tri = Tridiagonal::from_lower(dual_kernel_lower(slab, p, nb, opts.feedthrough));
    let (x, info) = ridge_tridiagonal(&tri, &yt, NormalForm::Dual, total, rows, opts.reg)?;
    let alpha = x.transpose(); // l x nb
    let gkz = dual_gamma_kz_matrix(dims, f, slab, &alpha, nb + 1);
    let (sv, x) = states_from_gkz(&gkz, nb)?;
    Ok((sv, x, info))
}

/// Kernel form restricted to the rows D of Algorithm 3: min ||Y - alpha_D K_{D,:}||^2
/// (+ Tikhonov with GCV, the same spectrum formula as the other forms), then eq. (25)
/// with alpha zero outside D.
pub(crate) fn selected_rows_states(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    windows: usize,
    max_rows: usize,
    opts: &PbsidOptions,
) -> Result<(Vec<f64>, DMatrix<f64>, RegressionInfo), FitError> {
    let (p, l) = (dims.p, dims.l);
    let nb = windows;
    let (rows, _) = select_kernel_rows(dims, slab, max_rows, opts.kernel_tol, opts.feedthrough)?;
    let m = rows.len();
    let kd = DMatrix::from_fn(m, nb, |a, b| {
        dual_kernel(slab, rows[a], slab, b, p, opts.feedthrough)
    });
    let y = DMatrix::from_fn(l, nb, |j, k| slab.y(k + p)[j]);
    let s_ff = &kd * kd.transpose();
    let s_fy = &kd * y.transpose();
    let (x, info) = ridge_solve(
        &s_ff,
        &s_fy,
        NormalForm::Primal,
        y.norm_squared(),
        nb as f64,
        opts.reg,
    )?;
    let alpha_d = x.transpose(); // l x m
    let mut alpha = DMatrix::zeros(l, nb);
    for (a, &w) in rows.iter().enumerate() {
        alpha.set_column(w, &alpha_d.column(a));
    }
    let gkz = dual_gamma_kz_matrix(dims, f, slab, &alpha, nb + 1);
    let (sv, x) = states_from_gkz(&gkz, nb)?;
    Ok((sv, x, info))
}

/// Kernel paper, Algorithm 3 (kernel selection, section 6.2): the dictionary of windows the core admits by its
/// linear-dependence test (at most `max_rows`, tolerance relative to the mean k(w, w)).
pub fn select_kernel_rows(
    dims: &PbsidDims,
    slab: &Slab<'_, f64>,
    max_rows: usize,
    tol: f64,
    feedthrough: bool,
) -> Result<(Vec<usize>, String), FitError> {
    let n = slab.len();
    if max_rows == 0 {
        return Err(FitError::NoKernelRows);
    }
    let windows = n - dims.p;
    let mean_diag = (0..windows)
        .map(|k| dual_kernel(slab, k, slab, k, dims.p, feedthrough))
        .sum::<f64>()
        / windows as f64;
    let config = DictionaryConfig::new(max_rows, tol * mean_diag, feedthrough);
    let (r, l, s, p) = (dims.r, dims.l, dims.s, dims.p);
    let mut dict = KernelDictionary::with_storage(
        *dims,
        config,
        vec![0.0; lpvid::window_storage_len(r, l, s, p)],
        vec![0.0; dictionary_storage_len(r, l, s, p, max_rows)],
        vec![0.0; dictionary_gram_len(l, max_rows)],
    )?;
    let mut rows = Vec::new();
    for k in 0..n {
        let step = dict.update(slab.u(k), slab.y(k), &slab.mu(k)[1..])?;
        if let Step::Admitted { window, .. } = step {
            if (window as usize) < windows {
                rows.push(window as usize);
            }
        }
    }
    let mut why = format!(
        "{} of {windows} rows kept by the linear-dependence test (tolerance {tol:.1e} x mean k(w,w))",
        rows.len()
    );
    if dict.rejected_full() > 0 {
        why.push_str(&format!(
            "; {} more independent rows did not fit in --kernel-rows {max_rows}",
            dict.rejected_full()
        ));
    }
    if let Some(period) = detect_period(slab, dims.s) {
        why.push_str(&format!(
            "; the scheduling is periodic with period {period} (section 6.1)"
        ));
    }
    Ok((rows, why))
}

/// Kernel paper, section 6.1 (periodic scheduling): the smallest period P <= N/3 with
/// p_{k+P} = p_k for every k (to 1e-9 relative), if any.
pub fn detect_period(slab: &Slab<'_, f64>, s: usize) -> Option<usize> {
    let n = slab.len();
    if s == 0 {
        return None;
    }
    let scale = (0..n)
        .flat_map(|k| slab.mu(k)[1..].iter().map(|v| v.abs()))
        .fold(0.0, f64::max)
        .max(1e-300);
    (1..=n / 3).find(|&per| {
        (0..n - per).all(|k| {
            slab.mu(k)[1..]
                .iter()
                .zip(&slab.mu(k + per)[1..])
                .all(|(a, b)| (a - b).abs() <= 1e-9 * scale)
        })
    })
}

/// Multiply-adds of a kernel sweep (window columns x entries x p) from which it runs on two
/// threads (`benches/kernel.rs`, group `kernel_sweep_threads`, one thread against two at
/// N = 75, 250, 1000). Measured 2026-11-26 at a load average of 1.5 on the 2-core VM: B1
/// N = 1000 p = 5 (work 2.5e6) Gamma K Z 13.5 ms on one thread, 8.4 ms on two, the kernel
/// matrix 10.4 / 9.7 ms; B2 N = 75 (1.2e4) 28 us / 106 us, so small sweeps stay on one thread.
/// Under a load of 10-12 (other builds on both cores) the second thread waits for a core and
/// loses even on B1 (18 / 24 ms).
pub const SWEEP_SPLIT_MIN_WORK: f64 = 1e6;

/// Threads for a sweep of `work` multiply-adds: two from [`SWEEP_SPLIT_MIN_WORK`] on when
/// the machine has two cores, else one.
pub fn sweep_workers(work: f64) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if work >= SWEEP_SPLIT_MIN_WORK && cores >= 2 {
        2
    } else {
        1
    }
}

/// Run `job(columns, out)` over the column range `0..cols` of a column-major output of
/// `rows` rows: on the calling thread (`workers` 1), or split at `cut` with the two parts on
/// two threads (`workers` 2): faer's thread pool when `pool` (now), else the calling thread
/// and a scoped thread of its own (before). Each part writes only its own columns, so the
/// result does not depend on the split or the threads.
///
/// Why the pool: in a kernel-form fit the sweeps run just before and just after the
/// tridiagonal reduction of the kernel, which runs on faer's (rayon) pool from
/// [`crate::linalg::PAR_MIN_DIM`] rows on. Its two workers, out of work, keep spinning in
/// `sched_yield` for a while; two threads of our own then share the two cores with them.
/// Handing both halves to the pool instead gives them to those very workers (B1 N = 1000
/// p = 5, whole process under a load of 10: Gamma K Z 29-86 ms -> 7-12 ms;
/// `benches/kernel.rs`, group `sweep_after_reduction`).
fn split_columns(
    out: &mut [f64],
    rows: usize,
    cols: usize,
    cut: usize,
    workers: usize,
    pool: bool,
    job: impl Fn(std::ops::Range<usize>, &mut [f64]) + Sync,
) {
    let cut = cut.min(cols);
    if workers < 2 || cut == 0 || cut == cols {
        job(0..cols, out);
        return;
    }
    let (first, second) = out.split_at_mut(cut * rows);
    let job = &job;
    if pool {
        faer::utils::thread::join_raw(
            move |_| job(0..cut, first),
            move |_| job(cut..cols, second),
            faer::Par::rayon(2),
        );
        return;
    }
    std::thread::scope(|sc| {
        let h = sc.spawn(move || job(cut..cols, second));
        job(0..cut, first);
        h.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
    });
}

/// Kernel paper, eq. (25); the batched form of `lpvid::kernel::shifted_kernel` over
/// [`KernelSweep`]: row block i of Gamma^p K^p Z is alpha sum_{j >= i} (Z^{i,j})^T Z^{1,j}.
/// Entry (a, b) of that kernel is `shifted_kernel(slab, a, slab, b, i, p)`, Theorem 10
/// between the window starting at a - i + 1 and window b summed over t0 >= i - 1; one
/// backward pass over t gives it for every i at once. Columns are windows b = 0..cols (a
/// window needs only its p samples, not a target). The columns are split over two threads
/// when the sweep is large enough to gain ([`sweep_workers`]).
pub fn dual_gamma_kz_matrix(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    alpha: &DMatrix<f64>,
    cols: usize,
) -> DMatrix<f64> {
    let work = (cols * (alpha.ncols() + dims.p) * dims.p) as f64;
    dual_gamma_kz_matrix_with(dims, f, slab, alpha, cols, sweep_workers(work))
}

/// [`dual_gamma_kz_matrix`] on `workers` threads (1 or 2; the result does not depend on it).
pub fn dual_gamma_kz_matrix_with(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    alpha: &DMatrix<f64>,
    cols: usize,
    workers: usize,
) -> DMatrix<f64> {
    gamma_kz(dims, f, slab, alpha, cols, workers, true)
}

/// [`dual_gamma_kz_matrix_with`] with the second half on a scoped thread of its own instead
/// of the pool, as before (the same bits; `benches/kernel.rs` compares the two).
#[doc(hidden)]
pub fn dual_gamma_kz_matrix_scoped(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    alpha: &DMatrix<f64>,
    cols: usize,
    workers: usize,
) -> DMatrix<f64> {
    gamma_kz(dims, f, slab, alpha, cols, workers, false)
}

fn gamma_kz(
    dims: &PbsidDims,
    f: usize,
    slab: &Slab<'_, f64>,
    alpha: &DMatrix<f64>,
    cols: usize,
    workers: usize,
    pool: bool,
) -> DMatrix<f64> {
    let (p, l) = (dims.p, dims.l);
    let nb = alpha.ncols();
    // alpha row by row, contiguous
    let alpha_rows: Vec<Vec<f64>> = (0..l)
        .map(|j| alpha.row(j).iter().copied().collect())
        .collect();
    let rows = f * l;
    let mut out = DMatrix::zeros(rows, cols);
    // window starts s = -(p-1) .. nb-1; row block i = t + 1 pairs window a with s = a - t
    let s0 = -(p as isize - 1);
    let job = |range: std::ops::Range<usize>, dst: &mut [f64]| {
        let mut sweep = KernelSweep::new(slab, p);
        let first = range.start;
        for b in range {
            let col = &mut dst[(b - first) * rows..(b - first + 1) * rows];
            sweep.window(b, s0, nb + p - 1, |t, ks| {
                if t < f {
                    let k = &ks[p - 1 - t..p - 1 - t + nb];
                    for (j, ar) in alpha_rows.iter().enumerate() {
                        col[t * l + j] = dot4(ar, k);
                    }
                }
            });
        }
    };
    split_columns(out.as_mut_slice(), rows, cols, cols / 2, workers, pool, job);
    out
}

/// Kernel paper, eq. (19) with Theorem 10: the dual kernel [Z^T Z + U^T U] over windows
/// 0..nb (the U^T U term only with feedthrough), for all pairs by [`KernelSweep`] (the
/// batched form of `lpvid::kernel::dual_kernel`). The columns are split over two threads
/// when the sweep is large enough to gain ([`sweep_workers`]).
pub fn dual_kernel_matrix(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
) -> DMatrix<f64> {
    let work = (nb * nb / 2 * p) as f64;
    dual_kernel_matrix_with(slab, p, nb, feedthrough, sweep_workers(work))
}

/// [`dual_kernel_matrix`] on `workers` threads (1 or 2; the result does not depend on it).
pub fn dual_kernel_matrix_with(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
    workers: usize,
) -> DMatrix<f64> {
    kernel_matrix(slab, p, nb, feedthrough, workers, true)
}

/// [`dual_kernel_matrix_with`] with the second half on a scoped thread of its own instead
/// of the pool, as before (the same bits; `benches/kernel.rs` compares the two).
#[doc(hidden)]
pub fn dual_kernel_matrix_scoped(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
    workers: usize,
) -> DMatrix<f64> {
    kernel_matrix(slab, p, nb, feedthrough, workers, false)
}

fn kernel_matrix(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
    workers: usize,
    pool: bool,
) -> DMatrix<f64> {
    let mut g = kernel_lower(slab, p, nb, feedthrough, workers, pool);
    for b in 0..nb {
        for a in 0..b {
            g[(a, b)] = g[(b, a)];
        }
    }
    g
}

/// The lower triangle of [`dual_kernel_matrix`] (the strict upper one zero), all a
/// Tikhonov ridge step needs ([`crate::linalg::Tridiagonal::from_lower`]). Column b is the
/// sweep around window b over the starts s >= b: entry (s, b) has the same bits as entry
/// (b, s) of the sweep over s <= b (the sample Gram matrices are symmetric to the bit and
/// Theorem 10 sums in the same order), so the full matrix is this one mirrored.
pub(crate) fn dual_kernel_lower(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
) -> DMatrix<f64> {
    let work = (nb * nb / 2 * p) as f64;
    kernel_lower(slab, p, nb, feedthrough, sweep_workers(work), true)
}

fn kernel_lower(
    slab: &Slab<'_, f64>,
    p: usize,
    nb: usize,
    feedthrough: bool,
    workers: usize,
    pool: bool,
) -> DMatrix<f64> {
    let mut g = DMatrix::<f64>::zeros(nb, nb);
    // column b holds nb - b entries: the first nb (1 - 1/sqrt(2)) columns are half the work
    let cut = (nb as f64 * (1.0 - std::f64::consts::FRAC_1_SQRT_2)).round() as usize;
    let job = |range: std::ops::Range<usize>, dst: &mut [f64]| {
        let mut sweep = KernelSweep::new(slab, p);
        let first = range.start;
        for b in range {
            let col = &mut dst[(b - first) * nb..(b - first + 1) * nb];
            sweep.window(b, b as isize, nb - b, |t, ks| {
                if t == 0 {
                    col[b..].copy_from_slice(ks);
                }
            });
            if feedthrough {
                let ub = slab.u(b + p);
                for (a, v) in col.iter_mut().enumerate().skip(b) {
                    *v += lpvid::real::dot(slab.u(a + p), ub);
                }
            }
        }
    };
    split_columns(g.as_mut_slice(), nb, nb, cut, workers, pool, job);
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use lpvid::kernel::shifted_kernel;

    /// Both sweeps give the same matrices on one thread and on two, on the pool or on a
    /// scoped thread (each column is computed by the same code whichever thread runs it).
    #[test]
    fn sweeps_on_two_threads_equal_one() {
        let (r, l, s, p) = (1usize, 2usize, 1usize, 3usize);
        let dims = PbsidDims::new(r, l, s, p).unwrap();
        let n = 41;
        let rows = crate::kernel_sweep::tests::record(r, l, dims.m(), n);
        let slab = Slab::new(&rows, r, l, dims.m()).unwrap();
        let nb = n - p;
        for ft in [false, true] {
            let one = dual_kernel_matrix_with(&slab, p, nb, ft, 1);
            let two = dual_kernel_matrix_with(&slab, p, nb, ft, 2);
            assert_eq!(one, two);
            assert_eq!(one, dual_kernel_matrix_scoped(&slab, p, nb, ft, 2));
            // the lower triangle alone, to the bit; the full matrix symmetric
            let lower = dual_kernel_lower(&slab, p, nb, ft);
            assert_eq!(lower.lower_triangle(), one.lower_triangle());
            assert_eq!(
                lower.upper_triangle(),
                DMatrix::from_diagonal(&one.diagonal())
            );
            assert_eq!(one, one.transpose());
            assert!(one.iter().any(|v| *v != 0.0));
        }
        let alpha = DMatrix::from_fn(l, nb, |j, a| ((j * nb + a) as f64 * 0.37).cos());
        let one = dual_gamma_kz_matrix_with(&dims, p, &slab, &alpha, nb + 1, 1);
        let two = dual_gamma_kz_matrix_with(&dims, p, &slab, &alpha, nb + 1, 2);
        assert_eq!(one, two);
        let base = dual_gamma_kz_matrix_scoped(&dims, p, &slab, &alpha, nb + 1, 2);
        assert_eq!(one, base);
        assert_eq!(sweep_workers(0.0), 1);
    }

    /// Eq. (25) by the batched sweep equals alpha times the core's per-entry
    /// `shifted_kernel`, row block by row block, including the successor window N - p.
    #[test]
    fn dual_gamma_kz_equals_core_shifted_kernel() {
        let (r, l, s, p) = (1usize, 2usize, 1usize, 3usize);
        let dims = PbsidDims::new(r, l, s, p).unwrap();
        let m = dims.m();
        let n = 19;
        let rows = crate::kernel_sweep::tests::record(r, l, m, n);
        let slab = Slab::new(&rows, r, l, m).unwrap();
        let nb = n - p;
        let alpha = DMatrix::from_fn(l, nb, |j, a| ((j * nb + a) as f64 * 0.37).cos());
        for f in [1, 2, p] {
            let batched = dual_gamma_kz_matrix(&dims, f, &slab, &alpha, nb + 1);
            for b in 0..=nb {
                for i in 1..=f {
                    for j in 0..l {
                        let e: f64 = (0..nb)
                            .map(|a| alpha[(j, a)] * shifted_kernel(&slab, a, &slab, b, i, p))
                            .sum();
                        let got = batched[((i - 1) * l + j, b)];
                        assert!(
                            (e - got).abs() <= 1e-12 * (1.0 + e.abs()),
                            "f {f} block {i} output {j} window {b}: {e} vs {got}"
                        );
                    }
                }
            }
        }
    }
}
