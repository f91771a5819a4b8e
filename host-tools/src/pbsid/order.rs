//! The model order from the singular values of Gamma^p K^p Z (kernel paper,
//! `papers/lpv-pbsid-kernel-automatica2009.md`, eq. (15) and the gap rule of section 4.3),
//! or given.

use super::error::FitError;
use super::settings::{Order, PbsidOptions};

/// Order from the singular values of Gamma K Z (the gap of section 4.3). Gaps are
/// d_n = log(sigma_n / sigma_{n+1}). The noise floor is the median of the smaller half of
/// the singular values; an order is a candidate when sigma_n stands at least
/// [`FLOOR_FACTOR`] times above that floor. Among candidates the order is the LARGEST n
/// whose gap is at least half the largest candidate gap, so a big drop after the first
/// singular value (one mode dominating the output energy) does not hide the drop into the
/// noise floor, while gaps inside the floor are never chosen.
pub fn select_order(sv: &[f64], max_n: usize) -> (usize, String) {
    let tiny = sv.first().copied().unwrap_or(0.0) * 1e-13;
    let mut sorted: Vec<f64> = sv.to_vec();
    sorted.sort_by(f64::total_cmp);
    let half = &sorted[..(sorted.len() / 2).max(1)];
    let floor = half[half.len() / 2].max(tiny);
    let upto = max_n.min(sv.len().saturating_sub(1));
    let gaps: Vec<(usize, f64)> = (1..=upto)
        .filter(|&n| n == 1 || sv[n - 1] >= FLOOR_FACTOR * floor)
        .map(|n| (n, (sv[n - 1].max(tiny) / sv[n].max(tiny)).ln()))
        .collect();
    if gaps.is_empty() {
        return (1, "only one singular value".into());
    }
    let (nbig, dmax) = gaps
        .iter()
        .copied()
        .fold((0, f64::MIN), |a, g| if g.1 > a.1 { g } else { a });
    let &(n, d) = gaps
        .iter()
        .rev()
        .find(|g| g.1 >= ALPHA_GAP * dmax)
        .unwrap_or(&gaps[0]);
    let mut reason = format!(
        "singular-value gap after sigma_{n}: sigma_{n}/sigma_{} = {:.1}, sigma_{n} is {:.0}x the noise floor {:.3e}",
        n + 1,
        d.exp(),
        sv[n - 1] / floor,
        floor
    );
    if nbig != n {
        reason.push_str(&format!(
            "; the larger gap {:.1} after sigma_{nbig} is followed by this one",
            dmax.exp()
        ));
    }
    (n, reason)
}

/// Fraction of the largest log-gap a later gap needs to be chosen (see [`select_order`]).
const ALPHA_GAP: f64 = 0.65;

/// How far above the noise floor a singular value must stand to count as signal.
pub const FLOOR_FACTOR: f64 = 4.0;

/// Order: given, or from the singular values.
pub(crate) fn choose_order(
    sv: &[f64],
    windows: usize,
    opts: &PbsidOptions,
) -> Result<(usize, String), FitError> {
    let max_n = opts.max_order.min(sv.len()).min(windows / 2).max(1);
    match opts.order {
        Order::Fixed(n) => {
            if n > sv.len() {
                return Err(FitError::OrderTooLarge {
                    order: n,
                    available: sv.len(),
                });
            }
            Ok((n, format!("order {n} given")))
        }
        Order::Auto => Ok(select_order(sv, max_n)),
    }
}
