//! The rules of a finding (issue 14; docs/diagnose-measured.md, "the rules of a finding").
//! Each effect is represented by its best significant variant ([`effects::best_variants`]).
//! Before it is a finding, that variant must pass, in this order: the full-data test
//! ([`effects::significant`]; on a short record pooled with the cross-validation folds), the
//! replication (each half of the training data, [`replicate::replicated`], or the folds'
//! agreement, [`replicate::cv_agree`]), the refit of the model's own structure when it has a
//! null of its own ([`effects::beats_user`]), that structure with a larger past window
//! ([`effects::larger_past`]; not for order-too-low, which is that structure), for an
//! own-output variant that structure refined from the variant's fit with its own-output
//! signals linearised ([`output::linearised_null`]), for a periodic-disturbance variant the
//! same fit without its sinusoids ([`catalogue::without_sinusoids`]), that structure refined by output error
//! from the best of its starts ([`output::refined_structure`]; the scheduling effects,
//! unused-signal, input-nonlinearity and coloured-noise,
//! [`effects::needs_refined_null`]; coloured-noise, order-too-low and input-delay by
//! [`states::states_check`]) and the memory rule ([`memory::forgets_as_null`]). A rule is
//! tested only on a variant that passed the ones before it. An effect is a finding when one
//! of its variants passes every rule: a best variant that does not replicate, or replicates
//! and fails a later rule, gives way to the effect's next variants
//! ([`replicate::alternatives`]). [`Judgement`] keeps what each rule found: the evidence of a
//! finding, and the one rule named when it is blocked. A variant whose held-out run
//! runs away ([`effects::Eval::runs_away`]) is not judged at all: [`effects::score`] fails it.

use std::cell::OnceCell;

use super::effects::{self, evidence, Candidate, Effect, Eval, Finding, Scored};
use super::memory::{self, Basis, Memory};
use super::refit::{Fitted, Spec};
use super::replicate::{Halves, Replication};
use super::residual::{ResidualReport, ALPHA};
use super::{catalogue, encompass, output, replicate, states};
use super::{fit_eval, fit_eval_order, mean_vaf, mode_name};
use crate::data::Dataset;
use crate::model::ModelFile;
use crate::simulate::Mode;

/// (explained, p): a head-to-head comparison of held-out errors ([`effects::versus`]).
type Versus = (f64, f64);

/// What one step's variants are judged with: the variants as scored and the structures the
/// rules compare them with.
pub(crate) struct Bench<'a> {
    /// The model's structure.
    pub spec: &'a Spec,
    /// The order its refit on the whole training record took (what a replication refits it
    /// at when the order is left to `--order auto`, [`replicate::null_at_order`]).
    pub order: usize,
    /// The training data the refits are fitted on.
    pub train: &'a Dataset,
    /// The held-out data they are scored on.
    pub val: &'a Dataset,
    /// The model's fit settings.
    pub fit: &'a serde_json::Value,
    /// Every variant of the step, scored.
    pub scored: &'a [Scored],
    /// How many variants were tried (the Bonferroni divisor).
    pub tried: usize,
    /// The null refit of the model's structure, evaluated on the held-out data.
    pub base_eval: &'a Eval,
    /// The model's structure with a larger past window ([`effects::larger_past`]).
    pub larger: Option<&'a Candidate>,
    /// ... and its evaluation among the scored variants.
    pub larger_eval: Option<&'a Eval>,
    /// The null structures of the step's candidates, fitted once ([`super::NullFit`]).
    pub nulls: &'a [super::NullFit],
}

