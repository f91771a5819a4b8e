//! An LPV state-space model as a flat slice of values, and its one-step-ahead predictor: the
//! one definition the device engine (which runs the predictor on streamed samples) and the
//! host (which packs a fitted model to push it, `docs/wire.md`) share.
//!
//! **Model** (kernel paper eq. (1)-(2) in innovation form, DESIGN.md section 5 `lpv-ss`):
//! x_{k+1} = sum_i mu_k^(i) (A^(i) x_k + B^(i) u_k + K^(i) e_k), y_k = C x_k + D u_k + e_k,
//! mu_k = [1, p_k] (m = s + 1 local models); C and D are either one matrix each or, with a
//! scheduled output equation (the LPV output equation section 2.1 of the kernel paper sets
//! aside; DESIGN.md section 5), C(mu) = sum_i mu^(i) C^(i) and likewise D.
//!
//! **Value layout** `[A | B | K | C | D]`, every matrix row-major, local models in order:
//! A^(1..m) (n x n each), B^(1..m) (n x r), K^(1..m) (n x l), then C^(1..mc) (l x n) and
//! D^(1..mc) (l x r) with mc = m when `scheduled_output`, else 1. Length
//! m n (n + r + l) + mc l (n + r) ([`ModelDims::values_len`], [`values_len`]); offsets
//! [`ModelDims::a_offset`] .. [`ModelDims::d_offset`].
//!
//! **Predictor** (the model with e_k replaced by the measured innovation: the predictor form
//! (3)-(4) of the kernel paper, section 2.1, kept in the A, B, K of (1) rather than A~, B~):
//! yhat_k = C(mu_k) x_k + D(mu_k) u_k, e_k = y_k - yhat_k,
//! x_{k+1} = sum_i mu_k^(i) (A^(i) x_k + B^(i) u_k + K^(i) e_k), from x_0 = 0. Its state is a
//! slice of [`ModelDims::state_len`] = 2 n + 3 l values `[x (n) | x_next (n) | e (l) |
//! sse (l) | yhat (l)]`: the state, scratch, the last innovation, the running sum of squared
//! innovations per output, the last prediction. Zero it to start over.
//!
//! **Host, step by step** (what `lpvid device push` and a host-side predictor call):
//! 1. `let dims = ModelDims::new(n, r, l, m, scheduled_output)?;`
//! 2. `let mut values = vec![0.0; dims.values_len()?];`
//! 3. `dims.pack(&mut values, &a, &b, &k, &c, &d)?;` with each argument a slice of row-major
//!    matrices (`&[&[f64]]`; for an nalgebra `DMatrix` `mat`, `mat.transpose().as_slice()`
//!    is its row-major data); `c` and `d` may hold one matrix even when the other is
//!    scheduled (it is repeated).
//! 4. push `values` (device link), or run the predictor:
//!    `let view = dims.view(&values)?; let mut state = vec![0.0; dims.state_len()];` and per
//!    sample `view.predict_step(&mut state, u, y, p)?; let yhat = dims.prediction(&state);`.

use crate::error::{Error, Field};
use crate::real::Real;

/// Values of an LPV-SS model with these dimensions (see the module's value layout), or
/// `None` on overflow: m n (n + r + l) + mc l (n + r).
pub const fn values_len(
    n: usize,
    r: usize,
    l: usize,
    m: usize,
    scheduled_output: bool,
) -> Option<usize> {
    let mc = if scheduled_output { m } else { 1 };
    let Some(nrl) = n.checked_add(r) else {
        return None;
    };
    let Some(nrl) = nrl.checked_add(l) else {
        return None;
    };
    let Some(per_local) = n.checked_mul(nrl) else {
        return None;
    };
    let Some(nr) = n.checked_add(r) else {
        return None;
    };
    let Some(out) = l.checked_mul(nr) else {
        return None;
    };
    let Some(locals) = m.checked_mul(per_local) else {
        return None;
    };
    let Some(outs) = mc.checked_mul(out) else {
        return None;
    };
    locals.checked_add(outs)
}

/// Dimensions of an LPV state-space model: order `n`, `r` inputs, `l` outputs, `m` local
/// models (m = 1 + s), and whether C and D depend on the scheduling.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelDims {
    /// State dimension n.
    pub n: usize,
    /// Inputs r.
    pub r: usize,
    /// Outputs l.
    pub l: usize,
    /// Local models m = 1 + s.
    pub m: usize,
    /// C and D are m matrices each (C(mu) = sum_i mu^(i) C^(i)) instead of one.
    pub scheduled_output: bool,
}

