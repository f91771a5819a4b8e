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
    caps, decode_frame_checked, encode_frame, encode_frame_version, max_raw, read_value,
    write_values, Config, Deframer, ErrorCode, ErrorReply, Estimate, Event, Info, Layout, Message,
    ModelChunk, Prediction, Rejected, SolveRequest, SolveSummary, Status, Track, WireReal,
    MESSAGE_HEADROOM, OLDEST_ANSWERED, VERSION,
};
use crate::sliding::{inline_window_len, rebase_gram, HalfWindow};
use crate::stats::Gram;
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
    fn configure(
        &mut self,
        dims: PbsidDims,
        layout: StatsLayout,
        summation: Summation,
    ) -> Result<(), Error> {
        self.ready = false;
        PbsidStatsArrays::init_in_place_with(&mut self.val, dims, layout, summation)?;
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
    /// The sliding window's bookkeeping (the snapshot is in the Gram's spare storage).
    window: Option<HalfWindow>,
    /// The recursive estimate's settings and record.
    track: Option<Track>,
    est: EstimateRecord<T>,
    vals: [u8; F],
    raw: [u8; F],
    tx: [u8; F],
}

/// The one-step prediction errors of a solution in force (the VARX predictor of problem
/// (13), kernel paper eq. (12)-(13)): e = y_{k+p} - Theta [z_k^p; u_{k+p}] on every new
/// statistic vector. The device keeps one per recursive estimate; the host replays it to
/// check the device bit for bit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneStep<T> {
    /// Predictions made.
    pub count: u32,
    /// Sum of squared errors per output (the first l entries).
    pub sse: [T; MAX_CHANNELS],
    /// The last error per output.
    pub last: [T; MAX_CHANNELS],
}

impl<T: Real> Default for OneStep<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T: Real> OneStep<T> {
    /// An empty record.
    pub const fn new() -> Self {
        OneStep {
            count: 0,
            sse: [T::ZERO; MAX_CHANNELS],
            last: [T::ZERO; MAX_CHANNELS],
        }
    }

    /// Predict y_{k+p} of the statistic vector `v` (head [z_k^p; u_{k+p}; y_{k+p}], e.g.
    /// [`PbsidStats::last_vector`]) with `theta` (l x `columns`, row-major, columns = q + r)
    /// and record the error. Too short a `v` or `theta`, or l > [`MAX_CHANNELS`]: nothing.
    pub fn add(&mut self, v: &[T], theta: &[T], columns: usize, l: usize) {
        if v.len() < columns + l || theta.len() < l * columns || l > MAX_CHANNELS {
            return;
        }
        let (phi, y) = (&v[..columns], &v[columns..columns + l]);
        for o in 0..l {
            let row = &theta[o * columns..(o + 1) * columns];
            let mut yhat = T::ZERO;
            for (t, x) in row.iter().zip(phi) {
                yhat += *t * *x;
            }
            let e = y[o] - yhat;
            self.sse[o] += e * e;
            self.last[o] = e;
        }
        self.count = self.count.wrapping_add(1);
    }
}

/// The recursive estimate's record ([`Message::Estimate`]).
#[derive(Debug, Clone, Copy)]
struct EstimateRecord<T> {
    since_solve: u32,
    solves: u32,
    failures: u32,
    at_sample: u32,
    summary: Option<SolveSummary>,
    /// The solution in force since it was solved.
    one_step: OneStep<T>,
    /// The previous solution over its whole interval (between the last two solves).
    interval: OneStep<T>,
}

impl<T: Real> EstimateRecord<T> {
    const fn new() -> Self {
        EstimateRecord {
            since_solve: 0,
            solves: 0,
            failures: 0,
            at_sample: 0,
            summary: None,
            one_step: OneStep::new(),
            interval: OneStep::new(),
        }
    }