/// One effect's variant and what each rule of a finding found for it (None: the rule was
/// not reached, or does not apply to this variant).
pub(crate) struct Judgement {
    /// The effect.
    pub effect: Effect,
    /// The variant judged: the effect's best, or the alternative that replicated in its
    /// place (index into the scored variants).
    pub index: usize,
    /// How many variants of the effect were scored.
    pub variants: usize,
    /// A short record's (t, p) of the held-out batches pooled with the folds'.
    pub pooled: Option<(f64, f64)>,
    /// A short record's per-sample losses of the variant on each fold's left-out block
    /// ([`replicate::Fold::loss`]; empty on a long record).
    pub fold_loss: Vec<Vec<f64>>,
    /// The full-data test passed.
    pub full_data: bool,
    /// (explained, p) on each training half, or on each fold of a short record.
    pub replication: Option<Vec<Versus>>,
    /// How each half's refit was compared with the null refit on that half.
    pub replication_basis: Option<Vec<Basis>>,
    /// The halves refit with a longer past window because a refit ran away, in words
    /// ([`Halves`]).
    pub replication_widened: Vec<String>,
    /// Replicated only with each half scored inside its own operating range
    /// ([`Replication::within_range`]).
    pub within_range: bool,
    /// The best variant, when it did not replicate and this one did in its place, with what
    /// it explained on the halves.
    pub swapped_from: Option<(usize, Vec<Versus>)>,
    /// The variant this one stands in for when that one replicated but failed a later rule
    /// ([`second_chance`]), with the rule it failed, in words.
    pub set_aside: Option<(usize, String)>,
    /// Against the refit of the model's own structure (a variant with a null of its own).
    pub vs_user: Option<Versus>,
    /// Against the model's structure with a larger past window, and how they were compared.
    pub vs_larger: Option<(Versus, Basis)>,
    /// Against the model's structure refined by output error.
    pub vs_refined: Option<Versus>,
    /// An own-output variant against the model's structure refined from the variant's fit
    /// linearised ([`super::output::linearised_null`]).
    pub vs_linearised: Option<Versus>,
    /// A periodic-disturbance variant against itself without its sinusoids
    /// ([`catalogue::without_sinusoids`]).
    pub vs_without: Option<Versus>,
    /// A coloured-noise or order-too-low variant against that structure refined
    /// ([`states::states_check`]).
    pub states: Option<states::StatesCheck>,
    /// How much its free run leans on its estimated start.
    pub memory: Option<Memory>,
    /// Every rule passed.
    pub passed: bool,
}

/// Judge every effect's best variant of one step by the rules of a finding (module docs).
/// Returns the judgements, one per effect with a significant variant, and whether the record
/// was judged as a short one (blocked cross-validation, [`replicate::short_record`]).
pub(crate) fn judge(
    b: &Bench<'_>,
    notes: &mut Vec<String>,
) -> (Vec<Judgement>, bool, Option<RefinedEstimate>) {
    let scored = b.scored;
    let best = effects::best_variants(scored, b.tried);
    let mut js: Vec<Judgement> = best
        .iter()
        .map(|&(effect, index, variants)| Judgement::new(effect, index, variants))
        .collect();
    // a short held-out record: blocked cross-validation over the record the diagnosis sees
    // (replicate::cv_folds): the held-out batches pooled with those of the training folds in
    // one test, and the folds' agreement is the replication
    let could = |j: &Judgement| {
        let s = &scored[j.index];
        s.error.is_none() && s.explained >= effects::MIN_EXPLAINED
    };
    let short =
        replicate::short_record(b.base_eval.loss(Mode::FreeRun).len()) && js.iter().any(could);
    if short {
        cross_validate(b, &mut js, could, notes);
    }
    for j in js.iter_mut() {
        j.full_data = effects::significant(scored[j.index].explained, j.p(scored), b.tried);
    }
    let halves = if !short && js.iter().any(|j| j.full_data) {
        replicate_on_halves(b, &mut js, notes)
    } else {
        None
    };
    let refs = References {
        base_memory: Memory::of(b.base_eval),
        larger_refined: OnceCell::new(),
        refined: OnceCell::new(),
    };
    for j in js.iter_mut() {
        b.rules_beyond_full_data(j, short, &refs);
        if let Some(halves) = halves
            .as_ref()
            .filter(|_| j.failed_beyond_replication(b, short))
        {
            if let Some(alt) = second_chance(b, j, halves, &refs) {
                *j = alt;
            }
        }
    }
    // no finding on a structure fitted by PBSID alone: its refinement by output error is
    // fitted now if no rule needed it, since a biased estimate is then what is left to fix
    if !js.iter().any(|j| j.passed) && !b.spec.fitted_refined() {
        refs.refined(b);
    }
    // when the refined structure was fitted and predicts much better than the refit, say so;
    // with `--fix` and no finding it is what the diagnosis writes (`super::fix_steps`)
    let refined = refs
        .refined
        .into_inner()
        .flatten()
        .and_then(|(model, eval)| {
            let (explained, p_value) = states::refined_gain(b.base_eval, &eval, b.tried)?;
            notes.push(states::refined_note(explained, p_value, &eval, b.base_eval));
            Some(RefinedEstimate {
                model,
                eval,
                explained,
                p_value,
            })
        });
    (js, short, refined)
}

