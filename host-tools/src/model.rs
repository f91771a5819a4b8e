//! Model files (DESIGN.md section 5): JSON `lpv-ss` and `lpv-arx` models with the map from
//! data columns to model signals (products of factors) and the free `fit` record.
//! Reading validates everything and names file, line and column; writing is atomic.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::data::{DataError, Dataset};
use crate::lpvss::{LpvSs, ShapeError, Signals};

/// The column name that stands for the sample index k (so `sin` of it is a sinusoid in time).
pub const SAMPLE_INDEX: &str = "k";

/// A function applied to a factor's (delayed) value before the power.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FactorFn {
    /// |v|.
    Abs,
    /// signum(v), 0 at 0.
    Sign,
    /// sin(omega v).
    Sin,
    /// cos(omega v).
    Cos,
}

fn one() -> f64 {
    1.0
}

/// Write a power that is a whole number as a JSON integer (`"pow": 2`), any other as a float.
fn ser_pow<S: serde::Serializer>(p: &f64, s: S) -> Result<S::Ok, S::Error> {
    if p.fract() == 0.0 && p.abs() < 9.0e15 {
        s.serialize_i64(*p as i64)
    } else {
        s.serialize_f64(*p)
    }
}

/// One factor of a model signal: `fn(col(k - delay))^pow`, e.g. `{"col": "u1", "pow": 2}`.
///
/// When `col` is one of the model's outputs (a column an output product reads plainly,
/// [`SignalMap::own_outputs`]) the factor reads the model's **own** output: the simulated one
/// in free run, the measured one in one-step prediction and identification (DESIGN.md
/// section 5; this is how a Lur'e feedback y^3 or a quasi-LPV scheduling on y^2 is written).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Factor {
    /// Data column, or [`SAMPLE_INDEX`] (`"k"`) for the sample index.
    pub col: String,
    /// Power, default 1: a whole number (may be 0 or negative) applies to the value, any
    /// other to its magnitude (`"pow": 0.5` is sqrt|x|).
    #[serde(default = "one", serialize_with = "ser_pow")]
    pub pow: f64,
    /// Delay in samples, default 0; values before the start of the record are 0.
    #[serde(default)]
    pub delay: usize,
    /// Optional function, JSON key `"fn"`.
    #[serde(rename = "fn", default)]
    pub func: Option<FactorFn>,
    /// Angular frequency for `sin`/`cos` (rad per unit of the column; 1 when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub omega: Option<f64>,
    /// Causal first-order low-pass of the data column, JSON key `"smooth"`, applied first
    /// (before delay, fn and pow): s(k) = a s(k-1) + (1 - a) x(k) with pole a in [0, 1),
    /// started at s(0) = x(0) so the start is not pulled towards 0 (a noisy scheduling
    /// sensor; `diagnose`'s scheduling-noise correction). Absent = no smoothing. Refused on
    /// `"k"` and on the model's own output (a free run would have to carry the filter's
    /// state through the loop; [`SignalMap::check`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smooth: Option<f64>,
}

impl Factor {
    /// The plain column `name`: power 1, no delay, no function.
    pub fn col(name: &str) -> Factor {
        Factor {
            col: name.to_owned(),
            pow: 1.0,
            delay: 0,
            func: None,
            omega: None,
            smooth: None,
        }
    }

    /// Is this factor the plain column (power 1, no delay, no function, no smoothing)?
    pub fn is_plain(&self) -> bool {
        self.pow == 1.0 && self.delay == 0 && self.func.is_none() && self.smooth.is_none()
    }

    /// Check the factor on its own (a column name, a finite power, `omega` only with
    /// `sin`/`cos` and finite).
    pub fn check(&self) -> Result<(), String> {
        if self.col.is_empty() {
            return Err("\"col\" is empty: name a data column or \"k\"".into());
        }
        if !self.pow.is_finite() {
            return Err(format!("\"pow\" {} is not finite", self.pow));
        }
        if let Some(a) = self.smooth {
            if !(0.0..1.0).contains(&a) {
                return Err(format!(
                    "\"smooth\" {a} is not a low-pass pole in [0, 1) (s(k) = a s(k-1) + (1 - a) x(k))"
                ));
            }
            if self.col == SAMPLE_INDEX {
                return Err(
                    "\"smooth\" does not apply to the sample index \"k\": smooth a data column"
                        .into(),
                );
            }
        }
        match (self.func, self.omega) {
            (Some(FactorFn::Sin | FactorFn::Cos), Some(w)) if !w.is_finite() => {
                Err(format!("\"omega\" {w} is not finite"))
            }
            (Some(FactorFn::Abs | FactorFn::Sign) | None, Some(_)) => {
                Err("\"omega\" is only used with \"fn\": \"sin\" or \"cos\"".into())
            }
            _ => Ok(()),
        }
    }

    /// The factor's value for a (delayed) column value `v`: the function, then the power (a
    /// non-integer power of |fn(v)|). NaN for a negative power of 0 (the caller reports it).
    pub fn apply(&self, v: f64) -> f64 {
        let w = self.omega.unwrap_or(1.0);
        let v = match self.func {
            None => v,
            Some(FactorFn::Abs) => v.abs(),
            Some(FactorFn::Sign) => {
                if v == 0.0 {
                    0.0
                } else {
                    v.signum()
                }
            }
            Some(FactorFn::Sin) => (w * v).sin(),
            Some(FactorFn::Cos) => (w * v).cos(),
        };
        if self.pow == 1.0 {
            return v;
        }
        if self.pow < 0.0 && v == 0.0 {
            return f64::NAN;
        }
        if self.pow.fract() == 0.0 && self.pow.abs() <= i32::MAX as f64 {
            v.powi(self.pow as i32)
        } else {
            v.abs().powf(self.pow)
        }
    }

    /// The derivative of [`Factor::apply`] at `v` (the chain rule through the function and
    /// the power; 0 for `sign`, and for `abs` at 0), for the forward sensitivities of a free
    /// run through the feedback ([`crate::sensitivity`]). Not finite where the power is below
    /// 1 and the function is 0 (sqrt|y| at y = 0); the caller decides what to do there.
    pub fn slope(&self, v: f64) -> f64 {
        let w = self.omega.unwrap_or(1.0);
        let (g, dg) = match self.func {
            None => (v, 1.0),
            Some(FactorFn::Abs) => (v.abs(), if v == 0.0 { 0.0 } else { v.signum() }),
            Some(FactorFn::Sign) => return 0.0,
            Some(FactorFn::Sin) => ((w * v).sin(), w * (w * v).cos()),
            Some(FactorFn::Cos) => ((w * v).cos(), -w * (w * v).sin()),
        };
        let p = self.pow;
        if p == 1.0 {
            dg
        } else if p == 0.0 {
            0.0
        } else if p.fract() == 0.0 && p.abs() <= i32::MAX as f64 {
            p * g.powi(p as i32 - 1) * dg
        } else {
            let s = if g == 0.0 { 0.0 } else { g.signum() };
            p * g.abs().powf(p - 1.0) * s * dg
        }
    }

    /// The column's values as the factor reads them before the delay: the data as they are,
    /// or their causal low-pass s(k) = a s(k-1) + (1 - a) x(k), s(0) = x(0), with `"smooth": a`.
    pub fn smoothed<'d>(&self, data: &'d [f64]) -> std::borrow::Cow<'d, [f64]> {
        match self.smooth {
            None => std::borrow::Cow::Borrowed(data),
            Some(a) => std::borrow::Cow::Owned(low_pass(data, a)),
        }
    }

    /// The factor in words, e.g. `abs(u1(k-2))^2`, `sin(0.3*k)`, `y1^0.5` or
    /// `lowpass0.8(p1)(k-1)` (`"smooth": 0.8`, then the delay).
    pub fn describe(&self) -> String {
        let col = match self.smooth {
            Some(a) => format!("lowpass{a}({})", self.col),
            None => self.col.clone(),
        };
        let base = if self.delay == 0 {
            col
        } else if self.col == SAMPLE_INDEX {
            format!("(k-{})", self.delay)
        } else {
            format!("{col}(k-{})", self.delay)
        };
        let w = self.omega.unwrap_or(1.0);
        let trig = |name: &str| {
            if w == 1.0 {
                format!("{name}({base})")
            } else {
                format!("{name}({w}*{base})")
            }
        };
        let mut s = match self.func {
            None => base.clone(),
            Some(FactorFn::Abs) => format!("abs({base})"),
            Some(FactorFn::Sign) => format!("sign({base})"),
            Some(FactorFn::Sin) => trig("sin"),
            Some(FactorFn::Cos) => trig("cos"),
        };
        if self.pow != 1.0 {
            if self.pow.fract() != 0.0 && self.func.is_none() {
                s = format!("|{base}|");
            }
            let _ = write!(s, "^{}", self.pow);
        }
        s
    }
}

/// The causal first-order low-pass s(k) = a s(k-1) + (1 - a) x(k) of `x`, started at
/// s(0) = x(0) (a unit-gain filter: a constant passes unchanged, and the first samples are not
/// pulled towards 0 as from s(-1) = 0). The factor key `"smooth": a` ([`Factor::smooth`]).
pub fn low_pass(x: &[f64], a: f64) -> Vec<f64> {
    let mut s = x.first().copied().unwrap_or(0.0);
    x.iter()
        .map(|&v| {
            s = a * s + (1.0 - a) * v;
            s
        })
        .collect()
}

/// A product of factors in words (`1` for the empty product).
pub fn describe(product: &[Factor]) -> String {
    if product.is_empty() {
        return "1".into();
    }
    product
        .iter()
        .map(Factor::describe)
        .collect::<Vec<_>>()
        .join("*")
}

/// The values of a product of factors at every sample of `ds` (the empty product is 1).
/// `role` names the model signal (e.g. "input 2") in errors.
pub fn eval_product(product: &[Factor], ds: &Dataset, role: &str) -> Result<Vec<f64>, DataError> {
    let n = ds.len();
    let mut out = vec![1.0; n];
    for f in product {
        let what = format!("{role} ({}) of the model", describe(product));
        f.check()
            .map_err(|m| DataError::new(&ds.source, None, Some(&f.col), format!("{what}: {m}")))?;
        let data = if f.col == SAMPLE_INDEX {
            None
        } else {
            Some(ds.column(&f.col).ok_or_else(|| {
                DataError::new(
                    &ds.source,
                    Some(1),
                    Some(&f.col),
                    format!(
                        "no such column, needed by {what}; the columns are: {}",
                        ds.names.join(", ")
                    ),
                )
            })?)
        };
        let data = data.map(|d| f.smoothed(d));
        for (k, o) in out.iter_mut().enumerate() {
            let v = match (k.checked_sub(f.delay), &data) {
                (None, _) => 0.0,
                (Some(j), None) => j as f64,
                (Some(j), Some(d)) => d[j],
            };
            let x = f.apply(v);
            if x.is_nan() && f.pow < 0.0 {
                return Err(DataError::new(
                    &ds.source,
                    Some(k + 2),
                    Some(&f.col),
                    format!(
                        "{what}: {} is 0 at sample {k}, so the power {} is undefined",
                        f.describe(),
                        f.pow
                    ),
                ));
            }
            *o *= x;
        }
    }
    if let Some(k) = out.iter().position(|v| !v.is_finite()) {
        let col = product.first().map(|f| f.col.as_str());
        return Err(DataError::new(
            &ds.source,
            Some(k + 2),
            col,
            format!(
                "{role} ({}) of the model overflows at sample {k} (value {})",
                describe(product),
                out[k]
            ),
        ));
    }
    Ok(out)
}

/// What each model input, scheduling basis function and output is, as products of factors
/// read from the data file. The first scheduling basis function is the constant `[]`.
#[derive(Debug, Clone, PartialEq)]
pub struct SignalMap {
    /// One product per input channel.
    pub inputs: Vec<Vec<Factor>>,
    /// One product per scheduling basis function mu^(1..m); mu^(1) = `[]` = 1.
    pub scheduling: Vec<Vec<Factor>>,
    /// One product per output channel.
    pub outputs: Vec<Vec<Factor>>,
}

