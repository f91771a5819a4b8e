//! Whether one model's held-out error is significantly lower than another's: paired batch
//! tests on per-sample losses that stay valid for coloured residuals. Diagnose's noise
//! threshold (its findings, replications and ranking) and the order check of `--order auto`
//! both judge a comparison here, so they judge it the same way.

/// Non-overlapping batch means (Schmeiser 1982): the series is cut into `batches` contiguous
/// batches; for batches much longer than the correlation time their means are nearly
/// independent, so t = mean / (sd(batch means) / sqrt(B)) is Student t with B - 1 degrees of
/// freedom under a zero mean, whatever the colour of the series. Returns (t, B - 1).
pub fn batch_means_t(d: &[f64], batches: usize) -> (f64, f64) {
    let n = d.len();
    let b = batches.min(n / 2).max(2);
    let len = n / b;
    if len == 0 {
        return (0.0, 1.0);
    }
    let means: Vec<f64> = (0..b)
        .map(|i| d[i * len..(i + 1) * len].iter().sum::<f64>() / len as f64)
        .collect();
    mean_t(&means)
}

/// Paired batch test of a relative improvement: `loss0` and `loss1` (per-sample squared
/// errors of two models on the same held-out samples) are cut into `batches` contiguous
/// batches and r_b = ln(sum_b loss0 / sum_b loss1) is t-tested for a positive mean (B - 1
/// degrees of freedom). Batch means keep the test valid for coloured residuals (batches longer
/// than the correlation time are nearly independent); the log ratio makes it scale-free, so
/// stretches of large error (e.g. at extreme scheduling) do not dominate. Returns (t, B - 1).
pub fn batch_log_ratio_t(loss0: &[f64], loss1: &[f64], batches: usize) -> (f64, f64) {
    let r = batch_log_ratios(loss0, loss1, batches);
    if r.is_empty() {
        return (0.0, 1.0);
    }
    mean_t(&r)
}

/// The per-batch log ratios r_b of [`batch_log_ratio_t`] (empty when a batch would be
/// empty): ratios of several independent comparisons can be pooled in one t test
/// ([`mean_t`]).
pub fn batch_log_ratios(loss0: &[f64], loss1: &[f64], batches: usize) -> Vec<f64> {
    let n = loss0.len().min(loss1.len());
    let b = batches.min(n / 2).max(2);
    let len = n / b;
    if len == 0 {
        return vec![];
    }
    (0..b)
        .map(|i| {
            let a: f64 = loss0[i * len..(i + 1) * len].iter().sum();
            let c: f64 = loss1[i * len..(i + 1) * len].iter().sum();
            (a.max(1e-300) / c.max(1e-300)).ln()
        })
        .collect()
}

/// One-sample t statistic of the mean of `v` (B = len(v) >= 2 values): mean / (sd / sqrt(B)),
/// +-inf for a zero spread with a nonzero mean. Returns (t, B - 1).
pub fn mean_t(v: &[f64]) -> (f64, f64) {
    let b = v.len();
    let m = v.iter().sum::<f64>() / b as f64;
    let s2 = v.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (b - 1) as f64;
    let se = (s2 / b as f64).sqrt();
    let t = if se > 0.0 {
        m / se
    } else if m > 0.0 {
        f64::INFINITY
    } else if m < 0.0 {
        f64::NEG_INFINITY
    } else {
        0.0
    };
    (t, (b - 1) as f64)
}

