//! The first stage of a fit made once per data and settings while a [`Scope`] is open
//! ([`super::state_candidates`]): the regression (13), the SVD (15) and the state candidates
//! (16) depend on the signals and on the settings of the regression, not on the order, the
//! refinement or what is done with the states afterwards. A diagnosis refits the model's
//! structure many times on the same record with only those changed (one or two more states,
//! a noise model on the residual, the structure refined by output error, an output equation
//! on the states), and each refit repeated the regression: on a scheduled 2x1 family plant
//! (kernel regressions of 764 columns) 32 of 134 regressions were repeats, 23 % of the
//! diagnosis's regression time.
//!
//! Entries are found by exact comparison of the signals and of the settings' text (no hash
//! that could collide), at most [`CAPACITY`] of them, each of at most [`MAX_VALUES`] sample
//! values, the least recently used dropped first. Outside a scope nothing is kept: a
//! one-off `lpvid pbsid` pays no copy, and memory is returned when the last scope closes.

use std::sync::Mutex;

use super::settings::{Order, PbsidOptions, Reg};
use super::StateCandidates;
use crate::lpvss::Signals;

/// Entries kept at most (the structures of one diagnosis step on one record).
pub const CAPACITY: usize = 16;

/// Largest record (samples x signals, training and validation together) an entry keeps: a
/// copy of at most 16 MB per entry.
pub const MAX_VALUES: usize = 1 << 21;

/// What the first stage of a fit depends on.
struct Key {
    sig: Signals,
    val: Option<Signals>,
    /// The settings as text, the order left out where only the realization reads it.
    opts: String,
}

impl Key {
    /// The key of `sig`, `val` with the settings' text `opts` ([`settings_text`]); None
    /// when the record is too long to keep ([`MAX_VALUES`]).
    fn new(sig: &Signals, val: Option<&Signals>, opts: String) -> Option<Key> {
        let values = |s: &Signals| s.len() * (s.u.ncols() + s.y.ncols() + s.p.ncols());
        if values(sig) + val.map_or(0, values) > MAX_VALUES {
            return None;
        }
        Some(Key {
            sig: sig.clone(),
            val: val.cloned(),
            opts,
        })
    }

    fn matches(&self, sig: &Signals, val: Option<&Signals>, opts: &str) -> bool {
        self.opts == opts && self.sig == *sig && self.val.as_ref() == val
    }
}

/// The settings the first stage reads, as text: all but the refinement (applied to the
/// realized model) and, unless the regression is sparse (whose path scores orders), the
/// order (chosen or given at the realization).
fn settings_text(opts: &PbsidOptions) -> String {
    let mut o = opts.clone();
    o.refine = false;
    if !matches!(o.reg, Reg::BpdnAic | Reg::BpdnSv) {
        o.order = Order::Auto;
    }
    format!("{o:?}")
}

/// The open scopes and the entries, most recently used last.
struct Entries {
    scopes: usize,
    entries: Vec<(Key, StateCandidates)>,
}

/// A memo of first stages: the process's one is [`MEMO`]; tests make their own.
struct Table(Mutex<Entries>);