impl SignalMap {
    /// The plain map: inputs u1..ur, outputs y1..yl, scheduling 1, p1..ps.
    pub fn standard(r: usize, l: usize, s: usize) -> SignalMap {
        let plain = |prefix: char, count: usize| -> Vec<Vec<Factor>> {
            (1..=count)
                .map(|i| vec![Factor::col(&format!("{prefix}{i}"))])
                .collect()
        };
        let mut scheduling = vec![Vec::new()];
        scheduling.extend(plain('p', s));
        SignalMap {
            inputs: plain('u', r),
            scheduling,
            outputs: plain('y', l),
        }
    }

    /// The plain map for the channels `ds` has (u1.., y1.., p1.. counted from 1).
    pub fn default_for(ds: &Dataset) -> Result<SignalMap, DataError> {
        let (r, l, s) = (
            ds.channels('u').len(),
            ds.channels('y').len(),
            ds.channels('p').len(),
        );
        if l == 0 {
            return Err(DataError::new(
                &ds.source,
                Some(1),
                Some("y1"),
                format!(
                    "no output column: outputs are named y1, y2, ...; the columns are: {}",
                    ds.names.join(", ")
                ),
            ));
        }
        Ok(SignalMap::standard(r, l, s))
    }

    /// Number of local models m (scheduling basis functions, the constant included).
    pub fn m(&self) -> usize {
        self.scheduling.len()
    }

    /// The names of the scheduling functions mu^(2..m) ([`describe`]), as the stability
    /// region and the observer's box report them (the constant mu^(1) has none).
    pub fn scheduling_names(&self) -> Vec<String> {
        self.scheduling
            .iter()
            .skip(1)
            .map(|p| describe(p))
            .collect()
    }

    /// Check the map on its own: at least one output, first scheduling function `[]`,
    /// every factor valid. The error says where (e.g. `scheduling[0]`).
    pub fn check(&self) -> Result<(), String> {
        self.check_located()
            .map_err(|l| format!("{}: {}", path_string(&l.path), l.msg))
    }

