//! The `output-nonlinearity` effect: the model lacks a dependence on its own output level (a
//! cubic spring, a pendulum's sin, a tank's square-root outflow). Written with the model
//! contract's own-output factors (DESIGN.md section 5, docs/model-format.md), tried both ways:
//!
//! - **Lur'e feedback**: an input channel f(y) of the model's own output, f one of y^2, y^3,
//!   |y| y, sin y, sqrt|y|, and sin(y / spread) when the output's spread is far from 1
//!   (delay 0: the output equation does not use it);
//! - **quasi-LPV**: a scheduling function y^2 or |y| (only with an output equation that does
//!   not depend on scheduling).
//!
//! Each variant is fitted by [`crate::pipeline::fit_map`] (the pipeline's PBSID with the
//! measured output in the new signal, as with feedback, then the output-error refinement
//! through the feedback) and scored by the catalogue's held-out test like every other effect
//! ([`super::effects`]): it is applied only when the free run on held-out data improves
//! significantly and replicates on both training halves.

use serde_json::{json, Map, Value};

use super::catalogue::Context;
use super::effects::Scored;
use super::refit::{Fitted, Noise, RefitError, Spec};
use crate::data::Dataset;
use crate::error::Error;
use crate::model::{describe, Factor, FactorFn, ModelFile, ModelKind};

/// Most Levenberg-Marquardt iterations of the refinement through the feedback: a ceiling,
/// not the usual stop. The refinement ends when no step improves the fit or the cost
/// stalls ([`crate::refine::stalled`]), and large problems get fewer iterations from the
/// operations budget in [`fit`]. The former cap of 60 cut small problems off mid-descent: on
/// the cascaded tanks (1024 rows, 3 states, sin y1 fed back) the training free-run MSE went
/// 2.87 -> 0.200 in 60 iterations and 0.164 when run to its stall at 266 (validation RMSE
/// 0.490 -> 0.437 V with x0 estimated; docs/benchmarks-measured.md).
pub const REFINE_ITERATIONS: usize = 500;

/// The iteration ceiling of a refinement with `parameters` parameters over `residuals`
/// residual values: an operations budget of 5e9 for the Gauss-Newton normal matrices
/// (parameters^2 x residuals per iteration), within 5..=[`REFINE_ITERATIONS`].
pub fn refine_iterations(parameters: f64, residuals: usize) -> usize {
    let budget = 5e9 / (parameters * parameters * residuals.max(1) as f64);
    (budget as usize).clamp(5, REFINE_ITERATIONS)
}

fn own(col: &str, pow: f64, func: Option<FactorFn>) -> Factor {
    Factor {
        pow,
        func,
        ..Factor::col(col)
    }
}

/// Named products of factors.
type Shapes = Vec<(String, Vec<Factor>)>;

/// The Lur'e channels and scheduling functions of output column `c`, with their names;
/// `spread` is the standard deviation of the column on the training data.
fn shapes(c: &str, spread: f64) -> (Shapes, Shapes) {
    let mut lure = vec![
        (format!("{c}^2"), vec![own(c, 2.0, None)]),
        (format!("{c}^3"), vec![own(c, 3.0, None)]),
        (
            format!("|{c}|*{c}"),
            vec![own(c, 1.0, Some(FactorFn::Abs)), own(c, 1.0, None)],
        ),
        (format!("sin({c})"), vec![own(c, 1.0, Some(FactorFn::Sin))]),
        (format!("sqrt|{c}|"), vec![own(c, 0.5, None)]),
    ];
    // sin is the one shape that is not homogeneous: sin(y) suits an angle in radians, and an
    // output in other units (degrees, counts, a scaled sensor) needs sin(omega y).
    // omega = 1 / spread is tried besides it unless the spread is within a factor 1.5 of 1,
    // where the two are nearly the same shape. On the plant family (diagnose::plants, a sin
    // of the output in units of its spread; seeds 1000-1015) it was the variant named on 3 of
    // the 7 sin plants found
    if spread.is_finite() && spread > 0.0 && spread.ln().abs() > 1.5f64.ln() {
        let w = 1.0 / spread;
        lure.push((
            format!("sin({w:.4}*{c}) (omega = 1 / the output's spread)"),
            vec![Factor {
                omega: Some(w),
                ..own(c, 1.0, Some(FactorFn::Sin))
            }],
        ));
    }
    let sched = vec![
        (format!("{c}^2"), vec![own(c, 2.0, None)]),
        (format!("|{c}|"), vec![own(c, 1.0, Some(FactorFn::Abs))]),
    ];
    (lure, sched)
}

