//! Dense linear algebra the host needs beyond nalgebra's basics: a fast symmetric
//! eigendecomposition (faer, blocked and vectorised — nalgebra's is an order of magnitude
//! slower at the sizes of problem (13)), pseudo-inverse least squares and helpers.

use nalgebra::{DMatrix, DVector};

/// Eigendecomposition of a symmetric matrix: eigenvalues in DEScending order and the
/// matching orthonormal eigenvectors as columns.
pub fn sym_eig(a: &DMatrix<f64>) -> Result<(Vec<f64>, DMatrix<f64>), String> {
    let n = a.nrows();
    if n == 0 {
        return Ok((Vec::new(), DMatrix::zeros(0, 0)));
    }
    let m = faer::Mat::<f64>::from_fn(n, n, |i, j| 0.5 * (a[(i, j)] + a[(j, i)]));
    let eig = m
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|e| format!("symmetric eigendecomposition failed: {e:?}"))?;
    let s = eig.S();
    let u = eig.U();
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
) -> Result<(DMatrix<f64>, usize), String> {
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

/// Mean and (population) standard deviation of a column.
pub fn mean_std(v: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = v.clone().count() as f64;
    let mean = v.clone().sum::<f64>() / n;
    let var = v.map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// Spectral radius of a square matrix.
pub fn spectral_radius(a: &DMatrix<f64>) -> f64 {
    a.clone()
        .complex_eigenvalues()
        .iter()
        .map(|c| c.norm())
        .fold(0.0, f64::max)
}

/// Column vector from a slice.
pub fn col(v: &[f64]) -> DVector<f64> {
    DVector::from_column_slice(v)
}

#[cfg(test)]
mod tests {
    use super::*;
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