    fn check_located(&self) -> Result<(), Loc> {
        if self.outputs.is_empty() {
            return Err(Loc::new(
                vec![key("outputs")],
                "the model needs at least one output",
            ));
        }
        match self.scheduling.first() {
            None => {
                return Err(Loc::new(
                    vec![key("scheduling")],
                    "the first scheduling basis function must be [] (the constant 1)",
                ))
            }
            Some(first) if !first.is_empty() => {
                return Err(Loc::new(
                    vec![key("scheduling"), Seg::Index(0)],
                    "the first scheduling basis function must be [] (the constant 1)",
                ))
            }
            _ => {}
        }
        for (name, list) in [
            ("inputs", &self.inputs),
            ("scheduling", &self.scheduling),
            ("outputs", &self.outputs),
        ] {
            for (i, prod) in list.iter().enumerate() {
                for (j, f) in prod.iter().enumerate() {
                    let at = || vec![key(name), Seg::Index(i), Seg::Index(j)];
                    f.check().map_err(|m| Loc::new(at(), m))?;
                    if f.smooth.is_some() && name != "outputs" && self.own_output(f).is_some() {
                        return Err(Loc::new(
                            at(),
                            format!(
                                "\"smooth\" on the model's own output {} is not supported: a free run \
                                 would have to carry the filter's state through the output loop; \
                                 smooth a data column, or read {0} without \"smooth\"",
                                f.col
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// The first signal that differs from the plain map [`SignalMap::standard`] of the same
    /// counts (its place, e.g. `scheduling[1]`, and what it is against what the plain map
    /// reads there), if any. The device's predictor reads its frame's channels u1.., y1..,
    /// p1.. as they come, so a model that needs anything else (a power, a delay, a function,
    /// a low-pass, an own-output feedback, another column) cannot run there and is refused
    /// before it is pushed.
    pub fn first_non_standard(&self) -> Option<String> {
        let plain = SignalMap::standard(
            self.inputs.len(),
            self.outputs.len(),
            self.scheduling.len().saturating_sub(1),
        );
        for (name, list, want) in [
            ("inputs", &self.inputs, &plain.inputs),
            ("scheduling", &self.scheduling, &plain.scheduling),
            ("outputs", &self.outputs, &plain.outputs),
        ] {
            for (i, (prod, w)) in list.iter().zip(want).enumerate() {
                if prod != w {
                    return Some(format!(
                        "{name}[{i}] is {} where the device reads {}",
                        describe(prod),
                        describe(w)
                    ));
                }
            }
        }
        None
    }

    /// The model's signals on `ds`: u (N x r), y (N x l) and p (N x (m-1), the scheduling
    /// basis functions after the constant). Missing columns name the signal that needs them.
    pub fn evaluate(&self, ds: &Dataset) -> Result<Signals, DataError> {
        self.check().map_err(|m| {
            DataError::new(&ds.source, None, None, format!("invalid signal map: {m}"))
        })?;
        let n = ds.len();
        let build = |list: &[Vec<Factor>], role: &str, skip: usize| {
            let mut m = DMatrix::<f64>::zeros(n, list.len() - skip);
            for (j, prod) in list.iter().enumerate().skip(skip) {
                let v = eval_product(prod, ds, &format!("{role} {}", j + 1))?;
                m.set_column(j - skip, &nalgebra::DVector::from_vec(v));
            }
            Ok::<_, DataError>(m)
        };
        Ok(Signals {
            u: build(&self.inputs, "input", 0)?,
            y: build(&self.outputs, "output", 0)?,
            p: build(&self.scheduling, "scheduling basis function", 1)?,
        })
    }

    /// Per output, the data column it reads plainly (`[{"col": "y1"}]`), if it does: a factor
    /// on that column elsewhere in the map reads the model's **own** output.
    pub fn own_outputs(&self) -> Vec<Option<&str>> {
        self.outputs
            .iter()
            .map(|p| match p.as_slice() {
                [f] if f.is_plain() && f.col != SAMPLE_INDEX => Some(f.col.as_str()),
                _ => None,
            })
            .collect()
    }

    /// The output a factor reads when its column is one of the model's own outputs.
    pub fn own_output(&self, f: &Factor) -> Option<usize> {
        self.own_outputs()
            .iter()
            .position(|c| *c == Some(f.col.as_str()))
    }

    /// Does any input channel or scheduling function read the model's own output?
    pub fn has_feedback(&self) -> bool {
        self.inputs
            .iter()
            .chain(self.scheduling.iter())
            .flatten()
            .any(|f| self.own_output(f).is_some())
    }

    /// The own-output dependence of the map on `ds` ([`Feedback`]; empty when there is none):
    /// what a free run must recompute from the simulated outputs at each sample.
    pub fn feedback(&self, ds: &Dataset) -> Result<Feedback, DataError> {
        let mut fb = Feedback::default();
        if !self.has_feedback() {
            return Ok(fb);
        }
        let build = |prod: &[Factor], role: &str| -> Result<Option<Loop>, DataError> {
            let (own, data): (Vec<&Factor>, Vec<&Factor>) =
                prod.iter().partition(|f| self.own_output(f).is_some());
            if own.is_empty() {
                return Ok(None);
            }
            let data: Vec<Factor> = data.into_iter().cloned().collect();
            Ok(Some(Loop {
                data: eval_product(&data, ds, role)?,
                own: own
                    .into_iter()
                    .map(|f| OwnFactor {
                        output: self.own_output(f).unwrap_or(0),
                        factor: f.clone(),
                    })
                    .collect(),
            }))
        };
        for (i, prod) in self.inputs.iter().enumerate() {
            if let Some(l) = build(prod, &format!("input {}", i + 1))? {
                fb.inputs.push((i, l));
            }
        }
        for (q, prod) in self.scheduling.iter().enumerate().skip(1) {
            if let Some(l) = build(prod, &format!("scheduling basis function {}", q + 1))? {
                fb.scheduling.push((q - 1, l));
            }
        }
        Ok(fb)
    }

    /// Refuse a model whose output equation would need the output it is computing: a
    /// delay-0 own-output factor in an input channel with a non-zero D column (lpv-arx: b_0),
    /// or in a scheduling function that C^(i) or D^(i) use (lpv-arx: any, since a_i(p(k))
    /// multiplies the past outputs at sample k).
    pub fn check_loops(&self, kind: &ModelKind) -> Result<(), AlgebraicLoop> {
        let own_now = |prod: &[Factor]| {
            prod.iter()
                .position(|f| f.delay == 0 && self.own_output(f).is_some())
        };
        for (i, prod) in self.inputs.iter().enumerate() {
            let Some(j) = own_now(prod) else { continue };
            let used = match kind {
                ModelKind::Ss(ss) => ss.d.iter().any(|d| d.column(i).amax() != 0.0),
                ModelKind::Arx(a) => a.b[i].first().is_some_and(|b| b.iter().any(|v| *v != 0.0)),
            };
            if used {
                return Err(AlgebraicLoop::Input {
                    input: i,
                    factor: j,
                    col: prod[j].col.clone(),
                    arx: matches!(kind, ModelKind::Arx(_)),
                });
            }
        }
        for (q, prod) in self.scheduling.iter().enumerate().skip(1) {
            let Some(j) = own_now(prod) else { continue };
            let used = match kind {
                ModelKind::Ss(ss) => {
                    let nz = |ms: &[DMatrix<f64>]| ms.len() > 1 && ms[q].amax() != 0.0;
                    nz(&ss.c) || nz(&ss.d)
                }
                ModelKind::Arx(_) => true,
            };
            if used {
                return Err(AlgebraicLoop::Scheduling {
                    function: q,
                    factor: j,
                    col: prod[j].col.clone(),
                    arx: matches!(kind, ModelKind::Arx(_)),
                });
            }
        }
        Ok(())
    }
}

/// A model whose output at sample k would need itself (an algebraic loop through a delay-0
/// own-output factor); [`SignalMap::check_loops`]. Indices are 0-based.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AlgebraicLoop {
    /// An input channel reads the output at the same sample and enters the output equation.
    #[error("{} at the same sample (delay 0), but {}: the output equation would need the output it is computing; give the factor a delay >= 1{}", input_what(*input, col), if *arx { "the lag-0 coefficient b_0 of this input is non-zero".to_string() } else { format!("column {} of D is non-zero", input + 1) }, if *arx { " or set b_0 to zero" } else { " or make that D column zero" })]
    Input {
        /// Input channel.
        input: usize,
        /// Factor within the channel's product.
        factor: usize,
        /// The output column it reads.
        col: String,
        /// The model is lpv-arx.
        arx: bool,
    },
    /// A scheduling function reads the output at the same sample and the output equation
    /// depends on it.
    #[error("scheduling basis function {} reads the model's output {col} at the same sample (delay 0), but {}: the output equation would need the output it is computing; give the factor a delay >= 1", function + 1, if *arx { "an lpv-arx model's coefficients a_i(p(k)) at sample k multiply its past outputs".to_string() } else { format!("C^({0}) or D^({0}) is non-zero", function + 1) })]
    Scheduling {
        /// Scheduling basis function (0 is the constant).
        function: usize,
        /// Factor within the function's product.
        factor: usize,
        /// The output column it reads.
        col: String,
        /// The model is lpv-arx.
        arx: bool,
    },
}

fn input_what(input: usize, col: &str) -> String {
    format!("input {} reads the model's output {col}", input + 1)
}

impl AlgebraicLoop {
    fn path(&self) -> Vec<Seg> {
        match self {
            AlgebraicLoop::Input { input, factor, .. } => {
                vec![key("inputs"), Seg::Index(*input), Seg::Index(*factor)]
            }
            AlgebraicLoop::Scheduling {
                function, factor, ..
            } => vec![
                key("scheduling"),
                Seg::Index(*function),
                Seg::Index(*factor),
            ],
        }
    }
}

/// A factor that reads the model's own output `output` (0-based).
#[derive(Debug, Clone, PartialEq)]
pub struct OwnFactor {
    /// Which model output.
    pub output: usize,
    /// The factor (its delay, function and power).
    pub factor: Factor,
}

/// A model signal that reads the model's own output: the product of its data factors per
/// sample, times its own-output factors evaluated on the outputs of the run.
#[derive(Debug, Clone, PartialEq)]
pub struct Loop {
    /// Product of the factors that read data (1 without any), per sample.
    pub data: Vec<f64>,
    /// The factors that read the model's own outputs.
    pub own: Vec<OwnFactor>,
}

impl Loop {
    /// The signal at sample k from the outputs `y` of the run (rows `< avail` known; an
    /// unknown or pre-record value counts as 0).
    pub fn value(&self, k: usize, y: &DMatrix<f64>, avail: usize) -> f64 {
        let mut v = self.data[k];
        for o in &self.own {
            let x = match k.checked_sub(o.factor.delay) {
                Some(j) if j < avail => y[(j, o.output)],
                _ => 0.0,
            };
            v *= o.factor.apply(x);
        }
        v
    }
}

/// The own-output dependence of a model's signals on a data set ([`SignalMap::feedback`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Feedback {
    /// (input channel, its loop).
    pub inputs: Vec<(usize, Loop)>,
    /// (column of p, i.e. scheduling basis function - 1, its loop).
    pub scheduling: Vec<(usize, Loop)>,
}

impl Loop {
    /// Does the signal read an output at the same sample (delay 0)? Such a signal stays out
    /// of the output equation ([`SignalMap::check_loops`]).
    pub fn reads_same_sample(&self) -> bool {
        self.own.iter().any(|o| o.factor.delay == 0)
    }
}

impl Feedback {
    /// No signal reads the model's own output.
    pub fn is_empty(&self) -> bool {
        self.inputs.is_empty() && self.scheduling.is_empty()
    }

    /// The feedback over samples `start..start + len` of its record (the signals'
    /// [`crate::lpvss::Signals::slice`]): each loop's data factors over those rows.
    pub fn rows(&self, start: usize, len: usize) -> Feedback {
        let cut = |loops: &[(usize, Loop)]| -> Vec<(usize, Loop)> {
            loops
                .iter()
                .map(|(i, lp)| {
                    let data = lp.data[start..start + len].to_vec();
                    (
                        *i,
                        Loop {
                            data,
                            own: lp.own.clone(),
                        },
                    )
                })
                .collect()
        };
        Feedback {
            inputs: cut(&self.inputs),
            scheduling: cut(&self.scheduling),
        }
    }

    /// The largest delay of an own-output factor (0 without any): how many outputs before a
    /// sample the feedback reads.
    pub fn max_delay(&self) -> usize {
        self.inputs
            .iter()
            .chain(&self.scheduling)
            .flat_map(|(_, lp)| lp.own.iter().map(|o| o.factor.delay))
            .max()
            .unwrap_or(0)
    }

    /// The input channels that read an output at the same sample ([`Loop::reads_same_sample`]):
    /// their D columns are zero.
    pub fn same_sample_inputs(&self) -> Vec<usize> {
        self.inputs
            .iter()
            .filter(|(_, l)| l.reads_same_sample())
            .map(|(i, _)| *i)
            .collect()
    }

    /// Overwrite the inputs `u` (r values) and scheduling signals `p` of sample k with the
    /// loops' values from the run's outputs `y` (rows `< avail` known); a loop on a
    /// scheduling signal beyond `p` is not written (the model has no weight for it). The
    /// state-space free run's sample loop ([`crate::simulate::free_run_ss_into`]).
    pub fn fill_sample(
        &self,
        k: usize,
        y: &DMatrix<f64>,
        avail: usize,
        u: &mut [f64],
        p: &mut [f64],
    ) {
        for (i, l) in &self.inputs {
            u[*i] = l.value(k, y, avail);
        }
        for (q, l) in &self.scheduling {
            if let Some(v) = p.get_mut(*q) {
                *v = l.value(k, y, avail);
            }
        }
    }

    /// Overwrite sample k of the inputs `u` (N x r) and scheduling `p` (N x s) with the loops'
    /// values from the run's outputs `y` (rows `< avail` known): the ARX recursion, which
    /// reads the inputs at past lags ([`crate::simulate::arx_run_from`]).
    pub fn fill(
        &self,
        k: usize,
        y: &DMatrix<f64>,
        avail: usize,
        u: &mut DMatrix<f64>,
        p: &mut DMatrix<f64>,
    ) {
        for (i, l) in &self.inputs {
            u[(k, *i)] = l.value(k, y, avail);
        }
        for (q, l) in &self.scheduling {
            p[(k, *q)] = l.value(k, y, avail);
        }
    }
}

/// An LPV-ARX model y(k) = -sum_i a_i(p(k)) y(k-i) + sum_j b_j(p(k)) u(k-j), single output.
#[derive(Debug, Clone, PartialEq)]
pub struct ArxModel {
    /// Number of output lags.
    pub na: usize,
    /// Largest input lag (lags 0..=nb).
    pub nb: usize,
    /// `a[i-1][q]`: coefficient of lag i on scheduling basis function q.
    pub a: Vec<Vec<f64>>,
    /// `b[input][j][q]`: coefficient of input lag j on scheduling basis function q.
    pub b: Vec<Vec<Vec<f64>>>,
}

/// The model proper: state space or ARX.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelKind {
    /// `"type": "lpv-ss"`.
    Ss(LpvSs),
    /// `"type": "lpv-arx"`.
    Arx(ArxModel),
}

/// A model file: the model, what its signals are, and how it was fitted.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFile {
    /// The model.
    pub kind: ModelKind,
    /// Data columns -> model signals.
    pub signals: SignalMap,
    /// Free record of settings and data fingerprints (a JSON object), kept as is.
    pub fit: Value,
}

const TYPES: &str = "the model types are \"lpv-ss\" and \"lpv-arx\"";
const SIGNAL_KEYS: [&str; 5] = ["type", "inputs", "scheduling", "outputs", "fit"];
const SS_KEYS: [&str; 5] = ["A", "B", "K", "C", "D"];
const ARX_KEYS: [&str; 4] = ["na", "nb", "a", "b"];

impl ModelFile {
    /// Read and validate a model file; errors name the file as `path` displays.
    pub fn read(path: &Path) -> Result<ModelFile, DataError> {
        let source = path.display().to_string();
        let bytes = std::fs::read(path)
            .map_err(|e| DataError::new(&source, None, None, format!("cannot read: {e}")))?;
        let text = String::from_utf8(bytes).map_err(|e| {
            let at = e.utf8_error().valid_up_to();
            let line = e.as_bytes()[..at].iter().filter(|&&b| b == b'\n').count() + 1;
            DataError::new(&source, Some(line), None, "invalid UTF-8 text")
        })?;
        ModelFile::from_json_str(&source, &text)
    }

    /// Parse and validate model JSON; `source` is the file name used in errors.
    pub fn from_json_str(source: &str, text: &str) -> Result<ModelFile, DataError> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let v: Value = serde_json::from_str(text).map_err(|e| syntax_error(source, text, &e))?;
        let v = exact_value(text).unwrap_or(v);
        parse_model(&v).map_err(|l| l.into_error(source, text))
    }

    /// The model as pretty JSON (matrix rows and factors on one line each).
    pub fn to_json_string(&self) -> String {
        let mut entries: Vec<(&str, String)> = Vec::new();
        let render = |v: &Value| {
            let mut s = String::new();
            pretty(v, 1, &mut s);
            s
        };
        let type_name = match self.kind {
            ModelKind::Ss(_) => "lpv-ss",
            ModelKind::Arx(_) => "lpv-arx",
        };
        entries.push(("type", render(&Value::from(type_name))));
        entries.push(("inputs", products_text(&self.signals.inputs)));
        entries.push(("scheduling", products_text(&self.signals.scheduling)));
        entries.push(("outputs", products_text(&self.signals.outputs)));
        match &self.kind {
            ModelKind::Ss(ss) => {
                let list =
                    |ms: &[DMatrix<f64>]| Value::Array(ms.iter().map(matrix_value).collect());
                let one_or_list = |ms: &[DMatrix<f64>]| {
                    if ms.len() == 1 {
                        matrix_value(&ms[0])
                    } else {
                        list(ms)
                    }
                };
                entries.push(("A", render(&list(&ss.a))));
                entries.push(("B", render(&list(&ss.b))));
                entries.push(("K", render(&list(&ss.k))));
                entries.push(("C", render(&one_or_list(&ss.c))));
                entries.push(("D", render(&one_or_list(&ss.d))));
            }
            ModelKind::Arx(arx) => {
                let nested = |x: Value| render(&x);
                entries.push(("na", arx.na.to_string()));
                entries.push(("nb", arx.nb.to_string()));
                entries.push(("a", nested(floats2(&arx.a))));
                entries.push((
                    "b",
                    nested(Value::Array(arx.b.iter().map(|l| floats2(l)).collect())),
                ));
            }
        }
        entries.push(("fit", render(&self.fit)));
        let mut out = String::from("{\n");
        for (i, (k, v)) in entries.iter().enumerate() {
            out.push_str("  ");
            out.push_str(&Value::from(*k).to_string());
            out.push_str(": ");
            out.push_str(v);
            out.push_str(if i + 1 < entries.len() { ",\n" } else { "\n" });
        }
        out.push_str("}\n");
        out
    }

    /// Validate and write atomically (temporary file + rename): an invalid model is refused
    /// and nothing half-written is ever left at `path`.
    pub fn write(&self, path: &Path) -> Result<(), DataError> {
        self.stage(path)?.commit()
    }

    /// Validate and prepare writing to `path` ([`crate::data::stage_write`]): nothing at
    /// `path` changes until the returned write is committed, so a command can write all its
    /// outputs together at the end.
    pub fn stage(&self, path: &Path) -> Result<crate::data::StagedWrite, DataError> {
        let file = path.display().to_string();
        if let Some(at) = self.first_non_finite() {
            return Err(DataError::new(
                &file,
                None,
                None,
                format!("not written: {at} is not finite"),
            ));
        }
        let text = self.to_json_string();
        ModelFile::from_json_str(&file, &text).map_err(|e| DataError {
            line: None,
            message: format!(
                "not written, the model is invalid (line {} of the text it would have): {}",
                e.line.unwrap_or(1),
                e.message
            ),
            ..e
        })?;
        crate::data::stage_write(path, text.as_bytes())
    }

    /// The path of the first NaN or infinite number in the model, if any.
    fn first_non_finite(&self) -> Option<String> {
        let bad = |x: &f64| !x.is_finite();
        match &self.kind {
            ModelKind::Ss(ss) => {
                for (name, ms) in [
                    ("A", &ss.a),
                    ("B", &ss.b),
                    ("K", &ss.k),
                    ("C", &ss.c),
                    ("D", &ss.d),
                ] {
                    for (i, m) in ms.iter().enumerate() {
                        if let Some(idx) = m.iter().position(bad) {
                            let (r, c) = (idx % m.nrows(), idx / m.nrows());
                            return Some(format!("{name}[{i}][{r}][{c}]"));
                        }
                    }
                }
            }
            ModelKind::Arx(arx) => {
                for (i, row) in arx.a.iter().enumerate() {
                    if let Some(q) = row.iter().position(bad) {
                        return Some(format!("a[{i}][{q}]"));
                    }
                }
                for (i, lags) in arx.b.iter().enumerate() {
                    for (j, row) in lags.iter().enumerate() {
                        if let Some(q) = row.iter().position(bad) {
                            return Some(format!("b[{i}][{j}][{q}]"));
                        }
                    }
                }
            }
        }
        for (name, list) in [
            ("inputs", &self.signals.inputs),
            ("scheduling", &self.signals.scheduling),
            ("outputs", &self.signals.outputs),
        ] {
            for (i, prod) in list.iter().enumerate() {
                for (j, f) in prod.iter().enumerate() {
                    if f.omega.is_some_and(|w| !w.is_finite()) {
                        return Some(format!("{name}[{i}][{j}].omega"));
                    }
                    if f.smooth.is_some_and(|a| !a.is_finite()) {
                        return Some(format!("{name}[{i}][{j}].smooth"));
                    }
                }
            }
        }
        None
    }
}

// ---------------------------------------------------------------------------------------
// Reading: serde_json gives a Value (syntax errors with line/column); the conversion below
// reports semantic errors as a JSON path, located back in the text by `locate`.

/// One step of a JSON path.
#[derive(Debug, Clone, PartialEq)]
enum Seg {
    Key(String),
    Index(usize),
}

fn key(k: &str) -> Seg {
    Seg::Key(k.to_owned())
}

fn with(path: &[Seg], seg: Seg) -> Vec<Seg> {
    let mut p = path.to_vec();
    p.push(seg);
    p
}

/// A semantic error at a JSON path.
#[derive(Debug)]
struct Loc {
    path: Vec<Seg>,
    msg: String,
}

impl Loc {
    fn new(path: Vec<Seg>, msg: impl Into<String>) -> Loc {
        Loc {
            path,
            msg: msg.into(),
        }
    }

    fn into_error(self, source: &str, text: &str) -> DataError {
        let (line, col) = locate(text, &self.path);
        let msg = if self.path.is_empty() {
            format!("column {col}: {}", self.msg)
        } else {
            format!("column {col}: {}: {}", path_string(&self.path), self.msg)
        };
        DataError::new(source, Some(line), None, msg)
    }
}

fn path_string(path: &[Seg]) -> String {
    let mut s = String::new();
    for (i, seg) in path.iter().enumerate() {
        match seg {
            Seg::Key(k) if i == 0 => s.push_str(k),
            Seg::Key(k) => {
                let _ = write!(s, ".{k}");
            }
            Seg::Index(n) => {
                let _ = write!(s, "[{n}]");
            }
        }
    }
    if s.is_empty() {
        s.push_str("(top level)");
    }
    s
}

fn syntax_error(source: &str, text: &str, e: &serde_json::Error) -> DataError {
    let full = e.to_string();
    let mut msg = match full.rfind(" at line ") {
        Some(i) => full[..i].to_string(),
        None => full,
    };
    let line_text = text.lines().nth(e.line().saturating_sub(1)).unwrap_or("");
    let from = e.column().saturating_sub(2);
    let near: String = line_text
        .get(from..)
        .unwrap_or("")
        .chars()
        .take(10)
        .collect::<String>()
        .to_lowercase();
    if msg.contains("number out of range") || near.contains("nan") || near.contains("inf") {
        msg.push_str(" (non-finite numbers such as NaN or Infinity are not allowed)");
    }
    DataError::new(
        source,
        Some(e.line().max(1)),
        None,
        format!("column {}: {msg}", e.column()),
    )
}

fn kind_of(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
}

fn number(v: &Value, path: &[Seg]) -> Result<f64, Loc> {
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(x),
        Some(x) => Err(Loc::new(path.to_vec(), format!("{x} is not finite"))),
        None => Err(Loc::new(
            path.to_vec(),
            format!("expected a number, found {}", kind_of(v)),
        )),
    }
}

fn array<'a>(v: &'a Value, path: &[Seg], what: &str) -> Result<&'a Vec<Value>, Loc> {
    v.as_array().ok_or_else(|| {
        Loc::new(
            path.to_vec(),
            format!("expected {what}, found {}", kind_of(v)),
        )
    })
}