/// The model's own structure refined by output error when it predicts the held-out record
/// significantly better than the structure's subspace refit ([`states::refined_gain`]).
pub(crate) struct RefinedEstimate {
    /// The refined model.
    pub model: ModelFile,
    /// Its held-out evaluation.
    pub eval: Eval,
    /// Fraction of the refit's held-out free-run error it explains.
    pub explained: f64,
    /// The p-value of that comparison.
    pub p_value: f64,
}

/// A short record's test: each variant that could be a finding refit on the cross-validation
/// folds ([`replicate::cross_fold`]), its held-out batches pooled with theirs.
fn cross_validate(
    b: &Bench<'_>,
    js: &mut [Judgement],
    could: impl Fn(&Judgement) -> bool,
    notes: &mut Vec<String>,
) {
    let folds = replicate::cv_folds(b.train, b.val);
    let null = replicate::null_at_order(b.spec, b.order);
    let nulls: Option<Vec<Eval>> = folds
        .iter()
        .map(|(fit_on, score_on)| fit_eval(&null, fit_on, score_on, b.fit))
        .collect();
    let Some(nulls) = nulls.filter(|_| !folds.is_empty()) else {
        notes.push("the null structure cannot be refit on the cross-validation folds: the short held-out record's test is not pooled with them".into());
        return;
    };
    for j in js.iter_mut().filter(|j| could(j)) {
        let s = &b.scored[j.index];
        let f = replicate::cross_fold(&replicate::as_fitted(s, b.order), &folds, &nulls, b.fit);
        j.pooled = Some(replicate::pooled_p(&s.ratios, &f));
        j.replication = Some(f.iter().map(|x| (x.explained, x.p_value)).collect());
        j.fold_loss = f.into_iter().map(|x| x.loss).collect();
    }
}

/// The replication of each variant significant on the full data: refit on each half of the
/// training data ([`Halves::replicate`]). When the effect's best variant does not hold up,
/// its next variants that pass every full-data test of a finding take its place, lowest
/// held-out error first ([`replicate::alternatives`]): on the plant family a quasi-LPV y^2 /
/// |y| variant or a refined p^2 had the lowest error and its refit on a half diverged, while
/// another variant of the same effect replicated. Each alternative with its own null must
/// also beat the model's structure refit (on the planted output-offset plant,
/// diagnose_planted seed 3, a scheduling-noise alternative that explained 100 % of its own
/// LPV-ARX null's error replicated). When none replicates on the whole held-out record, the
/// variants of a scheduling effect or of `output-nonlinearity` are tried again in the same
/// order with each half scored inside its own range of the operating point (the scheduling
/// signals; the output fed back) ([`Halves::replicate_within_range`]): the whole record's
/// evidence first, since a structure whose half-refits carry over the range has shown more.
fn replicate_on_halves<'b>(
    b: &Bench<'b>,
    js: &mut [Judgement],
    notes: &mut Vec<String>,
) -> Option<Halves<'b>> {
    let Some(halves) = Halves::new(
        replicate::null_at_order(b.spec, b.order),
        b.train,
        b.val,
        b.fit,
    ) else {
        notes.push("the null structure cannot be refit on half of the training data: findings are not replicated on independent halves".into());
        return None;
    };
    for j in js.iter_mut().filter(|j| j.full_data) {
        let best = j.index;
        let mut r = halves.replicate(&replicate::as_fitted(&b.scored[best], b.order));
        if !replicate::replicated(&r.versus) {
            let cand = |i: usize| replicate::as_fitted(&b.scored[i], b.order);
            let alts = replicate::alternatives(b.scored, best, b.tried, b.base_eval, b.larger_eval);
            // on the whole held-out record first: the best variant, then its alternatives
            let mut found = None;
            let mut failed = Vec::new();
            for i in alts {
                let r2 = halves.replicate(&cand(i));
                if replicate::replicated(&r2.versus) {
                    found = Some((i, r2));
                    break;
                }
                failed.push((i, r2));
            }
            // then a variant inside each half's range of the operating point, in the same
            // order (Halves::replicate_within_range: scheduling and own-output effects)
            if found.is_none() {
                let whole = std::iter::once((best, &r)).chain(failed.iter().map(|(i, w)| (*i, w)));
                found = whole
                    .filter_map(|(i, w)| Some((i, halves.replicate_within_range(&cand(i), w)?)))
                    .find(|(_, r2)| replicate::replicated(&r2.versus));
            }
            if let Some((i, r2)) = found {
                if i != best {
                    j.swapped_from = Some((best, r.versus.clone()));
                    j.index = i;
                }
                r = r2;
            }
        }
        j.take_replication(r);
    }
    Some(halves)
}