/// The variants of `output-nonlinearity` for the current structure, or why there are none.
pub fn candidates(ctx: &Context<'_>) -> (Vec<(String, Spec)>, Option<String>) {
    let spec = ctx.spec;
    let map = &spec.signals;
    if spec.noise != Noise::Pbsid {
        return (
            vec![],
            Some(
                "the model has a noise model; output feedback refits are implemented without one"
                    .into(),
            ),
        );
    }
    let outs: Vec<String> = map
        .own_outputs()
        .iter()
        .flatten()
        .map(|c| c.to_string())
        .collect();
    if outs.is_empty() {
        return (
            vec![],
            Some("no output is a plain data column the model could feed back".into()),
        );
    }
    let present = |p: &[Factor]| map.inputs.iter().chain(&map.scheduling).any(|q| q == p);
    let mut out = Vec::new();
    for c in &outs {
        let Some(col) = ctx.train.column(c) else {
            continue;
        };
        let mean = col.iter().sum::<f64>() / col.len().max(1) as f64;
        let spread = (col.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>()
            / col.len().max(1) as f64)
            .sqrt();
        let (lure, sched) = shapes(c, spread);
        for (name, prod) in lure {
            if present(&prod) {
                continue;
            }
            let mut sp = spec.clone();
            sp.signals.inputs.push(prod);
            out.push((
                format!("Lur'e feedback: {name} of the model's own output as an input channel"),
                sp,
            ));
        }
        if spec.scheduled_output {
            continue;
        }
        for (name, prod) in sched {
            if present(&prod) {
                continue;
            }
            let mut sp = spec.clone();
            sp.signals.scheduling.push(prod);
            out.push((
                format!("quasi-LPV: scheduling on {name} of the model's own output"),
                sp,
            ));
        }
    }
    let why = out
        .is_empty()
        .then(|| "every output-feedback shape is already in the model".to_string());
    (out, why)
}

/// Whether a refinement from a second start reached a lower minimum than the first: its
/// training mean-square error `alt` below `first` by more than two standard errors of a
/// mean square over `samples` values (relative 2 sqrt(2 / samples) for white Gaussian
/// residuals; a lower bound for coloured ones). A smaller difference is the same fit reached
/// by another path, and the user's own start is kept: on a training half of the family's
/// scheduling-nonlinearity plant 37000 (750 samples) the second start was 2 % lower, and the
/// p1^2 structure refined from it went to the stability boundary and lost on held-out data.
pub fn another_minimum(alt: f64, first: f64, samples: usize) -> bool {
    let margin = 2.0 * (2.0 / samples.max(1) as f64).sqrt();
    alt.is_finite() && (!first.is_finite() || alt < first * (1.0 - margin))
}

