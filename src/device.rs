//! The device engine: bytes in, bytes out (DESIGN.md section 3.6; the wire is written down in
//! `docs/wire.md`). Transport-agnostic (a UART in the firmware, a pseudo-terminal in the
//! host's tests), allocation-free, and it owns the statistics. Cargo feature `device`.
//! Where it touches the papers: the statistics of problem (13) of the kernel paper
//! ([`crate::stats`]), their solve with the l1 / l2,1 Lasso (sparse paper problem (33),
//! [`crate::lasso`]) and the one-step predictor of an LPV state-space model (kernel paper
//! eq. (1)-(2) in innovation form, [`crate::model`]).
//!
//! - **Framing**: a [`Deframer`] splits the input at 0x00; every frame is decoded with
//!   [`decode_frame`]. A frame that fails (garbage, bytes lost or flipped, cut short, too
//!   long, another protocol version, an unknown message) is counted and answered with an
//!   unsolicited [`Message::Error`] (seq 0, a NAK with the reason); the engine is back in
//!   step at the next delimiter and its state is untouched.
//! - **Exactly once**: a state-changing request (configure, samples, solve, push model,
//!   reset) whose `seq` equals the previous request's is a retransmission: it is answered
//!   from a cache, not applied again. Samples carry their stream index on top of that: only
//!   samples at or after the next expected index are applied (a duplicate is acknowledged and
//!   counted in [`Status::duplicate_samples`]), and samples that start after it are refused
//!   with [`ErrorCode::Gap`]: no sample is counted twice or silently lost.
//! - **Statistics**: a [`PbsidStats`] over static arrays (`W` window, `G` Gram, `R` vector
//!   values), built at [`Message::Configure`]; the Gram sums compensated
//!   ([`Summation::Compensated`], `G` holds two packed triangles: see [`crate::stats`]).
//! - **Solve**: problem (13), y_{k+p} on [z_k^p; u_{k+p}], from the leading block of the
//!   statistics by the core's coordinate-descent Lasso ([`crate::lasso`], l1 or l2,1,
//!   optionally on standardised columns, lambda as a fraction of lambda_max; 0 gives least
//!   squares). Needs (3 l + 2)(q + r) of the `X` solver values.
//! - **Prediction**: a pushed LPV state-space model (values in the `[A|B|K|C|D]` layout of
//!   [`crate::model`]) runs its one-step-ahead predictor ([`crate::model::ModelView::predict_step`])
//!   on every applied sample and accumulates the squared error per output. Needs the
//!   model's values plus its predictor state (2 n + 3 l) of the `M` model values.
//!
//! Size: the struct holds all storage inline: W + G + R + X + M floats, 3 F bytes (receive,
//! scratch, transmit buffers; F bytes cover a raw frame of [`max_raw`]`(F)`), and about 100
//! bytes of counters. A configuration builds the statistics in place
//! ([`PbsidStatsArrays::init_in_place`]): only the window (`W` values) passes through the
//! stack, never the Gram.

use crate::error::Error;
use crate::lasso::{cross_from, CoordinateDescent, Leading, Penalty, Problem, Settings};
use crate::protocol::{
    caps, decode_frame, encode_frame, max_raw, read_value, write_values, Config, Deframer,
    ErrorCode, ErrorReply, Event, Info, Layout, Message, ModelChunk, Prediction, SolveRequest,
    SolveSummary, Status, WireReal, MESSAGE_HEADROOM, VERSION,
};
use core::mem::MaybeUninit;

use crate::model::{values_len, ModelDims};
use crate::real::Real;
use crate::stats::{
    packed_len, stat_vector_len, PbsidStats, PbsidStatsArrays, StatsLayout, Summation,
};
use crate::window::{window_storage_len, PbsidDims};

/// Largest r + l + s a device accepts (one sample is decoded into a stack array of this
/// many values).
pub const MAX_CHANNELS: usize = 32;

/// Statistics over the device's static arrays.
pub type DeviceStats<T, const W: usize, const G: usize, const R: usize> =
    PbsidStats<T, [T; W], [T; G], [T; R]>;

