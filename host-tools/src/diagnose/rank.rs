//! Which finding comes first, the one `--fix` applies (issue 14; docs/diagnose-measured.md,
//! "which finding comes first"): the findings that passed every rule of a finding
//! ([`super::judge`]) ranked by their own held-out errors, then by parsimony with the
//! encompassing test, then like with like (a refined finding against a PBSID-fitted one
//! refined the same way), then the two scheduling effects by the encompassing test. Each rule
//! that moves a finding writes its numbers first in that finding's evidence.

use super::effects::{self, held_out_mse, parameter_count, Finding, Scored};
use super::encompass;
use super::fit_eval;
use super::residual::ALPHA;
use super::stats::t_sf;
use crate::data::Dataset;
use crate::significance::{batch_count, batch_log_ratios, mean_t, signed_rank_p};
use crate::simulate::Mode;

/// Rank the findings of one step: those above the threshold first, by the explained
/// fraction, then the rules of the module docs in order. `tried`: the variants of the step;
/// `train`, `val`, `base_fit`: what the comparisons refit with.
pub(crate) fn rank(
    findings: &mut Vec<(Finding, usize)>,
    scored: &[Scored],
    tried: usize,
    (train, val, base_fit): (&Dataset, &Dataset, &serde_json::Value),
    folds: FoldLosses<'_>,
) {
    findings.sort_by(|a, b| {
        b.0.significant
            .cmp(&a.0.significant)
            .then(b.0.explained.total_cmp(&a.0.explained))
    });
    rank_by_own_error(findings, scored);
    prefer_simpler_first(findings, scored, tried, (train, val, base_fit), folds);
    let k = findings.iter().take_while(|f| f.0.significant).count();
    like_with_like_first(&mut findings[..k], scored, tried, (train, val, base_fit));
    // the two scheduling effects judged by the encompassing test also when parsimony did not
    // reorder them (encompass::scheduling_pair_first)
    encompass::scheduling_pair_first(&mut findings[..k], scored, train, val, base_fit);
}

/// The significant findings ranked on their own held-out errors ([`order_by_own_error`]),
/// the rest kept in place.
fn rank_by_own_error(findings: &mut [(Finding, usize)], scored: &[Scored]) {
    let k = findings.iter().take_while(|f| f.0.significant).count();
    let mut order: Vec<usize> = findings[..k].iter().map(|f| f.1).collect();
    order_by_own_error(&mut order, scored);
    findings[..k].sort_by_key(|f| order.iter().position(|&i| i == f.1));
}