/// Fit a structure that reads the model's own output (the hook of
/// [`super::refit::fit_spec`]): [`crate::pipeline::fit_map`], then the model file with its
/// `fit` record extended. With the automatic order, a fit with more states than the model
/// diagnosed (its record's `order`) is fitted again at that order and the one with the lower
/// [`bic`] kept (the record's `order_choice`).
pub fn fit(spec: &Spec, train: &Dataset, base_fit: &Value) -> Result<Fitted, RefitError> {
    if spec.arx.is_some() || spec.noise != Noise::Pbsid || spec.scheduled_output {
        return Err(RefitError::Unsupported(
            "a structure that reads the model's own output is refit as lpv-ss with a constant output equation and no noise model".into(),
        ));
    }
    // the refinement's cost grows with (parameters)^2 x samples: fewer iterations for large
    // models (a 9-state, 2-output rotor model gets about 20)
    let n = match spec.opts.order {
        crate::pbsid::Order::Fixed(n) => n,
        crate::pbsid::Order::Auto => spec.opts.max_order.min(10),
    };
    let (r, l, m) = (
        spec.signals.inputs.len(),
        spec.signals.outputs.len(),
        spec.signals.m(),
    );
    let np = (m * n * (n + r) + l * n + n) as f64;
    let iters = refine_iterations(np, train.len() * l);
    let mut opts = spec.opts.clone();
    // the null structure of a candidate: refined the same way (refit::Spec::refined)
    opts.refine |= spec.refined;
    // a sin channel's frequency is refined with the matrices (its start: the candidate's)
    let fit_at = |opts: &crate::pbsid::PbsidOptions| {
        crate::pipeline::fit_map_frequencies(&spec.signals, train, opts, iters, true).map_err(|e| {
            match e {
                Error::Data(d) => RefitError::Data(d),
                Error::Fit { source, .. } => RefitError::Fit(source),
                other => RefitError::Numerical(other.to_string()),
            }
        })
    };
    let mut mf = fit_at(&opts)?;
    // a second start: the PBSID estimate at a past window two samples longer, refined the
    // same way (same structure, same order: the past window only sets where the descent
    // starts), kept when its training free-run error is clearly lower ([`another_minimum`]).
    // From the user's window the refinement can stop in a local minimum: on the family's
    // clean plant 121000 (pole 0.79, past 7) at a training MSE of 3.78e-2, where from past
    // 8-10 it reaches 1.739e-2 (the noise floor); the leftover bias then coloured the refined
    // residual and a noise model was named
    let mut start_past = spec.opts.past;
    if spec.refined && !spec.signals.has_feedback() {
        if let Some(wider) = super::effects::with_past(spec, spec.opts.past + 2, train.len()) {
            let mut o2 = wider.opts.clone();
            o2.refine = true;
            let after = |m: &crate::pipeline::MapFit| {
                m.refinement
                    .map(|(_, a, _)| a)
                    .filter(|a| a.is_finite())
                    .unwrap_or(f64::INFINITY)
            };
            if let Ok(alt) = fit_at(&o2) {
                if alt.model.n() == mf.model.n()
                    && another_minimum(after(&alt), after(&mf), train.len() * l)
                {
                    start_past = o2.past;
                    mf = alt;
                }
            }
        }
    }
    let own_order = base_fit
        .get("order")
        .and_then(Value::as_u64)
        .map(|v| v as usize);
    let mut order_choice = Value::Null;
    if let (crate::pbsid::Order::Auto, Some(n0)) = (spec.opts.order, own_order) {
        if n0 >= 1 && mf.model.n() > n0 {
            let at_own = crate::pbsid::PbsidOptions {
                order: crate::pbsid::Order::Fixed(n0),
                ..opts.clone()
            };
            if let Ok(alt) = fit_at(&at_own) {
                let rows = train.len() * l;
                let (b_auto, b_own) = (bic(&mf, rows), bic(&alt, rows));
                order_choice = json!({
                    "rule": "the model's own order against the order PBSID chose with the output in the signals, by BIC on the training free-run error",
                    "orders": [mf.model.n(), alt.model.n()],
                    "bic": [b_auto, b_own],
                });
                if b_own <= b_auto {
                    mf = alt;
                }
            }
        }
    }
    let mut rec = match base_fit {
        Value::Object(m) => m.clone(),
        _ => Map::new(),
    };
    let train_rec = json!({"file": train.source, "rows": train.len()});
    let common = crate::record::pbsid_fit_record(&spec.opts, &mf.fit, train_rec);
    let fed: Vec<String> = mf
        .signals
        .inputs
        .iter()
        .chain(mf.signals.scheduling.iter())
        .filter(|p| p.iter().any(|f| mf.signals.own_output(f).is_some()))
        .map(|p| describe(p))
        .collect();
    let updates = json!({
        "reg": spec.reg_text,
        "output_equation": "constant",
        "output_feedback": {
            "signals": fed,
            "identification": "PBSID with the measured output in these signals, then output-error refinement (Levenberg-Marquardt) of the free run through the feedback, a sin channel's frequency with it",
            "refinement_mse": mf.refinement.map(|(a, b, _)| json!([a, b])),
            "refinement_iterations": mf.refinement.map(|(_, _, i)| i),
            "refinement_start_past": start_past,
        },
        "constant_inputs": if mf.constant_inputs.is_empty() {
            Value::Null
        } else {
            Value::from("varying inputs and outputs centred for PBSID; constant channels' B, D from the means, then refined")
        },
        "train_rows": train.len(),
        "states": mf.model.n(),
        "order_choice": order_choice,
    });
    for u in [common, updates] {
        if let Value::Object(u) = u {
            for (k, v) in u {
                rec.insert(k, v);
            }
        }
    }
    let model = ModelFile {
        kind: ModelKind::Ss(mf.model),
        signals: mf.signals.clone(),
        fit: Value::Object(rec),
    };
    // the loops must be well posed (the refinement keeps them so)
    model
        .signals
        .check_loops(&model.kind)
        .map_err(|e| RefitError::Numerical(e.to_string()))?;
    Ok(Fitted {
        model,
        singular_values: mf.fit.singular_values.clone(),
        order: mf.fit.order,
        noise_orders: vec![],
        sigma_p: None,
    })
}