fn numbers(v: &Value, path: &[Seg], what: &str) -> Result<Vec<f64>, Loc> {
    array(v, path, what)?
        .iter()
        .enumerate()
        .map(|(i, x)| number(x, &with(path, Seg::Index(i))))
        .collect()
}

fn matrix(v: &Value, path: &[Seg]) -> Result<DMatrix<f64>, Loc> {
    const WHAT: &str = "a matrix (a list of rows, each a list of numbers)";
    let rows = array(v, path, WHAT)?;
    if rows.is_empty() {
        return Err(Loc::new(path.to_vec(), "a matrix needs at least one row"));
    }
    let mut data = Vec::new();
    let mut ncols = 0;
    for (i, row) in rows.iter().enumerate() {
        let rp = with(path, Seg::Index(i));
        let row = numbers(row, &rp, "a matrix row (a list of numbers)")?;
        if i == 0 {
            ncols = row.len();
        } else if row.len() != ncols {
            return Err(Loc::new(
                rp,
                format!(
                    "ragged matrix: this row has {} entries, the first row has {ncols}",
                    row.len()
                ),
            ));
        }
        data.extend(row);
    }
    Ok(DMatrix::from_row_slice(rows.len(), ncols, &data))
}

fn matrix_list(v: &Value, path: &[Seg]) -> Result<Vec<DMatrix<f64>>, Loc> {
    let list = array(
        v,
        path,
        "a list of matrices, one per scheduling basis function",
    )?;
    if list.is_empty() {
        return Err(Loc::new(path.to_vec(), "the list of matrices is empty"));
    }
    list.iter()
        .enumerate()
        .map(|(i, m)| matrix(m, &with(path, Seg::Index(i))))
        .collect()
}

/// A single matrix (nesting depth 2) or a list of matrices (depth 3).
fn matrix_or_list(v: &Value, path: &[Seg]) -> Result<Vec<DMatrix<f64>>, Loc> {
    let depth3 = v
        .as_array()
        .and_then(|a| a.first())
        .and_then(Value::as_array)
        .and_then(|a| a.first())
        .is_some_and(Value::is_array);
    if depth3 {
        matrix_list(v, path)
    } else {
        Ok(vec![matrix(v, path)?])
    }
}

fn products(v: &Value, path: &[Seg]) -> Result<Vec<Vec<Factor>>, Loc> {
    let list = array(v, path, "a list of products of factors")?;
    let mut out = Vec::with_capacity(list.len());
    for (i, prod) in list.iter().enumerate() {
        let pp = with(path, Seg::Index(i));
        let factors = array(
            prod,
            &pp,
            "a product: a list of factors ([] is the constant 1)",
        )?;
        let mut fs = Vec::with_capacity(factors.len());
        for (j, f) in factors.iter().enumerate() {
            let fp = with(&pp, Seg::Index(j));
            let fac: Factor = serde_json::from_value(f.clone()).map_err(|e| {
                Loc::new(
                    fp.clone(),
                    format!("not a factor {{\"col\", \"pow\", \"delay\", \"fn\", \"omega\", \"smooth\"}}: {e}"),
                )
            })?;
            fs.push(fac);
        }
        out.push(fs);
    }
    Ok(out)
}

fn usize_field(obj: &Map<String, Value>, name: &str) -> Result<usize, Loc> {
    let v = obj
        .get(name)
        .ok_or_else(|| Loc::new(vec![], format!("missing \"{name}\"")))?;
    v.as_u64()
        .and_then(|x| usize::try_from(x).ok())
        .ok_or_else(|| {
            Loc::new(
                vec![key(name)],
                format!("expected a non-negative integer, found {}", kind_of(v)),
            )
        })
}

fn parse_model(v: &Value) -> Result<ModelFile, Loc> {
    let obj = v.as_object().ok_or_else(|| {
        Loc::new(
            vec![],
            format!("a model file is a JSON object, found {}", kind_of(v)),
        )
    })?;
    let ty = match obj.get("type") {
        None => return Err(Loc::new(vec![], format!("missing \"type\": {TYPES}"))),
        Some(Value::String(s)) => s.as_str(),
        Some(other) => {
            return Err(Loc::new(
                vec![key("type")],
                format!(
                    "\"type\" must be a string, found {}: {TYPES}",
                    kind_of(other)
                ),
            ))
        }
    };
    let model_keys: &[&str] = match ty {
        "lpv-ss" => &SS_KEYS,
        "lpv-arx" => &ARX_KEYS,
        _ => {
            return Err(Loc::new(
                vec![key("type")],
                format!("unknown model type \"{ty}\": {TYPES}"),
            ))
        }
    };
    for k in obj.keys() {
        if !SIGNAL_KEYS.contains(&k.as_str()) && !model_keys.contains(&k.as_str()) {
            let known: Vec<&str> = SIGNAL_KEYS.iter().chain(model_keys).copied().collect();
            return Err(Loc::new(
                vec![key(k)],
                format!(
                    "unknown key \"{k}\" in an {ty} model (the keys are: {})",
                    known.join(", ")
                ),
            ));
        }
    }
    let sig = |name: &str| -> Result<Option<Vec<Vec<Factor>>>, Loc> {
        obj.get(name).map(|v| products(v, &[key(name)])).transpose()
    };
    let (inputs, scheduling, outputs) = (sig("inputs")?, sig("scheduling")?, sig("outputs")?);
    let fit = match obj.get("fit") {
        None => Value::Object(Map::new()),
        Some(f @ (Value::Object(_) | Value::Null)) => f.clone(),
        Some(f) => {
            return Err(Loc::new(
                vec![key("fit")],
                format!("\"fit\" must be an object, found {}", kind_of(f)),
            ))
        }
    };
    let require = |name: &str| {
        obj.get(name)
            .ok_or_else(|| Loc::new(vec![], format!("missing \"{name}\" in an {ty} model")))
    };
    let count_mismatch = |name: &str, have: usize, want: usize, why: &str| {
        Loc::new(
            vec![key(name)],
            format!("lists {have} {name} but the model has {want} ({why})"),
        )
    };

    let (kind, signals) = if ty == "lpv-ss" {
        let ss = LpvSs {
            a: matrix_list(require("A")?, &[key("A")])?,
            b: matrix_list(require("B")?, &[key("B")])?,
            k: matrix_list(require("K")?, &[key("K")])?,
            c: matrix_or_list(require("C")?, &[key("C")])?,
            d: matrix_or_list(require("D")?, &[key("D")])?,
        };
        if let Err(e) = ss.validate() {
            return Err(locate_shape_error(&ss, &e));
        }
        let (r, l, m) = (ss.r(), ss.l(), ss.m());
        let signals = SignalMap {
            inputs: inputs.unwrap_or_else(|| SignalMap::standard(r, 0, 0).inputs),
            scheduling: scheduling.unwrap_or_else(|| SignalMap::standard(0, 0, m - 1).scheduling),
            outputs: outputs.unwrap_or_else(|| SignalMap::standard(0, l, 0).outputs),
        };
        if signals.inputs.len() != r {
            return Err(count_mismatch(
                "inputs",
                signals.inputs.len(),
                r,
                "columns of B and D",
            ));
        }
        if signals.outputs.len() != l {
            return Err(count_mismatch(
                "outputs",
                signals.outputs.len(),
                l,
                "rows of C and D",
            ));
        }
        if signals.scheduling.len() != m {
            return Err(count_mismatch(
                "scheduling",
                signals.scheduling.len(),
                m,
                "matrices in A, one per scheduling basis function",
            ));
        }
        (ModelKind::Ss(ss), signals)
    } else {
        let na = usize_field(obj, "na")?;
        let nb = usize_field(obj, "nb")?;
        let a_val = require("a")?;
        let b_val = require("b")?;
        let a_list = array(
            a_val,
            &[key("a")],
            "a list of lags, each a list of coefficients",
        )?;
        let b_list = array(b_val, &[key("b")], "a list of inputs, each a list of lags")?;
        let a: Vec<Vec<f64>> = a_list
            .iter()
            .enumerate()
            .map(|(i, x)| numbers(x, &[key("a"), Seg::Index(i)], "a list of coefficients"))
            .collect::<Result<_, _>>()?;
        let mut b = Vec::with_capacity(b_list.len());
        for (i, lags) in b_list.iter().enumerate() {
            let p = [key("b"), Seg::Index(i)];
            let lags = array(
                lags,
                &p,
                "a list of lags 0..nb, each a list of coefficients",
            )?;
            let coefs: Vec<Vec<f64>> = lags
                .iter()
                .enumerate()
                .map(|(j, x)| numbers(x, &with(&p, Seg::Index(j)), "a list of coefficients"))
                .collect::<Result<_, _>>()?;
            b.push(coefs);
        }
        if a.len() != na {
            return Err(Loc::new(
                vec![key("a")],
                format!("has {} lags but na = {na}", a.len()),
            ));
        }
        for (i, lags) in b.iter().enumerate() {
            if lags.len() != nb + 1 {
                return Err(Loc::new(
                    vec![key("b"), Seg::Index(i)],
                    format!(
                        "has {} lags but nb = {nb} means lags 0..={nb}, {} entries",
                        lags.len(),
                        nb + 1
                    ),
                ));
            }
        }
        let m = match &scheduling {
            Some(s) => s.len(),
            None => a
                .first()
                .or_else(|| b.first().and_then(|l| l.first()))
                .map_or(1, Vec::len),
        };
        let coef_paths = a
            .iter()
            .enumerate()
            .map(|(i, c)| (vec![key("a"), Seg::Index(i)], c))
            .chain(b.iter().enumerate().flat_map(|(i, lags)| {
                lags.iter()
                    .enumerate()
                    .map(move |(j, c)| (vec![key("b"), Seg::Index(i), Seg::Index(j)], c))
            }));
        for (p, c) in coef_paths {
            if c.len() != m {
                return Err(Loc::new(
                    p,
                    format!(
                        "has {} coefficients but there are {m} scheduling basis functions",
                        c.len()
                    ),
                ));
            }
        }
        if m == 0 {
            return Err(Loc::new(
                vec![key("scheduling")],
                "the first scheduling basis function must be [] (the constant 1)",
            ));
        }
        let r = b.len();
        let signals = SignalMap {
            inputs: inputs.unwrap_or_else(|| SignalMap::standard(r, 0, 0).inputs),
            scheduling: scheduling.unwrap_or_else(|| SignalMap::standard(0, 0, m - 1).scheduling),
            outputs: outputs.unwrap_or_else(|| SignalMap::standard(0, 1, 0).outputs),
        };
        if signals.inputs.len() != r {
            return Err(count_mismatch(
                "inputs",
                signals.inputs.len(),
                r,
                "entries of b",
            ));
        }
        if signals.outputs.len() != 1 {
            return Err(Loc::new(
                vec![key("outputs")],
                format!(
                    "an lpv-arx model has exactly one output, this lists {}",
                    signals.outputs.len()
                ),
            ));
        }
        (ModelKind::Arx(ArxModel { na, nb, a, b }), signals)
    };
    signals.check_located()?;
    signals
        .check_loops(&kind)
        .map_err(|e| Loc::new(e.path(), e.to_string()))?;
    Ok(ModelFile { kind, signals, fit })
}