/// Parsimony among the significant findings ([`prefer_simpler`]): a simpler
/// significant finding that the first one does not beat head to head is put first, with
/// the reason in its evidence (first, so the human summary shows it), unless the
/// encompassing test ([`encompass::encompass`], for two findings whose structures combine: the
/// two scheduling effects, order-too-low with output-nonlinearity, and order-too-low with
/// added input channels when both are refined from the model's structure refined)
/// finds that the first one adds to the simpler one and not the reverse (it stays first),
/// or that both add (the one with the lower own held-out error first). When neither adds,
/// the simpler goes first, except for the two scheduling effects, whose structures differ by
/// a few coefficients in kind rather than number: the lower own held-out error first, as
/// [`encompass::scheduling_pair_first`] does (family plants 113000 and 113002, p1^2 planted:
/// the scheduled output equation was named by 18 coefficients against 21). Its numbers go in
/// the first finding's evidence in every case.
fn prefer_simpler_first(
    findings: &mut Vec<(Finding, usize)>,
    scored: &[Scored],
    tried: usize,
    (train, val, base_fit): (&Dataset, &Dataset, &serde_json::Value),
    folds: FoldLosses<'_>,
) {
    let order: Vec<usize> = findings
        .iter()
        .take_while(|f| f.0.significant)
        .map(|f| f.1)
        .collect();
    let Some((k, why)) = prefer_simpler(&order, scored, tried, folds) else {
        return;
    };
    let (s, r) = (&scored[order[k]], &scored[order[0]]);
    let (sn, rn) = (s.cand.effect.name(), r.cand.effect.name());
    let Some(e) = encompass::encompass(s, r, scored, train, val, base_fit) else {
        let mut f = findings.remove(k);
        f.0.evidence.insert(0, why);
        findings.insert(0, f);
        return;
    };
    let numbers = e.numbers(sn, rn);
    let better_is_simpler = effects::held_out_mse(s) < effects::held_out_mse(r);
    let (first, line) = match e.verdict {
        encompass::Encompassed::Richer => (
            0,
            format!("{numbers}: {rn} adds to {sn} and {sn} adds nothing to it, so {rn} is the effect ({sn} would otherwise be first by parsimony: {why})"),
        ),
        encompass::Encompassed::Simpler => (
            k,
            format!("{numbers}: {sn} adds to {rn} and {rn} adds nothing to it; {why}"),
        ),
        encompass::Encompassed::Both => (
            if better_is_simpler { k } else { 0 },
            format!(
                "{numbers}: each adds to the other, both effects are present; {} first (the lower held-out error), {} is the other effect",
                if better_is_simpler { sn } else { rn },
                if better_is_simpler { rn } else { sn }
            ),
        ),
        // the two scheduling effects: the comprehensive structure stands in for the
        // coefficient count, and a tie is decided as encompass::scheduling_pair_first decides
        // it (the lower held-out error first)
        encompass::Encompassed::Neither
            if encompass::encompassable(s.cand.effect) && encompass::encompassable(r.cand.effect) =>
        {
            let (simpler_first, reason) =
                encompass::scheduling_tie(&findings[k].0, &findings[0].0, better_is_simpler);
            (
                if simpler_first { k } else { 0 },
                format!(
                    "{numbers}: neither adds to the other, the data do not tell them apart; {} first ({reason}; for the two scheduling effects the encompassing test, not the coefficient count, decides)",
                    if simpler_first { sn } else { rn }
                ),
            )
        }
        encompass::Encompassed::Neither => (
            k,
            format!("{numbers}: neither adds to the other, the data do not tell them apart; {why}"),
        ),
    };
    let mut f = findings.remove(first);
    f.0.evidence.insert(0, line);
    findings.insert(0, f);
}

