//! Dense linear algebra the host needs beyond nalgebra's basics: a fast symmetric
//! eigendecomposition (faer, blocked and vectorised — nalgebra's is an order of magnitude
//! slower at the sizes of problem (13)), pseudo-inverse least squares and helpers. No paper
//! equation lives here: these are the numerical tools the equations of [`crate::pbsid`],
//! [`crate::observer`] and [`crate::diagnose`] are solved with.

use nalgebra::{DMatrix, DVector};

/// Why a dense linear-algebra step failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LinalgError {
    /// faer's symmetric eigendecomposition failed (e.g. it did not converge); faer's own
    /// reason in words.
    #[error("symmetric eigendecomposition failed: {0}")]
    Eigen(String),
    /// The implicit QL iteration of [`Tridiagonal::eigen_projection`] did not converge.
    #[error("tridiagonal QL did not converge")]
    TridiagonalQl,
}

/// Eigendecomposition of a symmetric matrix: eigenvalues in DEScending order and the
/// matching orthonormal eigenvectors as columns.
pub fn sym_eig(a: &DMatrix<f64>) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
    let n = a.nrows();
    let m = faer::Mat::<f64>::from_fn(n, n, |i, j| 0.5 * (a[(i, j)] + a[(j, i)]));
    faer_evd_descending(n, |s, u, par, stack| {
        faer::linalg::evd::self_adjoint_evd(m.as_ref(), s, Some(u), par, stack, Default::default())
    })
}

/// Runs one of faer's symmetric eigendecomposition drivers of dimension `n` (`evd`: given
/// the eigenvalue and eigenvector storage, the parallelism and the workspace) and returns
/// its result in descending order. faer's `self_adjoint_eigen` asks the global parallelism,
/// which starts the thread pool even for a 4 x 4: the drivers get that of [`par_for`].
fn faer_evd_descending(
    n: usize,
    evd: impl FnOnce(
        faer::diag::DiagMut<'_, f64>,
        faer::MatMut<'_, f64>,
        faer::Par,
        &mut faer::dyn_stack::MemStack,
    ) -> Result<(), faer::linalg::evd::EvdError>,
) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::evd::{self_adjoint_evd_scratch, ComputeEigenvectors};
    if n == 0 {
        return Ok((Vec::new(), DMatrix::zeros(0, 0)));
    }
    let par = par_for(n);
    let mut u = faer::Mat::<f64>::zeros(n, n);
    let mut s = faer::diag::Diag::<f64>::zeros(n);
    // the dense driver's workspace (it covers the tridiagonal one's too)
    let scratch =
        self_adjoint_evd_scratch::<f64>(n, ComputeEigenvectors::Yes, par, Default::default());
    evd(
        s.as_mut(),
        u.as_mut(),
        par,
        MemStack::new(&mut MemBuffer::new(scratch)),
    )
    .map_err(|e| LinalgError::Eigen(format!("{e:?}")))?;
    let vals: Vec<f64> = (0..n).rev().map(|i| s[i]).collect();
    let vecs = DMatrix::from_fn(n, n, |i, j| u[(i, n - 1 - j)]);
    Ok((vals, vecs))
}

/// Minimum-norm least squares X = B A^+ for the row-regression X A = B given the normal
/// equations: `gram` = A A^T (symmetric) and `cross` = B A^T. Eigenvalues below
/// `rel_tol * max` are treated as zero. Returns (X, numerical rank).
pub fn min_norm_from_normal(
    gram: &DMatrix<f64>,
    cross: &DMatrix<f64>,
    rel_tol: f64,
) -> Result<(DMatrix<f64>, usize), LinalgError> {
    let (vals, vecs) = sym_eig(gram)?;
    let vmax = vals.first().copied().unwrap_or(0.0).max(0.0);
    let tol = vmax * rel_tol;
    let proj = cross * &vecs; // rows x k
    let mut scaled = proj.clone();
    let mut rank = 0;
    for (j, &v) in vals.iter().enumerate() {
        if v > tol && v > 0.0 {
            rank += 1;
            scaled.column_mut(j).scale_mut(1.0 / v);
        } else {
            scaled.column_mut(j).fill(0.0);
        }
    }
    Ok((scaled * vecs.transpose(), rank))
}

/// Below this dimension the dense reductions run on the calling thread: a thread pool's
/// spin-up and hand-offs cost more than they gain on problems of a few milliseconds
/// (`benches/process.rs`, `tridiagonal_seq_vs_par`, 2026-11-26: at 422 rows 8.7 ms on one
/// thread against 11.5 ms on the pool; at 995 rows the pool wins, 94 -> 72 ms).
pub const PAR_MIN_DIM: usize = 600;

/// faer's parallelism for a dense reduction of dimension `n`: the global one (the thread
/// pool) from [`PAR_MIN_DIM`] on, sequential below.
pub fn par_for(n: usize) -> faer::Par {
    if n >= PAR_MIN_DIM {
        faer::get_global_parallelism()
    } else {
        faer::Par::Seq
    }
}

/// Run, on a short-lived thread of its own, the one-time set-up of faer's large matrix
/// product: its first call in a process reads the cache sizes from about a hundred sysfs
/// files (private-gemm-x86's `cache_info`, 0.6-0.8 ms of wall time, which callgrind does not
/// count). A command that will reduce or multiply matrices calls this first, so the reads
/// overlap its CSV parsing instead of stalling the first product; the result is the same
/// (the set-up is behind a `OnceLock`: a product that comes first waits for it, as before).
pub fn prefetch_matmul_setup() {
    let _detached = std::thread::Builder::new()
        .name("matmul-setup".into())
        .spawn(|| {
            // 17^3 > faer's small-product threshold (16^3): the large-product path
            let a = faer::Mat::<f64>::zeros(17, 17);
            let mut c = faer::Mat::<f64>::zeros(17, 17);
            faer::linalg::matmul::matmul(
                c.as_mut(),
                faer::Accum::Replace,
                a.as_ref(),
                a.as_ref(),
                1.0,
                faer::Par::Seq,
            );
        });
}

/// Vectors per batch of a host-side Gram update: enough for the block product to run at
/// matrix-multiply speed, few enough that the batch stays in cache.
pub const GRAM_BATCH: usize = 256;

/// The host's Gram accumulation, one batch of vectors at a time (issue 16, the flop limit).
/// A batch's sum of outer products is a syrk: it is computed by faer's triangular product
/// (packed panels, SIMD micro-kernels: what a BLAS does; 4-10x the core's portable register
/// tiles on this machine, `benches/gram_syrk.rs`) and added with the core's
/// [`lpvid::Gram::add_packed`], so counting, compensation and merge semantics stay the
/// core's. Accumulators with forgetting (each vector weighted differently) take the core's
/// own batch update. The scratch (a dense product and a packed block) is kept between
/// batches.
pub struct GramBatch {
    len: usize,
    dense: faer::Mat<f64>,
    packed: Vec<f64>,
}

impl GramBatch {
    /// Scratch for vectors of length `len`.
    pub fn new(len: usize) -> Self {
        Self {
            len,
            dense: faer::Mat::zeros(len, len),
            packed: vec![0.0; lpvid::packed_len(len)],
        }
    }