impl References {
    /// The model's structure refined by output error, fitted when a rule first needs it (or
    /// at the end of a step without a finding, [`judge`]).
    fn refined(&self, b: &Bench<'_>) -> Option<&Eval> {
        self.refined
            .get_or_init(|| {
                let key = effects::refined_null(b.spec).key();
                let fitted = b
                    .nulls
                    .iter()
                    .find(|n| n.key == key)
                    .map(|n| &n.fitted.model);
                let m = output::refined_structure(b.spec, b.scored, b.train, b.fit, fitted)?;
                let e = Eval::new(&m, b.val).ok()?;
                Some((m, e))
            })
            .as_ref()
            .map(|(_, e)| e)
    }
}

/// The structures some rules compare with, refit when a variant first reaches them.
struct References {
    /// The null refit's memory ([`memory::forgets_as_null`]).
    base_memory: Memory,
    /// The model's structure with a larger past window, refined by output error.
    larger_refined: OnceCell<Option<Eval>>,
    /// The model's structure refined by output error, and its held-out evaluation.
    refined: OnceCell<Option<(ModelFile, Eval)>>,
}

/// A second chance for an effect whose judged variant replicated but failed a later rule
/// (the larger past window, the refined structure, the memory rule): the effect's next
/// variants ([`replicate::alternatives`], lowest held-out error first, at most
/// [`replicate::MAX_ALTERNATIVES`]) go through the replication and every rule, and the first
/// that passes them all represents the effect. An effect is a finding when one of its
/// variants passes every rule, as with a variant that did not replicate (the swap of
/// [`replicate_on_halves`]); each variant was already counted in the level of the full-data
/// test. On the physical tank 4024 (docs/bench-diagnose.md) a Lur'e sin(5.5 y) channel had
/// the lowest error of the own-output variants and leaned on its estimated start, so
/// input-nonlinearity was named, at half the oracle's error ratio.
fn second_chance(
    b: &Bench<'_>,
    j: &Judgement,
    halves: &Halves<'_>,
    refs: &References,
) -> Option<Judgement> {
    let why = j.rule_failed(b, false)?;
    let first = j.swapped_from.as_ref().map_or(j.index, |s| s.0);
    let alts = replicate::alternatives(b.scored, first, b.tried, b.base_eval, b.larger_eval);
    for i in alts.into_iter().filter(|&i| i != j.index) {
        let r = halves.replicate(&replicate::as_fitted(&b.scored[i], b.order));
        if !replicate::replicated(&r.versus) {
            continue;
        }
        let mut alt = Judgement {
            full_data: true,
            set_aside: Some((j.index, why.clone())),
            ..Judgement::new(j.effect, i, j.variants)
        };
        alt.take_replication(r);
        b.rules_beyond_full_data(&mut alt, false, refs);
        if alt.passed {
            return Some(alt);
        }
    }
    None
}