/// Own held-out errors compared like with like (issue 14). A variant fitted with the
/// output-error refinement gains from the refinement as well as from its effect, so ranked
/// first on its own error, or kept first by the parsimony rule's head-to-head test, it can
/// hide a finding that was fitted by PBSID alone: on the family's output-offset plant 31002
/// a Lur'e sqrt|y1| (36.8 % of the refined null, one coefficient fewer) came before the
/// offset (88.4 % of the PBSID null). When the first significant free-run finding R is
/// refined, each PBSID-fitted free-run finding U after it is refit with its structure
/// refined the same way ([`effects::refined_null`]); U goes first when that refit's held-out
/// error is not above R's and, if R has fewer free coefficients, it also beats R head to
/// head (the parsimony rule's test, [`effects::versus`] at ALPHA / `tried`, now like with
/// like). The U with the lowest such error is taken, with the numbers in its evidence. What is
/// applied is still the finding as scored. Applied after [`prefer_simpler_first`].
fn like_with_like_first(
    findings: &mut [(Finding, usize)],
    scored: &[Scored],
    tried: usize,
    (train, val, base_fit): (&Dataset, &Dataset, &serde_json::Value),
) {
    let Some(top) = findings.first().map(|f| &scored[f.1]) else {
        return;
    };
    let free = |s: &Scored| s.cand.effect.metric() == Mode::FreeRun;
    if !free(top) || !top.cand.spec.fitted_refined() {
        return;
    }
    let Some(top_eval) = top.eval.as_ref() else {
        return;
    };
    let count = |s: &Scored| {
        s.fitted
            .as_ref()
            .map(|f| effects::parameter_count(&f.model, Mode::FreeRun))
    };
    let top_loss = top_eval.loss(Mode::FreeRun);
    let top_mse = top_eval.mse(Mode::FreeRun);
    let level = ALPHA / tried.max(1) as f64;
    // (explained, p) of a head-to-head test
    type HeadToHead = Option<(f64, f64)>;
    // (position, refined error, head to head when R is simpler)
    let mut best: Option<(usize, f64, HeadToHead)> = None;
    for (j, (_, i)) in findings.iter().enumerate().skip(1) {
        let s = &scored[*i];
        if !free(s) || s.cand.spec.fitted_refined() || s.cand.spec.arx.is_some() {
            continue;
        }
        let Some(e) = fit_eval(&effects::refined_null(&s.cand.spec), train, val, base_fit) else {
            continue;
        };
        let mse = e.mse(Mode::FreeRun);
        if !mse.is_finite() || mse > top_mse || best.is_some_and(|(_, b, _)| mse >= b) {
            continue;
        }
        let h2h = match (count(top), count(s)) {
            (Some(kr), Some(ku)) if kr < ku => {
                let v = effects::versus(&top_loss, &e.loss(Mode::FreeRun));
                if v.1 >= level {
                    continue;
                }
                Some(v)
            }
            _ => None,
        };
        best = Some((j, mse, h2h));
    }
    let Some((j, mse, h2h)) = best else {
        return;
    };
    let line = format!(
        "ranked before {} ({}): fitted the same way, with the output-error refinement, its structure's held-out error is {mse:.3e} against {top_mse:.3e}{}; the lower error of that finding than this one's as fitted ({:.3e}) came from the refinement, not from its effect",
        top.cand.effect.name(),
        top.cand.detail,
        h2h.map_or(String::new(), |(x, p)| format!(
            " (head to head, as that structure has fewer free coefficients: explains {:.1} % of its error, p = {p:.1e} < {level:.1e})",
            100.0 * x
        )),
        effects::held_out_mse(&scored[findings[j].1])
    );
    findings[..=j].rotate_right(1);
    findings[0].0.evidence.insert(0, line);
}

/// Significant findings ranked on their own held-out errors (issue 14): `order` (indices into
/// `scored`, significant findings first, most explained first) with the free-run findings
/// sorted by [`held_out_mse`] among the positions they hold (a one-step finding keeps its
/// place: its error is of another residual). Two findings judged against different nulls
/// (the refined model structure of an own-output or refined scheduling variant, the PBSID
/// refit of the rest) were ranked by fractions of different nulls: on the family's
/// input-nonlinearity plant 11002 a Lur'e sqrt|y1| (99.9 % of the refined null) came before
/// u1^2 (99.8 % of the PBSID null). With one null this is the order by explained.
fn order_by_own_error(order: &mut [usize], scored: &[Scored]) {
    let slots: Vec<usize> = (0..order.len())
        .filter(|&k| scored[order[k]].cand.effect.metric() == Mode::FreeRun)
        .collect();
    let mut free: Vec<usize> = slots.iter().map(|&k| order[k]).collect();
    free.sort_by(|a, b| held_out_mse(&scored[*a]).total_cmp(&held_out_mse(&scored[*b])));
    for (k, i) in slots.into_iter().zip(free) {
        order[k] = i;
    }
}