    /// Add the outer products of the `n` vectors stored row-major in `rows` (n x len) to
    /// `gram`, as [`lpvid::Gram::update_batch`] does: the same checks and errors, and on
    /// error nothing changes.
    pub fn add<S: AsRef<[f64]> + AsMut<[f64]>>(
        &mut self,
        gram: &mut lpvid::Gram<f64, S>,
        rows: &[f64],
        n: usize,
    ) -> Result<(), lpvid::Error> {
        let len = self.len;
        if gram.dim() != len || gram.forgetting() != 1.0 {
            return gram.update_batch(rows, n);
        }
        if n.checked_mul(len) != Some(rows.len()) {
            return gram.check_batch(rows, n);
        }
        // the rows are the columns of a column-major len x n matrix W: the block is W W^T
        let w = faer::MatRef::from_column_major_slice(rows, len, n);
        faer::linalg::matmul::triangular::matmul(
            self.dense.as_mut(),
            faer::linalg::matmul::triangular::BlockStructure::TriangularLower,
            faer::Accum::Replace,
            w,
            faer::linalg::matmul::triangular::BlockStructure::Rectangular,
            w.transpose(),
            faer::linalg::matmul::triangular::BlockStructure::Rectangular,
            1.0,
            faer::Par::Seq,
        );
        // row i of the packed upper triangle is column i of the lower one from the diagonal
        let mut off = 0;
        for i in 0..len {
            let col = self.dense.col_as_slice(i);
            self.packed[off..off + len - i].copy_from_slice(&col[i..]);
            off += len - i;
        }
        // a non-finite value or an overflowing product shows in the block (its diagonal
        // holds the sums of squares); the row-wise check then names it
        gram.add_packed(&self.packed, n as u64)
            .or_else(|e| gram.check_batch(rows, n).and(Err(e)))
    }
}

/// A'A of a column-major `a` with many more rows than columns (the normal equations' J'J
/// of the output-error refinement, whose Jacobian has a row per residual): faer's
/// triangular product of the lower half, mirrored. Half the multiply-adds of the dense
/// product `a.transpose() * a`, and no transposed copy of `a` (benches/gram_syrk.rs,
/// `normal_equations`).
pub fn gram_of_columns(a: &DMatrix<f64>) -> DMatrix<f64> {
    use faer::linalg::matmul::triangular::{matmul, BlockStructure};
    let (rows, n) = a.shape();
    let mut lower = faer::Mat::<f64>::zeros(n, n);
    let v = faer::MatRef::from_column_major_slice(a.as_slice(), rows, n);
    matmul(
        lower.as_mut(),
        BlockStructure::TriangularLower,
        faer::Accum::Replace,
        v.transpose(),
        BlockStructure::Rectangular,
        v,
        BlockStructure::Rectangular,
        1.0,
        faer::Par::Seq,
    );
    DMatrix::from_fn(n, n, |i, j| lower[(i.max(j), i.min(j))])
}

/// The core's Gram of `count` vectors of length `len`, each written by `row(k, dst)` into a
/// batch of [`GRAM_BATCH`] and accumulated by [`GramBatch`].
pub fn gram_from_rows(
    len: usize,
    count: usize,
    mut row: impl FnMut(usize, &mut [f64]),
) -> Result<lpvid::Gram<f64, Vec<f64>>, lpvid::Error> {
    let mut gram = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)])?;
    add_rows(&mut gram, 0..count, &mut row)?;
    Ok(gram)
}

/// Add the vectors `range` (each written by `row(k, dst)`) into `gram`, in batches of
/// [`GRAM_BATCH`] through [`GramBatch`]: the one batching loop of the host's statistics
/// (the primal regression, the streamed statistics, the diagnosis' residual regressions).
pub fn gram_add_rows<S: AsRef<[f64]> + AsMut<[f64]>>(
    gram: &mut lpvid::Gram<f64, S>,
    range: std::ops::Range<usize>,
    row: &(impl Fn(usize, &mut [f64]) + ?Sized),
) -> Result<(), lpvid::Error> {
    add_rows(gram, range, &mut |k, dst| row(k, dst))
}

/// The loop of [`gram_add_rows`] for any closure.
fn add_rows<S: AsRef<[f64]> + AsMut<[f64]>>(
    gram: &mut lpvid::Gram<f64, S>,
    range: std::ops::Range<usize>,
    row: &mut dyn FnMut(usize, &mut [f64]),
) -> Result<(), lpvid::Error> {
    let len = gram.dim();
    let mut batch = GramBatch::new(len);
    let mut buf = vec![0.0; GRAM_BATCH.min(range.len()) * len];
    let mut k = range.start;
    while k < range.end {
        let nb = GRAM_BATCH.min(range.end - k);
        for b in 0..nb {
            row(k + b, &mut buf[b * len..(b + 1) * len]);
        }
        batch.add(gram, &buf[..nb * len], nb)?;
        k += nb;
    }
    Ok(())
}

/// Multiply-adds (count x len^2 / 2) from which a Gram accumulation is split over two
/// threads: below it the thread's start and the merge cost more than half the work
/// (`benches/spine.rs`, `gram_two_halves`).
pub const SPLIT_MIN_WORK: f64 = 5e7;

/// Whether accumulating `count` vectors of length `len` gains from two threads.
pub fn split_pays(len: usize, count: usize) -> bool {
    let work = count as f64 * (len * len) as f64 / 2.0;
    work >= SPLIT_MIN_WORK && cores() >= 2
}

/// `std::thread::available_parallelism` (1 if unknown), asked once per process: on Linux
/// each call reads the cgroup's CPU quota (three files, 40-60 us of a 3 ms process).
pub fn cores() -> usize {
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// Whether a second thread is likely to get a core of its own now: at least two cores and a
/// one-minute load average (Linux `/proc/loadavg`; elsewhere taken as idle) below the number
/// of cores, the judgement `make -l` makes. Only for work whose result does not depend on
/// the thread it runs on (never for a split of sums, whose rounding would then depend on
/// the load).
pub fn spare_core() -> bool {
    let cores = cores();
    if cores < 2 {
        return false;
    }
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .unwrap_or(0.0);
    load < cores as f64
}

/// Add the vectors `range` into `a` and the second half of them into `b` on a second thread
/// when `split` (the statistics are sums: the caller merges `b` into `a` with the core's
/// merge when done), else all into `a` on this thread.
pub fn gram_add_rows_split<S: AsRef<[f64]> + AsMut<[f64]> + Send>(
    a: &mut lpvid::Gram<f64, S>,
    b: &mut lpvid::Gram<f64, S>,
    range: std::ops::Range<usize>,
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    split: bool,
) -> Result<(), lpvid::Error> {
    if !split || range.len() < 2 * GRAM_BATCH {
        return gram_add_rows(a, range, row);
    }
    let mid = range.start + range.len() / 2;
    let (first, second) = std::thread::scope(|sc| {
        let h = sc.spawn(|| gram_add_rows(b, mid..range.end, row));
        let first = gram_add_rows(a, range.start..mid, row);
        let second = h.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
        (first, second)
    });
    first.and(second)
}

/// [`gram_from_rows`] with the two halves on two threads when [`split_pays`] (`split`
/// false: always one thread), merged with the core's merge.
pub fn gram_from_rows_split(
    len: usize,
    count: usize,
    row: impl Fn(usize, &mut [f64]) + Sync,
    split: bool,
) -> Result<lpvid::Gram<f64, Vec<f64>>, lpvid::Error> {
    let mut a = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)])?;
    let mut b = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)])?;
    let split = split && split_pays(len, count);
    gram_add_rows_split(&mut a, &mut b, 0..count, &row, split)?;
    if split {
        a.merge(&b)?;
    }
    Ok(a)
}

