//! The device link (DESIGN.md section 4): the host end of the wire protocol of
//! [`lpvid::protocol`] (written down in `docs/wire.md`) over a serial port (or anything
//! `Read + Write`). The `lpvid device` command is in the command line (`cli::device`).
//!
//! [`Link`] is stop-and-wait: one request in flight, a fresh `seq` per request, the same
//! `seq` for its retransmissions. A request is retransmitted when no valid reply arrives
//! within the timeout, when a frame fails to decode (a reply corrupted on the way), and
//! when the device NAKs the request (an unsolicited error with seq 0: the device could not
//! decode it). Replies with another `seq` (late duplicates of earlier replies) are dropped.
//! The device answers retransmissions of state-changing requests from a cache and applies
//! samples by stream index, so a retry never double-counts. Every frame the host sends is
//! led by a 0x00 so a partial frame left on the line by a fault cannot swallow it.
//!
//! The statistics pulled from a device are turned into a model by
//! [`crate::pipeline::identify_from_stats`], the same code as a fit from statistics
//! accumulated on the host; [`compare::compare_with_file`] checks both against a file fit.

pub mod compare;
pub mod watch;

pub use compare::{
    compare_as_device, compare_with_file, extended_gram, fit_pulled, gram_difference, host_stats,
    host_stats_as_device, model_difference, replay_tracking, sample_rows, CompareError, Comparison,
    HostStats, ReplayPoint,
};

use std::io::{self, Read, Write};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use lpvid::device::Device;
use lpvid::protocol::{
    encode_frame, max_raw, Config, Deframer, ErrorCode, ErrorReply, Event, Info, Layout, Message,
    ModelChunk, Rejected, SolveRequest, SolveSummary, Status, Track, VersionMismatch, WireReal,
    MESSAGE_HEADROOM, VERSION,
};
use lpvid::{PbsidDims, StatsLayout};

use crate::lpvss::LpvSs;

/// Receive buffer of the host's deframer (frames are at most a device's `max_frame`).
const HOST_FRAME_BUF: usize = 8192;

/// Retransmissions of a multi-sample frame (or multi-value pull) before it is halved.
const SHRINK_AFTER: u32 = 4;

/// Clean exchanges before a shrunk frame size doubles again.
const GROW_AFTER: u32 = 8;

/// Everything that can go wrong on the link.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The port failed.
    #[error("serial port: {0}")]
    Io(#[from] io::Error),
    /// No valid reply within the retries.
    #[error("no valid reply from the device after {attempts} attempts (last problem: {last})")]
    NoReply {
        /// Transmissions made.
        attempts: u32,
        /// What went wrong on the last one.
        last: String,
    },
    /// The device rejected the request.
    #[error("device rejected the request: {code} (detail {detail})")]
    Device {
        /// Reason.
        code: ErrorCode,
        /// Qualifier.
        detail: u32,
    },
    /// An unexpected reply or state.
    #[error("protocol: {0}")]
    Protocol(String),
    /// The model to push has matrices whose shapes disagree.
    #[error("model: {0}")]
    Shape(#[from] crate::lpvss::ShapeError),
    /// The device speaks another protocol version (its frames carry another version byte,
    /// or it NAKed ours naming its version).
    #[error("{0} (the device and the host must speak the same protocol version)")]
    Version(VersionMismatch),
}

/// Counters of a link's life: what the faults cost.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LinkStats {
    /// Requests completed.
    pub requests: u64,
    /// Retransmissions (any cause).
    pub retries: u64,
    /// Attempts that timed out.
    pub timeouts: u64,
    /// Received frames that failed to decode (CRC, COBS, ...).
    pub bad_frames: u64,
    /// NAKs from the device (it could not decode what we sent).
    pub naks: u64,
    /// Valid replies to an earlier request, dropped.
    pub stale: u64,
    /// Bytes written.
    pub bytes_sent: u64,
    /// Bytes read.
    pub bytes_received: u64,
}

/// A reply, owned (values converted to f64).
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// Handshake.
    Info(Info),
    /// Request applied.
    Ack,
    /// Device state.
    Status(Status),
    /// A chunk of values.
    Values {
        /// First index.
        offset: u32,
        /// Whole length.
        total: u32,
        /// The values.
        values: Vec<f64>,
    },
    /// Solve summary.
    Solved(SolveSummary),
    /// Rejection.
    Error(ErrorReply),
    /// Predictor record.
    Prediction {
        /// Samples predicted.
        count: u32,
        /// Sum of squared errors per output.
        sse: Vec<f64>,
        /// Last prediction per output.
        last: Vec<f64>,
    },
    /// The recursive estimate's record (protocol 2).
    Estimate(EstimateReply),
    /// A request-type message (a device never sends one).
    Other,
}