/// Turn an `LpvSs::check` message into a located error: which list and which matrix.
fn locate_shape_error(ss: &LpvSs, e: &ShapeError) -> Loc {
    let msg = e.to_string();
    let (n, r, l, m) = (ss.n(), ss.r(), ss.l(), ss.m());
    let (name, mats, rows, cols, counts): (&str, &[DMatrix<f64>], usize, usize, &[usize]) = match e
    {
        ShapeError::A { .. } => ("A", &ss.a, n, n, &[m]),
        ShapeError::B { .. } => ("B", &ss.b, n, r, &[m]),
        ShapeError::K { .. } => ("K", &ss.k, n, l, &[m]),
        ShapeError::C { .. } => ("C", &ss.c, l, n, &[1, m]),
        ShapeError::D { .. } => ("D", &ss.d, l, r, &[1, m]),
    };
    let dims = format!("(n = {n} states from A, r = {r} inputs from B, l = {l} outputs from C)");
    if !counts.contains(&mats.len()) {
        return Loc::new(
            vec![key(name)],
            format!("{msg}, found {} {dims}", mats.len()),
        );
    }
    match mats
        .iter()
        .position(|x| x.nrows() != rows || x.ncols() != cols)
    {
        Some(i) => {
            let x = &mats[i];
            let path = if mats.len() == 1 && (name == "C" || name == "D") {
                vec![key(name)]
            } else {
                vec![key(name), Seg::Index(i)]
            };
            Loc::new(
                path,
                format!("{msg}, this one is {}x{} {dims}", x.nrows(), x.ncols()),
            )
        }
        None => Loc::new(vec![key(name)], msg),
    }
}

/// Find the text position (1-based line and column) of a JSON path in valid JSON `text`:
/// the key's quote for object members, the element's first character for list entries.
/// Falls back to the deepest part of the path that was found.
fn locate(text: &str, path: &[Seg]) -> (usize, usize) {
    let b = text.as_bytes();
    let mut i = skip_ws(b, 0);
    let mut best = i;
    for seg in path {
        match (seg, b.get(i)) {
            (Seg::Key(k), Some(b'{')) => {
                let mut j = skip_ws(b, i + 1);
                let mut found = None;
                while b.get(j) == Some(&b'"') {
                    let key_start = j;
                    let key_end = skip_string(b, j);
                    let raw = text
                        .get(key_start + 1..key_end.saturating_sub(1))
                        .unwrap_or("");
                    j = skip_ws(b, key_end);
                    if b.get(j) != Some(&b':') {
                        break;
                    }
                    j = skip_ws(b, j + 1);
                    if raw == k {
                        found = Some((key_start, j));
                        break;
                    }
                    j = skip_ws(b, skip_value(b, j));
                    if b.get(j) != Some(&b',') {
                        break;
                    }
                    j = skip_ws(b, j + 1);
                }
                match found {
                    Some((ks, vs)) => {
                        best = ks;
                        i = vs;
                    }
                    None => break,
                }
            }
            (Seg::Index(n), Some(b'[')) => {
                let mut j = skip_ws(b, i + 1);
                let mut ok = true;
                for _ in 0..*n {
                    if j >= b.len() || b[j] == b']' {
                        ok = false;
                        break;
                    }
                    j = skip_ws(b, skip_value(b, j));
                    if b.get(j) != Some(&b',') {
                        ok = false;
                        break;
                    }
                    j = skip_ws(b, j + 1);
                }
                if !ok || j >= b.len() || b[j] == b']' {
                    break;
                }
                best = j;
                i = j;
            }
            _ => break,
        }
    }
    let best = best.min(b.len());
    let before = &b[..best];
    let line = before.iter().filter(|&&c| c == b'\n').count() + 1;
    let line_start = before
        .iter()
        .rposition(|&c| c == b'\n')
        .map_or(0, |p| p + 1);
    let col = before[line_start..]
        .iter()
        .filter(|&&c| c & 0xC0 != 0x80)
        .count()
        + 1;
    (line, col)
}

/// serde_json without its `float_roundtrip` feature can read a decimal number 1 ulp off, so
/// written models would not read back exactly: re-read the text serde_json has accepted (so
/// nesting is at most 128 deep) with numbers converted by the correctly rounded std parser.
fn exact_value(text: &str) -> Option<Value> {
    let b = text.as_bytes();
    let (v, end) = exact_at(text, skip_ws(b, 0))?;
    (skip_ws(b, end) == b.len()).then_some(v)
}

fn exact_at(text: &str, i: usize) -> Option<(Value, usize)> {
    let b = text.as_bytes();
    match *b.get(i)? {
        open @ (b'{' | b'[') => {
            let close = if open == b'{' { b'}' } else { b']' };
            let mut map = Map::new();
            let mut list = Vec::new();
            let mut j = skip_ws(b, i + 1);
            if b.get(j) == Some(&close) {
                j += 1;
            } else {
                loop {
                    if open == b'{' {
                        let end = skip_string(b, j);
                        let k: String = serde_json::from_str(text.get(j..end)?).ok()?;
                        j = skip_ws(b, end);
                        if b.get(j) != Some(&b':') {
                            return None;
                        }
                        let (v, e) = exact_at(text, skip_ws(b, j + 1))?;
                        map.insert(k, v);
                        j = skip_ws(b, e);
                    } else {
                        let (v, e) = exact_at(text, j)?;
                        list.push(v);
                        j = skip_ws(b, e);
                    }
                    match b.get(j) {
                        Some(b',') => j = skip_ws(b, j + 1),
                        Some(&c) if c == close => {
                            j += 1;
                            break;
                        }
                        _ => return None,
                    }
                }
            }
            let v = if open == b'{' {
                Value::Object(map)
            } else {
                Value::Array(list)
            };
            Some((v, j))
        }
        b'"' => {
            let end = skip_string(b, i);
            Some((serde_json::from_str(text.get(i..end)?).ok()?, end))
        }
        _ => {
            let end = skip_value(b, i);
            let tok = text.get(i..end)?;
            let v = match tok {
                "true" => Value::Bool(true),
                "false" => Value::Bool(false),
                "null" => Value::Null,
                _ => {
                    if let Ok(u) = tok.parse::<u64>() {
                        Value::from(u)
                    } else if let Ok(n) = tok.parse::<i64>() {
                        Value::from(n)
                    } else {
                        let x = tok.parse::<f64>().ok().filter(|x| x.is_finite())?;
                        Value::Number(serde_json::Number::from_f64(x)?)
                    }
                }
            };
            Some((v, end))
        }
    }
}

fn skip_ws(b: &[u8], mut i: usize) -> usize {
    while i < b.len() && matches!(b[i], b' ' | b'\t' | b'\n' | b'\r') {
        i += 1;
    }
    i
}

/// `i` at an opening quote; returns the index after the closing quote.
fn skip_string(b: &[u8], mut i: usize) -> usize {
    i += 1;
    while i < b.len() {
        match b[i] {
            b'\\' => i += 2,
            b'"' => return i + 1,
            _ => i += 1,
        }
    }
    b.len()
}

fn skip_value(b: &[u8], mut i: usize) -> usize {
    match b.get(i) {
        Some(b'"') => skip_string(b, i),
        Some(b'{' | b'[') => {
            let mut depth = 0usize;
            while i < b.len() {
                match b[i] {
                    b'"' => {
                        i = skip_string(b, i);
                        continue;
                    }
                    b'{' | b'[' => depth += 1,
                    b'}' | b']' => {
                        depth = depth.saturating_sub(1);
                        if depth == 0 {
                            return i + 1;
                        }
                    }
                    _ => {}
                }
                i += 1;
            }
            b.len()
        }
        _ => {
            while i < b.len() && !matches!(b[i], b',' | b']' | b'}' | b' ' | b'\t' | b'\n' | b'\r')
            {
                i += 1;
            }
            i
        }
    }
}

// ---------------------------------------------------------------------------------------
// Writing.

fn matrix_value(m: &DMatrix<f64>) -> Value {
    Value::Array(
        m.row_iter()
            .map(|row| Value::Array(row.iter().map(|&x| Value::from(x)).collect()))
            .collect(),
    )
}

fn floats2(rows: &[Vec<f64>]) -> Value {
    Value::Array(
        rows.iter()
            .map(|r| Value::Array(r.iter().map(|&x| Value::from(x)).collect()))
            .collect(),
    )
}

/// A factor on one line with its keys in the documented order: col, pow, delay, fn, omega.
fn factor_text(f: &Factor) -> String {
    let func = match f.func {
        None => Value::Null,
        Some(x) => serde_json::to_value(x).unwrap_or(Value::Null),
    };
    let mut s = format!(
        "{{\"col\": {}, \"pow\": {}, \"delay\": {}, \"fn\": {}",
        Value::from(f.col.as_str()),
        f.pow,
        f.delay,
        func
    );
    if let Some(w) = f.omega {
        let _ = write!(s, ", \"omega\": {}", Value::from(w));
    }
    if let Some(a) = f.smooth {
        let _ = write!(s, ", \"smooth\": {}", Value::from(a));
    }
    s.push('}');
    s
}