/// Bayesian information criterion of a fit through the loop on its training data:
/// `rows` ln(free-run MSE after the refinement) + k ln(`rows`), k the free coefficients (the
/// non-zero entries of A^(i), B^(i), C, D and the initial state); infinite without a finite
/// refined error. Compares the two orders [`fit`] may try for one structure: a channel of
/// the measured output is nearly collinear with it (sqrt|y| on a tank's level), which moves
/// the singular-value gap PBSID's automatic order reads, and the larger order then always
/// wins on the raw training error (physical tank 4025: order 2, 11 coefficients, training
/// MSE 0.0046134 against order 1, 5 coefficients, 0.0046187, the plant's own order and the
/// same held-out error as the true model).
fn bic(mf: &crate::pipeline::MapFit, rows: usize) -> f64 {
    let Some((before, after, _)) = mf.refinement else {
        return f64::INFINITY;
    };
    let mse = after.min(before);
    let m = &mf.model;
    let nz = |ms: &[nalgebra::DMatrix<f64>]| {
        ms.iter()
            .map(|x| x.iter().filter(|v| **v != 0.0).count())
            .sum::<usize>()
    };
    let k = nz(&m.a) + nz(&m.b) + nz(&m.c) + nz(&m.d) + m.n();
    let n = rows.max(1) as f64;
    if mse.is_finite() && mse > 0.0 {
        n * mse.ln() + k as f64 * n.ln()
    } else {
        f64::INFINITY
    }
}

/// Evidence for `output-nonlinearity`: what the best variant feeds back and how the
/// refinement through the loop went on the training data.
pub fn evidence(best: Option<&Scored>) -> Vec<String> {
    let mut ev = Vec::new();
    if let Some(s) = best {
        ev.push(format!(
            "refit with {} explains {:.1} % of the held-out free-run error",
            s.cand.detail,
            100.0 * s.explained
        ));
        if let Some(f) = &s.fitted {
            if let Some(r) = f.model.fit.get("output_feedback") {
                if let Some(m) = r.get("refinement_mse").and_then(Value::as_array) {
                    let (a, b) = (
                        m.first().and_then(Value::as_f64).unwrap_or(f64::NAN),
                        m.get(1).and_then(Value::as_f64).unwrap_or(f64::NAN),
                    );
                    ev.push(format!(
                        "training free-run MSE through the feedback {a:.3e} after PBSID, {b:.3e} after the output-error refinement"
                    ));
                }
            }
            ev.extend(refined_frequencies(
                &s.cand.spec.signals.inputs,
                &f.model.signals.inputs,
            ));
        }
    }
    ev
}