/// The statistics of a configured device, built in place by
/// [`PbsidStatsArrays::init_in_place`] at every configuration: the `G` Gram values are zeroed
/// where the engine lives (a `static` in firmware) instead of being built on the stack and
/// moved in, so configuring needs no stack of the Gram's size.
struct StatsSlot<T: Real, const W: usize, const G: usize, const R: usize> {
    /// `val` is initialised.
    ready: bool,
    val: MaybeUninit<DeviceStats<T, W, G, R>>,
}

impl<T: Real, const W: usize, const G: usize, const R: usize> StatsSlot<T, W, G, R> {
    const fn empty() -> Self {
        StatsSlot {
            ready: false,
            val: MaybeUninit::uninit(),
        }
    }

    fn get(&self) -> Option<&DeviceStats<T, W, G, R>> {
        // SAFETY: `ready` is set only after `init_in_place` initialised `val`.
        self.ready.then(|| unsafe { self.val.assume_init_ref() })
    }

    fn get_mut(&mut self) -> Option<&mut DeviceStats<T, W, G, R>> {
        // SAFETY: as in `get`.
        self.ready.then(|| unsafe { self.val.assume_init_mut() })
    }

    fn is_some(&self) -> bool {
        self.ready
    }

    /// (Re)build the statistics for `dims` in place; on error the device is unconfigured.
    fn configure(&mut self, dims: PbsidDims, layout: StatsLayout) -> Result<(), Error> {
        self.ready = false;
        PbsidStatsArrays::init_in_place_with(&mut self.val, dims, layout, Summation::Compensated)?;
        self.ready = true;
        Ok(())
    }
}

impl<T: Real, const W: usize, const G: usize, const R: usize> Clone for StatsSlot<T, W, G, R> {
    fn clone(&self) -> Self {
        let mut c = Self::empty();
        if let Some(st) = self.get() {
            c.val.write(st.clone());
            c.ready = true;
        }
        c
    }
}

impl<T: Real, const W: usize, const G: usize, const R: usize> core::fmt::Debug
    for StatsSlot<T, W, G, R>
{
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        self.get().fmt(f)
    }
}

/// The reply a state-changing request got, kept to answer a retransmission.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cached {
    Ack,
    Status(Status),
    Solved(SolveSummary),
    Error(ErrorReply),
}

impl Cached {
    fn message(&self) -> Message<'static> {
        match *self {
            Cached::Ack => Message::Ack,
            Cached::Status(s) => Message::Status(s),
            Cached::Solved(s) => Message::Solved(s),
            Cached::Error(e) => Message::Error(e),
        }
    }
}

fn err(code: ErrorCode, detail: usize) -> Cached {
    Cached::Error(ErrorReply {
        code,
        detail: u32::try_from(detail).unwrap_or(u32::MAX),
    })
}

/// Shape of a pushed model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct ModelShape {
    n: usize,
    scheduled_output: bool,
    total: usize,
}

impl ModelShape {
    /// The model's dimensions under configuration `c` (the layout of [`crate::model`]).
    fn dims(&self, c: &Config) -> ModelDims {
        ModelDims {
            n: self.n,
            r: c.r as usize,
            l: c.l as usize,
            m: c.s as usize + 1,
            scheduled_output: self.scheduled_output,
        }
    }
}

/// Everything but the receive buffer (so a frame borrowed from it can be handled by a
/// method of this part).
#[derive(Debug, Clone)]
struct Engine<
    T: WireReal,
    const W: usize,
    const G: usize,
    const R: usize,
    const X: usize,
    const M: usize,
    const F: usize,
> {
    stats: StatsSlot<T, W, G, R>,
    config: Option<Config>,
    next_sample: u32,
    duplicate_samples: u32,
    frames_ok: u32,
    frames_rejected: u32,
    last_seq: Option<u32>,
    cached: Option<Cached>,
    solver: [T; X],
    solved: Option<SolveSummary>,
    model: [T; M],
    shape: Option<ModelShape>,
    received: usize,
    model_loaded: bool,
    pred_count: u32,
    vals: [u8; F],
    raw: [u8; F],
    tx: [u8; F],
}

/// The device engine with its static capacities: `W` window values, `G` Gram values, `R`
/// statistic-vector values, `X` solver values, `M` model values (all of float type `T`)
/// and `F` bytes per frame buffer. See the module documentation.
#[derive(Debug, Clone)]
pub struct Device<
    T: WireReal,
    const W: usize,
    const G: usize,
    const R: usize,
    const X: usize,
    const M: usize,
    const F: usize,