impl Bench<'_> {
    /// The rules after the full-data test, in order, each only when the ones before passed:
    /// the replication (already made), the model's structure refit, the larger past window,
    /// the refined structure, the memory rule. Sets what each found and `passed`.
    fn rules_beyond_full_data(&self, j: &mut Judgement, short: bool, refs: &References) {
        let s = &self.scored[j.index];
        let mode = j.effect.metric();
        // a variant with its own null replaces the model's structure when applied: it must
        // also beat the null refit of that structure, under the symmetric memory rule
        // (memory::judged)
        j.vs_user = s.cand.null.as_ref().and_then(|_| {
            let (b, l0, l1) = memory::judged(s.eval.as_ref()?, self.base_eval, mode);
            Some(effects::versus_in(&l0, &l1, b.batches(l0.len())))
        });
        if !(j.full_data && j.replicated(self, short) && self.beaten(j.vs_user, short)) {
            return;
        }
        // every finding but order-too-low must also beat the model's own structure with a
        // larger past window; an own-output variant, fitted with the output-error
        // refinement, that structure refined the same way, compared as scored (it is not a
        // refit of the model's own structure)
        if j.effect != Effect::OrderTooLow {
            j.vs_larger = s.eval.as_ref().and_then(|e| {
                let (basis, l0, l1) = if j.effect == Effect::OutputNonlinearity {
                    let l = refs
                        .larger_refined
                        .get_or_init(|| {
                            let l = self.larger?;
                            fit_eval(
                                &effects::refined_null(&l.spec),
                                self.train,
                                self.val,
                                self.fit,
                            )
                        })
                        .as_ref()?;
                    (Basis::EstimatedStart, l.loss(mode), e.loss(mode))
                } else {
                    memory::judged(e, self.larger_eval?, mode)
                };
                effects::versus_larger_in(&l0, &l1, basis.batches(l0.len())).map(|v| (v, basis))
            });
        }
        if !self.beaten(j.vs_larger.map(|v| v.0), short) {
            return;
        }
        // an own-output variant must also beat the model's structure refined from its own
        // fit with the added signals linearised: the null at the variant's minimum
        // (output::linearised_null)
        if j.effect == Effect::OutputNonlinearity {
            j.vs_linearised = s.fitted.as_ref().zip(s.eval.as_ref()).and_then(|(f, e)| {
                let null = s.cand.null.as_ref().unwrap_or(self.spec);
                let null = output::twin_null(null, &f.model.signals);
                let m = output::linearised_null(&f.model, &null, self.train).ok()?;
                let l = Eval::new(&m, self.val).ok()?;
                effects::versus_larger(&l.loss(mode), &e.loss(mode))
            });
        }
        if !self.beaten(j.vs_linearised, short) {
            return;
        }
        // a periodic-disturbance variant must owe its gain to its sinusoids: against the same
        // fit with them removed (catalogue::without_sinusoids)
        if j.effect == Effect::PeriodicDisturbance {
            j.vs_without = s.fitted.as_ref().zip(s.eval.as_ref()).and_then(|(f, e)| {
                let null = s.cand.null.as_ref().unwrap_or(self.spec);
                let m = catalogue::without_sinusoids(&f.model, &null.signals)?;
                let l = Eval::new(&m, self.val).ok()?;
                effects::versus_larger(&l.loss(mode), &e.loss(mode))
            });
        }
        if !self.beaten(j.vs_without, short) {
            return;
        }
        // a variant fitted by PBSID and judged against the model's structure refit must also
        // beat that structure refined by output error (effects::needs_refined_null: the
        // scheduling effects, unused-signal, input-nonlinearity, coloured-noise)
        if effects::needs_refined_null(s) {
            j.vs_refined = s.eval.as_ref().and_then(|e| {
                let r = refs.refined(self)?;
                effects::versus_larger(&r.loss(mode), &e.loss(mode))
            });
        }
        if !self.beaten(j.vs_refined, short) {
            return;
        }
        // coloured-noise, order-too-low and input-delay against that structure refined
        // (states::states_check: a white refined residual; the order refined like with like)
        if states::needs_states_check(s) {
            j.states = refs.refined(self).and_then(|r| {
                let refit = |sp: &Spec| fit_eval_order(sp, self.train, self.val, self.fit);
                states::states_check(s, self.base_eval, r, self.order, refit, self.tried, short)
            });
        }
        if !j.states.as_ref().is_none_or(|c| c.passes) {
            return;
        }
        // a fix must forget its initial state as the model's structure refit does: its score
        // from the state estimated on the first held-out samples must not lean on that state
        // at the end of the record
        if mode == Mode::FreeRun {
            j.memory = s.eval.as_ref().map(Memory::of);
        }
        j.passed = j
            .memory
            .is_none_or(|m| memory::forgets_as_null(&m, &refs.base_memory));
    }

    /// A comparison with one of the model's own structures passes (none made: passes).
    fn beaten(&self, v: Option<Versus>, short: bool) -> bool {
        v.is_none_or(|v| effects::beats_user(v, self.tried, short))
    }

    /// The level each variant's full-data test is held to.
    fn level(&self) -> f64 {
        ALPHA / self.tried.max(1) as f64
    }
}

impl Judgement {
    /// Keep the replication on the two halves of the variant judged.
    fn take_replication(&mut self, r: Replication) {
        self.replication = Some(r.versus);
        self.replication_basis = Some(r.bases);
        self.replication_widened = r.widened;
        self.within_range = r.within_range;
    }

    /// Variant `index` of `effect` (one of its `variants`), before any rule is tested.
    fn new(effect: Effect, index: usize, variants: usize) -> Judgement {
        Judgement {
            effect,
            index,
            variants,
            pooled: None,
            fold_loss: Vec::new(),
            full_data: false,
            replication: None,
            replication_basis: None,
            replication_widened: Vec::new(),
            within_range: false,
            swapped_from: None,
            set_aside: None,
            vs_user: None,
            vs_larger: None,
            vs_refined: None,
            vs_linearised: None,
            vs_without: None,
            states: None,
            memory: None,
            passed: false,
        }
    }