/// Parsimony among significant findings (issue 14). Two effects can both pass the noise
/// threshold against the null refit because one structure reaches what the other models
/// exactly: with p in the output equation the output is p x, which a p^2 basis of the state
/// equation also reaches (the family's scheduled-output plants were named
/// scheduling-nonlinearity in 2 of 4). The richer structure is kept first only when it
/// earns its extra coefficients with the evidence a finding needs: its held-out batches
/// beat the simpler finding's head to head: a one-sided t test of the batch log ratios
/// ([`batch_log_ratios`], at ALPHA / `tried`; a finding against its null is judged by the
/// signed-rank test of the same ratios, [`crate::significance::compare`]). Otherwise the finding with
/// fewer free coefficients ([`parameter_count`]) that the richer one does not beat comes
/// first (the one explaining most of them), and the rule is applied again from it. At equal
/// counts a structure linear in the data is the simpler of the two when the other feeds a
/// function of the model's own output back, and the other must beat it at ALPHA (one
/// pairwise test; it earns no extra coefficients): a Lur'e y1^2 or |y1| y1 channel reaches a
/// constant through the output's level, and on plants with an output offset identified with
/// `--order auto` (a random-walk scheduling signal) it came first by a held-out error lower
/// than the offset's in the fourth digit of the VAF, while on the physical tank 4025 the
/// true sqrt|y1| beats the offset of equal size at p = 1e-3 (not at ALPHA / variants).
///
/// On a short record the head-to-head pools the cross-validation folds as the finding's own
/// test does ([`head_to_head`]).
///
/// `order`: indices into `scored` of the significant findings, best (most explained) first;
/// `folds`: a short record's fold losses of each ([`FoldLosses`]).
/// Returns the position in `order` to put first and why, when that is not position 0.
fn prefer_simpler(
    order: &[usize],
    scored: &[Scored],
    tried: usize,
    folds: FoldLosses<'_>,
) -> Option<(usize, String)> {
    if order.len() < 2 {
        return None;
    }
    let level = ALPHA / tried.max(1) as f64;
    // (held-out losses, free coefficients, metric, reads the model's own output)
    type Info = (Vec<f64>, usize, Mode, bool);
    let info = |i: usize| -> Option<Info> {
        let s = &scored[i];
        let mode = s.cand.effect.metric();
        let e = s.eval.as_ref()?;
        let f = s.fitted.as_ref()?;
        let own = effects::own_output_signals(&f.model.signals) > 0;
        Some((e.loss(mode), parameter_count(&f.model, mode), mode, own))
    };
    let infos: Vec<Option<Info>> = order.iter().map(|&i| info(i)).collect();
    let mut top = 0usize;
    let mut why = String::new();
    let mut visited = vec![false; order.len()];
    loop {
        visited[top] = true;
        let Some((l_top, k_top, m_top, own_top)) = &infos[top] else {
            break;
        };
        let mut next: Option<usize> = None;
        for (j, inf) in infos.iter().enumerate() {
            let Some((l_j, k_j, m_j, own_j)) = inf else {
                continue;
            };
            // simpler: fewer free coefficients, or as many (a tie) and linear in the data
            // where the richer one feeds a function of its own output back
            let tie = k_j == k_top;
            let simpler = k_j < k_top || (tie && *own_top && !own_j);
            if visited[j] || m_j != m_top || !simpler {
                continue;
            }
            if scored[order[j]].cand.effect == scored[order[top]].cand.effect {
                continue;
            }
            // does the richer top beat the simpler j on the held-out batches (pooled with
            // the folds' on a short record)?
            let (p, pooled) =
                head_to_head((l_j, folds.of(order[j])), (l_top, folds.of(order[top])));
            // at equal counts the richer earns no extra coefficients: one pairwise test at
            // ALPHA decides, the data's preference kept unless it is within chance
            let needs = if tie { ALPHA } else { level };
            if p >= needs && next.is_none_or(|n| j < n) {
                next = Some(j);
                if why.is_empty() {
                    why = format!(
                        "preferred to {} ({} free coefficients against {}{}): that richer structure does not beat it on the held-out batches{} (p = {p:.1e}, needs < {needs:.1e})",
                        scored[order[top]].cand.effect.name(),
                        k_j,
                        k_top,
                        if tie {
                            ", the other a function of the model's own output fed back"
                        } else {
                            ""
                        },
                        if pooled > 0 {
                            format!(" pooled with those of the {pooled} cross-validation folds")
                        } else {
                            String::new()
                        }
                    );
                }
            }
        }
        match next {
            Some(j) => top = j,
            None => break,
        }
    }
    (top != 0).then_some((top, why))
}