> {
    rx: Deframer<F>,
    eng: Engine<T, W, G, R, X, M, F>,
}

impl<
        T: WireReal,
        const W: usize,
        const G: usize,
        const R: usize,
        const X: usize,
        const M: usize,
        const F: usize,
    > Default for Device<T, W, G, R, X, M, F>
{
    fn default() -> Self {
        Self::new()
    }
}

/// Encode `msg` into `tx` (via `raw`) and hand the frame to `send`. A message too large for
/// the buffers (not produced by this engine: chunks are sized to fit) is replaced by an
/// error reply, which always fits.
fn emit<S: FnMut(&[u8])>(raw: &mut [u8], tx: &mut [u8], seq: u32, msg: &Message<'_>, send: &mut S) {
    let n = match encode_frame(seq, msg, raw, tx) {
        Ok(n) => n,
        Err(_) => {
            let e = Message::Error(ErrorReply {
                code: ErrorCode::Capacity,
                detail: 0,
            });
            match encode_frame(seq, &e, raw, tx) {
                Ok(n) => n,
                Err(_) => return,
            }
        }
    };
    send(&tx[..n]);
}

impl<
        T: WireReal,
        const W: usize,
        const G: usize,
        const R: usize,
        const X: usize,
        const M: usize,
        const F: usize,
    > Device<T, W, G, R, X, M, F>
{
    /// An unconfigured device (`const`: firmware can place it in a `static`).
    pub const fn new() -> Self {
        Device {
            rx: Deframer::new(),
            eng: Engine {
                stats: StatsSlot::empty(),
                config: None,
                next_sample: 0,
                duplicate_samples: 0,
                frames_ok: 0,
                frames_rejected: 0,
                last_seq: None,
                cached: None,
                solver: [T::ZERO; X],
                solved: None,
                model: [T::ZERO; M],
                shape: None,
                received: 0,
                model_loaded: false,
                pred_count: 0,
                vals: [0; F],
                raw: [0; F],
                tx: [0; F],
            },
        }
    }

    /// Feed received bytes; every reply frame is passed to `send` (complete, delimiter
    /// included) as soon as it is ready. Never allocates, never panics on any input.
    pub fn handle<S: FnMut(&[u8])>(&mut self, input: &[u8], mut send: S) {
        for &b in input {
            match self.rx.push(b) {
                Event::Pending => {}
                Event::Oversize => self.eng.reject(ErrorCode::Oversize, &mut send),
                Event::Frame(buf) => match decode_frame(buf) {
                    Err(code) => self.eng.reject(code, &mut send),
                    Ok(pkt) => {
                        self.eng.frames_ok = self.eng.frames_ok.wrapping_add(1);
                        self.eng.on_packet(pkt.seq, &pkt.msg, &mut send);
                    }
                },
            }
        }
    }

    /// What the device reports in its handshake.
    pub fn info(&self) -> Info {
        self.eng.info()
    }

    /// The device's state.
    pub fn status(&self) -> Status {
        self.eng.status()
    }

    /// The statistics, once configured.
    pub fn stats(&self) -> Option<&DeviceStats<T, W, G, R>> {
        self.eng.stats.get()
    }
}