/// One line per sin/cos input factor whose frequency the fit moved from where the variant
/// started it ([`crate::pipeline::fit_map_frequencies`]): the variant's name keeps the
/// starting omega, the model file holds the fitted one.
fn refined_frequencies(started: &[Vec<Factor>], fitted: &[Vec<Factor>]) -> Vec<String> {
    let mut lines = Vec::new();
    for (a, b) in started.iter().zip(fitted) {
        for (fa, fb) in a.iter().zip(b) {
            if !matches!(fa.func, Some(FactorFn::Sin | FactorFn::Cos)) {
                continue;
            }
            let (w0, w1) = (fa.omega.unwrap_or(1.0), fb.omega.unwrap_or(1.0));
            if w0 != w1 {
                let func = if fa.func == Some(FactorFn::Sin) {
                    "sin"
                } else {
                    "cos"
                };
                lines.push(format!(
                    "the frequency of {func}(omega {}) refined with the matrices: omega {w0:.4} -> {w1:.4}",
                    fa.col
                ));
            }
        }
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_start_counts_only_below_the_first_by_two_standard_errors() {
        // 750 samples: a margin of 2 sqrt(2/750) = 10.3 %
        assert!(!another_minimum(0.02819, 0.02875, 750)); // 37000's second half: 2 %
        assert!(another_minimum(1.739e-2, 3.78e-2, 1500)); // clean 121000: 54 %
        assert!(!another_minimum(0.0929, 0.1, 750));
        assert!(another_minimum(0.0890, 0.1, 750));
        assert!(another_minimum(1.0, f64::INFINITY, 750));
        assert!(!another_minimum(f64::NAN, 1.0, 750));
        assert!(!another_minimum(0.5, 1.0, 0)); // no samples: a margin of 2 sqrt 2, never
    }

    fn sin_of(col: &str, omega: f64) -> Vec<Factor> {
        vec![Factor {
            omega: Some(omega),
            ..own(col, 1.0, Some(FactorFn::Sin))
        }]
    }

    fn user_spec() -> Spec {
        Spec {
            signals: crate::model::SignalMap::standard(1, 1, 0),
            opts: crate::pbsid::PbsidOptions::new(8),
            reg_text: "none".into(),
            scheduled_output: false,
            output_ls: false,
            noise: Noise::Pbsid,
            arx: None,
            refined: false,
            nested_in: None,
            latent: None,
        }
    }

    /// The comprehensive structure of an order-too-low variant and a Lur'e variant
    /// (`encompass::order_union_spec`): the Lur'e channel with the larger windows and the fixed
    /// order, and the order structure refined; nothing for two structures it cannot combine.
    #[test]
    fn the_union_of_a_larger_structure_and_a_lure_channel() {
        let user = user_spec();
        let mut lure = user.clone();
        lure.signals.inputs.push(sin_of("y1", 1.0));
        let mut past = user.clone();
        past.opts.past = 10;
        let mut order = user.clone();
        order.opts.order = crate::pbsid::Order::Fixed(3);
        order.opts.future = Some(2);
        let (u, s) = super::super::encompass::order_union_spec(&past, &lure).expect("combines");
        assert_eq!(u.signals, lure.signals);
        assert_eq!((u.opts.past, u.opts.future), (10, None));
        assert_eq!(u.opts.order, crate::pbsid::Order::Auto);
        assert!(s.refined && s.signals == user.signals && s.opts.past == 10);
        let (u, _) = super::super::encompass::order_union_spec(&order, &lure).expect("combines");
        assert_eq!(u.opts.order, crate::pbsid::Order::Fixed(3));
        // the larger future window of the two: the Lur'e variant's (None = its past, 8)
        assert_eq!((u.opts.past, u.opts.future), (8, Some(8)));
        // not the order structure plus own-output channels: an ordinary input, or nothing added
        let mut other = user.clone();
        other.signals.inputs.push(vec![Factor::col("u2")]);
        assert!(super::super::encompass::order_union_spec(&past, &other).is_none());
        assert!(super::super::encompass::order_union_spec(&past, &user).is_none());
        // a noise model is not combined
        let mut noisy = lure.clone();
        noisy.noise = Noise::Innovation;
        assert!(super::super::encompass::order_union_spec(&past, &noisy).is_none());
    }

    #[test]
    fn a_moved_frequency_is_named_with_both_values() {
        let started = vec![vec![Factor::col("u1")], sin_of("y1", 0.3778)];
        let fitted = vec![vec![Factor::col("u1")], sin_of("y1", 0.4012)];
        let lines = refined_frequencies(&started, &fitted);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert_eq!(
            lines[0],
            "the frequency of sin(omega y1) refined with the matrices: omega 0.3778 -> 0.4012"
        );
        // a frequency the fit kept, and a channel without one, say nothing
        assert!(refined_frequencies(&started, &started).is_empty());
    }
}