impl ModelDims {
    /// Validate and build: n, l, m >= 1 and a length that fits `usize`.
    pub fn new(
        n: usize,
        r: usize,
        l: usize,
        m: usize,
        scheduled_output: bool,
    ) -> Result<Self, Error> {
        if n == 0 || l == 0 || m == 0 {
            return Err(Error::InvalidConfig(
                "model needs n >= 1, l >= 1 and m >= 1",
            ));
        }
        let d = ModelDims {
            n,
            r,
            l,
            m,
            scheduled_output,
        };
        d.values_len()?;
        d.n.checked_mul(2)
            .and_then(|v| v.checked_add(3 * l))
            .ok_or(Error::Overflow)?;
        Ok(d)
    }

    /// Number of C (and D) matrices: m when scheduled, else 1.
    pub const fn mc(&self) -> usize {
        if self.scheduled_output {
            self.m
        } else {
            1
        }
    }

    /// Number of values of the model ([`values_len`]).
    pub fn values_len(&self) -> Result<usize, Error> {
        values_len(self.n, self.r, self.l, self.m, self.scheduled_output).ok_or(Error::Overflow)
    }

    /// Offset of A^(i) (i = 0..m, 0-based), n x n row-major.
    pub const fn a_offset(&self, i: usize) -> usize {
        i * self.n * self.n
    }

    /// Offset of B^(i), n x r row-major.
    pub const fn b_offset(&self, i: usize) -> usize {
        self.m * self.n * self.n + i * self.n * self.r
    }

    /// Offset of K^(i), n x l row-major.
    pub const fn k_offset(&self, i: usize) -> usize {
        self.b_offset(self.m) + i * self.n * self.l
    }

    /// Offset of C^(i) (i = 0..mc), l x n row-major.
    pub const fn c_offset(&self, i: usize) -> usize {
        self.k_offset(self.m) + i * self.l * self.n
    }

    /// Offset of D^(i) (i = 0..mc), l x r row-major.
    pub const fn d_offset(&self, i: usize) -> usize {
        self.c_offset(self.mc()) + i * self.l * self.r
    }

    /// Values of the predictor state: 2 n + 3 l (see the module documentation).
    pub const fn state_len(&self) -> usize {
        2 * self.n + 3 * self.l
    }

    /// The state x_k inside a predictor state.
    pub fn state<'a, T>(&self, state: &'a [T]) -> &'a [T] {
        sub(state, 0, self.n)
    }

    /// The running sum of squared innovations per output inside a predictor state.
    pub fn sse<'a, T>(&self, state: &'a [T]) -> &'a [T] {
        sub(state, 2 * self.n + self.l, self.l)
    }

    /// The last prediction yhat_k inside a predictor state.
    pub fn prediction<'a, T>(&self, state: &'a [T]) -> &'a [T] {
        sub(state, 2 * self.n + 2 * self.l, self.l)
    }

    /// Fill `out` (length [`ModelDims::values_len`]) with the model's values in the layout of the
    /// module documentation. Each matrix is given row-major: `a`, `b`, `k` hold m matrices
    /// (n x n, n x r, n x l); `c` and `d` hold [`ModelDims::mc`] matrices (l x n, l x r), or
    /// one, which is then repeated. A wrong count or size is an error and `out` is left
    /// unchanged.
    pub fn pack<T: Real>(
        &self,
        out: &mut [T],
        a: &[&[T]],
        b: &[&[T]],
        k: &[&[T]],
        c: &[&[T]],
        d: &[&[T]],
    ) -> Result<(), Error> {
        let (n, r, l, m, mc) = (self.n, self.r, self.l, self.m, self.mc());
        let len = self.values_len()?;
        if out.len() != len {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: len,
                got: out.len(),
            });
        }
        // (matrices, count, values each, whether one matrix may stand for all)
        let blocks: [(&[&[T]], usize, usize, bool); 5] = [
            (a, m, n * n, false),
            (b, m, n * r, false),
            (k, m, n * l, false),
            (c, mc, l * n, true),
            (d, mc, l * r, true),
        ];
        for (mats, count, size, may_repeat) in blocks {
            if mats.len() != count && !(may_repeat && mats.len() == 1) {
                return Err(Error::Dimension {
                    field: Field::Storage,
                    expected: count,
                    got: mats.len(),
                });
            }
            if let Some(bad) = mats.iter().find(|x| x.len() != size) {
                return Err(Error::Dimension {
                    field: Field::Storage,
                    expected: size,
                    got: bad.len(),
                });
            }
        }
        let mut off = 0;
        for (mats, count, size, _) in blocks {
            for i in 0..count {
                let src = if mats.len() == 1 { mats[0] } else { mats[i] };
                out[off..off + size].copy_from_slice(src);
                off += size;
            }
        }
        Ok(())
    }

    /// A read-only view of `values` (length [`ModelDims::values_len`]).
    pub fn view<'a, T: Real>(&self, values: &'a [T]) -> Result<ModelView<'a, T>, Error> {
        let len = self.values_len()?;
        if values.len() != len {
            return Err(Error::Dimension {
                field: Field::Storage,
                expected: len,
                got: values.len(),
            });
        }
        Ok(ModelView {
            dims: *self,
            values,
        })
    }
}