impl Table {
    const fn new() -> Table {
        Table(Mutex::new(Entries {
            scopes: 0,
            entries: Vec::new(),
        }))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Entries> {
        // a panic elsewhere while the lock was held leaves entries that are each whole
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn open(&'static self) -> Scope {
        self.lock().scopes += 1;
        Scope(self)
    }

    fn get_or_compute<E>(
        &self,
        sig: &Signals,
        val: Option<&Signals>,
        opts: &PbsidOptions,
        compute: impl FnOnce() -> Result<StateCandidates, E>,
    ) -> Result<StateCandidates, E> {
        let text = {
            let mut m = self.lock();
            if m.scopes == 0 {
                drop(m);
                return compute();
            }
            let text = settings_text(opts);
            if let Some(i) = m
                .entries
                .iter()
                .position(|(k, _)| k.matches(sig, val, &text))
            {
                let e = m.entries.remove(i);
                let out = e.1.clone();
                m.entries.push(e);
                return Ok(out);
            }
            text
        };
        // computed outside the lock: other threads' fits go on meanwhile
        let out = compute()?;
        if let Some(key) = Key::new(sig, val, text) {
            let mut m = self.lock();
            if m.scopes > 0
                && !m
                    .entries
                    .iter()
                    .any(|(k, _)| k.matches(sig, val, &key.opts))
            {
                if m.entries.len() >= CAPACITY {
                    m.entries.remove(0);
                }
                m.entries.push((key, out.clone()));
            }
        }
        Ok(out)
    }
}

/// The process's memo.
static MEMO: Table = Table::new();

/// While one is alive (on any thread), first stages are kept and reused
/// ([`super::state_candidates`]). Closing the last one drops every entry.
#[must_use = "the memo is kept only while the scope lives"]
pub struct Scope(&'static Table);

impl Scope {
    /// Open a scope of the process's memo.
    pub fn open() -> Scope {
        MEMO.open()
    }
}

impl Drop for Scope {
    fn drop(&mut self) {
        let mut m = self.0.lock();
        m.scopes = m.scopes.saturating_sub(1);
        if m.scopes == 0 {
            m.entries.clear();
        }
    }
}

/// `compute()` (the first stage of a fit of `sig`, `val` with `opts`), or the copy kept from
/// an earlier call with the same signals and settings while a [`Scope`] is open. Failures
/// are not kept.
pub(crate) fn state_candidates<E>(
    sig: &Signals,
    val: Option<&Signals>,
    opts: &PbsidOptions,
    compute: impl FnOnce() -> Result<StateCandidates, E>,
) -> Result<StateCandidates, E> {
    MEMO.get_or_compute(sig, val, opts, compute)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    fn signals(n: usize, seed: u64) -> Signals {
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let u = DMatrix::from_fn(n, 1, |_, _| next());
        let p = DMatrix::from_fn(n, 1, |_, _| next());
        let mut y = DMatrix::zeros(n, 1);
        let mut x = 0.0;
        for k in 0..n {
            y[(k, 0)] = x + 0.01 * next();
            x = (0.6 + 0.2 * p[(k, 0)]) * x + u[(k, 0)];
        }
        Signals { u, y, p }
    }

    /// Inside a scope the same data and regression settings give the same candidates once
    /// computed (another order or the refinement changes nothing of the first stage); other
    /// data or other regression settings are computed; outside a scope nothing is kept.
    #[test]
    fn the_first_stage_is_reused_only_for_the_same_data_and_regression() {
        let sig = signals(300, 1);
        let opts = PbsidOptions::new(3);
        static TABLE: Table = Table::new();
        let calls = std::cell::Cell::new(0);
        let run = |sig: &Signals, o: &PbsidOptions| {
            TABLE
                .get_or_compute(sig, None, o, || {
                    calls.set(calls.get() + 1);
                    super::super::state_candidates(sig, None, o)
                })
                .unwrap()
        };
        let scope = TABLE.open();
        let a = run(&sig, &opts);
        let other_order = PbsidOptions {
            order: Order::Fixed(2),
            refine: true,
            ..opts.clone()
        };
        let b = run(&sig, &other_order);
        assert_eq!(calls.get(), 1);
        assert_eq!(a.singular_values(), b.singular_values());
        let wider = PbsidOptions::new(4);
        run(&sig, &wider);
        run(&signals(300, 2), &opts);
        assert_eq!(calls.get(), 3);
        // the realized models are the same to the bit
        let ma = a.realize(&sig, &opts, Some(2)).unwrap().model;
        let fresh = super::super::state_candidates(&sig, None, &opts).unwrap();
        let mb = fresh.realize(&sig, &opts, Some(2)).unwrap().model;
        assert_eq!(format!("{ma:?}"), format!("{mb:?}"));
        drop(scope);
        run(&sig, &opts);
        assert_eq!(calls.get(), 4);
    }
}