/// The list of products of a signal map (at indent level 1), one product per line.
fn products_text(list: &[Vec<Factor>]) -> String {
    if list.is_empty() {
        return "[]".into();
    }
    let mut out = String::from("[\n");
    for (i, prod) in list.iter().enumerate() {
        let factors: Vec<String> = prod.iter().map(factor_text).collect();
        let one_line = format!("[{}]", factors.join(", "));
        out.push_str("    ");
        if one_line.len() + 4 <= 100 || factors.len() < 2 {
            out.push_str(&one_line);
        } else {
            out.push_str("[\n      ");
            out.push_str(&factors.join(",\n      "));
            out.push_str("\n    ]");
        }
        out.push_str(if i + 1 < list.len() { ",\n" } else { "\n" });
    }
    out.push_str("  ]");
    out
}

fn is_scalar(v: &Value) -> bool {
    !matches!(v, Value::Array(_) | Value::Object(_))
}

fn inline(v: &Value, out: &mut String) {
    match v {
        Value::Array(a) => {
            out.push('[');
            for (i, x) in a.iter().enumerate() {
                if i > 0 {
                    out.push_str(", ");
                }
                inline(x, out);
            }
            out.push(']');
        }
        Value::Object(o) => {
            out.push('{');
            for (i, (k, x)) in o.iter().enumerate() {
                if i > 0 {
                    out.push_str(", ");
                }
                out.push_str(&Value::from(k.as_str()).to_string());
                out.push_str(": ");
                inline(x, out);
            }
            out.push('}');
        }
        _ => out.push_str(&v.to_string()),
    }
}