/// The recursive estimate's record ([`lpvid::protocol::Estimate`]), values as f64.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct EstimateReply {
    /// Successful tracking solves.
    pub solves: u32,
    /// Failed tracking solves.
    pub failures: u32,
    /// Stream index of the next sample when the last solve ran.
    pub at_sample: u32,
    /// The last solve's summary.
    pub summary: SolveSummary,
    /// One-step predictions of the previous solution over its interval.
    pub count: u32,
    /// Their sum of squared errors per output.
    pub sse: Vec<f64>,
    /// The newest one-step error per output.
    pub last_error: Vec<f64>,
}

/// How the device accumulates (protocol 2): exponential forgetting or a sliding window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Accumulation {
    /// Forgetting factor in (0, 1] (1: plain sums).
    pub forgetting: f32,
    /// Sliding window in statistic vectors (0: none).
    pub window: u32,
}

impl Default for Accumulation {
    fn default() -> Self {
        Accumulation {
            forgetting: 1.0,
            window: 0,
        }
    }
}

/// Little-endian floats of `float_bytes` (4 or 8) each, as f64.
pub fn values_to_f64(bytes: &[u8], float_bytes: u8) -> Result<Vec<f64>, LinkError> {
    let w = float_bytes as usize;
    if (w != 4 && w != 8) || bytes.len() % w != 0 {
        return Err(LinkError::Protocol(format!(
            "{} value bytes are not a whole number of {w}-byte floats",
            bytes.len()
        )));
    }
    Ok(bytes
        .chunks_exact(w)
        .map(|c| {
            if w == 4 {
                f32::read_le(c) as f64
            } else {
                f64::read_le(c)
            }
        })
        .collect())
}