    /// The p-value of the full-data test (pooled with the folds on a short record).
    pub fn p(&self, scored: &[Scored]) -> f64 {
        self.pooled.map_or(scored[self.index].p_value, |x| x.1)
    }

    /// The t statistic of the full-data test (pooled with the folds on a short record).
    pub fn t(&self, scored: &[Scored]) -> f64 {
        self.pooled.map_or(scored[self.index].t, |x| x.0)
    }

    /// The finding this judgement makes: `explained` is the fraction credited to it (a noise
    /// model's discounted by what an input-driven finding explains), the evidence is the
    /// residual tests' and every rule's that was reached.
    pub fn finding(
        &self,
        b: &Bench<'_>,
        explained: f64,
        (free, one): (&ResidualReport, &ResidualReport),
        base: &Fitted,
    ) -> Finding {
        let s = &b.scored[self.index];
        let mut ev = evidence(self.effect, free, one, base, Some(s));
        if let Some(e) = &s.error {
            ev.push(format!("the refit failed: {e}"));
        }
        if let Some((k, r)) = &self.swapped_from {
            ev.push(format!(
                "in place of the variant with the lowest held-out error, {} ({:.1} %), which did not replicate (refit on each training half it explains {} of the null's error): the next variant that passes every full-data test",
                b.scored[*k].cand.detail,
                100.0 * b.scored[*k].explained,
                r.iter().map(|x| format!("{:.1} % (p = {:.1e})", 100.0 * x.0, x.1)).collect::<Vec<_>>().join(" and ")
            ));
        }
        if let Some((k, why)) = &self.set_aside {
            ev.push(format!(
                "in place of the variant with a lower held-out error, {} ({:.1} %), which replicated but is not a finding: {why}; the next variant of the effect that passes every rule",
                b.scored[*k].cand.detail,
                100.0 * b.scored[*k].explained,
            ));
        }
        if let (Some(r), Some((_, p))) = (&self.replication, self.pooled) {
            ev.push(format!(
                "short held-out record, blocked cross-validation in {} folds: refit without each of the {} blocks of the training data (on the other blocks and the held-out record) and scored on the block left out, it explains {} of the null's error there (p = {}); pooled with the held-out batches p = {p:.1e}",
                r.len() + 1,
                r.len(),
                r.iter().map(|x| format!("{:.1} %", 100.0 * x.0)).collect::<Vec<_>>().join(" and "),
                r.iter().map(|x| format!("{:.1e}", x.1)).collect::<Vec<_>>().join(", ")
            ));
        } else if let Some(r) = &self.replication {
            ev.push(format!(
                "refit on each half of the training data: explains {} of the held-out error (p = {}){}{}",
                r.iter().map(|x| format!("{:.1} %", 100.0 * x.0)).collect::<Vec<_>>().join(" and "),
                r.iter().map(|x| format!("{:.1e}", x.1)).collect::<Vec<_>>().join(", "),
                self.halves_basis(),
                self.replication_widened.iter().map(|w| format!("; {w}")).collect::<String>()
            ));
        }
        if s.basis == Basis::ZeroStartTail {
            if let Some(e) = &s.eval {
                let null = s.cand.null.is_none().then_some(b.base_eval);
                ev.push(symmetric_memory_evidence(e, null));
            }
        }
        if let Some(c) = self.states.as_ref().filter(|c| c.passes) {
            ev.push(c.text.clone());
        }
        if let Some(v) = self.vs_refined {
            ev.push(format!(
                "against the model's own structure refined by output error: explains {:.1} % of its held-out error (p = {:.2e})",
                100.0 * v.0,
                v.1
            ));
        }
        if let Some(v) = self.vs_linearised {
            ev.push(format!(
                "against the model's own structure refined from this variant's fit with its own-output signals linearised: explains {:.1} % of its held-out error (p = {:.2e})",
                100.0 * v.0,
                v.1
            ));
        }
        if let Some(v) = self.vs_without {
            ev.push(format!(
                "against the same fit without its sinusoids (their columns of B and D set to zero): they explain {:.1} % of its held-out error (p = {:.2e})",
                100.0 * v.0,
                v.1
            ));
        }
        if let Some((v, basis)) = self.vs_larger {
            ev.push(format!(
                "against the model's own structure with a larger past window ({}{}): explains {:.1} % of its held-out error (p = {:.2e}; {})",
                b.larger.map_or("", |l| l.detail.as_str()),
                if self.effect == Effect::OutputNonlinearity { ", refined" } else { "" },
                100.0 * v.0,
                v.1,
                basis.describe()
            ));
        }
        Finding {
            effect: self.effect.name(),
            detail: s.cand.detail.clone(),
            explained,
            residual: mode_name(self.effect.metric()),
            t: self.t(b.scored),
            p_value: self.p(b.scored),
            significant: self.passed && explained >= effects::MIN_EXPLAINED,
            replication: self
                .replication
                .as_ref()
                .map(|r| r.iter().map(|x| x.0).collect()),
            basis: s.basis,
            replication_basis: self.replication_basis.clone(),
            vaf: s.eval.as_ref().map(mean_vaf),
            variants: self.variants,
            evidence: ev,
            blocked_by: None,
            replicated_within_range: self.within_range,
        }
    }