impl<
        T: WireReal,
        const W: usize,
        const G: usize,
        const R: usize,
        const X: usize,
        const M: usize,
        const F: usize,
    > Engine<T, W, G, R, X, M, F>
{
    fn reject<S: FnMut(&[u8])>(&mut self, code: ErrorCode, send: &mut S) {
        self.frames_rejected = self.frames_rejected.wrapping_add(1);
        let detail = if code == ErrorCode::WrongVersion {
            VERSION as u32
        } else {
            0
        };
        let msg = Message::Error(ErrorReply { code, detail });
        emit(&mut self.raw, &mut self.tx, 0, &msg, send);
    }

    fn info(&self) -> Info {
        let c = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        Info {
            version: VERSION,
            float_bytes: T::BYTES as u8,
            max_frame: u16::try_from(max_raw(F)).unwrap_or(u16::MAX),
            window_cap: c(W),
            // packed Gram values a configuration may have (the storage holds twice as many:
            // the compensated sums' low parts)
            gram_cap: c(G / 2),
            vector_cap: c(R),
            solver_cap: c(X),
            model_cap: c(M),
            max_channels: MAX_CHANNELS as u16,
            capabilities: caps::EXTENDED | caps::SOLVE | caps::PREDICT,
        }
    }

    fn status(&self) -> Status {
        let (r, l, s, p) = match &self.config {
            Some(c) => (c.r, c.l, c.s, c.p),
            None => (0, 0, 0, 0),
        };
        let (windows, gram_len) = match self.stats.get() {
            Some(st) => (
                st.gram().count(),
                u32::try_from(st.gram().packed().len()).unwrap_or(u32::MAX),
            ),
            None => (0, 0),
        };
        Status {
            configured: self.stats.is_some(),
            r,
            l,
            s,
            p,
            next_sample: self.next_sample,
            windows,
            gram_len,
            duplicate_samples: self.duplicate_samples,
            frames_ok: self.frames_ok,
            frames_rejected: self.frames_rejected,
            model_loaded: self.model_loaded,
        }
    }

    /// Values per [`Message::Values`] chunk that fit a frame.
    fn chunk_values() -> usize {
        (max_raw(F).saturating_sub(MESSAGE_HEADROOM) / T::BYTES).max(1)
    }

    fn on_packet<S: FnMut(&[u8])>(&mut self, seq: u32, msg: &Message<'_>, send: &mut S) {
        match *msg {
            Message::Hello { .. } => {
                // a new session: forget the retransmission cache
                self.last_seq = Some(seq);
                self.cached = None;
                let m = Message::Info(self.info());
                emit(&mut self.raw, &mut self.tx, seq, &m, send);
            }
            Message::GetStatus => {
                let m = Message::Status(self.status());
                emit(&mut self.raw, &mut self.tx, seq, &m, send);
            }
            Message::PullStats { offset, count } => self.pull(seq, offset, count, false, send),
            Message::PullSolution { offset, count } => self.pull(seq, offset, count, true, send),
            Message::GetPrediction => self.prediction(seq, send),
            Message::Configure(_)
            | Message::Samples { .. }
            | Message::Solve(_)
            | Message::PushModel(_)
            | Message::Reset => {
                if seq != 0 && self.last_seq == Some(seq) {
                    if let Some(c) = self.cached {
                        emit(&mut self.raw, &mut self.tx, seq, &c.message(), send);
                        return;
                    }
                }
                let c = match *msg {
                    Message::Configure(c) => self.configure(c),
                    Message::Samples { first, values } => self.samples(first, values),
                    Message::Solve(req) => self.solve(req),
                    Message::PushModel(ch) => self.push_model(&ch),
                    _ => self.reset(),
                };
                self.last_seq = Some(seq);
                self.cached = Some(c);
                emit(&mut self.raw, &mut self.tx, seq, &c.message(), send);
            }
            Message::Info(_)
            | Message::Status(_)
            | Message::Values { .. }
            | Message::Solved(_)
            | Message::Ack
            | Message::Error(_)
            | Message::Prediction(_) => {
                let m = Message::Error(ErrorReply {
                    code: ErrorCode::UnexpectedMessage,
                    detail: 0,
                });
                emit(&mut self.raw, &mut self.tx, seq, &m, send);
            }
        }
    }

    fn pull<S: FnMut(&[u8])>(
        &mut self,
        seq: u32,
        offset: u32,
        count: u16,
        solution: bool,
        send: &mut S,
    ) {
        let src: Result<&[T], ErrorCode> = if solution {
            match (&self.solved, self.stats.get()) {
                (Some(s), Some(_)) => {
                    let n = (s.columns as usize).saturating_mul(s.outputs as usize);
                    Ok(&self.solver[..n.min(X)])
                }
                (None, Some(_)) => Err(ErrorCode::SolveFailed),
                _ => Err(ErrorCode::NotConfigured),
            }
        } else {
            match self.stats.get() {
                Some(st) => Ok(st.gram().packed()),
                None => Err(ErrorCode::NotConfigured),
            }
        };
        let msg = match src {
            Err(code) => Message::Error(ErrorReply { code, detail: 0 }),
            Ok(vals) => {
                let total = vals.len();
                let off = offset as usize;
                if off > total {
                    Message::Error(ErrorReply {
                        code: ErrorCode::OutOfRange,
                        detail: total as u32,
                    })
                } else {
                    let n = (count as usize)
                        .min(Self::chunk_values())
                        .min(total - off)
                        .min(F / T::BYTES);
                    let bytes = write_values(&vals[off..off + n], &mut self.vals).unwrap_or(0);
                    Message::Values {
                        offset,
                        total: total as u32,
                        values: &self.vals[..bytes],
                    }
                }
            }
        };
        emit(&mut self.raw, &mut self.tx, seq, &msg, send);
    }

    fn prediction<S: FnMut(&[u8])>(&mut self, seq: u32, send: &mut S) {
        let msg = match (self.shape, &self.config) {
            (Some(sh), Some(c)) if self.model_loaded => {
                let md = sh.dims(c);
                let l = md.l;
                let end = sh.total + md.state_len();
                let bytes = 2 * l * T::BYTES;
                if end > M || bytes > F {
                    Message::Error(ErrorReply {
                        code: ErrorCode::Capacity,
                        detail: 0,
                    })
                } else {
                    let state = &self.model[sh.total..end];
                    let a =
                        write_values(md.sse(state), &mut self.vals[..l * T::BYTES]).unwrap_or(0);
                    let b = write_values(md.prediction(state), &mut self.vals[a..]).unwrap_or(0);
                    Message::Prediction(Prediction {
                        count: self.pred_count,
                        sse: &self.vals[..a],
                        last: &self.vals[a..a + b],
                    })
                }
            }
            _ => Message::Error(ErrorReply {
                code: ErrorCode::ModelInvalid,
                detail: 0,
            }),
        };
        emit(&mut self.raw, &mut self.tx, seq, &msg, send);
    }

    fn configure(&mut self, c: Config) -> Cached {
        if c.forgetting != 1.0 {
            return err(ErrorCode::Unsupported, 0);
        }
        let (r, l, s, p) = (c.r as usize, c.l as usize, c.s as usize, c.p as usize);
        let dims = match PbsidDims::new(r, l, s, p) {
            Ok(d) => d,
            Err(_) => return err(ErrorCode::BadConfig, 0),
        };
        if r + l + s > MAX_CHANNELS {
            return err(ErrorCode::Capacity, r + l + s);
        }
        let layout: StatsLayout = c.layout.into();
        let wl = window_storage_len(r, l, s, p);
        if wl > W {
            return err(ErrorCode::Capacity, wl);
        }
        let len = match stat_vector_len(&dims, layout) {
            Ok(v) => v,
            Err(_) => return err(ErrorCode::BadConfig, 0),
        };
        if len > R {
            return err(ErrorCode::Capacity, len);
        }
        // compensated sums: two packed triangles (totals and their low parts)
        let g = len.saturating_mul(len + 1);
        if g > G {
            return err(ErrorCode::Capacity, g / 2);
        }
        // in place: the Gram is zeroed where it lives, never copied through the stack
        if self.stats.configure(dims, layout).is_err() {
            return err(ErrorCode::BadConfig, 0);
        }
        self.config = Some(c);
        self.next_sample = 0;
        self.duplicate_samples = 0;
        self.solved = None;
        self.shape = None;
        self.received = 0;
        self.model_loaded = false;
        self.pred_count = 0;
        Cached::Ack
    }

    fn reset(&mut self) -> Cached {
        let Some(st) = self.stats.get_mut() else {
            return err(ErrorCode::NotConfigured, 0);
        };
        st.gram_mut().reset();
        st.break_window();
        self.next_sample = 0;
        self.duplicate_samples = 0;
        self.solved = None;
        self.clear_predictor();
        Cached::Ack
    }

    fn clear_predictor(&mut self) {
        if let (Some(sh), Some(c)) = (self.shape, &self.config) {
            let end = (sh.total + sh.dims(c).state_len()).min(M);
            let start = sh.total.min(end);
            for v in self.model[start..end].iter_mut() {
                *v = T::ZERO;
            }
        }
        self.pred_count = 0;
    }

    fn samples(&mut self, first: u32, values: &[u8]) -> Cached {
        let Some(st) = self.stats.get_mut() else {
            return err(ErrorCode::NotConfigured, 0);
        };
        let d = st.dims();
        let per = d.r + d.l + d.s;
        let bps = per * T::BYTES;
        if bps == 0 || values.len() % bps != 0 {
            return err(ErrorCode::BadLength, bps);
        }
        let n = values.len() / bps;
        if first > self.next_sample {
            return err(ErrorCode::Gap, self.next_sample as usize);
        }
        let skip = (self.next_sample - first) as usize;
        let skip = skip.min(n);
        self.duplicate_samples = self.duplicate_samples.wrapping_add(skip as u32);
        let mut buf = [T::ZERO; MAX_CHANNELS];
        for i in skip..n {
            for (j, v) in buf[..per].iter_mut().enumerate() {
                *v = read_value(values, i * per + j);
            }
            let (u, rest) = buf[..per].split_at(d.r);
            let (y, p) = rest.split_at(d.l);
            if st.update(u, y, p).is_err() {
                return err(
                    ErrorCode::SampleRejected,
                    (first as usize).saturating_add(i),
                );
            }
            if self.model_loaded {
                if let (Some(sh), Some(c)) = (self.shape, &self.config) {
                    let (vals, state) = self.model.split_at_mut(sh.total);
                    if let Ok(view) = sh.dims(c).view(vals) {
                        // lengths were checked at the push; the state fits (need <= M)
                        let _ = view.predict_step(state, u, y, p);
                    }
                    self.pred_count = self.pred_count.wrapping_add(1);
                }
            }
            self.next_sample = self.next_sample.wrapping_add(1);
        }
        Cached::Status(self.status())
    }

    fn solve(&mut self, req: SolveRequest) -> Cached {
        self.solved = None;
        let Some(st) = self.stats.get() else {
            return err(ErrorCode::NotConfigured, 0);
        };
        let d = st.dims();
        let Ok(q) = d.q() else {
            return err(ErrorCode::BadConfig, 0);
        };
        let (qc, l) = (q + d.r, d.l);
        let need = (3 * l + 2).saturating_mul(qc);
        if need > X {
            return err(ErrorCode::Capacity, need);
        }
        let ratio = req.lambda_ratio;
        if !(ratio.is_finite() && ratio >= 0.0) {
            return err(ErrorCode::BadConfig, 0);
        }
        let gram = st.gram();
        if gram.count() == 0 {
            return err(ErrorCode::SolveFailed, 0);
        }
        let (theta, rest) = self.solver.split_at_mut(l * qc);
        let (cross, rest) = rest.split_at_mut(l * qc);
        let (weights, rest) = rest.split_at_mut(qc);
        let work = &mut rest[..(l + 1) * qc];
        let nwin = T::of(gram.count() as f64);
        for (j, w) in weights.iter_mut().enumerate() {
            let g = gram.get(j, j);
            *w = if req.standardise && g > T::ZERO {
                (g / nwin).sqrt()
            } else {
                T::ONE
            };
        }
        for v in theta.iter_mut() {
            *v = T::ZERO;
        }
        let res = (|| -> Result<SolveSummary, Error> {
            let lead = Leading::new(gram, qc)?;
            cross_from(gram, qc, l, cross)?;
            let penalty = if req.group {
                Penalty::Group
            } else {
                Penalty::L1
            };
            let prob = Problem::new(&lead, cross, l, penalty)?.with_weights(weights)?;
            let mut cd = CoordinateDescent::new(l, qc, work)?;
            let settings = Settings::default();
            let lmax = cd.lambda_max(&prob, theta, &settings)?;
            let lambda = lmax * T::of(ratio as f64);
            let fit = cd.solve(&prob, lambda, theta, &settings)?;
            Ok(SolveSummary {
                columns: qc as u32,
                outputs: l as u8,
                lambda: lambda.to_f64() as f32,
                lambda_max: lmax.to_f64() as f32,
                iterations: fit.iterations as u32,
                converged: fit.converged,
                active: fit.active as u32,
                kkt: fit.kkt.to_f64() as f32,
                objective: fit.objective.to_f64() as f32,
            })
        })();
        match res {
            Ok(s) => {
                self.solved = Some(s);
                Cached::Solved(s)
            }
            Err(e) => err(
                ErrorCode::SolveFailed,
                match e {
                    Error::Singular => 1,
                    Error::NoConvergence => 2,
                    Error::Overflow => 3,
                    _ => 4,
                },
            ),
        }
    }

    fn push_model(&mut self, ch: &ModelChunk<'_>) -> Cached {
        let Some(c) = self.config else {
            return err(ErrorCode::NotConfigured, 0);
        };
        let (r, l, m) = (c.r as usize, c.l as usize, c.s as usize + 1);
        let n = ch.n as usize;
        let Some(total) = values_len(n, r, l, m, ch.scheduled_output) else {
            return err(ErrorCode::ModelInvalid, 0);
        };
        if n == 0 || ch.total as usize != total {
            return err(ErrorCode::ModelInvalid, total);
        }
        let need = total + 2 * n + 3 * l;
        if need > M {
            return err(ErrorCode::Capacity, need);
        }
        if ch.values.len() % T::BYTES != 0 {
            return err(ErrorCode::BadLength, T::BYTES);
        }
        let cnt = ch.values.len() / T::BYTES;
        let shape = ModelShape {
            n,
            scheduled_output: ch.scheduled_output,
            total,
        };
        if ch.offset == 0 {
            self.shape = Some(shape);
            self.received = 0;
            self.model_loaded = false;
        } else if self.shape != Some(shape) || ch.offset as usize != self.received {
            return err(ErrorCode::OutOfRange, self.received);
        }
        let off = self.received;
        if off + cnt > total {
            return err(ErrorCode::OutOfRange, total);
        }
        for (i, v) in self.model[off..off + cnt].iter_mut().enumerate() {
            *v = read_value(ch.values, i);
        }
        self.received += cnt;
        if self.received == total {
            if self.model[..total].iter().any(|v| !v.is_finite()) {
                self.shape = None;
                self.received = 0;
                return err(ErrorCode::ModelInvalid, 0);
            }
            self.model_loaded = true;
            self.clear_predictor();
        }
        Cached::Ack
    }
}