    /// A new solution is in force: the finished one's record becomes the interval's, and
    /// the new one starts empty.
    fn clear_predictions(&mut self) {
        self.interval = self.one_step;
        self.one_step = OneStep::new();
    }
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
                window: None,
                track: None,
                est: EstimateRecord::new(),
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
                Event::Frame(buf) => match decode_frame_checked(buf) {
                    Err(Rejected::Frame(code)) => self.eng.reject(code, &mut send),
                    Err(Rejected::Version(v)) => self.eng.reject_version(v.theirs, &mut send),
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
    /// NAK a frame of another protocol version: `detail` is this device's version, and an
    /// older peer (from [`OLDEST_ANSWERED`]) gets the NAK in its own framing so it can read
    /// it (the `Error` reply is encoded alike in every version); a newer peer reads our
    /// version byte.
    fn reject_version<S: FnMut(&[u8])>(&mut self, theirs: u8, send: &mut S) {
        self.frames_rejected = self.frames_rejected.wrapping_add(1);
        let msg = Message::Error(ErrorReply {
            code: ErrorCode::WrongVersion,
            detail: VERSION as u32,
        });
        let version = if (OLDEST_ANSWERED..VERSION).contains(&theirs) {
            theirs
        } else {
            VERSION
        };
        if let Ok(n) = encode_frame_version(version, 0, &msg, &mut self.raw, &mut self.tx) {
            send(&self.tx[..n]);
        }
    }

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
            capabilities: caps::EXTENDED
                | caps::SOLVE
                | caps::PREDICT
                | caps::FORGETTING
                | caps::WINDOW
                | caps::TRACK,
        }
    }

    fn status(&self) -> Status {
        let (r, l, s, p) = match &self.config {
            Some(c) => (c.r, c.l, c.s, c.p),
            None => (0, 0, 0, 0),
        };
        let (windows, gram_len, weight) = match self.stats.get() {
            Some(st) => (
                st.gram().count(),
                u32::try_from(st.gram().packed().len()).unwrap_or(u32::MAX),
                st.gram().weight() as f32,
            ),
            None => (0, 0, 0.0),
        };
        let (forgetting, window) = match &self.config {
            Some(c) => (c.forgetting, c.window),
            None => (1.0, 0),
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
            forgetting,
            window,
            weight,
            solves: self.est.solves,
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
            Message::GetEstimate => self.estimate(seq, send),
            Message::Configure(_)
            | Message::Samples { .. }
            | Message::Solve(_)
            | Message::PushModel(_)
            | Message::Track(_)
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
                    Message::Track(t) => self.set_track(t),
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
            | Message::Prediction(_)
            | Message::Estimate(_) => {
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
        let lambda = c.forgetting;
        if !(lambda.is_finite() && lambda > 0.0 && lambda <= 1.0) {
            return err(ErrorCode::Unsupported, 1);
        }
        let window = match c.window {
            0 => None,
            1 => return err(ErrorCode::Unsupported, 3),
            _ if lambda != 1.0 => return err(ErrorCode::Unsupported, 2),
            n => match HalfWindow::new(n as u64) {
                Ok(w) => Some(w),
                Err(_) => return err(ErrorCode::Unsupported, 3),
            },
        };
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
        // compensated sums: two packed triangles (totals and their low parts); a window also
        // keeps its snapshot there (plain totals when three triangles do not fit)
        let Some(summation) = device_summation(len, window.is_some(), G) else {
            return err(ErrorCode::Capacity, packed_len(len));
        };
        // in place: the Gram is zeroed where it lives, never copied through the stack
        if self.stats.configure(dims, layout, summation).is_err() {
            return err(ErrorCode::BadConfig, 0);
        }
        if let Some(st) = self.stats.get_mut() {
            if st.set_forgetting(T::of(lambda as f64)).is_err() {
                self.stats.ready = false;
                return err(ErrorCode::Unsupported, 1);
            }
        }
        self.config = Some(c);
        self.window = window;
        self.track = None;
        self.est = EstimateRecord::new();
        self.next_sample = 0;
        self.duplicate_samples = 0;
        self.solved = None;
        // the recursive estimate of a new configuration starts from zero, as the host's
        // replay does (a warm start from the previous configuration's solution would make
        // the first solves depend on what ran before)
        self.solver.fill(T::ZERO);
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
        // the window's snapshot lives after the sums
        st.gram_mut().storage_parts().2.fill(T::ZERO);
        if let Some(w) = self.window.as_mut() {
            w.clear();
        }
        st.break_window();
        self.next_sample = 0;
        self.duplicate_samples = 0;
        self.solved = None;
        self.solver.fill(T::ZERO);
        self.est = EstimateRecord::new();
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
            let accumulated = match st.update(u, y, p) {
                Ok(a) => a,
                Err(_) => {
                    return err(
                        ErrorCode::SampleRejected,
                        (first as usize).saturating_add(i),
                    )
                }
            };
            if accumulated {
                if let Some(w) = self.window.as_mut() {
                    if w.added() {
                        // the spare storage was sized at the configuration: cannot fail
                        let _ = rebase_gram(st.gram_mut(), None, w.half());
                    }
                }
                if let Some(sum) = &self.solved {
                    let cols = sum.columns as usize;
                    self.est
                        .one_step
                        .add(st.last_vector(), &self.solver, cols, d.l);
                }
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
            if let Some(t) = self.track {
                self.est.since_solve = self.est.since_solve.saturating_add(1);
                if t.every > 0 && self.est.since_solve >= t.every {
                    self.est.since_solve = 0;
                    match solve_statistics(st.gram(), &d, &t.solve, &mut self.solver, true) {
                        Ok(sum) => {
                            self.solved = Some(sum);
                            self.est.summary = Some(sum);
                            self.est.solves = self.est.solves.wrapping_add(1);
                            self.est.at_sample = self.next_sample;
                            self.est.clear_predictions();
                        }
                        Err(_) => self.est.failures = self.est.failures.wrapping_add(1),
                    }
                }
            }
        }
        Cached::Status(self.status())
    }

    fn solve(&mut self, req: SolveRequest) -> Cached {
        self.solved = None;
        let Some(st) = self.stats.get() else {
            return err(ErrorCode::NotConfigured, 0);
        };
        match solve_statistics(st.gram(), &st.dims(), &req, &mut self.solver, false) {
            Ok(s) => {
                self.solved = Some(s);
                self.est.clear_predictions();
                Cached::Solved(s)
            }
            Err(e) => Cached::Error(e),
        }
    }

    fn set_track(&mut self, t: Track) -> Cached {
        let Some(st) = self.stats.get() else {
            return err(ErrorCode::NotConfigured, 0);
        };
        let d = st.dims();
        let Ok(q) = d.q() else {
            return err(ErrorCode::BadConfig, 0);
        };
        let need = solver_len(d.l, q + d.r, true);
        if need > X {
            return err(ErrorCode::Capacity, need);
        }
        let ratio = t.solve.lambda_ratio;
        if !(ratio.is_finite() && ratio >= 0.0) {
            return err(ErrorCode::BadConfig, 0);
        }
        self.track = if t.every == 0 { None } else { Some(t) };
        self.est.since_solve = 0;
        Cached::Ack
    }

    fn estimate<S: FnMut(&[u8])>(&mut self, seq: u32, send: &mut S) {
        let msg = match &self.config {
            None => Message::Error(ErrorReply {
                code: ErrorCode::NotConfigured,
                detail: 0,
            }),
            Some(c) => {
                let l = c.l as usize;
                if 2 * l * T::BYTES > F {
                    Message::Error(ErrorReply {
                        code: ErrorCode::Capacity,
                        detail: 0,
                    })
                } else {
                    let rec = &self.est.interval;
                    let a =
                        write_values(&rec.sse[..l], &mut self.vals[..l * T::BYTES]).unwrap_or(0);
                    // the newest error: of the solution in force, or of the interval's
                    let last = if self.est.one_step.count > 0 {
                        &self.est.one_step.last
                    } else {
                        &rec.last
                    };
                    let b = write_values(&last[..l], &mut self.vals[a..]).unwrap_or(0);
                    Message::Estimate(Estimate {
                        solves: self.est.solves,
                        failures: self.est.failures,
                        at_sample: self.est.at_sample,
                        summary: self.est.summary.unwrap_or(EMPTY_SUMMARY),
                        count: rec.count,
                        sse: &self.vals[..a],
                        last_error: &self.vals[a..a + b],
                    })
                }
            }
        };
        emit(&mut self.raw, &mut self.tx, seq, &msg, send);
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

/// The summary a [`Message::Estimate`] carries before the first solve.
const EMPTY_SUMMARY: SolveSummary = SolveSummary {
    columns: 0,
    outputs: 0,
    lambda: 0.0,
    lambda_max: 0.0,
    iterations: 0,
    converged: false,
    active: 0,
    kkt: 0.0,
    objective: 0.0,
};

/// How a device with `g` Gram values sums a statistic vector of length `len`: compensated
/// without a window (two packed triangles); with a window (its snapshot is one more
/// triangle, [`crate::sliding::rebase_gram`]) compensated if three triangles fit, plain if
/// two do; `None` if it does not fit. The host's bit-for-bit check follows the same rule.
pub fn device_summation(len: usize, window: bool, g: usize) -> Option<Summation> {
    if !window {
        return (crate::stats::gram_storage_len(len) <= g).then_some(Summation::Compensated);
    }
    if inline_window_len(len, true) <= g {
        Some(Summation::Compensated)
    } else if inline_window_len(len, false) <= g {
        Some(Summation::Plain)
    } else {
        None
    }
}

/// Solver values a solve of problem (13) with `columns` = q + r regressors and `l`
/// outputs needs: (3 l + 2) columns from a cold start, (4 l + 2) columns warm-started (the
/// previous solution is kept, to restore it if the solve fails).
pub const fn solver_len(l: usize, columns: usize, warm: bool) -> usize {
    (if warm { 4 * l + 2 } else { 3 * l + 2 }) * columns
}

/// Solve problem (13), y_{k+p} on [z_k^p; u_{k+p}], from the leading block of `gram` with
/// the core's coordinate-descent Lasso (sparse paper problem (33); `req.lambda_ratio` 0 is
/// the least-squares PBSID/VARX regression). The device engine and the host's check call
/// this one function, so both compute the same bits.
///
/// `solver` ([`solver_len`] values) is [Theta (l x (q + r)) | C | weights | CD work |
/// previous Theta (warm only)]. `warm`: start from the Theta in `solver` (a recursive
/// estimate) and leave it unchanged on failure; cold: start from zeros. Standardising
/// weights are sqrt(G_jj / N) with N the effective count ([`Gram::weight`]: with forgetting,
/// sum of lambda^age).
pub fn solve_statistics<T: Real, S: AsRef<[T]> + AsMut<[T]>>(
    gram: &Gram<T, S>,
    dims: &PbsidDims,
    req: &SolveRequest,
    solver: &mut [T],
    warm: bool,
) -> Result<SolveSummary, ErrorReply> {
    let fail = |code: ErrorCode, detail: usize| ErrorReply {
        code,
        detail: u32::try_from(detail).unwrap_or(u32::MAX),
    };
    let q = dims.q().map_err(|_| fail(ErrorCode::BadConfig, 0))?;
    let (qc, l) = (q + dims.r, dims.l);
    let need = solver_len(l, qc, warm);
    if need > solver.len() {
        return Err(fail(ErrorCode::Capacity, need));
    }
    let ratio = req.lambda_ratio;
    if !(ratio.is_finite() && ratio >= 0.0) {
        return Err(fail(ErrorCode::BadConfig, 0));
    }
    if gram.count() == 0 {
        return Err(fail(ErrorCode::SolveFailed, 0));
    }
    let (theta, rest) = solver[..need].split_at_mut(l * qc);
    let (cross, rest) = rest.split_at_mut(l * qc);
    let (weights, rest) = rest.split_at_mut(qc);
    let (work, previous) = rest.split_at_mut((l + 1) * qc);
    let nwin = T::of(gram.weight());
    for (j, w) in weights.iter_mut().enumerate() {
        let g = gram.get(j, j);
        *w = if req.standardise && g > T::ZERO {
            (g / nwin).sqrt()
        } else {
            T::ONE
        };
    }
    if warm {
        previous.copy_from_slice(theta);
    } else {
        theta.fill(T::ZERO);
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
        if warm {
            // lambda_max leaves its own point in theta: start from the last solution
            theta.copy_from_slice(previous);
        }
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
    res.map_err(|e| {
        if warm {
            theta.copy_from_slice(previous);
        }
        fail(
            ErrorCode::SolveFailed,
            match e {
                Error::Singular => 1,
                Error::NoConvergence => 2,
                Error::Overflow => 3,
                _ => 4,
            },
        )
    })
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
    /// Solver values: (4 l + 2)(q + r) with l = 1, q + r = 61 (a warm-started solve of the
    /// recursive estimate keeps the previous solution: [`super::solver_len`]).
    pub const X: usize = super::solver_len(1, 61, true);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{decode_frame, encode_frame_version, Packet};
    use crate::stats::PbsidStats;
    use std::boxed::Box;
    use std::vec;
    use std::vec::Vec;

    type Dev = DefaultDevice<f32>;

    /// Send `msg` (framed in `version`) and return the raw reply frames (COBS-decoded, the
    /// delimiter removed).
    fn exchange(dev: &mut Dev, version: u8, seq: u32, msg: &Message<'_>) -> Vec<Vec<u8>> {
        let mut raw = vec![0u8; 600];
        let mut out = vec![0u8; 700];
        let n = encode_frame_version(version, seq, msg, &mut raw, &mut out).unwrap();
        let mut replies = Vec::new();
        dev.handle(&out[..n], |f| replies.push(f[..f.len() - 1].to_vec()));
        replies
    }

    /// Send a v2 request and decode its one reply with `f`.
    fn ask<R>(dev: &mut Dev, seq: u32, msg: &Message<'_>, f: impl FnOnce(Packet<'_>) -> R) -> R {
        let mut r = exchange(dev, VERSION, seq, msg);
        assert_eq!(r.len(), 1);
        f(decode_frame(&mut r[0]).unwrap())
    }

    /// A noise-free LPV-ARX plant: y_k = (0.5 + 0.3 p_{k-1}) y_{k-1} + u_{k-1} - 0.2 u_{k-2},
    /// p drifting slowly; samples [u, y, p].
    fn plant(n: usize) -> Vec<[f32; 3]> {
        let mut s = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let (mut y1, mut u1, mut u2, mut p1) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        (0..n)
            .map(|k| {
                let u = 2.0 * rnd();
                let p = (k as f64 * 0.003).sin();
                let y = (0.5 + 0.3 * p1) * y1 + u1 - 0.2 * u2;
                (y1, u2, u1, p1) = (y, u1, u, p);
                [u as f32, y as f32, p as f32]
            })
            .collect()
    }

    fn stream(dev: &mut Dev, seq: &mut u32, rows: &[[f32; 3]], first: usize) {
        for (c, chunk) in rows.chunks(20).enumerate() {
            let flat: Vec<f32> = chunk.iter().flatten().copied().collect();
            let mut b = vec![0u8; flat.len() * 4];
            write_values(&flat, &mut b).unwrap();
            *seq += 1;
            let msg = Message::Samples {
                first: (first + 20 * c) as u32,
                values: &b,
            };
            ask(dev, *seq, &msg, |p| {
                assert!(matches!(p.msg, Message::Status(_)), "{p:?}")
            });
        }
    }

    fn configure(dev: &mut Dev, seq: &mut u32, forgetting: f32, window: u32) {
        *seq += 1;
        let cfg = Config {
            r: 1,
            l: 1,
            s: 1,
            p: 2,
            layout: Layout::Extended,
            forgetting,
            window,
        };
        ask(dev, *seq, &Message::Configure(cfg), |p| {
            assert_eq!(p.msg, Message::Ack)
        });
    }

    /// Host statistics over the same storage as the device's (so the same summation).
    fn host(lambda: f32, window: bool) -> PbsidStats<f32, Vec<f32>, Vec<f32>, Vec<f32>> {
        let dims = PbsidDims::new(1, 1, 1, 2).unwrap();
        let len = stat_vector_len(&dims, StatsLayout::Extended).unwrap();
        let mut st = PbsidStats::with_storage(
            dims,
            StatsLayout::Extended,
            vec![0.0; window_storage_len(1, 1, 1, 2)],
            vec![0.0; sizes::G],
            vec![0.0; len],
        )
        .unwrap();
        let sum = device_summation(len, window, sizes::G).unwrap();
        let g = Gram::with_summation(len, vec![0.0; sizes::G], sum).unwrap();
        *st.gram_mut() = g;
        st.set_forgetting(lambda).unwrap();
        st
    }

    /// A version-1 host's Hello: the v2 device answers with a NAK framed as version 1 (so
    /// the old host can read it) naming version 2; the engine's state is untouched.
    #[test]
    fn an_older_host_gets_a_nak_it_can_read() {
        let mut dev = Box::new(Dev::new());
        let mut r = exchange(&mut dev, 1, 3, &Message::Hello { version: 1 });
        assert_eq!(r.len(), 1);
        let n = crate::protocol::cobs_decode_in_place(&mut r[0]).unwrap();
        // version 1, seq 0, Error (index 14), WrongVersion (4), detail = 2
        assert_eq!(&r[0][..n - 4], &[1, 0, 14, 4, 2]);
        assert_eq!(
            crate::protocol::crc32(&r[0][..n - 4]).to_le_bytes(),
            r[0][n - 4..n]
        );
        // a newer host (v3): NAK in our framing, detail 2
        let mut r = exchange(&mut dev, 3, 4, &Message::Hello { version: 3 });
        let p = decode_frame(&mut r[0]).unwrap();
        assert_eq!(
            p.msg,
            Message::Error(ErrorReply {
                code: ErrorCode::WrongVersion,
                detail: 2
            })
        );
        assert_eq!(dev.status().frames_rejected, 2);
        assert!(!dev.status().configured);
    }

    /// Forgetting and the sliding window on the device equal the core's statistics on the
    /// host bit for bit (same storage, same summation).
    #[test]
    fn forgetting_and_window_equal_the_core_bit_for_bit() {
        let rows = plant(1500);
        for (lambda, window) in [(0.99f32, 0u32), (1.0, 300), (1.0, 0)] {
            let mut dev = Box::new(Dev::new());
            let mut seq = 1;
            configure(&mut dev, &mut seq, lambda, window);
            stream(&mut dev, &mut seq, &rows, 0);
            let mut h = host(lambda, window > 0);
            let mut win = (window > 0).then(|| HalfWindow::new(window as u64).unwrap());
            for r in &rows {
                if h.update(&r[..1], &r[1..2], &r[2..]).unwrap() {
                    if let Some(w) = win.as_mut() {
                        if w.added() {
                            rebase_gram(h.gram_mut(), None, w.half()).unwrap();
                        }
                    }
                }
            }
            let d = dev.stats().unwrap().gram();
            assert_eq!(
                d.packed(),
                h.gram().packed(),
                "lambda {lambda} window {window}"
            );
            assert_eq!(d.count(), h.gram().count());
            let st = dev.status();
            assert_eq!((st.forgetting, st.window), (lambda, window));
            if window > 0 {
                // 1498 vectors: the newest half (150) and 1498 mod 150 = 148 more
                assert_eq!(d.count(), 298);
                assert_eq!(d.summation(), Summation::Compensated);
            }
            if lambda < 1.0 {
                let w = (1.0 - 0.99f64.powi(1498)) / 0.01;
                assert!(
                    (st.weight as f64 - w).abs() < 1e-3 * w,
                    "{} vs {w}",
                    st.weight
                );
            }
        }
    }

    /// The recursive estimate: solves every K samples warm-started, and its parameters and
    /// one-step errors equal a replay on the host with the same core functions, bit for
    /// bit; on a noise-free plant in the model class the one-step error is round-off.
    #[test]
    fn tracking_equals_a_host_replay_and_predicts() {
        let rows = plant(1200);
        let every = 100u32;
        let req = SolveRequest {
            lambda_ratio: 0.0,
            group: false,
            standardise: true,
        };
        let mut dev = Box::new(Dev::new());
        let mut seq = 1;
        configure(&mut dev, &mut seq, 0.995, 0);
        seq += 1;
        ask(
            &mut dev,
            seq,
            &Message::Track(Track { every, solve: req }),
            |p| assert_eq!(p.msg, Message::Ack),
        );
        stream(&mut dev, &mut seq, &rows, 0);
        // the host replay: same statistics, a warm solve after every K-th sample
        let mut h = host(0.995, false);
        let dims = h.dims();
        let cols = dims.q().unwrap() + 1;
        let mut solver = vec![0.0f32; sizes::X];
        let mut rec = OneStep::<f32>::new();
        let mut interval = OneStep::<f32>::new();
        // every one-step error after the first solve, each with the solution then in force
        let mut all = OneStep::<f32>::new();
        let mut solved = false;
        let mut solves = 0;
        for (k, r) in rows.iter().enumerate() {
            if h.update(&r[..1], &r[1..2], &r[2..]).unwrap() && solved {
                rec.add(h.last_vector(), &solver, cols, 1);
                all.add(h.last_vector(), &solver, cols, 1);
            }
            if (k + 1) % every as usize == 0
                && solve_statistics(h.gram(), &dims, &req, &mut solver, true).is_ok()
            {
                solved = true;
                solves += 1;
                interval = rec;
                rec = OneStep::new();
            }
        }
        let est = ask(&mut dev, seq + 1, &Message::GetEstimate, |p| match p.msg {
            Message::Estimate(e) => (
                e.solves,
                e.failures,
                e.at_sample,
                e.count,
                read_value::<f32>(e.sse, 0),
                read_value::<f32>(e.last_error, 0),
            ),
            m => panic!("{m:?}"),
        });
        // the interval between the last two solves (samples 1100..1200), the newest error
        assert_eq!(
            est,
            (
                solves,
                0,
                1200,
                interval.count,
                interval.sse[0],
                interval.last[0]
            )
        );
        assert_eq!(interval.count, 100);
        assert_eq!(solves, 12);
        assert_eq!(&dev.eng.solver[..cols], &solver[..cols]);
        // the one-step errors against the output's power: the plant is in the model class
        // and noise-free, so what is left is f32 round-off of the statistics and solve
        let power: f32 = rows[100..].iter().map(|r| r[1] * r[1]).sum::<f32>() / 1100.0;
        assert_eq!(all.count, 1100);
        let mse = all.sse[0] / all.count as f32;
        std::println!("one-step mse {mse:e}, output power {power}");
        assert!(
            mse < 1e-5 * power,
            "one-step mse {mse:e}, output power {power}"
        );
    }
    /// A new configuration or a reset starts the recursive estimate from zero, as the
    /// host's replay does: `make device-test` found the first solves of a second `watch`
    /// warm-started from the previous configuration's solution (1.3e-2 off the replay).
    #[test]
    fn reconfiguring_restarts_the_estimate_from_zero() {
        let rows = plant(300);
        let req = SolveRequest {
            lambda_ratio: 0.0,
            group: false,
            standardise: true,
        };
        let mut dev = Box::new(Dev::new());
        let mut seq = 1;
        for again in [false, true] {
            configure(&mut dev, &mut seq, 1.0, 0);
            assert!(dev.eng.solver.iter().all(|v| *v == 0.0));
            seq += 1;
            stream(&mut dev, &mut seq, &rows, 0);
            seq += 1;
            ask(&mut dev, seq, &Message::Solve(req), |p| {
                assert!(matches!(p.msg, Message::Solved(_)), "{:?}", p.msg)
            });
            assert!(dev.eng.solver.iter().any(|v| *v != 0.0));
            if again {
                seq += 1;
                ask(&mut dev, seq, &Message::Reset, |p| {
                    assert_eq!(p.msg, Message::Ack)
                });
                assert!(dev.eng.solver.iter().all(|v| *v == 0.0));
            }
            seq += 1;
        }
    }
}