/// One-sided exact p-value of the Wilcoxon signed-rank test (Wilcoxon 1945) that the values
/// `v` lean positive: P(W- <= w-) when, given |v|, every sign is + or - with probability 1/2
/// independently (H0: the v_b are independent and symmetric about zero), w- the sum of the
/// ranks of |v| of the non-positive values. The noise threshold's test of the per-batch log
/// ratios ([`batch_log_ratios`]): unlike the t test of their mean it is not inflated by a few
/// batches with a large ratio (heavy tails), and its smallest p-value is 2^-B (B = 20:
/// 9.5e-7). Tied |v| share their mid-rank and the null distribution is the exact one of those
/// ranks (dynamic programming over the doubled ranks: O(B^3) time, O(B^2) memory); a zero
/// counts against (as non-positive), so all-zero ratios (two identical models) give p = 1.
/// Empty input or a NaN gives p = 1.
pub fn signed_rank_p(v: &[f64]) -> f64 {
    let n = v.len();
    if n == 0 || v.iter().any(|x| x.is_nan()) {
        return 1.0;
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()));
    // doubled mid-ranks: positions i..=j (0-based) tied share (i + 1 + j + 1) / 2
    let mut rank2 = vec![0usize; n];
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && v[order[j + 1]].abs() == v[order[i]].abs() {
            j += 1;
        }
        for &k in &order[i..=j] {
            rank2[k] = i + j + 2;
        }
        i = j + 1;
    }
    let w_minus: usize = (0..n).filter(|&k| v[k] <= 0.0).map(|k| rank2[k]).sum();
    // null distribution of the sum of a random subset of the doubled ranks
    let total: usize = rank2.iter().sum();
    let mut dist = vec![0.0f64; total + 1];
    dist[0] = 1.0;
    let mut reach = 0;
    for &a in &rank2 {
        reach += a;
        for s in (0..=reach).rev() {
            let with = if s >= a { dist[s - a] } else { 0.0 };
            dist[s] = 0.5 * (dist[s] + with);
        }
    }
    dist[..=w_minus].iter().sum::<f64>().clamp(0.0, 1.0)
}

/// Number of batches for [`batch_means_t`] on `n` samples: 20, fewer for short records
/// (batches of at least 25 samples).
pub fn batch_count(n: usize) -> usize {
    (n / 25).clamp(2, 20)
}

/// A variant's held-out per-sample loss against a null's (same mode, same rows): diagnose's
/// noise threshold test (the null refit, a variant's own null, the user's structure) and the
/// order check's comparison of an order with a larger one, in one place.
#[derive(Debug, Clone)]
pub struct Comparison {
    /// 1 - sum(loss1) / sum(loss0): the fraction of the null's error removed.
    pub explained: f64,
    /// Batch-means t of the per-batch log ratios of the null's to the variant's error (shown
    /// beside the p-value; the test is the signed-rank one).
    pub t: f64,
    /// One-sided p-value of the exact Wilcoxon signed-rank test of the per-batch log ratios
    /// ([`signed_rank_p`]).
    pub p_value: f64,
    /// The per-batch log ratios (empty when the record is too short for one batch).
    pub ratios: Vec<f64>,
}

/// [`Comparison`] of finite losses `loss1` (variant) and `loss0` (null) of equal length, in
/// [`batch_count`] batches.
pub fn compare(loss0: &[f64], loss1: &[f64]) -> Comparison {
    compare_in(loss0, loss1, batch_count(loss0.len()))
}