/// A no_std-friendly default sizing: B2-like problems (r = l = s = 1) up to p = 4 with the
/// extended layout (L = 126, G = 8 001), solves up to q + r = 61 columns with l = 1, models
/// up to n = 8, and frames of 512 bytes.
pub mod sizes {
    use crate::stats::stat_vector_len_const;
    use crate::{gram_storage_len, window_storage_len};

    /// Window values (p = 4, r = l = s = 1, and e.g. r = 2, l = 3, s = 3 with p = 1).
    pub const W: usize = 64;
    /// Statistic vector values: the extended layout of r = l = s = 1, p = 4.
    pub const R: usize = stat_vector_len_const(1, 1, 1, 4, true);
    /// Gram storage: compensated sums, two packed triangles (8 001 values each).
    pub const G: usize = gram_storage_len(R);
    /// Solver values: (3 l + 2)(q + r) with l = 1, q + r = 61.
    pub const X: usize = 5 * 61;
    /// Model values: n = 8, r = l = 1, m = 2 with scheduled C, D: 2(64 + 8 + 8) + 2(8 + 1)
    /// + 2 n + 3 l = 197.
    pub const M: usize = 200;
    /// Frame buffer bytes.
    pub const F: usize = 512;
    /// Check that the window fits the largest configuration.
    const _: () = assert!(W >= window_storage_len(1, 1, 1, 4));
}

/// The device with the default [`sizes`].
pub type DefaultDevice<T> =
    Device<T, { sizes::W }, { sizes::G }, { sizes::R }, { sizes::X }, { sizes::M }, { sizes::F }>;

/// Layout on the wire of a statistics layout.
pub fn wire_layout(l: StatsLayout) -> Layout {
    match l {
        StatsLayout::Plain => Layout::Plain,
        StatsLayout::Extended => Layout::Extended,
    }
}

/// Number of packed Gram values the device will hold for a configuration (what a host
/// pulls), or `None` on overflow.
pub fn gram_values(dims: &PbsidDims, layout: StatsLayout) -> Option<usize> {
    stat_vector_len(dims, layout).ok().map(packed_len)
}