    /// How the halves' refits were compared with their nulls, when not both from the
    /// estimated start (for the replication's evidence line).
    fn halves_basis(&self) -> String {
        let Some(b) = self
            .replication_basis
            .as_ref()
            .filter(|b| b.contains(&Basis::ZeroStartTail))
        else {
            return String::new();
        };
        if b.windows(2).all(|w| w[0] == w[1]) {
            format!(
                "; each compared with the null refit on the same half {}",
                b[0].describe()
            )
        } else {
            format!(
                "; compared with the null refit on the same half {}",
                b.iter()
                    .map(|x| x.describe())
                    .collect::<Vec<_>>()
                    .join(" and ")
            )
        }
    }

    /// The replication passed (not made: passes): each training half, or all folds of a
    /// short record but one.
    fn replicated(&self, b: &Bench<'_>, short: bool) -> bool {
        let explained = b.scored[self.index].explained;
        self.replication.as_ref().is_none_or(|r| {
            if short {
                replicate::cv_agree(explained, r)
            } else {
                replicate::replicated(r)
            }
        })
    }

    /// Passed the full-data test, the replication and the comparison with the model's
    /// structure refit, then failed a later rule.
    fn failed_beyond_replication(&self, b: &Bench<'_>, short: bool) -> bool {
        !self.passed && self.full_data && self.replicated(b, short) && b.beaten(self.vs_user, short)
    }

    /// The rule that keeps `f` (this judgement's finding) from being a finding, in words, for
    /// the stop line and the summary (human text and JSON say the same).
    pub fn blocked_by(&self, f: &Finding, b: &Bench<'_>, short: bool) -> String {
        let p_max = b.level();
        if let Some(e) = &b.scored[self.index].error {
            format!("its refit failed ({e})")
        } else if f.explained < effects::MIN_EXPLAINED {
            format!(
                "it explains {:.1} % < {:.0} %",
                100.0 * f.explained,
                100.0 * effects::MIN_EXPLAINED
            )
        } else if f.p_value >= p_max {
            format!("p = {:.2e} is not below {p_max:.1e}", f.p_value)
        } else {
            self.rule_failed(b, short)
                .unwrap_or_else(|| "it is below the noise threshold".to_string())
        }
    }