/// f64 values as little-endian floats of `float_bytes` (4: rounded to f32).
pub fn f64_to_values(vals: &[f64], float_bytes: u8, out: &mut Vec<u8>) {
    out.clear();
    for &v in vals {
        if float_bytes == 4 {
            out.extend_from_slice(&(v as f32).to_le_bytes());
        } else {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// A model's values in the wire layout `[A | B | K | C | D]` of [`lpvid::model`] (the one
/// layout the device engine reads back).
pub fn model_values(model: &LpvSs) -> Result<Vec<f64>, LinkError> {
    let sched = model.c.len() > 1 || model.d.len() > 1;
    let dims = lpvid::model::ModelDims::new(model.n(), model.r(), model.l(), model.m(), sched)
        .map_err(|e| LinkError::Protocol(format!("model: {e}")))?;
    let len = dims
        .values_len()
        .map_err(|e| LinkError::Protocol(format!("model: {e}")))?;
    // row-major data of each matrix (nalgebra stores column-major)
    let rows = |mats: &[nalgebra::DMatrix<f64>]| -> Vec<Vec<f64>> {
        mats.iter()
            .map(|m| m.transpose().as_slice().to_vec())
            .collect()
    };
    let (a, b, k, c, d) = (
        rows(&model.a),
        rows(&model.b),
        rows(&model.k),
        rows(&model.c),
        rows(&model.d),
    );
    let mut vals = vec![0.0; len];
    dims.pack(
        &mut vals,
        &slices(&a),
        &slices(&b),
        &slices(&k),
        &slices(&c),
        &slices(&d),
    )
    .map_err(|e| LinkError::Protocol(format!("model: {e}")))?;
    Ok(vals)
}

/// Borrowed slices of owned rows.
fn slices(v: &[Vec<f64>]) -> Vec<&[f64]> {
    v.iter().map(Vec::as_slice).collect()
}

/// The size of the next frame's payload (samples streamed, values pulled) on a line that
/// may be noisy: halved when a multi-item frame is not acknowledged within
/// [`SHRINK_AFTER`] retransmissions (a single item gets the full budget), doubled back
/// toward `max` after [`GROW_AFTER`] clean exchanges.
#[derive(Debug, Clone, Copy)]
struct Adaptive {
    size: usize,
    max: usize,
    clean: u32,
}

impl Adaptive {
    fn new(max: usize) -> Adaptive {
        Adaptive {
            size: max,
            max,
            clean: 0,
        }
    }

    /// Retransmissions allowed for the next frame.
    fn retries(&self, budget: u32) -> u32 {
        if self.size > 1 {
            SHRINK_AFTER.min(budget)
        } else {
            budget
        }
    }

    /// After a frame went unanswered: halve, if there is anything to halve.
    fn shrink(&mut self) -> bool {
        if self.size <= 1 {
            return false;
        }
        self.size = (self.size / 2).max(1);
        self.clean = 0;
        true
    }

    /// After an acknowledged frame (`clean`: without retransmissions).
    fn exchanged(&mut self, clean: bool) {
        if !clean {
            self.clean = 0;
            return;
        }
        self.clean += 1;
        if self.clean >= GROW_AFTER && self.size < self.max {
            self.size = (self.size * 2).min(self.max);
            self.clean = 0;
        }
    }
}

/// A received frame: (seq, reply), or why it was rejected.
type Frame = Result<(u32, Reply), Rejected>;

/// Settings of a [`Link`].
#[derive(Debug, Clone, Copy)]
pub struct LinkOptions {
    /// Wait for a reply this long before retransmitting.
    pub timeout: Duration,
    /// Wait this long for the first reply of a session, on its first transmission only (a
    /// QEMU pseudo-terminal can hold the first bytes for about a second); retransmissions
    /// wait `timeout`.
    pub first_timeout: Duration,
    /// Retransmissions per request before giving up.
    pub retries: u32,
    /// Largest number of samples per frame (0: as many as fit the device's frame).
    pub batch: usize,
}

impl Default for LinkOptions {
    fn default() -> Self {
        LinkOptions {
            timeout: Duration::from_millis(500),
            first_timeout: Duration::from_millis(3000),
            retries: 25,
            batch: 0,
        }
    }
}

/// The host end of the protocol over `P` (a serial port whose reads time out after a short
/// poll interval, so the link can keep its own deadlines).
pub struct Link<P> {
    port: P,
    opts: LinkOptions,
    seq: u32,
    info: Option<Info>,
    deframer: Box<Deframer<HOST_FRAME_BUF>>,
    inbuf: Vec<u8>,
    in_pos: usize,
    raw: Vec<u8>,
    out: Vec<u8>,
    vals: Vec<u8>,
    stats: LinkStats,
    answered: bool,
}

/// Open a serial device (a real UART or a pseudo-terminal) for a [`Link`].
pub fn open_port(path: &Path) -> Result<serialport::TTYPort, LinkError> {
    let name = path.display().to_string();
    serialport::new(&name, 115_200)
        .timeout(Duration::from_millis(10))
        .open_native()
        .map_err(|e| LinkError::Io(io::Error::other(format!("cannot open {name}: {e}"))))
}

impl<P: Read + Write> Link<P> {
    /// A link over `port`.
    pub fn new(port: P, opts: LinkOptions) -> Self {
        // a session-unique starting seq: a device remembers the last seq it saw
        let seed = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos() ^ (d.as_secs() as u32))
            .unwrap_or(1)
            ^ std::process::id().rotate_left(16);
        Link {
            port,
            opts,
            seq: seed | 1,
            info: None,
            deframer: Box::new(Deframer::new()),
            inbuf: vec![0; 4096],
            in_pos: 0,
            raw: vec![0; HOST_FRAME_BUF],
            out: vec![0; HOST_FRAME_BUF + 1],
            vals: Vec::new(),
            stats: LinkStats::default(),
            answered: false,
        }
    }

    /// The counters.
    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// The device's handshake, once [`Link::hello`] has run.
    pub fn info(&self) -> Option<Info> {
        self.info
    }

    /// The port.
    pub fn port_mut(&mut self) -> &mut P {
        &mut self.port
    }

    fn float_bytes(&self) -> u8 {
        self.info.map(|i| i.float_bytes).unwrap_or(4)
    }

    /// Read until one frame is complete or `deadline` passes. `Ok(None)`: timeout.
    fn next_frame(&mut self, deadline: Instant) -> Result<Option<Frame>, LinkError> {
        let fb = self.float_bytes();
        loop {
            while self.in_pos < self.inbuf.len() {
                let b = self.inbuf[self.in_pos];
                self.in_pos += 1;
                match self.deframer.push(b) {
                    Event::Pending => {}
                    Event::Oversize => return Ok(Some(Err(Rejected::Frame(ErrorCode::Oversize)))),
                    Event::Frame(buf) => {
                        return Ok(Some(match lpvid::protocol::decode_frame_checked(buf) {
                            Err(r) => Err(r),
                            Ok(pkt) => match owned(&pkt.msg, fb) {
                                Ok(r) => Ok((pkt.seq, r)),
                                Err(_) => Err(Rejected::Frame(ErrorCode::Malformed)),
                            },
                        }))
                    }
                }
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            self.inbuf.resize(4096, 0);
            match self.port.read(&mut self.inbuf) {
                Ok(0) => {
                    self.inbuf.clear();
                    self.in_pos = 0;
                    std::thread::sleep(Duration::from_millis(1));
                }
                Ok(n) => {
                    self.inbuf.truncate(n);
                    self.in_pos = 0;
                    self.stats.bytes_received += n as u64;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut
                            | io::ErrorKind::WouldBlock
                            | io::ErrorKind::Interrupted
                    ) =>
                {
                    self.inbuf.clear();
                    self.in_pos = 0;
                }
                Err(e) => return Err(LinkError::Io(e)),
            }
        }
    }

    /// Send `msg` and wait for its reply, retransmitting as described in the module docs.
    /// A device [`Reply::Error`] is returned as `Err(LinkError::Device)`.
    pub fn request(&mut self, msg: &Message<'_>) -> Result<Reply, LinkError> {
        self.request_n(msg, self.opts.retries)
    }

    /// [`Link::request`] with at most `retries` retransmissions.
    fn request_n(&mut self, msg: &Message<'_>, retries: u32) -> Result<Reply, LinkError> {
        self.seq = self.seq.wrapping_add(1);
        if self.seq == 0 {
            self.seq = 1;
        }
        let seq = self.seq;
        self.out[0] = 0;
        let n = encode_frame(seq, msg, &mut self.raw, &mut self.out[1..])
            .map_err(|_| LinkError::Protocol("request too large for a frame".into()))?;
        let frame = self.out[..n + 1].to_vec();
        let mut last = String::from("none");
        let attempts = retries + 1;
        for attempt in 0..attempts {
            if attempt > 0 {
                self.stats.retries += 1;
            }
            self.port.write_all(&frame)?;
            self.port.flush()?;
            self.stats.bytes_sent += frame.len() as u64;
            // the longer first wait is for the first transmission of a session only: a silent
            // port costs first_timeout + retries x timeout, not (retries + 1) x first_timeout
            let wait = if self.answered || attempt > 0 {
                self.opts.timeout
            } else {
                self.opts.first_timeout
            };
            let deadline = Instant::now() + wait;
            loop {
                match self.next_frame(deadline)? {
                    None => {
                        self.stats.timeouts += 1;
                        last = format!("timeout after {} ms", wait.as_millis());
                        break;
                    }
                    Some(Err(Rejected::Version(v))) => {
                        // a valid frame of another version: no retransmission will help
                        self.answered = true;
                        return Err(LinkError::Version(v));
                    }
                    Some(Err(Rejected::Frame(code))) => {
                        self.stats.bad_frames += 1;
                        last = format!("reply frame rejected: {code}");
                        break;
                    }
                    Some(Ok((s, reply))) if s == seq => {
                        self.answered = true;
                        self.stats.requests += 1;
                        return match reply {
                            Reply::Error(e) => Err(LinkError::Device {
                                code: e.code,
                                detail: e.detail,
                            }),
                            r => Ok(r),
                        };
                    }
                    Some(Ok((0, Reply::Error(e)))) => {
                        self.answered = true;
                        if e.code == ErrorCode::WrongVersion {
                            return Err(LinkError::Version(VersionMismatch {
                                ours: VERSION,
                                theirs: u8::try_from(e.detail).unwrap_or(u8::MAX),
                            }));
                        }
                        self.stats.naks += 1;
                        last = format!("device NAK: {}", e.code);
                        break;
                    }
                    Some(Ok(_)) => {
                        self.stats.stale += 1;
                    }
                }
            }
        }
        Err(LinkError::NoReply { attempts, last })
    }

    /// Handshake: the device's version, float type and capacities.
    pub fn hello(&mut self) -> Result<Info, LinkError> {
        match self.request(&Message::Hello { version: VERSION })? {
            Reply::Info(i) => {
                if i.version != VERSION {
                    return Err(LinkError::Version(VersionMismatch {
                        ours: VERSION,
                        theirs: i.version,
                    }));
                }
                if i.float_bytes != 4 && i.float_bytes != 8 {
                    return Err(LinkError::Protocol(format!(
                        "unknown float width {}",
                        i.float_bytes
                    )));
                }
                self.info = Some(i);
                Ok(i)
            }
            r => Err(unexpected("Info", &r)),
        }
    }

    fn ensure_hello(&mut self) -> Result<Info, LinkError> {
        match self.info {
            Some(i) => Ok(i),
            None => self.hello(),
        }
    }

    /// The device's state.
    pub fn status(&mut self) -> Result<Status, LinkError> {
        match self.request(&Message::GetStatus)? {
            Reply::Status(s) => Ok(s),
            r => Err(unexpected("Status", &r)),
        }
    }

    /// Configure dimensions and layout (clears the device's statistics), plain sums.
    pub fn configure(&mut self, dims: &PbsidDims, layout: StatsLayout) -> Result<(), LinkError> {
        self.configure_with(dims, layout, Accumulation::default())
    }

    /// Configure dimensions, layout, forgetting and window (clears the statistics).
    pub fn configure_with(
        &mut self,
        dims: &PbsidDims,
        layout: StatsLayout,
        acc: Accumulation,
    ) -> Result<(), LinkError> {
        let b = |v: usize, what: &str| {
            u8::try_from(v).map_err(|_| LinkError::Protocol(format!("{what} = {v} is too large")))
        };
        let cfg = Config {
            r: b(dims.r, "r")?,
            l: b(dims.l, "l")?,
            s: b(dims.s, "s")?,
            p: b(dims.p, "p")?,
            layout: lpvid::device::wire_layout(layout),
            forgetting: acc.forgetting,
            window: acc.window,
        };
        match self.request(&Message::Configure(cfg))? {
            Reply::Ack => Ok(()),
            r => Err(unexpected("Ack", &r)),
        }
    }

    /// Start (every > 0), change or stop (every = 0) the recursive estimate.
    pub fn track(&mut self, t: Track) -> Result<(), LinkError> {
        match self.request(&Message::Track(t))? {
            Reply::Ack => Ok(()),
            r => Err(unexpected("Ack", &r)),
        }
    }

    /// The recursive estimate's record.
    pub fn estimate(&mut self) -> Result<EstimateReply, LinkError> {
        match self.request(&Message::GetEstimate)? {
            Reply::Estimate(e) => Ok(e),
            r => Err(unexpected("Estimate", &r)),
        }
    }

    /// The coefficients of the last solve (l x (q + r) values, `columns` x `outputs` as the
    /// solve summary says).
    pub fn solution(&mut self, columns: u32, outputs: u8) -> Result<Vec<f64>, LinkError> {
        self.pull_values(true, columns as usize * outputs as usize)
    }

    /// Clear the device's statistics and sample index.
    pub fn reset(&mut self) -> Result<(), LinkError> {
        match self.request(&Message::Reset)? {
            Reply::Ack => Ok(()),
            r => Err(unexpected("Ack", &r)),
        }
    }

    /// Samples per frame for `per` values per sample.
    pub fn batch_size(&self, per: usize) -> usize {
        let fb = self.float_bytes() as usize;
        let max = self
            .info
            .map(|i| i.max_frame as usize)
            .unwrap_or(max_raw(512));
        let fit = (max.saturating_sub(MESSAGE_HEADROOM) / (per * fb).max(1)).max(1);
        if self.opts.batch > 0 {
            fit.min(self.opts.batch)
        } else {
            fit
        }
    }

    /// Stream samples (row-major, each [u, y, p] of `per` values) starting at stream index
    /// `first`; `progress(done)` is called after every acknowledged frame. Returns the final
    /// status; fails if the device reports a next index outside the frame it acknowledged.
    ///
    /// Frames shrink on a noisy line: when a frame of several samples is not acknowledged
    /// within a few retransmissions its batch is halved (down to one sample, which gets the
    /// full retry budget), and it grows back after a run of clean exchanges. Re-sending a
    /// smaller frame is safe: the device applies samples by stream index.
    pub fn stream(
        &mut self,
        rows: &[f64],
        per: usize,
        first: u32,
        mut progress: impl FnMut(usize),
    ) -> Result<Status, LinkError> {
        self.ensure_hello()?;
        if per == 0 || rows.len() % per != 0 {
            return Err(LinkError::Protocol("sample rows of unequal length".into()));
        }
        let n = rows.len() / per;
        let mut bs = Adaptive::new(self.batch_size(per));
        let fb = self.float_bytes();
        let mut done = 0usize;
        let mut last = None;
        let mut vals = std::mem::take(&mut self.vals);
        let result = loop {
            if done >= n {
                break Ok(());
            }
            let k = bs.size.min(n - done);
            f64_to_values(&rows[done * per..(done + k) * per], fb, &mut vals);
            let start = first + done as u32;
            let retries = bs.retries(self.opts.retries);
            let before = self.stats.retries;
            let reply = self.request_n(
                &Message::Samples {
                    first: start,
                    values: &vals,
                },
                retries,
            );
            match reply {
                Ok(Reply::Status(s))
                    if s.next_sample >= start + k as u32
                        && (s.next_sample as usize) <= first as usize + n =>
                {
                    done = (s.next_sample - first) as usize;
                    last = Some(s);
                }
                Ok(Reply::Status(s)) => {
                    break Err(LinkError::Protocol(format!(
                        "device expects sample {} after samples {start}..{}",
                        s.next_sample,
                        start as usize + k
                    )))
                }
                Ok(r) => break Err(unexpected("Status", &r)),
                Err(LinkError::NoReply { .. }) if bs.shrink() => continue,
                Err(e) => break Err(e),
            }
            bs.exchanged(self.stats.retries == before);
            progress(done);
        };
        self.vals = vals;
        result?;
        match last {
            Some(s) => Ok(s),
            None => self.status(),
        }
    }

    fn pull_values(&mut self, solution: bool, total: usize) -> Result<Vec<f64>, LinkError> {
        let info = self.ensure_hello()?;
        let chunk = ((info.max_frame as usize).saturating_sub(MESSAGE_HEADROOM)
            / info.float_bytes as usize)
            .clamp(1, u16::MAX as usize);
        let mut out = Vec::with_capacity(total);
        // chunks shrink on a noisy line and grow back, as in `stream`
        let mut size = Adaptive::new(chunk);
        while out.len() < total {
            let offset = out.len() as u32;
            let count = size.size.min(total - out.len()) as u16;
            let msg = if solution {
                Message::PullSolution { offset, count }
            } else {
                Message::PullStats { offset, count }
            };
            let retries = size.retries(self.opts.retries);
            let before = self.stats.retries;
            match self.request_n(&msg, retries) {
                Ok(Reply::Values {
                    offset: o,
                    total: t,
                    values,
                }) if o == offset && t as usize == total && !values.is_empty() => {
                    out.extend_from_slice(&values);
                }
                Ok(r) => return Err(unexpected("Values", &r)),
                Err(LinkError::NoReply { .. }) if size.shrink() => continue,
                Err(e) => return Err(e),
            }
            size.exchanged(self.stats.retries == before);
        }
        out.truncate(total);
        Ok(out)
    }

    /// Pull the statistics: the status (dimensions, windows) and the packed Gram.
    pub fn pull_stats(&mut self) -> Result<(Status, Vec<f64>), LinkError> {
        let st = self.status()?;
        if !st.configured {
            return Err(LinkError::Device {
                code: ErrorCode::NotConfigured,
                detail: 0,
            });
        }
        let vals = self.pull_values(false, st.gram_len as usize)?;
        // the statistics must not have moved while we pulled
        let after = self.status()?;
        if after.windows != st.windows {
            return Err(LinkError::Protocol(
                "the statistics changed while they were pulled".into(),
            ));
        }
        Ok((st, vals))
    }

    /// Solve on the device; returns the summary and the coefficients (l x (q + r)).
    pub fn solve(&mut self, req: SolveRequest) -> Result<(SolveSummary, Vec<f64>), LinkError> {
        let s = match self.request(&Message::Solve(req))? {
            Reply::Solved(s) => s,
            r => return Err(unexpected("Solved", &r)),
        };
        let theta = self.pull_values(true, s.columns as usize * s.outputs as usize)?;
        Ok((s, theta))
    }

    /// Push an LPV-SS model for the device's one-step-ahead predictor.
    pub fn push_model(&mut self, model: &LpvSs) -> Result<usize, LinkError> {
        let info = self.ensure_hello()?;
        model.validate()?;
        let sched = model.c.len() > 1 || model.d.len() > 1;
        let vals = model_values(model)?;
        let n = u16::try_from(model.n())
            .map_err(|_| LinkError::Protocol("model order too large".into()))?;
        let fb = info.float_bytes;
        let chunk =
            ((info.max_frame as usize).saturating_sub(MESSAGE_HEADROOM) / fb as usize).max(1);
        let mut bytes = Vec::new();
        let mut off = 0;
        while off < vals.len() || off == 0 {
            let end = (off + chunk).min(vals.len());
            f64_to_values(&vals[off..end], fb, &mut bytes);
            let ch = ModelChunk {
                n,
                scheduled_output: sched,
                offset: off as u32,
                total: vals.len() as u32,
                values: &bytes,
            };
            match self.request(&Message::PushModel(ch))? {
                Reply::Ack => {}
                r => return Err(unexpected("Ack", &r)),
            }
            off = end;
            if vals.is_empty() {
                break;
            }
        }
        Ok(vals.len())
    }

    /// The predictor's record: (samples predicted, SSE per output, last prediction).
    pub fn prediction(&mut self) -> Result<(u32, Vec<f64>, Vec<f64>), LinkError> {
        match self.request(&Message::GetPrediction)? {
            Reply::Prediction { count, sse, last } => Ok((count, sse, last)),
            r => Err(unexpected("Prediction", &r)),
        }
    }
}

fn unexpected(want: &str, got: &Reply) -> LinkError {
    LinkError::Protocol(format!("expected {want}, the device sent {got:?}"))
}

fn owned(msg: &Message<'_>, fb: u8) -> Result<Reply, LinkError> {
    Ok(match *msg {
        Message::Info(i) => Reply::Info(i),
        Message::Ack => Reply::Ack,
        Message::Status(s) => Reply::Status(s),
        Message::Values {
            offset,
            total,
            values,
        } => Reply::Values {
            offset,
            total,
            values: values_to_f64(values, fb)?,
        },
        Message::Solved(s) => Reply::Solved(s),
        Message::Error(e) => Reply::Error(e),
        Message::Prediction(p) => Reply::Prediction {
            count: p.count,
            sse: values_to_f64(p.sse, fb)?,
            last: values_to_f64(p.last, fb)?,
        },
        Message::Estimate(e) => Reply::Estimate(EstimateReply {
            solves: e.solves,
            failures: e.failures,
            at_sample: e.at_sample,
            summary: e.summary,
            count: e.count,
            sse: values_to_f64(e.sse, fb)?,
            last_error: values_to_f64(e.last_error, fb)?,
        }),
        _ => Reply::Other,
    })
}

/// Serve a device engine on `port` until `stop` is set: read what arrives, hand it to the
/// engine, write its replies. What a firmware's main loop does, on the host (tests,
/// benchmarks). The port's reads must time out (to look at `stop`).
#[allow(clippy::type_complexity)]
pub fn serve<
    P: Read + Write,
    T: WireReal,
    const W: usize,
    const G: usize,
    const R: usize,
    const X: usize,
    const M: usize,
    const F: usize,
>(
    port: &mut P,
    dev: &mut Device<T, W, G, R, X, M, F>,
    stop: &AtomicBool,
) -> io::Result<()> {
    let mut buf = [0u8; 4096];
    let mut out: Vec<u8> = Vec::with_capacity(4096);
    while !stop.load(Ordering::Relaxed) {
        match port.read(&mut buf) {
            Ok(0) => std::thread::sleep(Duration::from_millis(1)),
            Ok(n) => {
                out.clear();
                dev.handle(&buf[..n], |f| out.extend_from_slice(f));
                if !out.is_empty() {
                    port.write_all(&out)?;
                    port.flush()?;
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut
                        | io::ErrorKind::WouldBlock
                        | io::ErrorKind::Interrupted
                ) => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Layout on the wire, for callers that build a [`Config`] themselves.
pub fn layout_of(l: StatsLayout) -> Layout {
    lpvid::device::wire_layout(l)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_conversion_round_trips() {
        let mut b = Vec::new();
        f64_to_values(&[1.5, -2.25], 4, &mut b);
        assert_eq!(values_to_f64(&b, 4).unwrap(), vec![1.5, -2.25]);
        f64_to_values(&[0.1], 8, &mut b);
        assert_eq!(values_to_f64(&b, 8).unwrap(), vec![0.1]);
        assert!(values_to_f64(&[0, 1, 2], 4).is_err());
    }
}