/// `len` values of `s` from `off`, clipped to what exists (never panics).
fn sub<T>(s: &[T], off: usize, len: usize) -> &[T] {
    let a = off.min(s.len());
    let b = off.saturating_add(len).min(s.len());
    &s[a..b]
}

/// An LPV state-space model read from its values ([`ModelDims::view`]): the matrices by
/// local model, and the one-step-ahead predictor.
#[derive(Debug, Clone, Copy)]
pub struct ModelView<'a, T> {
    dims: ModelDims,
    values: &'a [T],
}

impl<'a, T: Real> ModelView<'a, T> {
    /// The dimensions.
    pub fn dims(&self) -> ModelDims {
        self.dims
    }

    /// All values, in the layout of the module documentation.
    pub fn values(&self) -> &'a [T] {
        self.values
    }

    /// Number of values ([`ModelDims::values_len`]).
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// True for no values (never, for a validated [`ModelDims`]).
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// A^(i), n x n row-major (empty for i >= m).
    pub fn a(&self, i: usize) -> &'a [T] {
        let d = self.dims;
        self.block(i, d.m, d.a_offset(i), d.n * d.n)
    }

    /// B^(i), n x r row-major (empty for i >= m).
    pub fn b(&self, i: usize) -> &'a [T] {
        let d = self.dims;
        self.block(i, d.m, d.b_offset(i), d.n * d.r)
    }

    /// K^(i), n x l row-major (empty for i >= m).
    pub fn k(&self, i: usize) -> &'a [T] {
        let d = self.dims;
        self.block(i, d.m, d.k_offset(i), d.n * d.l)
    }

    /// C^(i), l x n row-major (empty for i >= mc).
    pub fn c(&self, i: usize) -> &'a [T] {
        let d = self.dims;
        self.block(i, d.mc(), d.c_offset(i), d.l * d.n)
    }

    /// D^(i), l x r row-major (empty for i >= mc).
    pub fn d(&self, i: usize) -> &'a [T] {
        let d = self.dims;
        self.block(i, d.mc(), d.d_offset(i), d.l * d.r)
    }

    fn block(&self, i: usize, count: usize, off: usize, len: usize) -> &'a [T] {
        if i >= count {
            return &[];
        }
        sub(self.values, off, len)
    }

    /// One step of the one-step-ahead predictor (module documentation) on sample
    /// (u_k, y_k, p_k), mu_k = [1, p_k]: writes yhat_k, e_k, adds e_k^2 to the running sum
    /// and advances x in `state` (length [`ModelDims::state_len`]). Lengths are checked
    /// (an error changes nothing); values are not (non-finite data give non-finite
    /// predictions, never a panic).
    pub fn predict_step(&self, state: &mut [T], u: &[T], y: &[T], p: &[T]) -> Result<(), Error> {
        let d = self.dims;
        let (n, r, l, m) = (d.n, d.r, d.l, d.m);
        let dim = |field, expected, got| Error::Dimension {
            field,
            expected,
            got,
        };
        if u.len() != r {
            return Err(dim(Field::Input, r, u.len()));
        }
        if y.len() != l {
            return Err(dim(Field::Output, l, y.len()));
        }
        if p.len() + 1 != m {
            return Err(dim(Field::Scheduling, m - 1, p.len()));
        }
        if state.len() < d.state_len() {
            return Err(dim(Field::Storage, d.state_len(), state.len()));
        }
        let mv = self.values;
        let mc = d.mc();
        let (a_off, b_off, k_off) = (d.a_offset(0), d.b_offset(0), d.k_offset(0));
        let (c_off, d_off) = (d.c_offset(0), d.d_offset(0));
        let (x, rest) = state.split_at_mut(n);
        let (xn, rest) = rest.split_at_mut(n);
        let (e, rest) = rest.split_at_mut(l);
        let (sse, rest) = rest.split_at_mut(l);
        let last = &mut rest[..l];
        let mu = |i: usize| if i == 0 { T::ONE } else { p[i - 1] };
        for o in 0..l {
            let mut acc = T::ZERO;
            for i in 0..mc {
                let w = if d.scheduled_output { mu(i) } else { T::ONE };
                let mut part = T::ZERO;
                for j in 0..n {
                    part += mv[c_off + i * l * n + o * n + j] * x[j];
                }
                for j in 0..r {
                    part += mv[d_off + i * l * r + o * r + j] * u[j];
                }
                acc += w * part;
            }
            let eo = y[o] - acc;
            last[o] = acc;
            e[o] = eo;
            sse[o] += eo * eo;
        }
        for row in 0..n {
            let mut acc = T::ZERO;
            for i in 0..m {
                let w = mu(i);
                if w == T::ZERO {
                    continue;
                }
                let mut part = T::ZERO;
                for j in 0..n {
                    part += mv[a_off + i * n * n + row * n + j] * x[j];
                }
                for j in 0..r {
                    part += mv[b_off + i * n * r + row * r + j] * u[j];
                }
                for j in 0..l {
                    part += mv[k_off + i * n * l + row * l + j] * e[j];
                }
                acc += w * part;
            }
            xn[row] = acc;
        }
        x.copy_from_slice(xn);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_pack_and_predictor() {
        // n = 2, r = 1, l = 1, m = 2, C and D scheduled
        let dims = ModelDims::new(2, 1, 1, 2, true).unwrap();
        assert_eq!(
            dims.values_len().unwrap(),
            2 * 2 * (2 + 1 + 1) + 2 * (2 + 1)
        );
        assert_eq!(values_len(2, 1, 1, 2, false), Some(16 + 3));
        let a0 = [0.5, 0.1, 0.0, 0.3];
        let a1 = [0.1, 0.0, 0.2, -0.1];
        let b0 = [1.0, 0.5];
        let b1 = [0.0, 0.2];
        let k0 = [0.3, 0.1];
        let k1 = [0.0, 0.0];
        let c0 = [1.0, 0.0];
        let c1 = [0.0, 0.5];
        let d0 = [0.2];
        let mut v = vec![0.0f64; dims.values_len().unwrap()];
        // d given once: repeated
        dims.pack(
            &mut v,
            &[&a0, &a1],
            &[&b0, &b1],
            &[&k0, &k1],
            &[&c0, &c1],
            &[&d0],
        )
        .unwrap();
        let view = dims.view(&v).unwrap();
        assert_eq!(view.a(1), &a1);
        assert_eq!(view.k(0), &k0);
        assert_eq!(view.c(1), &c1);
        assert_eq!(view.d(1), &d0);
        assert!(view.a(2).is_empty());
        // predictor against a hand computation
        let mut st = vec![0.0; dims.state_len()];
        st[0] = 1.0;
        st[1] = -1.0;
        let (u, y, p) = ([2.0], [0.7], [0.5]);
        view.predict_step(&mut st, &u, &y, &p).unwrap();
        let x = [1.0, -1.0];
        let mu = [1.0, 0.5];
        let yhat = (c0[0] * x[0] + c0[1] * x[1] + d0[0] * u[0])
            + mu[1] * (c1[0] * x[0] + c1[1] * x[1] + d0[0] * u[0]);
        let e = y[0] - yhat;
        assert!((dims.prediction(&st)[0] - yhat).abs() < 1e-15);
        assert!((dims.sse(&st)[0] - e * e).abs() < 1e-15);
        for row in 0..2 {
            let mut xn = 0.0;
            for (i, (a, b, k)) in [(&a0, &b0, &k0), (&a1, &b1, &k1)].iter().enumerate() {
                xn += mu[i]
                    * (a[2 * row] * x[0] + a[2 * row + 1] * x[1] + b[row] * u[0] + k[row] * e);
            }
            assert!((dims.state(&st)[row] - xn).abs() < 1e-15);
        }
        assert!(view.predict_step(&mut st, &u, &y, &[]).is_err());
        let mut w = v.clone();
        assert!(dims
            .pack(&mut w, &[&a0], &[&b0, &b1], &[&k0, &k1], &[&c0], &[&d0])
            .is_err());
        assert_eq!(w, v);
        assert!(ModelDims::new(0, 1, 1, 1, false).is_err());
    }
}