/// Pretty JSON that keeps lists of numbers (matrix rows) and short flat objects (factors)
/// on one line.
fn pretty(v: &Value, indent: usize, out: &mut String) {
    const WIDTH: usize = 100;
    let flat_object = |x: &Value| matches!(x, Value::Object(o) if o.values().all(is_scalar));
    let fits = |x: &Value| {
        let mut s = String::new();
        inline(x, &mut s);
        s.len() + 2 * indent <= WIDTH
    };
    let one_line = match v {
        Value::Array(a) => {
            a.iter().all(is_scalar) || (a.iter().all(|x| is_scalar(x) || flat_object(x)) && fits(v))
        }
        Value::Object(o) => o.is_empty() || (flat_object(v) && fits(v)),
        _ => true,
    };
    if one_line {
        inline(v, out);
        return;
    }
    let pad = "  ".repeat(indent + 1);
    let close = "  ".repeat(indent);
    match v {
        Value::Array(a) => {
            out.push_str("[\n");
            for (i, x) in a.iter().enumerate() {
                out.push_str(&pad);
                pretty(x, indent + 1, out);
                out.push_str(if i + 1 < a.len() { ",\n" } else { "\n" });
            }
            out.push_str(&close);
            out.push(']');
        }
        Value::Object(o) => {
            out.push_str("{\n");
            for (i, (k, x)) in o.iter().enumerate() {
                out.push_str(&pad);
                out.push_str(&Value::from(k.as_str()).to_string());
                out.push_str(": ");
                pretty(x, indent + 1, out);
                out.push_str(if i + 1 < o.len() { ",\n" } else { "\n" });
            }
            out.push_str(&close);
            out.push('}');
        }
        _ => inline(v, out),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn ds(text: &str) -> Dataset {
        Dataset::parse("d.csv", text.as_bytes()).unwrap()
    }

    fn f(v: Value) -> Factor {
        serde_json::from_value(v).unwrap()
    }

    fn ss_model() -> ModelFile {
        let m = |r, c, x: &[f64]| DMatrix::from_row_slice(r, c, x);
        ModelFile {
            kind: ModelKind::Ss(LpvSs {
                a: vec![
                    m(2, 2, &[0.5, 0.1, 0.0, 0.3]),
                    m(2, 2, &[0.1, 0.0, 0.2, 1.0 / 3.0]),
                ],
                b: vec![m(2, 1, &[1.0, 0.0]), m(2, 1, &[0.5, -1e-17])],
                k: vec![m(2, 1, &[0.2, 0.1]), m(2, 1, &[0.0, 0.0])],
                c: vec![m(1, 2, &[1.0, 0.0])],
                d: vec![m(1, 1, &[0.0])],
            }),
            signals: SignalMap::standard(1, 1, 1),
            fit: json!({"method": "pbsid", "past": 5, "order": 2, "data": {"sha256": "ab"}}),
        }
    }

    fn arx_model() -> ModelFile {
        let mut signals = SignalMap::standard(2, 1, 1);
        signals.inputs[1] = vec![f(json!({"col": "k", "fn": "sin", "omega": 0.3}))];
        ModelFile {
            kind: ModelKind::Arx(ArxModel {
                na: 2,
                nb: 1,
                a: vec![vec![-0.5, 0.1], vec![0.2, 0.0]],
                b: vec![
                    vec![vec![1.0, 0.5], vec![0.0, 0.25]],
                    vec![vec![0.1, 0.0], vec![0.0, 0.0]],
                ],
            }),
            signals,
            fit: json!({}),
        }
    }

    /// Parse `text` expecting an error; check file, line and "column N" are named.
    fn err(text: &str, line: usize, needle: &str) -> DataError {
        let e = ModelFile::from_json_str("m.json", text).expect_err("expected an error");
        let shown = e.to_string();
        assert_eq!(e.file, "m.json");
        assert_eq!(e.line, Some(line), "{shown}");
        assert!(
            shown.starts_with(&format!("m.json:{line}: column ")),
            "{shown}"
        );
        assert!(shown.contains(needle), "{shown} lacks {needle}");
        e
    }

    const SS: &str = r#"{
  "type": "lpv-ss",
  "A": [[[0.5]], [[0.1]]],
  "B": [[[1.0]], [[0.0]]],
  "K": [[[0.2]], [[0.0]]],
  "C": [[1.0]],
  "D": [[0.0]]
}"#;

    #[test]
    fn factor_defaults_and_serde_names() {
        let x = f(json!({"col": "u1"}));
        assert_eq!(x, Factor::col("u1"));
        let x = f(json!({"col": "u1", "pow": -2, "delay": 3, "fn": "abs"}));
        assert_eq!((x.pow, x.delay, x.func), (-2.0, 3, Some(FactorFn::Abs)));
        assert_eq!(
            serde_json::to_value(Factor::col("y1")).unwrap(),
            json!({"col": "y1", "pow": 1, "delay": 0, "fn": null})
        );
        assert!(serde_json::from_value::<Factor>(json!({"col": "u1", "dealy": 1})).is_err());
        assert_eq!(describe(&[]), "1");
        assert_eq!(
            describe(&[x, f(json!({"col": "k", "fn": "sin", "omega": 0.3}))]),
            "abs(u1(k-3))^-2*sin(0.3*k)"
        );
    }

    #[test]
    fn factor_evaluation() {
        let d = ds("u1,y1,p1\n1,-2,0\n2,0,3\n-3,4,5\n");
        let ev = |v: Value| {
            eval_product(
                &serde_json::from_value::<Vec<Factor>>(v).unwrap(),
                &d,
                "input 1",
            )
        };
        assert_eq!(ev(json!([])).unwrap(), [1.0, 1.0, 1.0]);
        assert_eq!(
            ev(json!([{"col": "u1", "delay": 1}])).unwrap(),
            [0.0, 1.0, 2.0]
        );
        assert_eq!(
            ev(json!([{"col": "u1", "delay": 7}])).unwrap(),
            [0.0, 0.0, 0.0]
        );
        assert_eq!(
            ev(json!([{"col": "u1", "pow": 2}])).unwrap(),
            [1.0, 4.0, 9.0]
        );
        assert_eq!(
            ev(json!([{"col": "u1", "pow": 0}])).unwrap(),
            [1.0, 1.0, 1.0]
        );
        assert_eq!(
            ev(json!([{"col": "y1", "pow": 0}])).unwrap(),
            [1.0, 1.0, 1.0]
        );
        assert_eq!(
            ev(json!([{"col": "y1", "fn": "abs"}])).unwrap(),
            [2.0, 0.0, 4.0]
        );
        assert_eq!(
            ev(json!([{"col": "y1", "fn": "sign"}])).unwrap(),
            [-1.0, 0.0, 1.0]
        );
        assert_eq!(
            ev(json!([{"col": "u1", "fn": "abs"}, {"col": "u1"}])).unwrap(),
            [1.0, 4.0, -9.0]
        );
        assert_eq!(
            ev(json!([{"col": "u1", "pow": -1}])).unwrap(),
            [1.0, 0.5, -1.0 / 3.0]
        );
        let s = ev(json!([{"col": "k", "fn": "sin", "omega": 0.3}])).unwrap();
        assert_eq!(s, [0.0, 0.3f64.sin(), 0.6f64.sin()]);
        let c = ev(json!([{"col": "k", "fn": "cos", "omega": 0.3, "delay": 1}])).unwrap();
        assert_eq!(c, [1.0, 1.0, 0.3f64.cos()]);
        assert_eq!(ev(json!([{"col": "k"}])).unwrap(), [0.0, 1.0, 2.0]);
        let c = ev(json!([{"col": "p1", "fn": "cos", "omega": 2.0}])).unwrap();
        assert_eq!(c, [1.0, 6.0f64.cos(), 10.0f64.cos()]);
    }

    #[test]
    fn factor_evaluation_errors() {
        let d = ds("u1,y1\n1,-2\n2,0\n");
        let ev = |v: Value| {
            eval_product(
                &serde_json::from_value::<Vec<Factor>>(v).unwrap(),
                &d,
                "input 1",
            )
        };
        let e = ev(json!([{"col": "y1", "pow": -1}])).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("y1")));
        assert!(
            e.to_string().starts_with("d.csv:3: column 'y1': input 1"),
            "{e}"
        );
        assert!(e.message.contains("sample 1"), "{e}");
        let e = ev(json!([{"col": "u1", "delay": 1, "pow": -2}])).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(2), Some("u1")));
        let e = ev(json!([{"col": "q_ref"}])).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("q_ref")));
        assert!(e.message.contains("input 1 (q_ref)"), "{e}");
        // sin/cos of any column, omega 1 when absent
        let s = ev(json!([{"col": "u1", "fn": "sin"}])).unwrap();
        assert_eq!(s, [1f64.sin(), 2f64.sin()]);
        // a non-integer power is of the magnitude
        let r = ev(json!([{"col": "y1", "pow": 0.5}])).unwrap();
        assert_eq!(r, [2f64.sqrt(), 0.0]);
        let e = ev(json!([{"col": "y1", "pow": -0.5}])).unwrap_err();
        assert!(e.message.contains("power -0.5 is undefined"), "{e}");
        let big = ds("u1,y1\n1e200,1\n");
        let e = eval_product(
            &[Factor {
                pow: 2.0,
                ..Factor::col("u1")
            }],
            &big,
            "input 1",
        )
        .unwrap_err();
        assert!(e.message.contains("overflows"), "{e}");
    }

    #[test]
    fn signal_map_default_and_evaluate() {
        let d = ds("t,u1,u2,y1,p1,p2\n0,1,2,3,4,5\n1,6,7,8,9,10\n");
        let map = SignalMap::default_for(&d).unwrap();
        assert_eq!(map, SignalMap::standard(2, 1, 2));
        assert_eq!(map.scheduling[0], Vec::<Factor>::new());
        let s = map.evaluate(&d).unwrap();
        assert_eq!(s.u, DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 6.0, 7.0]));
        assert_eq!(s.y, DMatrix::from_row_slice(2, 1, &[3.0, 8.0]));
        assert_eq!(s.p, DMatrix::from_row_slice(2, 2, &[4.0, 5.0, 9.0, 10.0]));

        let e = SignalMap::default_for(&ds("u1,p1\n1,2\n")).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("y1")));
        assert!(e.message.contains("no output column"), "{e}");

        let mut map = SignalMap::standard(3, 1, 1);
        let e = map.evaluate(&d).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("u3")));
        assert!(e
            .to_string()
            .starts_with("d.csv:1: column 'u3': no such column, needed by input 3"));
        map.scheduling[0] = vec![Factor::col("p1")];
        let e = map.evaluate(&d).unwrap_err();
        assert!(e.message.contains("scheduling[0]"), "{e}");
    }

    #[test]
    fn round_trips() {
        let dir = tempfile::tempdir().unwrap();
        for model in [ss_model(), arx_model()] {
            let text = model.to_json_string();
            assert_eq!(
                ModelFile::from_json_str("x", &text).unwrap(),
                model,
                "{text}"
            );
            let path = dir.path().join("m.json");
            model.write(&path).unwrap();
            let back = ModelFile::read(&path).unwrap();
            assert_eq!(back, model);
            assert_eq!(back.to_json_string(), text);
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        // C and D scheduled: written and read back as lists
        let mut model = ss_model();
        if let ModelKind::Ss(ss) = &mut model.kind {
            ss.c = vec![DMatrix::from_row_slice(1, 2, &[1.0, 0.0]); 2];
            ss.d = vec![
                DMatrix::from_row_slice(1, 1, &[0.0]),
                DMatrix::from_row_slice(1, 1, &[0.5]),
            ];
        }
        let text = model.to_json_string();
        assert!(text.contains("\"C\": [\n    [\n"), "{text}");
        assert_eq!(ModelFile::from_json_str("x", &text).unwrap(), model);
    }

    #[test]
    fn written_json_is_readable_by_humans() {
        let text = ss_model().to_json_string();
        assert!(text.starts_with("{\n  \"type\": \"lpv-ss\",\n"), "{text}");
        assert!(
            text.contains("[{\"col\": \"u1\", \"pow\": 1, \"delay\": 0, \"fn\": null}]"),
            "{text}"
        );
        assert!(text.contains("\"C\": [\n    [1.0, 0.0]\n  ]"), "{text}");
        assert!(text.contains("\"scheduling\": [\n    [],\n"), "{text}");
    }

    #[test]
    fn minimal_file_gets_default_signals() {
        let m = ModelFile::from_json_str("m.json", SS).unwrap();
        assert_eq!(m.signals, SignalMap::standard(1, 1, 1));
        assert_eq!(m.fit, json!({}));
        let ModelKind::Ss(ss) = &m.kind else { panic!() };
        assert_eq!((ss.n(), ss.m(), ss.c.len()), (1, 2, 1));
    }

    #[test]
    fn write_refuses_invalid_models_and_keeps_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.json");
        std::fs::write(&path, "old").unwrap();
        let mut model = ss_model();
        if let ModelKind::Ss(ss) = &mut model.kind {
            ss.a[1][(0, 1)] = f64::NAN;
        }
        let e = model.write(&path).unwrap_err();
        assert!(e.message.contains("A[1][0][1] is not finite"), "{e}");
        let mut model = ss_model();
        model.signals.inputs.push(vec![]);
        let e = model.write(&path).unwrap_err();
        assert!(e.message.contains("inputs"), "{e}");
        assert_eq!(e.line, None);
        let e = ss_model()
            .write(&dir.path().join("no/such/dir/m.json"))
            .unwrap_err();
        assert!(e.file.ends_with("no/such/dir/m.json") && e.message.contains("cannot write"));
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn syntax_errors_have_line_and_column() {
        let e = err(
            "{\n  \"type\": \"lpv-ss\",\n  \"A\": [[[0.5]]\n}",
            4,
            "column 1",
        );
        assert!(e.message.contains("expected"), "{e}");
        err("", 1, "EOF");
        err(
            "{\"type\": \"lpv-ss\",\n \"A\": [[[NaN]]]}",
            2,
            "non-finite",
        );
        err(
            "{\"type\": \"lpv-ss\",\n \"A\": [[[1e999]]]}",
            2,
            "non-finite",
        );
        err(
            "{\"type\": \"lpv-ss\",\n \"A\": [[[-Infinity]]]}",
            2,
            "non-finite",
        );
    }

    #[test]
    fn unknown_type_and_keys() {
        let e = err(
            &SS.replace("lpv-ss", "lpv-tf"),
            2,
            "column 3: type: unknown model type \"lpv-tf\"",
        );
        assert!(e.message.contains("\"lpv-ss\" and \"lpv-arx\""), "{e}");
        err(
            &SS.replace("\"type\": \"lpv-ss\",", ""),
            1,
            "column 1: missing \"type\"",
        );
        err("[1, 2]", 1, "a model file is a JSON object");
        err(
            &SS.replace("\"D\"", "\"Dd\""),
            7,
            "column 3: Dd: unknown key \"Dd\"",
        );
        err(
            &SS.replace("  \"D\": [[0.0]]\n", "  \"fit\": 3\n"),
            7,
            "column 3: fit: \"fit\" must be an object",
        );
    }

    #[test]
    fn missing_matrix() {
        let text = SS.replace(",\n  \"D\": [[0.0]]", "");
        err(&text, 1, "missing \"D\"");
    }

    #[test]
    fn ragged_and_non_numeric_matrices() {
        let text = SS.replace("\"C\": [[1.0]]", "\"C\": [[1.0], [2.0, 3.0]]");
        err(
            &text,
            6,
            "column 16: C[1]: ragged matrix: this row has 2 entries, the first row has 1",
        );
        let text = SS.replace("[[[0.2]], [[0.0]]]", "[[[0.2]], [[\"x\"]]]");
        err(
            &text,
            5,
            "column 20: K[1][0][0]: expected a number, found a string",
        );
        let text = SS.replace("[[[1.0]], [[0.0]]]", "[[[1.0]], []]");
        err(&text, 4, "B[1]: a matrix needs at least one row");
        let text = SS.replace("[[[1.0]], [[0.0]]]", "[]");
        err(&text, 4, "column 3: B: the list of matrices is empty");
        let text = SS.replace("[[[1.0]], [[0.0]]]", "{}");
        err(&text, 4, "B: expected a list of matrices");
    }

    #[test]
    fn shape_mismatches() {
        let text = SS.replace("[[[0.2]], [[0.0]]]", "[[[0.2]], [[0.0], [1.0]]]");
        err(
            &text,
            5,
            "column 18: K[1]: K must be 2 matrices of 1x1, this one is 2x1",
        );
        let text = SS.replace("[[[0.2]], [[0.0]]]", "[[[0.2]]]");
        err(
            &text,
            5,
            "column 3: K: K must be 2 matrices of 1x1, found 1",
        );
        let text = SS.replace("\"D\": [[0.0]]", "\"D\": [[0.0, 1.0]]");
        err(
            &text,
            7,
            "column 3: D: D must be one or 2 matrices of 1x1, this one is 1x2",
        );
        let text = SS.replace("\"C\": [[1.0]]", "\"C\": [[[1.0]], [[1.0]], [[2.0]]]");
        err(&text, 6, "C must be one or 2 matrices of 1x1, found 3");
        let text = SS.replace(
            "\"A\": [[[0.5]], [[0.1]]]",
            "\"A\": [[[0.5, 1.0]], [[0.1]]]",
        );
        err(
            &text,
            3,
            "column 9: A[0]: A must be 2 matrices of 1x1, this one is 1x2",
        );
    }

    #[test]
    fn signal_counts_must_agree_with_matrices() {
        let with_sig = |sig: &str| {
            SS.replace(
                "\"type\": \"lpv-ss\",",
                &format!("\"type\": \"lpv-ss\",\n  {sig},"),
            )
        };
        err(
            &with_sig("\"inputs\": [[{\"col\": \"u1\"}], []]"),
            3,
            "column 3: inputs: lists 2 inputs but the model has 1",
        );
        err(
            &with_sig("\"outputs\": []"),
            3,
            "outputs: lists 0 outputs but the model has 1",
        );
        err(
            &with_sig("\"scheduling\": [[], [{\"col\": \"p1\"}], [{\"col\": \"p2\"}]]"),
            3,
            "scheduling: lists 3 scheduling but the model has 2",
        );
        err(
            &with_sig("\"scheduling\": [[{\"col\": \"p1\"}], []]"),
            3,
            "column 18: scheduling[0]: the first scheduling basis function must be []",
        );
        err(
            &with_sig("\"inputs\": [[{\"col\": \"u1\", \"dealy\": 1}]]"),
            3,
            "column 15: inputs[0][0]: not a factor",
        );
        err(
            &with_sig("\"inputs\": [[{\"col\": \"u1\", \"fn\": \"abs\", \"omega\": 2}]]"),
            3,
            "inputs[0][0]: \"omega\" is only used with \"fn\": \"sin\" or \"cos\"",
        );
        err(
            &with_sig("\"inputs\": [[{\"col\": \"u1\", \"fn\": \"tan\"}]]"),
            3,
            "unknown variant `tan`",
        );
        err(
            &with_sig("\"inputs\": [{\"col\": \"u1\"}]"),
            3,
            "inputs[0]: expected a product",
        );
    }

    #[test]
    fn arx_errors() {
        let good = r#"{
  "type": "lpv-arx",
  "na": 1,
  "nb": 1,
  "a": [[0.5, 0.1]],
  "b": [[[1.0, 0.0], [0.5, 0.2]]]
}"#;
        let m = ModelFile::from_json_str("m.json", good).unwrap();
        assert_eq!(m.signals, SignalMap::standard(1, 1, 1));
        err(
            &good.replace("\"na\": 1", "\"na\": 2"),
            5,
            "column 3: a: has 1 lags but na = 2",
        );
        err(
            &good.replace("\"nb\": 1", "\"nb\": 0"),
            6,
            "column 9: b[0]: has 2 lags but nb = 0",
        );
        err(
            &good.replace("\"na\": 1", "\"na\": -1"),
            3,
            "na: expected a non-negative integer",
        );
        err(
            &good.replace("[0.5, 0.2]", "[0.5]"),
            6,
            "column 22: b[0][1]: has 1 coefficients but there are 2",
        );
        err(&good.replace("\"nb\": 1,\n", ""), 1, "missing \"nb\"");
        err(
            &good.replace("\"a\": [[0.5, 0.1]]", "\"a\": [[0.5, true]]"),
            5,
            "a[0][1]: expected a number, found a boolean",
        );
        let two_out = good.replace(
            "\"na\": 1",
            "\"outputs\": [[{\"col\": \"y1\"}], [{\"col\": \"y2\"}]],\n  \"na\": 1",
        );
        err(&two_out, 3, "exactly one output");
        err(
            &good.replace("\"a\"", "\"A\""),
            5,
            "unknown key \"A\" in an lpv-arx model",
        );
    }

    #[test]
    fn read_errors_name_the_file() {
        let e = ModelFile::read(Path::new("/nonexistent/m.json")).unwrap_err();
        assert_eq!(e.file, "/nonexistent/m.json");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.json");
        std::fs::write(&p, b"{\n\"type\": \"\xff\"}").unwrap();
        let e = ModelFile::read(&p).unwrap_err();
        assert_eq!(e.line, Some(2));
        assert!(e.message.contains("UTF-8"), "{e}");
    }

    #[test]
    fn numbers_read_back_exactly() {
        // serde_json's default float parser is off by one ulp on these
        for x in [
            1.1844674407370957e17,
            1.2345678901234567e-200,
            0.1 + 0.2,
            5e-324,
            f64::MAX,
        ] {
            let mut model = ss_model();
            if let ModelKind::Ss(ss) = &mut model.kind {
                ss.a[0][(0, 0)] = x;
            }
            let back = ModelFile::from_json_str("x", &model.to_json_string()).unwrap();
            assert_eq!(back, model, "{x:e}");
        }
        let v = exact_value("{\"a\": [1, -2, 2.5e3, \"\\u00e9\\\"\", true, null, {}], \"b\": []}");
        assert_eq!(
            v,
            Some(json!({"a": [1, -2, 2500.0, "é\"", true, null, {}], "b": []}))
        );
    }

    #[test]
    fn locate_finds_paths() {
        let t = "{\"x\": {\"y\": 1}, \"A\": [ [1, \"]\"],\n [ 2, 3 ] ]}";
        assert_eq!(locate(t, &[key("A")]), (1, 17));
        assert_eq!(locate(t, &[key("A"), Seg::Index(1), Seg::Index(1)]), (2, 7));
        assert_eq!(locate(t, &[key("A"), Seg::Index(5)]), (1, 17));
        assert_eq!(locate(t, &[key("nope")]), (1, 1));
    }

    /// A model with a Lur'e feedback channel y1^3 (input 2) and a scheduling function |y1|^0.5.
    fn feedback_text(d_fb: f64, delay: usize, c_sched: bool) -> String {
        let c = if c_sched {
            "[[[1.0]], [[0.3]]]"
        } else {
            "[[1.0]]"
        };
        format!(
            r#"{{
  "type": "lpv-ss",
  "inputs": [[{{"col": "u1"}}], [{{"col": "y1", "pow": 3, "delay": {delay}}}]],
  "scheduling": [[], [{{"col": "y1", "pow": 0.5, "delay": {delay}}}]],
  "outputs": [[{{"col": "y1"}}]],
  "A": [[[0.5]], [[0.1]]],
  "B": [[[1.0, -0.2]], [[0.0, 0.0]]],
  "K": [[[0.2]], [[0.0]]],
  "C": {c},
  "D": [[0.0, {d_fb}]]
}}"#
        )
    }

    #[test]
    fn own_output_factors_are_found_and_round_trip() {
        let m = ModelFile::from_json_str("m.json", &feedback_text(0.0, 0, false)).unwrap();
        assert_eq!(m.signals.own_outputs(), vec![Some("y1")]);
        assert!(m.signals.has_feedback());
        assert!(!SignalMap::standard(1, 1, 1).has_feedback());
        assert_eq!(describe(&m.signals.scheduling[1]), "|y1|^0.5");
        let text = m.to_json_string();
        assert!(
            text.contains("{\"col\": \"y1\", \"pow\": 3, \"delay\": 0"),
            "{text}"
        );
        assert!(text.contains("\"pow\": 0.5"), "{text}");
        assert_eq!(ModelFile::from_json_str("x", &text).unwrap(), m);
        // the loops on a data set: data part 1, the own factor reads output 0
        let d = ds("u1,y1\n1,2\n3,-4\n");
        let fb = m.signals.feedback(&d).unwrap();
        assert_eq!(fb.inputs.len(), 1);
        assert_eq!(fb.inputs[0].0, 1);
        assert_eq!(fb.inputs[0].1.data, [1.0, 1.0]);
        assert_eq!(fb.inputs[0].1.own[0].output, 0);
        assert_eq!(fb.scheduling[0].0, 0);
        // evaluated on a run's outputs: y^3 of row k when known, 0 otherwise
        let y = DMatrix::from_row_slice(2, 1, &[2.0, -4.0]);
        assert_eq!(fb.inputs[0].1.value(1, &y, 2), -64.0);
        assert_eq!(fb.inputs[0].1.value(1, &y, 1), 0.0);
        assert_eq!(fb.scheduling[0].1.value(1, &y, 2), 2.0);
        // identification and the predictor read the measured output
        let s = m.signals.evaluate(&d).unwrap();
        assert_eq!(
            s.u.column(1).iter().copied().collect::<Vec<_>>(),
            [8.0, -64.0]
        );
    }

    #[test]
    fn a_model_that_needs_the_output_it_computes_is_refused() {
        // D column of the feedback channel non-zero at delay 0
        let e = err(
            &feedback_text(0.5, 0, false),
            3,
            "inputs[1][0]: input 2 reads the model's output y1 at the same sample (delay 0), but column 2 of D is non-zero",
        );
        assert!(e.message.contains("give the factor a delay >= 1"), "{e}");
        // a delay of 1 breaks the loop
        assert!(ModelFile::from_json_str("m.json", &feedback_text(0.5, 1, true)).is_ok());
        // C scheduled on y1 at delay 0
        err(
            &feedback_text(0.0, 0, true),
            4,
            "scheduling[1][0]: scheduling basis function 2 reads the model's output y1 at the same sample (delay 0), but C^(2) or D^(2) is non-zero",
        );
        // lpv-arx: b_0 of a delay-0 feedback input, any delay-0 scheduling on y
        let arx = |b0: f64, sched: &str| {
            format!(
                r#"{{
  "type": "lpv-arx",
  "inputs": [[{{"col": "u1"}}], [{{"col": "y1", "fn": "sin"}}]],
  "scheduling": [[]{sched}],
  "na": 1,
  "nb": 1,
  "a": [[0.5{extra}]],
  "b": [[[1.0{extra}], [0.5{extra}]], [[{b0}{extra}], [0.1{extra}]]]
}}"#,
                extra = if sched.is_empty() { "" } else { ", 0.0" }
            )
        };
        assert!(ModelFile::from_json_str("m.json", &arx(0.0, "")).is_ok());
        err(
            &arx(0.2, ""),
            3,
            "the lag-0 coefficient b_0 of this input is non-zero",
        );
        err(
            &arx(0.0, ", [{\"col\": \"y1\", \"pow\": 2}]"),
            4,
            "an lpv-arx model's coefficients a_i(p(k)) at sample k multiply its past outputs",
        );
        let typed = SignalMap {
            inputs: vec![vec![Factor::col("u1")], vec![Factor::col("y1")]],
            scheduling: vec![vec![]],
            outputs: vec![vec![Factor::col("y1")]],
        };
        let ss = LpvSs {
            a: vec![DMatrix::from_element(1, 1, 0.5)],
            b: vec![DMatrix::from_element(1, 2, 1.0)],
            k: vec![DMatrix::zeros(1, 1)],
            c: vec![DMatrix::from_element(1, 1, 1.0)],
            d: vec![DMatrix::from_row_slice(1, 2, &[0.0, 1.0])],
        };
        assert_eq!(
            typed.check_loops(&ModelKind::Ss(ss)),
            Err(AlgebraicLoop::Input {
                input: 1,
                factor: 0,
                col: "y1".into(),
                arx: false
            })
        );
    }

    /// The model file with its scheduling function 2 = `p1` smoothed by `smooth` (JSON text).
    fn smooth_text(col: &str, smooth: &str) -> String {
        SS.replace(
            "\"type\": \"lpv-ss\",",
            &format!(
                "\"type\": \"lpv-ss\",\n  \"scheduling\": [[], [{{\"col\": \"{col}\", \"smooth\": {smooth}}}]],"
            ),
        )
    }

    #[test]
    fn smoothed_factor_reads_round_trips_and_filters() {
        let m = ModelFile::from_json_str("m.json", &smooth_text("p1", "0.5")).unwrap();
        let g = &m.signals.scheduling[1][0];
        assert_eq!(g.smooth, Some(0.5));
        assert!(!g.is_plain());
        assert_eq!(describe(&m.signals.scheduling[1]), "lowpass0.5(p1)");
        let text = m.to_json_string();
        assert!(
            text.contains(
                "{\"col\": \"p1\", \"pow\": 1, \"delay\": 0, \"fn\": null, \"smooth\": 0.5}"
            ),
            "{text}"
        );
        assert_eq!(ModelFile::from_json_str("x", &text).unwrap(), m);
        // s(0) = x(0), then s(k) = 0.5 s(k-1) + 0.5 x(k); before delay, fn and pow
        let d = ds("u1,y1,p1\n1,0,2\n1,0,4\n1,0,0\n1,0,8\n");
        let s = m.signals.evaluate(&d).unwrap();
        assert_eq!(
            s.p.column(0).iter().copied().collect::<Vec<_>>(),
            [2.0, 3.0, 1.5, 4.75]
        );
        let h = Factor {
            smooth: Some(0.5),
            delay: 1,
            pow: 2.0,
            ..Factor::col("p1")
        };
        assert_eq!(describe(std::slice::from_ref(&h)), "lowpass0.5(p1)(k-1)^2");
        let v = eval_product(&[h], &d, "x").unwrap();
        assert_eq!(v, [0.0, 4.0, 9.0, 2.25]);
        // a constant passes unchanged (unit gain, started at the first value)
        assert_eq!(low_pass(&[3.0; 4], 0.9), [3.0; 4]);
        assert!(low_pass(&[], 0.9).is_empty());
        // an old file without the key reads and writes as before
        let old = ModelFile::from_json_str("m.json", SS).unwrap();
        assert!(!old.to_json_string().contains("smooth"));
        assert_eq!(old.signals.first_non_standard(), None);
        assert_eq!(
            m.signals.first_non_standard().as_deref(),
            Some("scheduling[1] is lowpass0.5(p1) where the device reads p1")
        );
    }

    #[test]
    fn smoothing_where_it_cannot_be_evaluated_is_refused() {
        for bad in ["1", "1.5", "-0.1"] {
            err(
                &smooth_text("p1", bad),
                3,
                "is not a low-pass pole in [0, 1)",
            );
        }
        err(&smooth_text("p1", "\"x\""), 3, "not a factor");
        err(
            &smooth_text("k", "0.5"),
            3,
            "\"smooth\" does not apply to the sample index \"k\"",
        );
        // the model's own output: a free run cannot carry the filter through the loop
        let own = smooth_text("y1", "0.5").replace(
            "\"scheduling\"",
            "\"outputs\": [[{\"col\": \"y1\"}]],\n  \"scheduling\"",
        );
        let e = err(
            &own,
            4,
            "\"smooth\" on the model's own output y1 is not supported",
        );
        assert!(e.message.contains("scheduling[1][0]"), "{e}");
        // a smoothed output product is not an own output: a factor on y1 then reads data
        let m = SignalMap {
            inputs: vec![vec![Factor::col("u1")]],
            scheduling: vec![
                vec![],
                vec![Factor {
                    smooth: Some(0.2),
                    ..Factor::col("y1")
                }],
            ],
            outputs: vec![vec![Factor {
                smooth: Some(0.2),
                ..Factor::col("y1")
            }]],
        };
        assert!(m.check().is_ok());
        assert!(!m.has_feedback());
    }

    proptest::proptest! {
        /// Any pole in [0, 1) on any data column reads back exactly and evaluates to the
        /// recursion; any value outside is refused with the key named.
        #[test]
        fn smooth_key_parses_exactly(a in -2.0f64..2.0, x in proptest::collection::vec(-1e3f64..1e3, 1..12)) {
            let text = smooth_text("p1", &Value::from(a).to_string());
            match ModelFile::from_json_str("m.json", &text) {
                Ok(m) => {
                    proptest::prop_assert!((0.0..1.0).contains(&a));
                    let g = &m.signals.scheduling[1][0];
                    proptest::prop_assert_eq!(g.smooth, Some(a));
                    let back = ModelFile::from_json_str("x", &m.to_json_string()).unwrap();
                    proptest::prop_assert_eq!(&back, &m);
                    let csv: String = x.iter().map(|v| format!("1,0,{v}\n")).collect();
                    let d = ds(&format!("u1,y1,p1\n{csv}"));
                    let p = m.signals.evaluate(&d).unwrap().p;
                    let mut s = x[0];
                    for (k, v) in x.iter().enumerate() {
                        s = a * s + (1.0 - a) * v;
                        proptest::prop_assert_eq!(p[(k, 0)], s);
                    }
                }
                Err(e) => {
                    proptest::prop_assert!(!(0.0..1.0).contains(&a));
                    proptest::prop_assert!(e.message.contains("\"smooth\""), "{}", e);
                }
            }
        }
    }
}