    /// The rule beyond the full-data test that this variant failed, in words (None: none
    /// did). The comparisons with the model's own structures are named before the
    /// replication, as they were tested on the full data.
    fn rule_failed(&self, b: &Bench<'_>, short: bool) -> Option<String> {
        let explained = b.scored[self.index].explained;
        let beaten = |v: Option<Versus>| b.beaten(v, short);
        Some(
            if let Some(v) = self.vs_user.filter(|v| !beaten(Some(*v))) {
                format!(
                "it is judged against its own null; against the refit of the model's own structure it explains {:.1} % of the held-out error (p = {:.2e}), and a fix must improve on that model",
                100.0 * v.0,
                v.1
            )
            } else if let Some((v, _)) = self.vs_larger.filter(|v| !beaten(Some(v.0))) {
                format!(
                "the model's own structure with a larger past window ({}) removes that error as well: against it this variant explains {:.1} % of the held-out error (p = {:.2e}; {}); the error it removes is the bias of a past window too short for the model's own structure (see order-too-low)",
                b.larger.map_or("", |l| l.detail.as_str()),
                100.0 * v.0,
                v.1,
                encompass::improvement_needed(b.tried, short)
            )
            } else if let Some(v) = self.vs_linearised.filter(|v| !beaten(Some(*v))) {
                let s = &b.scored[self.index];
                let null = s.cand.null.as_ref().unwrap_or(b.spec);
                // a twin's null keeps its constant channel (output::twin_null)
                let (null_words, what) = if output::is_twin(&null.signals, &s.cand.spec.signals) {
                    (
                        " with the constant channel (an offset)",
                        "its function of the output stood for the output's level, which the offset holds, not for a dependence on the output level",
                    )
                } else {
                    (
                        "",
                        "what it removed is a local minimum of the structure's refinement, not a dependence on the output level",
                    )
                };
                format!(
                    "the model's own structure{null_words}, refined from this variant's fit, its own-output signals replaced by their best linear stand-ins, removes that error as well: against it this variant explains {:.1} % of the held-out error (p = {:.2e}); {what}",
                    100.0 * v.0,
                    v.1
                )
            } else if let Some(v) = self.vs_without.filter(|v| !beaten(Some(*v))) {
                format!(
                "the same fit without its sinusoids (their columns of B and D set to zero, every other coefficient as fitted) does as well: against it the sinusoids explain {:.1} % of the held-out error (p = {:.2e}); what the variant removed is a change in the rest of the estimate that adding two input channels to the refit made, not a periodic disturbance",
                100.0 * v.0,
                v.1
            )
            } else if let Some(c) = self.states.as_ref().filter(|c| !c.passes) {
                c.text.clone()
            } else if let Some(v) = self.vs_refined.filter(|v| !beaten(Some(*v))) {
                format!(
                "the model's own structure refined by output error removes that error as well: against it this variant explains {:.1} % of the held-out error (p = {:.2e}; a finding must improve on it as on the structure's refit); what it removes is the bias of the subspace estimate of the model's own structure, not {}",
                100.0 * v.0,
                v.1,
                match self.effect {
                    Effect::UnusedSignal => "a signal the model lacks",
                    Effect::InputNonlinearity => "a static nonlinearity of the input",
                    Effect::ColouredNoise => "coloured noise",
                    _ => "a missing scheduling dependence",
                }
            )
            } else if let Some(m) = self.memory.filter(|_| !self.passed) {
                format!(
                "its free run leans on the initial state estimated on the first held-out samples: at the end of the held-out record that state still moves its output by {:.3} (mean square, normalised) against its own error of {:.3} there, while the model's structure refit forgets its start; a fix must not depend on where its simulation starts",
                m.influence, m.error
            )
            } else if let Some(r) = self
                .replication
                .as_ref()
                .filter(|_| !self.replicated(b, short))
            {
                if short {
                    format!(
                    "its cross-validation folds disagree (held out: explains {:.1} %; refit without each training block and scored on it: {}; all folds but one need explained > 0)",
                    100.0 * explained,
                    r.iter().map(|x| format!("{:.1} %", 100.0 * x.0)).collect::<Vec<_>>().join(", ")
                )
                } else {
                    format!(
                    "it is not replicated on the two halves of the training data (explains {}, p = {}; each half needs explained > 0 and p < {})",
                    r.iter().map(|x| format!("{:.1} %", 100.0 * x.0)).collect::<Vec<_>>().join(" and "),
                    r.iter().map(|x| format!("{:.1e}", x.1)).collect::<Vec<_>>().join(", "),
                    replicate::REPLICATION_ALPHA
                )
                }
            } else {
                return None;
            },
        )
    }
}

/// The evidence line of a variant compared with its null under the symmetric memory rule
/// ([`memory::basis`]): with `null` the null refit of the model's structure (a variant with
/// its own null structure: None, only the rule is named), both runs' dependence on their
/// estimated starts and what the variant explains from the estimated states, as it would
/// have been judged without the rule.
fn symmetric_memory_evidence(cand: &Eval, null: Option<&Eval>) -> String {
    let rule = format!(
        "compared with its null {}",
        memory::Basis::ZeroStartTail.describe()
    );
    let Some(null) = null else {
        return rule;
    };
    let (c, n) = (Memory::of(cand), Memory::of(null));
    let v = effects::versus(&null.loss(Mode::FreeRun), &cand.loss(Mode::FreeRun));
    format!(
        "{rule}: at the end of the held-out record the null refit's estimated start moves its output by {:.3e} (mean square, normalised) against its own error of {:.3e} there (it leans on that start as a free offset or drift), this variant's by {:.3e} against {:.3e} (it forgets its start); from the estimated initial states over all scored rows it explains {:.1} % (p = {:.1e})",
        n.influence,
        n.error,
        c.influence,
        c.error,
        100.0 * v.0,
        v.1
    )
}