/// A short record's per-sample losses of each judged variant on each cross-validation fold's
/// left-out block (index into the scored variants, losses per fold; [`super::replicate::Fold::loss`]).
/// Empty on a long record.
#[derive(Clone, Copy)]
pub(crate) struct FoldLosses<'a>(pub &'a [(usize, &'a [Vec<f64>])]);

impl<'a> FoldLosses<'a> {
    /// The fold losses of variant `i` (empty when it has none).
    fn of(self, i: usize) -> &'a [Vec<f64>] {
        self.0.iter().find(|(j, _)| *j == i).map_or(&[], |(_, l)| l)
    }
}

/// The one-sided p-value that the richer `top` beats the simpler `simpler` head to head,
/// each given as (held-out losses, fold losses), and how many folds were pooled. On a long
/// record (or when a fold of either could not be scored): a t test of the held-out batch
/// log ratios ([`batch_log_ratios`]). On a short record whose folds both scored: the
/// held-out batches pooled with every fold's, each fold's left-out block cut into its own
/// batches, in the signed-rank test a short record's finding is judged by
/// ([`super::replicate::pooled_p`]): the 14 held-out batches of a 400-row record alone left
/// the richer periodic disturbance (96.4 % of its null's error, every fold 91-98 %) behind a
/// y1^3 channel (84.0 %, one fold 60 %) at p = 1.2e-3 (family 245203), and the parsimony rule
/// would otherwise judge on less evidence than the findings it ranks.
fn head_to_head(
    (l_s, f_s): (&[f64], &[Vec<f64>]),
    (l_top, f_top): (&[f64], &[Vec<f64>]),
) -> (f64, usize) {
    let held = batch_log_ratios(l_s, l_top, batch_count(l_s.len().min(l_top.len())));
    let folds_scored = !f_s.is_empty()
        && f_s.len() == f_top.len()
        && f_s
            .iter()
            .zip(f_top)
            .all(|(a, b)| !a.is_empty() && a.len() == b.len());
    if folds_scored {
        let all: Vec<f64> = f_s
            .iter()
            .zip(f_top)
            .flat_map(|(a, b)| batch_log_ratios(a, b, batch_count(a.len())))
            .chain(held)
            .collect();
        return (signed_rank_p(&all), f_s.len());
    }
    if held.len() < 2 {
        return (1.0, 0);
    }
    let (t, nu) = mean_t(&held);
    (t_sf(t, nu), 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A short record's head-to-head pools the folds: five held-out batches that do not tell
    /// two structures apart, and four folds in which the richer removes two thirds of the
    /// simpler's error in every batch. Without the folds, or with a fold of either unscored,
    /// it is the held-out t test alone.
    #[test]
    fn a_short_records_head_to_head_pools_the_folds() {
        // held out: 5 batches of 25, the richer better in 3 and worse in 2
        let simpler = vec![1.0; 125];
        let richer: Vec<f64> = (0..125).map(|k| if k < 75 { 0.6 } else { 1.6 }).collect();
        let alone = head_to_head((&simpler, &[]), (&richer, &[]));
        assert_eq!(alone.1, 0);
        assert!(alone.0 > 0.05, "{alone:?}");
        let fold_s = vec![vec![0.9; 100]; 4];
        let fold_r = vec![vec![0.3; 100]; 4];
        let (p, pooled) = head_to_head((&simpler, &fold_s), (&richer, &fold_r));
        assert_eq!(pooled, 4);
        // 16 fold batches and 3 held-out ones up, 2 down: the exact signed-rank p is small
        let mut all: Vec<f64> = vec![(0.9f64 / 0.3).ln(); 16];
        all.extend(batch_log_ratios(&simpler, &richer, 5));
        assert_eq!(p, signed_rank_p(&all));
        assert!(p < 1e-3, "{p}");
        // a fold the richer could not be scored on: the held-out test alone
        let mut unscored = fold_r.clone();
        unscored[2].clear();
        assert_eq!(
            head_to_head((&simpler, &fold_s), (&richer, &unscored)),
            alone
        );
        // the simpler one better in every fold: the richer does not beat it
        let (p, _) = head_to_head((&simpler, &fold_r), (&richer, &fold_s));
        assert!(p > 0.5, "{p}");
    }
}