/// Mean and (population) standard deviation of a column.
pub fn mean_std(v: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = v.clone().count() as f64;
    let mean = v.clone().sum::<f64>() / n;
    let var = v.map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// Spectral radius of a square matrix ([`SmallEig`], falling back to nalgebra's Schur
/// decomposition should the QR iteration not converge).
pub fn spectral_radius(a: &DMatrix<f64>) -> f64 {
    let n = a.nrows();
    let mut eig = SmallEig::default();
    let rows = eig.load(n);
    for i in 0..n {
        for j in 0..n {
            rows[i * n + j] = a[(i, j)];
        }
    }
    eig.spectral_radius(n)
        .unwrap_or_else(|| schur_spectral_radius(a))
}

/// Spectral radius by nalgebra's complex Schur decomposition (the reference
/// [`SmallEig`] is checked against).
pub fn schur_spectral_radius(a: &DMatrix<f64>) -> f64 {
    a.clone()
        .complex_eigenvalues()
        .iter()
        .map(|c| c.norm())
        .fold(0.0, f64::max)
}

/// Eigenvalues of small dense matrices without allocation per call: Householder reduction to
/// upper Hessenberg form, then the Francis double-shift QR iteration on it (eigenvalues
/// only, EISPACK `hqr` as in Numerical Recipes section 11.6). The frozen-scheduling
/// stability checks solve thousands of these for n of a few states; nalgebra's Schur
/// decomposition allocates and forms the Schur vectors each time, which made it most of a
/// small fit's run time.
#[derive(Debug, Default, Clone)]
pub struct SmallEig {
    /// The matrix, row-major, overwritten by its Hessenberg form and the QR iteration.
    h: Vec<f64>,
    /// Householder vector workspace.
    v: Vec<f64>,
}

impl SmallEig {
    /// The row-major n x n buffer to write the matrix into (contents unspecified).
    pub fn load(&mut self, n: usize) -> &mut [f64] {
        self.h.resize(n * n, 0.0);
        self.v.resize(n, 0.0);
        &mut self.h[..n * n]
    }

    /// Spectral radius of the matrix last written by [`SmallEig::load`] (destroyed); `None`
    /// when the QR iteration did not converge in 30 iterations per eigenvalue or the matrix
    /// holds a non-finite entry.
    pub fn spectral_radius(&mut self, n: usize) -> Option<f64> {
        let mut rho: f64 = 0.0;
        self.eigenvalues(n, |re, im| rho = rho.max(re.hypot(im)))?;
        Some(rho)
    }

    /// Reduce to Hessenberg form and run the QR iteration, calling `each(re, im)` once per
    /// eigenvalue; `None` as in [`SmallEig::spectral_radius`].
    fn eigenvalues(&mut self, n: usize, mut each: impl FnMut(f64, f64)) -> Option<()> {
        let h = &mut self.h[..n * n];
        if h.iter().any(|x| !x.is_finite()) {
            return None;
        }
        hessenberg(h, n, &mut self.v[..n]);
        hqr(h, n, &mut each)
    }
}

/// Householder reduction of the row-major n x n `a` to upper Hessenberg form in place
/// (similarity, so the eigenvalues are kept); entries below the subdiagonal are zeroed.
fn hessenberg(a: &mut [f64], n: usize, v: &mut [f64]) {
    for k in 0..n.saturating_sub(2) {
        let len = n - k - 1;
        let mut norm2 = 0.0;
        for i in 0..len {
            v[i] = a[(k + 1 + i) * n + k];
            norm2 += v[i] * v[i];
        }
        if norm2 == 0.0 {
            continue;
        }
        let alpha = if v[0] >= 0.0 {
            -norm2.sqrt()
        } else {
            norm2.sqrt()
        };
        let vv = norm2 - v[0] * v[0] + (v[0] - alpha) * (v[0] - alpha);
        v[0] -= alpha;
        if vv == 0.0 {
            continue;
        }
        // left: rows k+1.. of columns k..
        for j in k..n {
            let mut s = 0.0;
            for i in 0..len {
                s += v[i] * a[(k + 1 + i) * n + j];
            }
            let f = 2.0 * s / vv;
            for i in 0..len {
                a[(k + 1 + i) * n + j] -= f * v[i];
            }
        }
        // right: columns k+1.. of every row
        for i in 0..n {
            let row = &mut a[i * n + k + 1..i * n + n];
            let s: f64 = row.iter().zip(&v[..len]).map(|(x, y)| x * y).sum();
            let f = 2.0 * s / vv;
            for (x, y) in row.iter_mut().zip(&v[..len]) {
                *x -= f * y;
            }
        }
        a[(k + 1) * n + k] = alpha;
        for i in k + 2..n {
            a[i * n + k] = 0.0;
        }
    }
}

/// Eigenvalues of the row-major upper Hessenberg `a` (destroyed) by the Francis double-shift
/// QR iteration (EISPACK `hqr`; Numerical Recipes 2nd ed. section 11.6, kept in its 1-based
/// indexing); `None` after 30 iterations on one eigenvalue.
#[allow(clippy::many_single_char_names)]
fn hqr(a: &mut [f64], n: usize, each: &mut impl FnMut(f64, f64)) -> Option<()> {
    macro_rules! at {
        ($i:expr, $j:expr) => {
            a[($i - 1) * n + ($j - 1)]
        };
    }
    let sign = |a: f64, b: f64| if b >= 0.0 { a.abs() } else { -a.abs() };
    let mut anorm = 0.0;
    for i in 1..=n {
        for j in i.saturating_sub(1).max(1)..=n {
            anorm += at!(i, j).abs();
        }
    }
    let mut nn = n;
    let mut t = 0.0;
    while nn >= 1 {
        let mut its = 0;
        loop {
            let mut l = nn;
            while l >= 2 {
                let mut s = at!(l - 1, l - 1).abs() + at!(l, l).abs();
                if s == 0.0 {
                    s = anorm;
                }
                if at!(l, l - 1).abs() + s == s {
                    at!(l, l - 1) = 0.0;
                    break;
                }
                l -= 1;
            }
            let mut x = at!(nn, nn);
            if l == nn {
                each(x + t, 0.0);
                nn -= 1;
            } else {
                let mut y = at!(nn - 1, nn - 1);
                let mut w = at!(nn, nn - 1) * at!(nn - 1, nn);
                if l == nn - 1 {
                    let p = 0.5 * (y - x);
                    let q = p * p + w;
                    let mut z = q.abs().sqrt();
                    x += t;
                    if q >= 0.0 {
                        z = p + sign(z, p);
                        each(x + z, 0.0);
                        each(if z != 0.0 { x - w / z } else { x + z }, 0.0);
                    } else {
                        each(x + p, z);
                        each(x + p, -z);
                    }
                    nn -= 2;
                } else {
                    if its == 30 {
                        return None;
                    }
                    if its == 10 || its == 20 {
                        t += x;
                        for i in 1..=nn {
                            at!(i, i) -= x;
                        }
                        let s = at!(nn, nn - 1).abs() + at!(nn - 1, nn - 2).abs();
                        x = 0.75 * s;
                        y = x;
                        w = -0.4375 * s * s;
                    }
                    its += 1;
                    let mut m = nn - 2;
                    let (mut p, mut q, mut r, mut z);
                    loop {
                        z = at!(m, m);
                        let r0 = x - z;
                        let s0 = y - z;
                        p = (r0 * s0 - w) / at!(m + 1, m) + at!(m, m + 1);
                        q = at!(m + 1, m + 1) - z - r0 - s0;
                        r = at!(m + 2, m + 1);
                        let s = p.abs() + q.abs() + r.abs();
                        p /= s;
                        q /= s;
                        r /= s;
                        if m == l {
                            break;
                        }
                        let u = at!(m, m - 1).abs() * (q.abs() + r.abs());
                        let v =
                            p.abs() * (at!(m - 1, m - 1).abs() + z.abs() + at!(m + 1, m + 1).abs());
                        if u + v == v {
                            break;
                        }
                        m -= 1;
                    }
                    for i in m + 2..=nn {
                        at!(i, i - 2) = 0.0;
                        if i != m + 2 {
                            at!(i, i - 3) = 0.0;
                        }
                    }
                    let mut k = m;
                    while k < nn {
                        if k != m {
                            p = at!(k, k - 1);
                            q = at!(k + 1, k - 1);
                            r = 0.0;
                            if k != nn - 1 {
                                r = at!(k + 2, k - 1);
                            }
                            x = p.abs() + q.abs() + r.abs();
                            if x != 0.0 {
                                p /= x;
                                q /= x;
                                r /= x;
                            }
                        }
                        let s = sign((p * p + q * q + r * r).sqrt(), p);
                        if s != 0.0 {
                            if k == m {
                                if l != m {
                                    at!(k, k - 1) = -at!(k, k - 1);
                                }
                            } else {
                                at!(k, k - 1) = -s * x;
                            }
                            p += s;
                            x = p / s;
                            y = q / s;
                            z = r / s;
                            q /= p;
                            r /= p;
                            for j in k..=nn {
                                p = at!(k, j) + q * at!(k + 1, j);
                                if k != nn - 1 {
                                    p += r * at!(k + 2, j);
                                    at!(k + 2, j) -= p * z;
                                }
                                at!(k + 1, j) -= p * y;
                                at!(k, j) -= p * x;
                            }
                            let mmin = if nn < k + 3 { nn } else { k + 3 };
                            for i in l..=mmin {
                                p = x * at!(i, k) + y * at!(i, k + 1);
                                if k != nn - 1 {
                                    p += z * at!(i, k + 2);
                                    at!(i, k + 2) -= p * r;
                                }
                                at!(i, k + 1) -= p * q;
                                at!(i, k) -= p;
                            }
                        }
                        k += 1;
                    }
                }
            }
            if nn < 2 || l >= nn - 1 {
                break;
            }
        }
    }
    Some(())
}

/// Column vector from a slice.
pub fn col(v: &[f64]) -> DVector<f64> {
    DVector::from_column_slice(v)
}

/// A pivot usable in an LDL^T factorisation of a positive definite matrix.
fn positive_finite(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

/// Up to this dimension a tridiagonal reduction keeps its Householder reflectors one by one
/// ([`tridiagonal_block_size`]).
pub const TRIDIAG_UNBLOCKED_MAX: usize = 128;

/// Block size of the Householder factors kept by [`Tridiagonal`]: faer's recommendation,
/// except up to [`TRIDIAG_UNBLOCKED_MAX`] rows, where faer's block is only 8 reflectors and
/// [`Tridiagonal`] applies them to a few right-hand sides: one by one (block size 1) there is
/// no triangular factor to build, and no call reaches faer's large matrix product, whose
/// first use in a process reads the cache sizes from about a hundred sysfs files (0.6-1 ms,
/// most of the wait of a B2 fit; [`prefetch_matmul_setup`]). The same reflectors either way.
pub fn tridiagonal_block_size(n: usize) -> usize {
    if n <= TRIDIAG_UNBLOCKED_MAX {
        1
    } else {
        faer::linalg::qr::no_pivoting::factor::recommended_block_size::<f64>(n, n)
    }
}

/// A symmetric matrix reduced once to tridiagonal form, A = Q T Q^T (blocked Householder,
/// faer). What a ridge regression with a parameter chosen by GCV needs then costs O(n^2):
/// the eigenvalues with the eigen-coordinates V^T Q^T B of a few right-hand sides (implicit
/// QL on T with the rotations applied to those columns instead of accumulating the
/// eigenvectors, the O(n^3) part of a full eigendecomposition), and the solution
/// (A + lam I)^{-1} B by a tridiagonal solve.
pub struct Tridiagonal {
    n: usize,
    /// Householder vectors below the subdiagonal (faer's in-place layout), column-major
    /// n x n without padding.
    reflectors: Vec<f64>,
    /// Block Householder factors.
    factors: faer::Mat<f64>,
    diag: Vec<f64>,
    sub: Vec<f64>,
}

impl Tridiagonal {
    /// Reduce the symmetric matrix `a` (its lower triangle is read); on the thread pool
    /// only from [`PAR_MIN_DIM`] rows on ([`par_for`]).
    pub fn new(a: &DMatrix<f64>) -> Tridiagonal {
        Self::new_with(a, par_for(a.nrows()))
    }

    /// As [`Tridiagonal::new`] with the parallelism given (the benches compare both).
    pub fn new_with(a: &DMatrix<f64>, par: faer::Par) -> Tridiagonal {
        Self::new_blocked(a, par, tridiagonal_block_size(a.nrows()))
    }

    /// As [`Tridiagonal::new_with`] keeping the reflectors in blocks of `bs` (at least 1;
    /// the benches compare faer's recommendation with [`tridiagonal_block_size`]).
    pub fn new_blocked(a: &DMatrix<f64>, par: faer::Par, bs: usize) -> Tridiagonal {
        let n = a.nrows();
        // the lower triangle, column by column (the reduction reads no other entry)
        let mut m = vec![0.0; n * n];
        for j in 0..n {
            m[j * n + j..(j + 1) * n].copy_from_slice(&a.column(j).as_slice()[j..]);
        }
        Self::reduce(m, n, par, bs)
    }

    /// As [`Tridiagonal::new`], reducing `a` in its own storage: only its lower triangle is
    /// read (the strict upper one may hold anything). Saves the copy of an n x n matrix and
    /// its first-touch page faults (8 MB at n = 995) when the caller has no further use for
    /// `a`, as the kernel form's ridge step.
    pub fn from_lower(a: DMatrix<f64>) -> Tridiagonal {
        let n = a.nrows();
        assert_eq!(a.ncols(), n);
        let m = a.data.into();
        Self::reduce(m, n, par_for(n), tridiagonal_block_size(n))
    }

    /// faer's reduction of the column-major n x n `m` (lower triangle) in place, the
    /// reflectors kept in blocks of `bs`.
    fn reduce(mut m: Vec<f64>, n: usize, par: faer::Par, bs: usize) -> Tridiagonal {
        use faer::dyn_stack::{MemBuffer, MemStack};
        use faer::linalg::evd::tridiag;
        let mut h = faer::Mat::<f64>::zeros(bs.max(1), n.saturating_sub(1));
        if n > 0 {
            let mut buf = MemBuffer::new(tridiag::tridiag_in_place_scratch::<f64>(
                n,
                par,
                Default::default(),
            ));
            tridiag::tridiag_in_place(
                faer::MatMut::from_column_major_slice_mut(&mut m, n, n),
                h.as_mut(),
                par,
                MemStack::new(&mut buf),
                Default::default(),
            );
        }
        let diag = (0..n).map(|i| m[i * n + i]).collect();
        let sub = (0..n.saturating_sub(1)).map(|i| m[i * n + i + 1]).collect();
        Tridiagonal {
            n,
            reflectors: m,
            factors: h,
            diag,
            sub,
        }
    }

    /// Dimension.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Q^T B (`transpose`) or Q B.
    fn apply(&self, b: &DMatrix<f64>, transpose: bool) -> DMatrix<f64> {
        use faer::dyn_stack::{MemBuffer, MemStack};
        use faer::linalg::householder as hh;
        let (n, k) = (self.n, b.ncols());
        assert_eq!(b.nrows(), n);
        let mut x = faer::Mat::<f64>::from_fn(n, k, |i, j| b[(i, j)]);
        if n > 1 {
            // a few right-hand sides (the ridge targets: 2 columns on B1) are O(n^2 k) work,
            // less than the pool's hand-offs: 1.1-1.3 -> 0.5-0.6 ms each way at n = 995
            let par = if k <= 8 { faer::Par::Seq } else { par_for(n) };
            let bs = self.factors.nrows();
            let ess = faer::MatRef::from_column_major_slice(&self.reflectors, n, n).submatrix(
                1,
                0,
                n - 1,
                n - 1,
            );
            let rows = x.as_mut().subrows_mut(1, n - 1);
            let apply = if transpose {
                hh::apply_block_householder_sequence_transpose_on_the_left_in_place_with_conj::<f64>
            } else {
                hh::apply_block_householder_sequence_on_the_left_in_place_with_conj::<f64>
            };
            let mut buf =
                MemBuffer::new(faer::dyn_stack::StackReq::any_of(&[
                    hh::apply_block_householder_sequence_transpose_on_the_left_in_place_scratch::<
                        f64,
                    >(n - 1, bs, k),
                    hh::apply_block_householder_sequence_on_the_left_in_place_scratch::<f64>(
                        n - 1,
                        bs,
                        k,
                    ),
                ]));
            apply(
                ess,
                self.factors.as_ref(),
                faer::Conj::No,
                rows,
                par,
                MemStack::new(&mut buf),
            );
        }
        DMatrix::from_fn(n, k, |i, j| x[(i, j)])
    }

    /// Q^T B: right-hand sides in the tridiagonal coordinates.
    pub fn to_tridiagonal(&self, b: &DMatrix<f64>) -> DMatrix<f64> {
        self.apply(b, true)
    }

    /// Q X: back from the tridiagonal coordinates.
    pub fn from_tridiagonal(&self, x: &DMatrix<f64>) -> DMatrix<f64> {
        self.apply(x, false)
    }

    /// Eigenvalues of T (= of A) in descending order and V^T c for `c` given in the
    /// tridiagonal coordinates (row i: the coordinates along eigenvector i), by implicit QL
    /// with Wilkinson shifts whose rotations are applied to the columns of c only.
    pub fn eigen_projection(
        &self,
        c: &DMatrix<f64>,
    ) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
        let n = self.n;
        let k = c.ncols();
        assert_eq!(c.nrows(), n);
        let mut d = self.diag.clone();
        let mut e = self.sub.clone();
        e.push(0.0);
        // off-diagonals below this are zero (absolute accuracy: keeps a cluster of zero
        // eigenvalues of a rank-deficient Gram from stalling the relative test)
        let anorm = d.iter().chain(&e).fold(0.0f64, |acc, v| acc.max(v.abs()));
        let tiny = anorm * f64::EPSILON * 1e-6;
        // w[i * k + j]: coordinate i of right-hand side j
        let mut w: Vec<f64> = (0..n)
            .flat_map(|i| (0..k).map(move |j| c[(i, j)]))
            .collect();
        // LAPACK's budget (dsteqr: 30 iterations per eigenvalue in total, not each): a
        // cluster of eigenvalues at rounding level, as the Gram of lagged sine and cosine
        // channels has, can take more than 60 sweeps on one of them and few on the others
        let max_sweeps = 30 * n.max(2);
        let mut sweeps = 0;
        for l in 0..n {
            loop {
                let mut m = l;
                while m + 1 < n {
                    let dd = d[m].abs() + d[m + 1].abs();
                    if e[m].abs() <= f64::EPSILON * dd + tiny {
                        break;
                    }
                    m += 1;
                }
                if m == l {
                    break;
                }
                sweeps += 1;
                if sweeps > max_sweeps {
                    return Err(LinalgError::TridiagonalQl);
                }
                let mut g = (d[l + 1] - d[l]) / (2.0 * e[l]);
                let mut r = g.hypot(1.0);
                g = d[m] - d[l] + e[l] / (g + r.copysign(g));
                let (mut s, mut cc, mut p) = (1.0f64, 1.0f64, 0.0f64);
                let mut i = m;
                let mut deflated = false;
                while i > l {
                    i -= 1;
                    let f = s * e[i];
                    let b = cc * e[i];
                    r = (f * f + g * g).sqrt();
                    if !r.is_finite() {
                        r = f.hypot(g);
                    }
                    e[i + 1] = r;
                    if r == 0.0 {
                        d[i + 1] -= p;
                        e[m] = 0.0;
                        deflated = true;
                        break;
                    }
                    s = f / r;
                    cc = g / r;
                    g = d[i + 1] - p;
                    r = (d[i] - g) * s + 2.0 * cc * b;
                    p = s * r;
                    d[i + 1] = g + p;
                    g = cc * r - b;
                    let (lo, hi) = w.split_at_mut((i + 1) * k);
                    for (a, z) in lo[i * k..].iter_mut().zip(hi[..k].iter_mut()) {
                        let f = *z;
                        *z = s * *a + cc * f;
                        *a = cc * *a - s * f;
                    }
                }
                if deflated {
                    continue;
                }
                d[l] -= p;
                e[l] = g;
                e[m] = 0.0;
            }
        }
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| d[b].total_cmp(&d[a]));
        let vals = order.iter().map(|&i| d[i]).collect();
        let proj = DMatrix::from_fn(n, k, |row, j| w[order[row] * k + j]);
        Ok((vals, proj))
    }

    /// Eigenvalues of T (= of A) in descending order and the matching eigenvectors of T as
    /// columns, in the tridiagonal coordinates (faer's divide and conquer on T). What a
    /// cut-off or a ridge too small for [`Tridiagonal::solve_shifted`] needs, without
    /// reducing A again or turning all n eigenvectors back into A's coordinates: a solution
    /// of a few columns goes back by [`Tridiagonal::from_tridiagonal`].
    pub fn eigen(&self) -> Result<(Vec<f64>, DMatrix<f64>), LinalgError> {
        let mut sub = self.sub.clone();
        sub.push(0.0);
        faer_evd_descending(self.n, |s, u, par, stack| {
            faer::linalg::evd::tridiagonal_self_adjoint_evd(
                faer::ColRef::from_slice(&self.diag).as_diagonal(),
                faer::ColRef::from_slice(&sub).as_diagonal(),
                s,
                Some(u),
                par,
                stack,
                Default::default(),
            )
        })
    }

    /// T + lam I = L D L^T (unit lower bidiagonal L), or None when it is not numerically
    /// positive definite.
    fn shifted_ldl(&self, lam: f64) -> Option<ShiftedLdl> {
        let n = self.n;
        let mut d = vec![0.0; n];
        let mut l = vec![0.0; n];
        for i in 0..n {
            if i > 0 {
                l[i] = self.sub[i - 1] / d[i - 1];
            }
            d[i] = self.diag[i] + lam - if i > 0 { l[i] * self.sub[i - 1] } else { 0.0 };
            if !positive_finite(d[i]) {
                return None;
            }
        }
        Some(ShiftedLdl { d, l })
    }

    /// ||(T + lam I)^{-1} c||_F^2 and tr((T + lam I)^{-1}) in O(n) per column, or None when
    /// T + lam I is not numerically positive definite. These are the residual and the
    /// missing degrees of freedom of a dual ridge problem.
    ///
    /// One forward pass (the LDL^T recurrence, one division per row, and L^{-1} c for all
    /// columns) and one backward pass (D^{-1} then L^{-T}, with the inverse's diagonal
    /// X_ii = 1/d_i + l_{i+1}^2 X_{i+1,i+1}): GCV evaluates this about a hundred times per
    /// fit (B1 p = 5, n = 995: 4.2 ms in all as separate factor, solve and trace passes).
    pub fn shifted_norm_trace(&self, lam: f64, c: &DMatrix<f64>) -> Option<(f64, f64)> {
        let (n, k) = (self.n, c.ncols());
        assert_eq!(c.nrows(), n);
        let mut inv = vec![0.0; n];
        let mut mult = vec![0.0; n];
        // row-major: z[i * k + j], row i of L^{-1} c
        let mut z = vec![0.0; n * k];
        let mut prev_inv = 0.0;
        for i in 0..n {
            let (li, di) = if i == 0 {
                (0.0, self.diag[0] + lam)
            } else {
                let s = self.sub[i - 1];
                let li = s * prev_inv;
                (li, self.diag[i] + lam - li * s)
            };
            if !positive_finite(di) {
                return None;
            }
            prev_inv = 1.0 / di;
            inv[i] = prev_inv;
            mult[i] = li;
            for j in 0..k {
                let before = if i > 0 { z[(i - 1) * k + j] } else { 0.0 };
                z[i * k + j] = c[(i, j)] - li * before;
            }
        }
        let (mut norm, mut trace, mut xii) = (0.0, 0.0, 0.0);
        let mut next = vec![0.0; k];
        for i in (0..n).rev() {
            let ln = if i + 1 < n { mult[i + 1] } else { 0.0 };
            xii = inv[i] + ln * ln * xii;
            trace += xii;
            for (j, xn) in next.iter_mut().enumerate() {
                let x = z[i * k + j] * inv[i] - ln * *xn;
                *xn = x;
                norm += x * x;
            }
        }
        Some((norm, trace))
    }

    /// [`Tridiagonal::shifted_norm_trace`] as it was before (factor, then a solve per
    /// column, then the trace: four divisions per row); `benches/spine.rs` compares the two.
    #[doc(hidden)]
    pub fn shifted_norm_trace_passes(&self, lam: f64, c: &DMatrix<f64>) -> Option<(f64, f64)> {
        let ldl = self.shifted_ldl(lam)?;
        let mut norm = 0.0;
        let mut x = vec![0.0; self.n];
        for col in c.column_iter() {
            x.copy_from_slice(col.as_slice());
            ldl.solve_in_place(&mut x);
            norm += x.iter().map(|v| v * v).sum::<f64>();
        }
        Some((norm, ldl.inverse_trace()))
    }

    /// Number of eigenvalues of T below `x` (Sylvester's law of inertia on T - x I).
    fn count_below(&self, x: f64) -> usize {
        let mut count = 0;
        let mut d = 1.0;
        for i in 0..self.n {
            let off = if i > 0 { self.sub[i - 1] } else { 0.0 };
            d = self.diag[i] - x - if i > 0 { off * off / d } else { 0.0 };
            if d == 0.0 {
                d = -f64::EPSILON * (x.abs() + 1.0);
            }
            if d < 0.0 {
                count += 1;
            }
        }
        count
    }

    /// The largest eigenvalue, by bisection on Sturm counts from the Gershgorin interval.
    pub fn largest_eigenvalue(&self) -> f64 {
        let n = self.n;
        if n == 0 {
            return 0.0;
        }
        let radius = |i: usize| {
            let a = if i > 0 { self.sub[i - 1].abs() } else { 0.0 };
            let b = if i + 1 < n { self.sub[i].abs() } else { 0.0 };
            a + b
        };
        let mut hi = (0..n)
            .map(|i| self.diag[i] + radius(i))
            .fold(f64::MIN, f64::max);
        let mut lo = (0..n)
            .map(|i| self.diag[i] - radius(i))
            .fold(f64::MAX, f64::min);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if hi - lo <= 4.0 * f64::EPSILON * (lo.abs().max(hi.abs())) || mid == lo || mid == hi {
                break;
            }
            if self.count_below(mid) == n {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// (T + lam I)^{-1} c for `c` in the tridiagonal coordinates (symmetric LDL^T without
    /// pivoting), or None when T + lam I is not numerically positive definite.
    pub fn solve_shifted(&self, lam: f64, c: &DMatrix<f64>) -> Option<DMatrix<f64>> {
        let ldl = self.shifted_ldl(lam)?;
        let mut x = c.clone();
        for mut col in x.column_iter_mut() {
            ldl.solve_in_place(col.as_mut_slice());
        }
        Some(x)
    }
}

/// LDL^T factors of a shifted symmetric tridiagonal matrix: pivots `d`, multipliers `l`
/// (l[i] below the diagonal in row i; l[0] unused).
struct ShiftedLdl {
    d: Vec<f64>,
    l: Vec<f64>,
}

impl ShiftedLdl {
    /// x <- (L D L^T)^{-1} x.
    fn solve_in_place(&self, x: &mut [f64]) {
        let n = x.len();
        for i in 1..n {
            x[i] -= self.l[i] * x[i - 1];
        }
        for (v, d) in x.iter_mut().zip(&self.d) {
            *v /= d;
        }
        for i in (0..n.saturating_sub(1)).rev() {
            x[i] -= self.l[i + 1] * x[i + 1];
        }
    }

    /// tr((L D L^T)^{-1}) by the backward recurrence of the inverse's diagonal,
    /// X_ii = 1/d_i + l_{i+1}^2 X_{i+1,i+1}.
    fn inverse_trace(&self) -> f64 {
        let n = self.d.len();
        let mut trace = 0.0;
        let mut xii = 0.0;
        for i in (0..n).rev() {
            let next = if i + 1 < n {
                self.l[i + 1] * self.l[i + 1] * xii
            } else {
                0.0
            };
            xii = 1.0 / self.d[i] + next;
            trace += xii;
        }
        trace
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// gram_of_columns is A'A, symmetric, for tall, square, one-column and empty shapes
    /// (relative to the dense product, to rounding).
    #[test]
    fn gram_of_columns_is_the_dense_product() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(0x5eed_9a11);
        for (rows, cols) in [(1000, 37), (130, 130), (50, 1), (7, 0), (0, 5), (3, 9)] {
            let a = DMatrix::from_fn(rows, cols, |_, _| rng.gen_range(-1.0..1.0));
            let g = gram_of_columns(&a);
            let dense = a.transpose() * &a;
            assert_eq!(g.shape(), (cols, cols));
            assert_eq!(g, g.transpose());
            let err = (&g - &dense).amax();
            assert!(err <= 1e-12 * (1.0 + dense.amax()), "{rows}x{cols}: {err}");
        }
    }

    #[test]
    fn small_eig_spectral_radius_matches_schur() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(0x5eed_0016);
        let mut worst: f64 = 0.0;
        for trial in 0..3000 {
            let n = 1 + trial % 12;
            let mut a = DMatrix::from_fn(n, n, |_, _| rng.gen_range(-1.0..1.0));
            match trial % 5 {
                // companion (non-normal, clustered roots), as the LPV predictors are
                1 => {
                    a.fill(0.0);
                    for j in 0..n {
                        a[(0, j)] = rng.gen_range(-1.5..1.5);
                    }
                    for i in 1..n {
                        a[(i, i - 1)] = 1.0;
                    }
                }
                // repeated eigenvalues and exact zeros
                2 => {
                    a.fill_upper_triangle(0.0, 1);
                    for i in 0..n {
                        a[(i, i)] = 0.5;
                    }
                }
                // widely scaled rows and columns
                3 => {
                    for i in 0..n {
                        let f = 10f64.powi(i as i32 % 4 - 2);
                        a.row_mut(i).scale_mut(f);
                        a.column_mut(i).scale_mut(1.0 / f);
                    }
                }
                _ => {}
            }
            let fast = spectral_radius(&a);
            let slow = schur_spectral_radius(&a);
            let err = (fast - slow).abs() / slow.max(1e-300);
            worst = worst.max(if trial % 5 == 2 { 0.0 } else { err });
            // a defective eigenvalue (case 2: one Jordan block) is only determined to
            // eps^(1/n) by any backward-stable method
            let tol = if trial % 5 == 2 {
                10.0 * f64::EPSILON.powf(1.0 / n as f64)
            } else {
                1e-9
            };
            assert!(err < tol, "n = {n}, trial {trial}: {fast} vs {slow}");
        }
        assert!(worst < 1e-9, "{worst}");
        assert_eq!(spectral_radius(&DMatrix::zeros(3, 3)), 0.0);
        assert_eq!(spectral_radius(&DMatrix::zeros(0, 0)), 0.0);
        let rot = DMatrix::from_row_slice(2, 2, &[0.0, -2.0, 2.0, 0.0]);
        assert!((spectral_radius(&rot) - 2.0).abs() < 1e-15);
    }

    #[test]
    fn eig_and_min_norm() {
        let a = DMatrix::from_row_slice(3, 3, &[4.0, 1.0, 0.0, 1.0, 3.0, 0.5, 0.0, 0.5, 2.0]);
        let (vals, vecs) = sym_eig(&a).unwrap();
        assert!(vals[0] >= vals[1] && vals[1] >= vals[2]);
        let rec =
            &vecs * DMatrix::from_diagonal(&DVector::from_vec(vals.clone())) * vecs.transpose();
        assert!((rec - &a).amax() < 1e-12);
        // rank-deficient normal equations: min-norm solution equals the pseudo-inverse one
        let x = DMatrix::from_row_slice(2, 4, &[1.0, 2.0, 3.0, 4.0, 2.0, 4.0, 6.0, 8.0]);
        let b = DMatrix::from_row_slice(1, 4, &[1.0, 0.0, 1.0, 0.0]);
        let (sol, rank) =
            min_norm_from_normal(&(&x * x.transpose()), &(&b * x.transpose()), 1e-12).unwrap();
        assert_eq!(rank, 1);
        let pinv = x.clone().pseudo_inverse(1e-12).unwrap();
        assert!((sol - &b * pinv).amax() < 1e-10);
    }
}

#[cfg(test)]
mod tridiagonal_tests {
    use super::*;

    fn test_matrix(n: usize) -> DMatrix<f64> {
        let x = DMatrix::from_fn(n + 3, n, |i, j| ((i * 31 + j * 17) % 23) as f64 / 7.0 - 1.5);
        // rank-deficient on purpose (n + 3 rows but two equal columns)
        let mut x = x;
        let c0 = x.column(0).into_owned();
        x.set_column(n - 1, &c0);
        x.transpose() * x
    }

    #[test]
    fn tridiagonal_eigen_projection_matches_full_eigendecomposition() {
        for n in [1usize, 2, 5, 40, 130] {
            let a = test_matrix(n);
            let b = DMatrix::from_fn(n, 2, |i, j| (i as f64 * 0.3 + j as f64).sin());
            let t = Tridiagonal::new(&a);
            let (vals, proj) = t.eigen_projection(&t.to_tridiagonal(&b)).unwrap();
            let (v2, vecs) = sym_eig(&a).unwrap();
            let p2 = vecs.transpose() * &b;
            let scale = v2[0].abs().max(1.0);
            for i in 0..n {
                assert!((vals[i] - v2[i]).abs() < 1e-11 * scale, "{n} {i}");
            }
            // energies per distinct eigenvalue (vectors of clustered values are not unique)
            for i in 0..n {
                if (i > 0 && (v2[i - 1] - v2[i]).abs() < 1e-8 * scale)
                    || (i + 1 < n && (v2[i] - v2[i + 1]).abs() < 1e-8 * scale)
                {
                    continue;
                }
                for j in 0..2 {
                    assert!(
                        (proj[(i, j)].abs() - p2[(i, j)].abs()).abs() < 1e-9,
                        "{n} {i}"
                    );
                }
            }
        }
    }

    /// Reducing in the matrix's own storage reads only its lower triangle and gives the
    /// reduction of the copy, to the bit (faer's code on the same numbers).
    #[test]
    fn from_lower_equals_the_copy_and_ignores_the_upper_triangle() {
        for n in [1usize, 2, 7, 64] {
            let a = test_matrix(n);
            let mut junk = a.clone();
            for j in 0..n {
                for i in 0..j {
                    junk[(i, j)] = f64::NAN;
                }
            }
            let t = Tridiagonal::new(&a);
            let u = Tridiagonal::from_lower(junk);
            assert_eq!((&t.diag, &t.sub), (&u.diag, &u.sub), "{n}");
            let b = DMatrix::from_fn(n, 2, |i, j| (i as f64 * 0.3 + j as f64).cos());
            assert_eq!(t.to_tridiagonal(&b), u.to_tridiagonal(&b), "{n}");
        }
    }

    #[test]
    fn tridiagonal_norm_trace_and_largest_eigenvalue() {
        let n = 50;
        let a = test_matrix(n);
        let b = DMatrix::from_fn(n, 2, |i, j| ((3 * i + j) as f64).sin());
        let t = Tridiagonal::new(&a);
        let (vals, vecs) = sym_eig(&a).unwrap();
        assert!((t.largest_eigenvalue() - vals[0]).abs() < 1e-12 * vals[0]);
        let lam = 0.05 * vals[0];
        let (norm, trace) = t.shifted_norm_trace(lam, &t.to_tridiagonal(&b)).unwrap();
        let (n2, t2) = t
            .shifted_norm_trace_passes(lam, &t.to_tridiagonal(&b))
            .unwrap();
        assert!((norm - n2).abs() <= 1e-12 * n2 && (trace - t2).abs() <= 1e-12 * t2);
        let proj = vecs.transpose() * &b;
        let e_norm: f64 = (0..n)
            .map(|i| proj.row(i).norm_squared() / (vals[i] + lam).powi(2))
            .sum();
        let e_trace: f64 = vals.iter().map(|v| 1.0 / (v + lam)).sum();
        assert!((norm - e_norm).abs() < 1e-10 * e_norm, "{norm} {e_norm}");
        assert!(
            (trace - e_trace).abs() < 1e-10 * e_trace,
            "{trace} {e_trace}"
        );
        // a shift that leaves T + lam I indefinite is refused
        assert!(t.shifted_norm_trace(-0.5 * vals[0], &b).is_none());
    }

    /// T's eigenvectors taken back by Q are A's: A = (Q V) diag(vals) (Q V)^T, Q V orthonormal,
    /// and the eigenvalues those of the full decomposition (QL below faer's recursion
    /// threshold, divide and conquer above it).
    #[test]
    fn tridiagonal_eigenvectors_reconstruct_the_matrix() {
        for n in [1usize, 2, 5, 40, 130, 300] {
            let a = test_matrix(n);
            let t = Tridiagonal::new(&a);
            let (vals, v) = t.eigen().unwrap();
            let (full, _) = sym_eig(&a).unwrap();
            for (x, e) in vals.iter().zip(&full) {
                assert!((x - e).abs() <= 1e-11 * full[0], "n = {n}: {x} {e}");
            }
            assert!(
                vals.windows(2).all(|w| w[0] >= w[1]),
                "n = {n}: not descending"
            );
            let qv = t.from_tridiagonal(&v);
            let back = &qv * DMatrix::from_diagonal(&DVector::from_vec(vals)) * qv.transpose();
            assert!((&back - &a).norm() <= 1e-11 * a.norm(), "n = {n}");
            let gram = qv.transpose() * &qv;
            assert!(
                (gram - DMatrix::identity(n, n)).norm() <= 1e-11 * n as f64,
                "n = {n}"
            );
        }
    }

    #[test]
    fn tridiagonal_ridge_solve_matches_dense_solve() {
        let n = 60;
        let a = test_matrix(n);
        let b = DMatrix::from_fn(n, 3, |i, j| ((i + 2 * j) as f64).cos());
        let t = Tridiagonal::new(&a);
        let lam = 0.37;
        let x = t.from_tridiagonal(&t.solve_shifted(lam, &t.to_tridiagonal(&b)).unwrap());
        let shifted = &a + DMatrix::identity(n, n) * lam;
        let r = &shifted * &x - &b;
        assert!(r.norm() < 1e-10 * b.norm(), "{}", r.norm());
    }

    /// Lagged sine and cosine channels (a periodic-disturbance variant at a long past window)
    /// span 2 x harmonics dimensions, so their Gram has a cluster of dozens of eigenvalues at
    /// rounding level; with 60 sweeps allowed per eigenvalue QL failed on 10 of 300 such
    /// matrices (first: seed 1), e.g. in the family's periodic-disturbance oracle (seed 3002).
    #[test]
    fn eigen_projection_converges_on_clusters_of_zero_eigenvalues() {
        use rand::{Rng, SeedableRng};
        for seed in 0..12u64 {
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let (rows, lags, harm) = (1500usize, rng.gen_range(3..18usize), rng.gen_range(1..3));
            let w: f64 = rng.gen_range(0.1..3.0);
            let (extra, scale) = (rng.gen_range(5..40usize), rng.gen_range(0.1..10.0f64));
            let mut x = DMatrix::zeros(rows, 2 * harm * lags + extra);
            for k in 0..rows {
                for j in 0..lags {
                    let tj = k as f64 - j as f64;
                    for h in 0..harm {
                        let wh = (h + 1) as f64 * w * tj;
                        x[(k, 2 * harm * j + 2 * h)] = scale * wh.sin();
                        x[(k, 2 * harm * j + 2 * h + 1)] = scale * wh.cos();
                    }
                }
                for c in 0..extra {
                    x[(k, 2 * harm * lags + c)] = rng.gen_range(-1.0..1.0);
                }
            }
            let a = x.transpose() * &x;
            let b = DMatrix::from_fn(a.nrows(), 1, |i, _| (i as f64 * 0.7).cos());
            let t = Tridiagonal::new(&a);
            let (vals, _) = t.eigen_projection(&t.to_tridiagonal(&b)).unwrap();
            let (v2, _) = sym_eig(&a).unwrap();
            for (v, e) in vals.iter().zip(&v2) {
                assert!((v - e).abs() < 1e-11 * v2[0], "seed {seed}: {v} {e}");
            }
        }
    }
}

/// Golden-section search for the minimum of a unimodal `f` on [a, b]: at most `iters`
/// bracket reductions, stopping early once the bracket is narrower than `tol`; returns the
/// bracket's midpoint. The one refinement step of the GCV ridge parameter and of the
/// harmonic fundamental.
pub fn golden_section(
    f: impl Fn(f64) -> f64,
    mut a: f64,
    mut b: f64,
    iters: usize,
    tol: f64,
) -> f64 {
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let mut c = b - phi * (b - a);
    let mut d = a + phi * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..iters {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - phi * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + phi * (b - a);
            fd = f(d);
        }
        if b - a < tol {
            break;
        }
    }
    0.5 * (a + b)
}