/// [`compare`] in `batches` batches: a comparison on part of a record (the second half of
/// its scored rows, `diagnose::memory::Basis::batches`) keeps the batches of the whole, so
/// that the floor 2^-B of its test does not rise with the rows it leaves out.
pub fn compare_in(loss0: &[f64], loss1: &[f64], batches: usize) -> Comparison {
    let d: f64 = loss0.iter().zip(loss1).map(|(a, b)| a - b).sum();
    let m0 = loss0.iter().sum::<f64>();
    let explained = if m0 > 0.0 { d / m0 } else { 0.0 };
    let ratios = batch_log_ratios(loss0, loss1, batches);
    // no batch, no test: p = 1 (never significant)
    let (t, p_value) = if ratios.is_empty() {
        (0.0, 1.0)
    } else {
        (mean_t(&ratios).0, signed_rank_p(&ratios))
    };
    Comparison {
        explained,
        t,
        p_value,
        ratios,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// P(W- <= w) by enumerating all 2^n sign patterns of the ranks 1..=n (no ties).
    fn enumerated(n: usize, w: usize) -> f64 {
        let hits = (0u32..1 << n)
            .filter(|m| {
                (0..n)
                    .filter(|i| m >> i & 1 == 1)
                    .map(|i| i + 1)
                    .sum::<usize>()
                    <= w
            })
            .count();
        hits as f64 / (1u64 << n) as f64
    }

    /// Values whose |v| have ranks 1..=n, the ranks in `neg` negative.
    fn signed(n: usize, neg: &[usize]) -> Vec<f64> {
        (1..=n)
            .map(|r| {
                let x = 0.1 * r as f64;
                if neg.contains(&r) {
                    -x
                } else {
                    x
                }
            })
            .collect()
    }

    #[test]
    fn signed_rank_exact_small_samples() {
        // the table values: n = 5, W- = 0: 1/32; n = 8, W- = 5: 10/256;
        // n = 10, W- = 8: 25/1024 and W- = 10: 43/1024 (the one-sided 5 % critical value)
        assert_eq!(signed_rank_p(&signed(5, &[])), 1.0 / 32.0);
        assert_eq!(signed_rank_p(&signed(5, &[1])), 2.0 / 32.0);
        assert_eq!(signed_rank_p(&signed(8, &[2, 3])), 10.0 / 256.0);
        assert_eq!(signed_rank_p(&signed(10, &[8])), 25.0 / 1024.0);
        assert_eq!(signed_rank_p(&signed(10, &[1, 2, 7])), 43.0 / 1024.0);
        // n = 20, W- = 60: 51017 / 2^20 (the one-sided 5 % critical value of the tables)
        assert_eq!(
            signed_rank_p(&signed(20, &[20, 19, 16, 5])),
            51017.0 / 1048576.0
        );
        // every W- for n = 5..=10 against the enumeration of all sign patterns
        for n in 5..=10usize {
            for w in 0..=n * (n + 1) / 2 {
                // a set of ranks summing to w: greedily from the largest
                let (mut neg, mut left) = (vec![], w);
                for r in (1..=n).rev() {
                    if r <= left {
                        neg.push(r);
                        left -= r;
                    }
                }
                assert_eq!(left, 0);
                let p = signed_rank_p(&signed(n, &neg));
                assert!((p - enumerated(n, w)).abs() < 1e-15, "n {n} w {w}: {p}");
            }
        }
    }

    #[test]
    fn signed_rank_floor_order_and_ties() {
        // all positive: 2^-n whatever the magnitudes (20 batches: 9.5e-7)
        let v: Vec<f64> = (0..20).map(|k| 1e-3 * (1.0 + k as f64).powi(3)).collect();
        assert_eq!(signed_rank_p(&v), 2f64.powi(-20));
        // all negative: 1
        let neg: Vec<f64> = v.iter().map(|x| -x).collect();
        assert_eq!(signed_rank_p(&neg), 1.0);
        // one negative batch costs its rank, however large: the largest gives W- = 20,
        // P(W- <= 20) = 371 / 2^20 = 3.5e-4; the smallest W- = 1, 2 / 2^20
        let mut out = v.clone();
        out[19] = -1e6;
        assert_eq!(signed_rank_p(&out), 371.0 / 1048576.0);
        let mut small = v.clone();
        small[0] = -1e-9;
        assert_eq!(signed_rank_p(&small), 2.0 / 1048576.0);
        // ties share the mid-rank: |v| = 1, 1, 2, 3 with -3 gives doubled ranks 3, 3, 6, 8
        // and W- = 8: P(sum of a random subset of {3, 3, 6, 8} <= 8) = 6/16
        assert_eq!(signed_rank_p(&[1.0, 1.0, 2.0, -3.0]), 6.0 / 16.0);
        assert_eq!(signed_rank_p(&[-1.0, 1.0, 2.0, 3.0]), 3.0 / 16.0);
        // zeros count against: 0, 2, 3, 4 gives W- = 1 (doubled 2): P = 2/16
        assert_eq!(signed_rank_p(&[0.0, 2.0, 3.0, 4.0]), 2.0 / 16.0);
        // identical models (every ratio 0), no ratios, a NaN: p = 1
        assert_eq!(signed_rank_p(&[0.0; 20]), 1.0);
        assert_eq!(signed_rank_p(&[]), 1.0);
        assert_eq!(signed_rank_p(&[1.0, f64::NAN, 2.0]), 1.0);
    }
}
