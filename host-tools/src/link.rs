//! The device link (DESIGN.md section 4): the host end of the wire protocol of
//! [`lpvid::protocol`] over a serial port (or anything `Read + Write`), and the
//! `lpvid device` command.
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
//! [`crate::pbsid::fit_from_stats`], the same code as a fit from statistics accumulated on
//! the host; [`compare_with_file`] checks both against a file-based fit.

use std::io::{self, IsTerminal, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clap::{Args, Subcommand};
use lpvid::device::Device;
use lpvid::protocol::{
    encode_frame, max_raw, Config, Deframer, ErrorCode, ErrorReply, Event, Info, Layout, Message,
    ModelChunk, SolveRequest, SolveSummary, Status, WireReal, MESSAGE_HEADROOM, VERSION,
};
use lpvid::{packed_len, stat_vector_len, Gram, PbsidDims, PbsidStats, StatsLayout};
use serde_json::{json, Value};

use crate::cli::CliError;
use crate::data::Dataset;
use crate::lpvss::{LpvSs, Signals};
use crate::model::{ModelFile, ModelKind, SignalMap};
use crate::pbsid::{self, Order, PbsidFit, PbsidOptions, Reg, Solver};

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
    /// A request-type message (a device never sends one).
    Other,
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

/// A received frame: (seq, reply), or why it was rejected.
type Frame = Result<(u32, Reply), ErrorCode>;

/// Statistics accumulated on the host over `Vec`s.
pub type HostStats<T> = PbsidStats<T, Vec<T>, Vec<T>, Vec<T>>;

/// Settings of a [`Link`].
#[derive(Debug, Clone, Copy)]
pub struct LinkOptions {
    /// Wait for a reply this long before retransmitting.
    pub timeout: Duration,
    /// Wait this long for the first reply of a session (a QEMU pseudo-terminal can hold
    /// the first bytes for about a second).
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
                    Event::Oversize => return Ok(Some(Err(ErrorCode::Oversize))),
                    Event::Frame(buf) => {
                        return Ok(Some(match lpvid::protocol::decode_frame(buf) {
                            Err(code) => Err(code),
                            Ok(pkt) => match owned(&pkt.msg, fb) {
                                Ok(r) => Ok((pkt.seq, r)),
                                Err(_) => Err(ErrorCode::Malformed),
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
            let wait = if self.answered {
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
                    Some(Err(code)) => {
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
                            return Err(LinkError::Protocol(format!(
                                "the device speaks protocol version {}, this host {VERSION}",
                                e.detail
                            )));
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
                    return Err(LinkError::Protocol(format!(
                        "the device speaks protocol version {}, this host {VERSION}",
                        i.version
                    )));
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

    /// Configure dimensions and layout (clears the device's statistics).
    pub fn configure(&mut self, dims: &PbsidDims, layout: StatsLayout) -> Result<(), LinkError> {
        let b = |v: usize, what: &str| {
            u8::try_from(v).map_err(|_| LinkError::Protocol(format!("{what} = {v} is too large")))
        };
        let cfg = Config {
            r: b(dims.r, "r")?,
            l: b(dims.l, "l")?,
            s: b(dims.s, "s")?,
            p: b(dims.p, "p")?,
            layout: lpvid::device::wire_layout(layout),
            forgetting: 1.0,
        };
        match self.request(&Message::Configure(cfg))? {
            Reply::Ack => Ok(()),
            r => Err(unexpected("Ack", &r)),
        }
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
        let max_bs = self.batch_size(per);
        let mut bs = max_bs;
        let mut clean = 0u32;
        let fb = self.float_bytes();
        let mut done = 0usize;
        let mut last = None;
        let mut vals = std::mem::take(&mut self.vals);
        let result = loop {
            if done >= n {
                break Ok(());
            }
            let k = bs.min(n - done);
            f64_to_values(&rows[done * per..(done + k) * per], fb, &mut vals);
            let start = first + done as u32;
            let retries = if bs > 1 {
                SHRINK_AFTER.min(self.opts.retries)
            } else {
                self.opts.retries
            };
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
                Err(LinkError::NoReply { .. }) if bs > 1 => {
                    bs = (bs / 2).max(1);
                    clean = 0;
                    continue;
                }
                Err(e) => break Err(e),
            }
            if self.stats.retries == before {
                clean += 1;
                if clean >= GROW_AFTER && bs < max_bs {
                    bs = (bs * 2).min(max_bs);
                    clean = 0;
                }
            } else {
                clean = 0;
            }
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
        let mut size = chunk;
        let mut clean = 0u32;
        while out.len() < total {
            let offset = out.len() as u32;
            let count = size.min(total - out.len()) as u16;
            let msg = if solution {
                Message::PullSolution { offset, count }
            } else {
                Message::PullStats { offset, count }
            };
            let retries = if size > 1 {
                SHRINK_AFTER.min(self.opts.retries)
            } else {
                self.opts.retries
            };
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
                Err(LinkError::NoReply { .. }) if size > 1 => {
                    size = (size / 2).max(1);
                    clean = 0;
                    continue;
                }
                Err(e) => return Err(e),
            }
            if self.stats.retries == before {
                clean += 1;
                if clean >= GROW_AFTER && size < chunk {
                    size = (size * 2).min(chunk);
                    clean = 0;
                }
            } else {
                clean = 0;
            }
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
        model.check().map_err(LinkError::Protocol)?;
        let m = model.m();
        let sched = model.c.len() > 1 || model.d.len() > 1;
        let mut vals = Vec::new();
        let mut push = |mats: &[nalgebra::DMatrix<f64>], count: usize| {
            for i in 0..count {
                let mat = if mats.len() == 1 { &mats[0] } else { &mats[i] };
                for r in 0..mat.nrows() {
                    for c in 0..mat.ncols() {
                        vals.push(mat[(r, c)]);
                    }
                }
            }
        };
        push(&model.a, m);
        push(&model.b, m);
        push(&model.k, m);
        let mc = if sched { m } else { 1 };
        push(&model.c, mc);
        push(&model.d, mc);
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

// ---------------------------------------------------------------------------------------
// Host-side statistics and the comparison with a file

/// Extended (or plain) statistics of `sig` accumulated on the host with the core's code in
/// float type `T` (f32: exactly what an f32 device computes from the same samples).
pub fn host_stats<T: lpvid::Real>(
    sig: &Signals,
    p: usize,
    layout: StatsLayout,
) -> Result<HostStats<T>, lpvid::Error> {
    let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), p)?;
    let len = stat_vector_len(&dims, layout)?;
    let mut st = PbsidStats::with_storage(
        dims,
        layout,
        vec![T::ZERO; lpvid::window_storage_len(dims.r, dims.l, dims.s, p)],
        vec![T::ZERO; packed_len(len)],
        vec![T::ZERO; len],
    )?;
    for k in 0..sig.len() {
        let row =
            |m: &nalgebra::DMatrix<f64>| -> Vec<T> { m.row(k).iter().map(|v| T::of(*v)).collect() };
        st.update(&row(&sig.u), &row(&sig.y), &row(&sig.p))?;
    }
    Ok(st)
}

/// Samples of `sig` row-major [u, y, p], the order the wire carries them.
pub fn sample_rows(sig: &Signals) -> Vec<f64> {
    let mut rows = Vec::with_capacity(sig.len() * (sig.u.ncols() + sig.y.ncols() + sig.p.ncols()));
    for k in 0..sig.len() {
        rows.extend(sig.u.row(k).iter());
        rows.extend(sig.y.row(k).iter());
        rows.extend(sig.p.row(k).iter());
    }
    rows
}

/// Largest difference between two packed Grams, each entry relative to
/// sqrt(G_ii G_jj) of `reference` (the scale of a sum of products: what rounding in
/// the accumulation is proportional to).
pub fn gram_difference(pulled: &[f64], reference: &Gram<f64, Vec<f64>>) -> f64 {
    let dim = reference.dim();
    let mut worst: f64 = 0.0;
    let mut off = 0;
    for i in 0..dim {
        for j in i..dim {
            let a = pulled.get(off + j - i).copied().unwrap_or(f64::NAN);
            let b = reference.get(i, j);
            let scale = (reference.get(i, i) * reference.get(j, j))
                .sqrt()
                .max(1e-300);
            let d = (a - b).abs() / scale;
            worst = if d.is_nan() {
                f64::INFINITY
            } else {
                worst.max(d)
            };
        }
        off += dim - i;
    }
    worst
}

/// Largest difference of two models' free-run outputs on `sig`, relative to max |y|.
pub fn model_difference(a: &LpvSs, b: &LpvSs, sig: &Signals) -> f64 {
    let ya = a.simulate(sig, None);
    let yb = b.simulate(sig, None);
    let d = (ya - &yb).amax() / sig.y.amax().max(1e-300);
    if d.is_nan() {
        f64::INFINITY
    } else {
        d
    }
}

/// The outcome of comparing a device's statistics with the same file on the host.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Comparison {
    /// Windows the device accumulated / the host.
    pub windows: (u64, u64),
    /// Max relative Gram difference, device vs host f64 accumulation.
    pub stats_vs_f64: f64,
    /// Max absolute Gram difference, device vs host accumulation in the device's float type
    /// (0 when both round identically).
    pub stats_vs_same_type: f64,
    /// Max relative free-run output difference: model from the device's statistics vs the
    /// file-based (primal) fit of the same data.
    pub model_vs_file_fit: Option<f64>,
    /// Same, model from the host's f64 statistics vs the file fit (the f64 floor).
    pub host_stats_model_vs_file_fit: Option<f64>,
    /// Orders chosen (device statistics, file fit).
    pub orders: Option<(usize, usize)>,
}

/// Compare pulled statistics with the host's accumulation of `sig`, and (with `opts`) the
/// model fitted from them with the file-based fit.
pub fn compare_with_file(
    pulled: &[f64],
    windows: u64,
    float_bytes: u8,
    sig: &Signals,
    dims: &PbsidDims,
    layout: StatsLayout,
    opts: Option<&PbsidOptions>,
) -> Result<Comparison, String> {
    let h64 = host_stats::<f64>(sig, dims.p, layout).map_err(|e| e.to_string())?;
    if h64.gram().packed().len() != pulled.len() {
        return Err(format!(
            "the device holds {} statistic values, the host computes {} for these dimensions",
            pulled.len(),
            h64.gram().packed().len()
        ));
    }
    let same: Vec<f64> = if float_bytes == 4 {
        let h32 = host_stats::<f32>(sig, dims.p, layout).map_err(|e| e.to_string())?;
        h32.gram().packed().iter().map(|v| *v as f64).collect()
    } else {
        h64.gram().packed().to_vec()
    };
    let stats_vs_same_type = pulled
        .iter()
        .zip(&same)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let stats_vs_f64 = gram_difference(pulled, h64.gram());
    let mut cmp = Comparison {
        windows: (windows, h64.gram().count()),
        stats_vs_f64,
        stats_vs_same_type,
        model_vs_file_fit: None,
        host_stats_model_vs_file_fit: None,
        orders: None,
    };
    if let (Some(o), StatsLayout::Extended) = (opts, layout) {
        let mut fo = o.clone();
        fo.solver = Solver::Primal;
        let file = pbsid::fit(sig, &fo).map_err(|e| format!("file fit: {e}"))?;
        let dev = fit_pulled(pulled, windows, dims, o)
            .map_err(|e| format!("fit from device statistics: {e}"))?;
        let host = pbsid::fit_from_stats(h64.gram(), dims, o).map_err(|e| e.to_string())?;
        cmp.model_vs_file_fit = Some(model_difference(&dev.model, &file.model, sig));
        cmp.host_stats_model_vs_file_fit = Some(model_difference(&host.model, &file.model, sig));
        cmp.orders = Some((dev.order, file.order));
    }
    Ok(cmp)
}

/// Fit a model from pulled (extended) statistics with [`pbsid::fit_from_stats`].
pub fn fit_pulled(
    pulled: &[f64],
    windows: u64,
    dims: &PbsidDims,
    opts: &PbsidOptions,
) -> Result<PbsidFit, String> {
    let len = stat_vector_len(dims, StatsLayout::Extended).map_err(|e| e.to_string())?;
    let mut g = Gram::new(len, vec![0.0; packed_len(len)]).map_err(|e| e.to_string())?;
    g.load(pulled, windows).map_err(|e| {
        format!("pulled statistics do not fit the extended layout of these dimensions: {e}")
    })?;
    pbsid::fit_from_stats(&g, dims, opts).map_err(|e| e.to_string())
}

// ---------------------------------------------------------------------------------------
// The `lpvid device` command

/// `lpvid device`: talk to a device (firmware or emulator) over a serial port.
#[derive(Debug, Args)]
pub struct DeviceArgs {
    /// Serial port (e.g. /dev/ttyACM0, or the /dev/pts/N QEMU prints).
    #[arg(long)]
    port: PathBuf,
    /// Reply timeout in milliseconds before a retransmission.
    #[arg(long, default_value_t = 500)]
    timeout_ms: u64,
    /// Retransmissions per request before giving up.
    #[arg(long, default_value_t = 25)]
    retries: u32,
    /// Print a JSON summary instead of the human one.
    #[arg(long)]
    json: bool,
    #[command(subcommand)]
    action: DeviceAction,
}

#[derive(Debug, Subcommand)]
enum DeviceAction {
    /// Handshake: protocol version, float type, capacities, and the device's status.
    Info,
    /// Configure the device for a data file's channels and stream the file's samples.
    Stream(StreamArgs),
    /// Pull the statistics and identify a model from them (the same code as a file fit).
    Pull(PullArgs),
    /// Solve problem (13) (Lasso or least squares) on the device and pull the coefficients.
    Solve(SolveArgs),
    /// Push an lpv-ss model for the device's one-step-ahead predictor.
    Push(PushArgs),
    /// Clear the device's statistics and sample index (configuration and model stay).
    Reset,
}

#[derive(Debug, Args)]
struct StreamArgs {
    /// Data file (CSV: u1.., y1.., p1..).
    file: PathBuf,
    /// Past window p.
    #[arg(long, default_value_t = 3)]
    past: usize,
    /// Accumulate the plain statistics of problem (13) only (default: extended, from which
    /// the host finishes the whole fit).
    #[arg(long)]
    plain: bool,
    /// Continue the device's current stream instead of configuring afresh (samples already
    /// applied are acknowledged, not counted again).
    #[arg(long)]
    resume: bool,
    /// Largest number of samples per frame (default: as many as fit).
    #[arg(long, default_value_t = 0)]
    batch: usize,
}

#[derive(Debug, Args)]
struct PullArgs {
    /// Write the model identified from the statistics here (JSON).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the raw statistics here (JSON: dimensions, windows, packed Gram).
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Check against this data file: the host accumulates the same statistics and fits the
    /// file; fails if they differ by more than the tolerances.
    #[arg(long)]
    compare: Option<PathBuf>,
    /// Tolerance on the relative statistics difference for --compare.
    #[arg(long, default_value_t = 1e-4)]
    stats_tol: f64,
    /// Tolerance on the relative model output difference for --compare.
    #[arg(long, default_value_t = 1e-2)]
    model_tol: f64,
    /// Model order, or `auto`.
    #[arg(long, default_value = "auto")]
    order: Order,
    /// Regularisation: none or tikhonov-gcv.
    #[arg(long, default_value = "tikhonov-gcv")]
    reg: Reg,
    /// Assume D = 0.
    #[arg(long)]
    no_feedthrough: bool,
}

#[derive(Debug, Args)]
struct SolveArgs {
    /// lambda as a fraction of lambda_max (0: least squares).
    #[arg(long, default_value_t = 0.01)]
    lambda_ratio: f32,
    /// l2,1 (group) penalty instead of l1.
    #[arg(long)]
    group: bool,
    /// Penalise raw instead of standardised coefficients.
    #[arg(long)]
    raw: bool,
}

#[derive(Debug, Args)]
struct PushArgs {
    /// Model file (lpv-ss JSON).
    model: PathBuf,
}

fn link_err(e: LinkError) -> CliError {
    CliError::Other(format!("device: {e}"))
}

fn w(out: &mut dyn Write, s: String) -> Result<(), CliError> {
    writeln!(out, "{s}").map_err(|e| CliError::Other(format!("cannot write output: {e}")))
}

/// Run `lpvid device ...`.
pub fn device_cmd(a: &DeviceArgs, out: &mut dyn Write) -> Result<(), CliError> {
    let port = open_port(&a.port).map_err(link_err)?;
    let opts = LinkOptions {
        timeout: Duration::from_millis(a.timeout_ms),
        retries: a.retries,
        batch: match &a.action {
            DeviceAction::Stream(s) => s.batch,
            _ => 0,
        },
        ..LinkOptions::default()
    };
    let mut link = Link::new(port, opts);
    let info = link.hello().map_err(link_err)?;
    let result = match &a.action {
        DeviceAction::Info => {
            let st = link.status().map_err(link_err)?;
            let mut v = json!({"command": "device info", "info": info_json(&info), "status": st});
            if st.model_loaded {
                let (count, sse, last) = link.prediction().map_err(link_err)?;
                v["prediction"] = json!({"count": count, "sse": sse, "last": last});
            }
            Ok(v)
        }
        DeviceAction::Stream(s) => stream_cmd(&mut link, s, a.json),
        DeviceAction::Pull(p) => pull_cmd(&mut link, p, &info),
        DeviceAction::Solve(s) => {
            let req = SolveRequest {
                lambda_ratio: s.lambda_ratio,
                group: s.group,
                standardise: !s.raw,
            };
            let (sum, theta) = link.solve(req).map_err(link_err)?;
            Ok(json!({"command": "device solve", "summary": sum, "theta": theta}))
        }
        DeviceAction::Push(p) => {
            let mf = ModelFile::read(&p.model)?;
            let ModelKind::Ss(m) = &mf.kind else {
                return Err(CliError::Other(format!(
                    "{}: the device predictor runs lpv-ss models only",
                    p.model.display()
                )));
            };
            let n = link.push_model(m).map_err(link_err)?;
            Ok(
                json!({"command": "device push", "model": p.model.display().to_string(), "values": n, "order": m.n()}),
            )
        }
        DeviceAction::Reset => {
            link.reset().map_err(link_err)?;
            Ok(json!({"command": "device reset"}))
        }
    }?;
    let ls = link.stats();
    let mut result = result;
    result["link"] = serde_json::to_value(ls).unwrap_or(Value::Null);
    if a.json {
        w(
            out,
            serde_json::to_string_pretty(&result).unwrap_or_default(),
        )?;
    } else {
        print_human(&result, out)?;
    }
    Ok(())
}

fn info_json(i: &Info) -> Value {
    json!({
        "protocol": i.version,
        "float": if i.float_bytes == 4 { "f32" } else { "f64" },
        "max_frame_bytes": i.max_frame,
        "window_values": i.window_cap,
        "gram_values": i.gram_cap,
        "vector_values": i.vector_cap,
        "solver_values": i.solver_cap,
        "model_values": i.model_cap,
        "max_channels": i.max_channels,
        "capabilities": i.capabilities,
    })
}

fn stream_cmd(
    link: &mut Link<serialport::TTYPort>,
    s: &StreamArgs,
    json_out: bool,
) -> Result<Value, CliError> {
    let ds = Dataset::read_csv(&s.file)?;
    let map = SignalMap::default_for(&ds)?;
    let sig = map.evaluate(&ds)?;
    let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), s.past)
        .map_err(|e| CliError::Other(format!("{}: {e}", ds.source)))?;
    let layout = if s.plain {
        StatsLayout::Plain
    } else {
        StatsLayout::Extended
    };
    let first = if s.resume {
        let st = link.status().map_err(link_err)?;
        if !st.configured
            || (st.r as usize, st.l as usize, st.s as usize, st.p as usize)
                != (dims.r, dims.l, dims.s, dims.p)
        {
            return Err(CliError::Other(
                "--resume: the device is not configured for this file's dimensions".into(),
            ));
        }
        st.next_sample
    } else {
        link.configure(&dims, layout).map_err(link_err)?;
        0
    };
    let rows = sample_rows(&sig);
    let per = dims.r + dims.l + dims.s;
    let n = sig.len();
    let skip = (first as usize).min(n);
    let bar = if !json_out && io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new((n - skip) as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:40} {pos}/{len} samples {per_sec} eta {eta}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let t0 = Instant::now();
    let st = link
        .stream(&rows[skip * per..], per, first, |d| {
            bar.set_position(d as u64)
        })
        .map_err(link_err)?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    Ok(json!({
        "command": "device stream",
        "file": ds.source,
        "samples": n - skip,
        "first": first,
        "seconds": secs,
        "samples_per_second": (n - skip) as f64 / secs.max(1e-9),
        "status": st,
    }))
}

fn pull_cmd(
    link: &mut Link<serialport::TTYPort>,
    p: &PullArgs,
    info: &Info,
) -> Result<Value, CliError> {
    let (st, vals) = link.pull_stats().map_err(link_err)?;
    let dims = PbsidDims::new(st.r as usize, st.l as usize, st.s as usize, st.p as usize)
        .map_err(|e| CliError::Other(format!("device dimensions: {e}")))?;
    let ext_len = stat_vector_len(&dims, StatsLayout::Extended)
        .map(packed_len)
        .ok();
    let layout = if ext_len == Some(vals.len()) {
        StatsLayout::Extended
    } else {
        StatsLayout::Plain
    };
    let mut opts = PbsidOptions::new(dims.p);
    opts.order = p.order;
    opts.reg = p.reg;
    opts.feedthrough = !p.no_feedthrough;
    let mut res = json!({
        "command": "device pull",
        "status": st,
        "layout": if layout == StatsLayout::Extended { "extended" } else { "plain" },
        "values": vals.len(),
    });
    if let Some(path) = &p.stats {
        let v = json!({"r": dims.r, "l": dims.l, "s": dims.s, "p": dims.p,
            "layout": res["layout"], "windows": st.windows, "float": if info.float_bytes == 4 {"f32"} else {"f64"},
            "gram_packed_upper_row_major": vals});
        std::fs::write(path, serde_json::to_string(&v).unwrap_or_default())
            .map_err(|e| CliError::Other(format!("{}: cannot write: {e}", path.display())))?;
        res["stats_file"] = json!(path.display().to_string());
    }
    if let Some(path) = &p.out {
        if layout != StatsLayout::Extended {
            return Err(CliError::Other(
                "a model needs the extended statistics: stream without --plain".into(),
            ));
        }
        let fit = fit_pulled(&vals, st.windows, &dims, &opts).map_err(CliError::Other)?;
        let mf = ModelFile {
            kind: ModelKind::Ss(fit.model.clone()),
            signals: SignalMap::standard(dims.r, dims.l, dims.s),
            fit: json!({
                "method": "lpv-pbsid-opt",
                "source": "device statistics (lpvid device pull)",
                "float": if info.float_bytes == 4 {"f32"} else {"f64"},
                "past": dims.p,
                "order": fit.order,
                "order_reason": fit.order_reason,
                "reg": format!("{:?}", opts.reg),
                "lambda": fit.lambda,
                "feedthrough": opts.feedthrough,
                "windows": fit.windows,
                "singular_values": fit.singular_values,
                "lpvid_version": env!("CARGO_PKG_VERSION"),
            }),
        };
        mf.write(path)?;
        res["model"] = json!({"out": path.display().to_string(), "order": fit.order,
            "singular_values": fit.singular_values});
    }
    if let Some(path) = &p.compare {
        let ds = Dataset::read_csv(path)?;
        let sig = SignalMap::default_for(&ds)?.evaluate(&ds)?;
        let with_model = if layout == StatsLayout::Extended {
            Some(&opts)
        } else {
            None
        };
        let cmp = compare_with_file(
            &vals,
            st.windows,
            info.float_bytes,
            &sig,
            &dims,
            layout,
            with_model,
        )
        .map_err(CliError::Other)?;
        res["compare"] = serde_json::to_value(&cmp).unwrap_or(Value::Null);
        let mut bad = Vec::new();
        if cmp.windows.0 != cmp.windows.1 {
            bad.push(format!(
                "windows {} on the device, {} on the host",
                cmp.windows.0, cmp.windows.1
            ));
        }
        if cmp.stats_vs_f64.is_nan() || cmp.stats_vs_f64 > p.stats_tol {
            bad.push(format!(
                "statistics differ by {:.3e} > {:.1e}",
                cmp.stats_vs_f64, p.stats_tol
            ));
        }
        if let Some(d) = cmp.model_vs_file_fit {
            if d.is_nan() || d > p.model_tol {
                bad.push(format!(
                    "model outputs differ by {d:.3e} > {:.1e}",
                    p.model_tol
                ));
            }
        }
        if !bad.is_empty() {
            return Err(CliError::Other(format!(
                "device statistics do not match {}: {}",
                path.display(),
                bad.join("; ")
            )));
        }
    }
    Ok(res)
}

fn print_human(v: &Value, out: &mut dyn Write) -> Result<(), CliError> {
    let cmd = v["command"].as_str().unwrap_or("device");
    match cmd {
        "device info" => {
            let i = &v["info"];
            w(out, format!(
                "device: protocol v{}, {} statistics, frames up to {} bytes, capabilities {:#x}",
                i["protocol"], i["float"].as_str().unwrap_or("?"), i["max_frame_bytes"], i["capabilities"].as_u64().unwrap_or(0)
            ))?;
            w(out, format!(
                "  capacities (values): window {}, Gram {}, vector {}, solver {}, model {}; up to {} channels",
                i["window_values"], i["gram_values"], i["vector_values"], i["solver_values"], i["model_values"], i["max_channels"]
            ))?;
            let s = &v["status"];
            w(out, format!(
                "  status: configured {} (r={} l={} s={} p={}), next sample {}, {} windows, {} duplicate samples, frames ok {} rejected {}, model loaded {}",
                s["configured"], s["r"], s["l"], s["s"], s["p"], s["next_sample"], s["windows"],
                s["duplicate_samples"], s["frames_ok"], s["frames_rejected"], s["model_loaded"]
            ))?;
            if let Some(p) = v.get("prediction") {
                w(out, format!(
                    "  one-step predictor: {} samples, sum of squared errors {}, last prediction {}",
                    p["count"], p["sse"], p["last"]
                ))?;
            }
        }
        "device stream" => {
            let s = &v["status"];
            w(out, format!(
                "streamed {} samples of {} ({:.0} samples/s): device at sample {}, {} windows accumulated",
                v["samples"], v["file"].as_str().unwrap_or("?"), v["samples_per_second"].as_f64().unwrap_or(0.0),
                s["next_sample"], s["windows"]
            ))?;
        }
        "device pull" => {
            let s = &v["status"];
            w(
                out,
                format!(
                    "pulled {} {} statistic values ({} windows, r={} l={} s={} p={})",
                    v["values"],
                    v["layout"].as_str().unwrap_or("?"),
                    s["windows"],
                    s["r"],
                    s["l"],
                    s["s"],
                    s["p"]
                ),
            )?;
            if let Some(m) = v.get("model") {
                w(
                    out,
                    format!(
                        "  model of order {} written to {}",
                        m["order"],
                        m["out"].as_str().unwrap_or("?")
                    ),
                )?;
            }
            if let Some(c) = v.get("compare") {
                w(out, format!(
                    "  vs host: statistics differ by {:.3e} (relative, f64 host), {:.3e} (absolute, same float type); model outputs by {}",
                    c["stats_vs_f64"].as_f64().unwrap_or(f64::NAN),
                    c["stats_vs_same_type"].as_f64().unwrap_or(f64::NAN),
                    c["model_vs_file_fit"].as_f64().map(|d| format!("{d:.3e} vs the file fit")).unwrap_or("-".into())
                ))?;
            }
        }
        "device solve" => {
            let s = &v["summary"];
            w(out, format!(
                "solved on the device: {} columns x {} outputs, lambda {:.4e} (max {:.4e}), {} active, {} sweeps, converged {}, kkt {:.2e}",
                s["columns"], s["outputs"], s["lambda"].as_f64().unwrap_or(0.0), s["lambda_max"].as_f64().unwrap_or(0.0),
                s["active"], s["iterations"], s["converged"], s["kkt"].as_f64().unwrap_or(0.0)
            ))?;
            if let Some(t) = v["theta"].as_array() {
                let vals: Vec<String> = t
                    .iter()
                    .map(|x| format!("{:.4}", x.as_f64().unwrap_or(0.0)))
                    .collect();
                w(out, format!("  coefficients: {}", vals.join(" ")))?;
            }
        }
        "device push" => w(
            out,
            format!(
                "pushed {} (order {}, {} values): the device predicts from the next sample on",
                v["model"].as_str().unwrap_or("?"),
                v["order"],
                v["values"]
            ),
        )?,
        _ => w(
            out,
            "device reset: statistics and sample index cleared".to_string(),
        )?,
    }
    let l = &v["link"];
    w(
        out,
        format!(
            "  link: {} requests, {} retries ({} timeouts, {} bad frames, {} NAKs)",
            l["requests"], l["retries"], l["timeouts"], l["bad_frames"], l["naks"]
        ),
    )
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