#[cfg(test)]
mod gram_batch_tests {
    use super::*;

    fn rows(n: usize, len: usize, seed: u64) -> Vec<f64> {
        let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n * len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn syrk_batches_equal_the_core_update_plain_and_compensated() {
        for len in [1, 5, 32, 77] {
            for storage in [lpvid::packed_len(len), lpvid::gram_storage_len(len)] {
                let data = rows(300, len, len as u64);
                let mut core = lpvid::Gram::new(len, vec![0.0; storage]).unwrap();
                let mut host = lpvid::Gram::new(len, vec![0.0; storage]).unwrap();
                let mut batch = GramBatch::new(len);
                // uneven batches, as the loops hand them over
                let mut k = 0;
                for nb in [1usize, 128, 64, 107] {
                    let blk = &data[k * len..(k + nb) * len];
                    core.update_batch(blk, nb).unwrap();
                    batch.add(&mut host, blk, nb).unwrap();
                    k += nb;
                }
                assert_eq!(host.count(), 300);
                assert_eq!(host.weight(), 300.0);
                let scale = core.packed().iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for (a, b) in core.packed().iter().zip(host.packed()) {
                    assert!((a - b).abs() <= 1e-13 * scale, "len {len}: {a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn a_bad_batch_changes_nothing() {
        let len = 40;
        let mut data = rows(50, len, 3);
        let mut gram = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)]).unwrap();
        let mut batch = GramBatch::new(len);
        batch.add(&mut gram, &data[..10 * len], 10).unwrap();
        let before = gram.packed().to_vec();
        data[20 * len + 3] = f64::NAN;
        let e = batch.add(&mut gram, &data[10 * len..], 40).unwrap_err();
        assert!(matches!(e, lpvid::Error::NonFinite { index, .. } if index == 10 * len + 3));
        data[20 * len + 3] = 1e200;
        assert!(batch.add(&mut gram, &data[10 * len..], 40).is_err());
        assert!(batch.add(&mut gram, &data[10 * len..], 41).is_err());
        assert_eq!(gram.packed(), &before[..]);
        assert_eq!(gram.count(), 10);
    }

    #[test]
    fn forgetting_takes_the_core_path() {
        let len = 40;
        let data = rows(20, len, 9);
        let mut a = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)]).unwrap();
        let mut b = lpvid::Gram::new(len, vec![0.0; lpvid::packed_len(len)]).unwrap();
        a.set_forgetting(0.9).unwrap();
        b.set_forgetting(0.9).unwrap();
        GramBatch::new(len).add(&mut a, &data, 20).unwrap();
        b.update_batch(&data, 20).unwrap();
        assert_eq!(a.packed(), b.packed());
    }
}
