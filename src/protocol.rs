//! The wire protocol between a device and the host (DESIGN.md section 3.6; no paper equation
//! lives here): one definition, compiled into the firmware and into the host tool, so the two
//! cannot drift. Written down byte by byte in `docs/wire.md`. Cargo feature `device`.
//!
//! **Frame.** `COBS(raw) 0x00`, with
//! `raw = [version: u8] ++ postcard(Packet { seq, msg }) ++ crc32(version ++ body) as u32 LE`.
//! - COBS byte stuffing (Cheshire and Baker) removes every 0x00 from the frame, so 0x00 is an
//!   unambiguous delimiter: a receiver that has lost its place (garbage, a dropped or
//!   corrupted byte, a frame cut short) is back in step at the next 0x00. Empty frames
//!   (0x00 0x00) are ignored, so a sender may lead each frame with a 0x00 to cut off
//!   whatever partial frame the line held before. Overhead: one byte per 254, plus two.
//! - CRC-32 (IEEE 802.3, reflected polynomial 0xEDB88320, init and final xor 0xFFFFFFFF).
//!   Why 32 bits and not 16: statistics frames carry up to a few hundred bytes and a fault
//!   test corrupts one byte in a thousand, so thousands of corrupted frames reach the decoder
//!   in a long stream. CRC-16 lets one random corruption in 65 536 through, CRC-32 one in
//!   4.3e9; at these frame lengths CRC-32 also detects every error of up to 3 flipped bits and
//!   every burst up to 32 bits. The cost is 2 bytes per frame and a 1 KiB table in flash.
//! - The version byte sits outside the postcard body so a peer of another version is
//!   rejected as such ([`ErrorCode::WrongVersion`]) before any field is interpreted.
//! - postcard encodes enum variants by index: variants of [`Message`] and [`ErrorCode`] are
//!   only ever appended, never reordered or removed (a new variant reaching an old peer is
//!   rejected as [`ErrorCode::UnknownMessage`]).
//!
//! **Sequence numbers and acknowledgements.** Every request the host sends carries a `seq`
//! (never 0); the device answers each with exactly one reply carrying the same `seq` (its
//! acknowledgement). A retransmission reuses the `seq`: the device answers a repeated
//! state-changing request from a cache instead of applying it again. Independently, samples
//! carry their stream index (`first`): the device applies only samples it has not applied,
//! acknowledges duplicates without re-applying them, and reports a gap
//! ([`ErrorCode::Gap`]) instead of hiding it. `seq` 0 marks an unsolicited reply: the
//! rejection (NAK) of a frame the device could not decode, so the host need not wait for a
//! timeout to retransmit.
//!
//! **COBS: why this module has its own and not postcard's.** postcard 1.1 (our version) has a
//! COBS serializer flavor (`to_slice_cobs`), `from_bytes_cobs` and a `CobsAccumulator`; none
//! fits this frame, so the ~60 lines of [`cobs_encode`] / [`cobs_decode_in_place`] stay:
//! - they stuff the postcard body only, while our frame stuffs version byte + body + CRC-32,
//!   and the version and CRC must be checked *before* postcard interprets a field
//!   (`from_bytes_cobs` decodes and deserializes in one step; the in-place decoder alone lives
//!   in the `cobs` crate, which postcard does not re-export);
//! - the accumulator deserializes at each delimiter with no hook for those checks and no
//!   reason for a failure (one `DeserError` where we NAK with [`ErrorCode::BadCobs`],
//!   [`ErrorCode::BadCrc`], [`ErrorCode::WrongVersion`], ...), treats the empty frame a sender
//!   leads with (0x00 0x00) as an error, and after an over-long frame restarts in the middle
//!   of it (its tail becomes a second, bogus frame) where [`Deframer`] drops everything up to
//!   the next delimiter and reports [`ErrorCode::Oversize`] once;
//! - encoding alone could go through postcard's flavor (with a custom flavor for the version
//!   and the CRC), but then two COBS implementations would have to agree byte for byte
//!   (the 254-byte block boundary included), which is what keeping one avoids.
//!
//! Both directions are allocation-free, bounded by the caller's buffers and fuzzed
//! (`tests/protocol_fuzz.rs`); the bytes are pinned by a unit test and written down in
//! `docs/wire.md`.
//!
//! **Values.** Samples, statistics, solutions and models travel as little-endian floats of
//! the device's type ([`Info::float_bytes`]: 4 for f32, 8 for f64), in byte slices borrowed
//! from the frame buffer: decoding never copies and never allocates.

use serde::{Deserialize, Serialize};

use crate::real::Real;

/// Protocol version carried in the first byte of every frame.
pub const VERSION: u8 = 2;

/// Oldest protocol version whose error replies this side can still write: a frame of
/// version `OLDEST_ANSWERED..VERSION` is answered with a NAK framed in the peer's own
/// version (the `Error` message and [`ErrorReply`] are encoded the same in every version), so
/// an older host learns which version the device speaks instead of timing out.
pub const OLDEST_ANSWERED: u8 = 1;

/// Bytes a frame costs beyond its postcard body: version byte and CRC.
pub const FRAME_OVERHEAD: usize = 1 + 4;

/// Upper bound on the postcard bytes a message costs besides its value slice (version,
/// seq, variant, fields, length prefix, CRC): what to subtract from [`max_raw`] to size a
/// value payload.
pub const MESSAGE_HEADROOM: usize = 40;

/// Largest COBS encoding of `raw` bytes, without the delimiter.
pub const fn cobs_max_len(raw: usize) -> usize {
    raw + raw / 254 + 1
}

/// Largest raw frame (version + body + CRC) whose encoding plus delimiter fits a buffer of
/// `buf` bytes.
pub const fn max_raw(buf: usize) -> usize {
    // raw + raw/254 + 2 <= buf
    let mut raw = buf.saturating_sub(2);
    while raw > 0 && cobs_max_len(raw) + 1 > buf {
        raw -= 1;
    }
    raw
}

// ---------------------------------------------------------------------------------------
// CRC-32

const fn crc_table() -> [u32; 256] {
    let mut t = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

static CRC_TABLE: [u32; 256] = crc_table();

/// CRC-32 (IEEE 802.3) of `data`; `crc32(b"123456789") == 0xCBF43926`.
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in data {
        c = CRC_TABLE[((c ^ b as u32) & 0xFF) as usize] ^ (c >> 8);
    }
    c ^ 0xFFFF_FFFF
}

// ---------------------------------------------------------------------------------------
// COBS

/// COBS-encode `src` into `dst` (no delimiter appended). Returns the encoded length, or
/// `None` if `dst` is shorter than [`cobs_max_len`]`(src.len())` would need.
pub fn cobs_encode(src: &[u8], dst: &mut [u8]) -> Option<usize> {
    let mut code_at = 0usize;
    let mut out = 1usize;
    let mut code = 1u8;
    if dst.is_empty() {
        return None;
    }
    for &b in src {
        if b == 0 {
            *dst.get_mut(code_at)? = code;
            code_at = out;
            out += 1;
            code = 1;
        } else {
            *dst.get_mut(out)? = b;
            out += 1;
            code += 1;
            if code == 0xFF {
                *dst.get_mut(code_at)? = code;
                code_at = out;
                out += 1;
                code = 1;
            }
        }
    }
    *dst.get_mut(code_at)? = code;
    if out > dst.len() {
        return None;
    }
    Some(out)
}

/// COBS-decode `buf` (one frame, no delimiter) in place. Returns the decoded length, or
/// [`ErrorCode::BadCobs`] when a 0x00 appears inside the frame or a code byte points past
/// its end (what a frame cut short looks like).
pub fn cobs_decode_in_place(buf: &mut [u8]) -> Result<usize, ErrorCode> {
    let n = buf.len();
    let mut read = 0usize;
    let mut write = 0usize;
    while read < n {
        let code = buf[read] as usize;
        if code == 0 {
            return Err(ErrorCode::BadCobs);
        }
        read += 1;
        let end = read + code - 1;
        if end > n {
            return Err(ErrorCode::BadCobs);
        }
        while read < end {
            let b = buf[read];
            if b == 0 {
                return Err(ErrorCode::BadCobs);
            }
            buf[write] = b;
            write += 1;
            read += 1;
        }
        if code != 0xFF && read < n {
            buf[write] = 0;
            write += 1;
        }
    }
    Ok(write)
}

// ---------------------------------------------------------------------------------------
// Messages

/// Why a frame or a request was rejected (the `code` of [`ErrorReply`]). The first seven
/// are the frame decoder's reasons; variants are only ever appended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ErrorCode {
    /// The frame did not fit the receiver's buffer before its delimiter.
    Oversize,
    /// Invalid COBS stuffing (a zero inside, or a code past the end).
    BadCobs,
    /// Shorter than version + body + CRC, or the body ended inside a field.
    Truncated,
    /// The CRC-32 does not match.
    BadCrc,
    /// The version byte is not [`VERSION`]; `detail` carries the receiver's version (and the
    /// NAK's own version byte is the peer's when the peer is older: see [`OLDEST_ANSWERED`]).
    WrongVersion,
    /// A message variant this side does not know (a newer peer).
    UnknownMessage,
    /// A field with an invalid encoding, or bytes after the message.
    Malformed,
    /// Samples, solve, pull or model before a configuration.
    NotConfigured,
    /// Dimensions or settings the core rejects (`detail`: which, see the device docs).
    BadConfig,
    /// The device's static storage is too small; `detail`: values needed.
    Capacity,
    /// Samples start after the next expected index; `detail`: the expected index.
    Gap,
    /// The core rejected a sample (NaN/inf or overflow); `detail`: its stream index.
    SampleRejected,
    /// A value slice whose length is not a whole number of values/samples.
    BadLength,
    /// A feature this device does not have, or settings it cannot combine (`detail`: 1
    /// forgetting factor outside (0, 1], 2 forgetting together with a sliding window, 3 a
    /// window shorter than 2 vectors, 4 tracking needs solver storage, see [`Info`]).
    Unsupported,
    /// The on-device solve failed (singular, no convergence, no data).
    SolveFailed,
    /// A pushed model with wrong dimensions, order or non-finite values.
    ModelInvalid,
    /// A reply-type message sent to the device.
    UnexpectedMessage,
    /// A pull or model chunk outside the valid range; `detail`: the valid length.
    OutOfRange,
}

impl ErrorCode {
    /// True for the frame decoder's reasons (a NAK rather than a request's failure).
    pub fn is_frame_error(self) -> bool {
        matches!(
            self,
            ErrorCode::Oversize
                | ErrorCode::BadCobs
                | ErrorCode::Truncated
                | ErrorCode::BadCrc
                | ErrorCode::WrongVersion
                | ErrorCode::UnknownMessage
                | ErrorCode::Malformed
        )
    }

    /// A short description.
    pub fn describe(self) -> &'static str {
        match self {
            ErrorCode::Oversize => "frame larger than the receive buffer",
            ErrorCode::BadCobs => "invalid COBS stuffing",
            ErrorCode::Truncated => "frame truncated",
            ErrorCode::BadCrc => "CRC mismatch",
            ErrorCode::WrongVersion => "protocol version mismatch",
            ErrorCode::UnknownMessage => "unknown message type",
            ErrorCode::Malformed => "malformed message",
            ErrorCode::NotConfigured => "device not configured",
            ErrorCode::BadConfig => "configuration rejected",
            ErrorCode::Capacity => "device storage too small for this configuration",
            ErrorCode::Gap => "sample gap",
            ErrorCode::SampleRejected => "sample rejected (NaN/inf or overflow)",
            ErrorCode::BadLength => "value slice of invalid length",
            ErrorCode::Unsupported => "unsupported feature",
            ErrorCode::SolveFailed => "solve failed",
            ErrorCode::ModelInvalid => "model rejected",
            ErrorCode::UnexpectedMessage => "unexpected message",
            ErrorCode::OutOfRange => "range outside the valid values",
        }
    }
}

impl core::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.describe())
    }
}

/// Statistics layout on the wire (mirrors [`crate::StatsLayout`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Layout {
    /// [`crate::StatsLayout::Plain`].
    Plain,
    /// [`crate::StatsLayout::Extended`].
    Extended,
}

impl From<Layout> for crate::StatsLayout {
    fn from(l: Layout) -> Self {
        match l {
            Layout::Plain => crate::StatsLayout::Plain,
            Layout::Extended => crate::StatsLayout::Extended,
        }
    }
}

/// Capability bits of [`Info::capabilities`].
pub mod caps {
    /// Accumulates [`super::Layout::Extended`] statistics.
    pub const EXTENDED: u32 = 1;
    /// Solves the Lasso / least squares of problem (13) on the device.
    pub const SOLVE: u32 = 2;
    /// Runs a pushed model's one-step-ahead predictor on the streamed samples.
    pub const PREDICT: u32 = 4;
    /// Exponential forgetting ([`super::Config::forgetting`] < 1), protocol 2.
    pub const FORGETTING: u32 = 8;
    /// Sliding window of statistic vectors ([`super::Config::window`]), protocol 2.
    pub const WINDOW: u32 = 16;
    /// The recursive estimate ([`super::Message::Track`], [`super::Message::Estimate`]),
    /// protocol 2.
    pub const TRACK: u32 = 32;
}

/// What a device is (reply to [`Message::Hello`]). Capacities are in values of the
/// device's float type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Info {
    /// The device's protocol version.
    pub version: u8,
    /// Bytes per float: 4 (f32) or 8 (f64).
    pub float_bytes: u8,
    /// Largest raw frame (version + body + CRC) the device accepts and sends.
    pub max_frame: u16,
    /// Window storage, values ([`crate::window_storage_len`]).
    pub window_cap: u32,
    /// Gram storage, values ([`crate::packed_len`] of the statistic vector).
    pub gram_cap: u32,
    /// Statistic vector storage, values ([`crate::stat_vector_len`]).
    pub vector_cap: u32,
    /// Solver storage, values ((3 l + 2)(q + r) needed for a solve).
    pub solver_cap: u32,
    /// Model storage, values (parameters + the predictor state 2 n + 3 l needed for a
    /// pushed model, [`crate::model`]).
    pub model_cap: u32,
    /// Largest r + l + s.
    pub max_channels: u16,
    /// [`caps`] bits.
    pub capabilities: u32,
}

/// Dimensions and settings of the accumulation (request; resets the statistics).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Inputs r.
    pub r: u8,
    /// Outputs l.
    pub l: u8,
    /// Scheduling signals s.
    pub s: u8,
    /// Past window p.
    pub p: u8,
    /// Statistics layout.
    pub layout: Layout,
    /// Exponential forgetting factor lambda in (0, 1] per statistic vector: G <- lambda G +
    /// s_k s_k^T ([`crate::Gram::set_forgetting`]). 1: plain sums (mergeable, equal to a file
    /// fit); outside (0, 1]: [`ErrorCode::Unsupported`] (detail 1).
    pub forgetting: f32,
    /// Sliding window: the statistics hold the last N/2 + 1 ..= N statistic vectors (N even,
    /// an odd N rounded down; [`crate::sliding`]). 0: no window (the whole stream). Exclusive
    /// with forgetting < 1 ([`ErrorCode::Unsupported`] detail 2); N = 1 is detail 3.
    pub window: u32,
}

/// The device's state (reply to [`Message::GetStatus`] and to [`Message::Samples`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Status {
    /// Whether a configuration is active.
    pub configured: bool,
    /// Configured dimensions (0 when not configured).
    pub r: u8,
    /// Outputs.
    pub l: u8,
    /// Scheduling signals.
    pub s: u8,
    /// Past window.
    pub p: u8,
    /// Stream index of the next sample the device expects (= samples applied since the
    /// configuration or reset).
    pub next_sample: u32,
    /// Statistic vectors accumulated (windows).
    pub windows: u64,
    /// Values in the packed Gram (what [`Message::PullStats`] ranges over).
    pub gram_len: u32,
    /// Samples received again and acknowledged without being re-applied.
    pub duplicate_samples: u32,
    /// Frames decoded.
    pub frames_ok: u32,
    /// Frames rejected by the decoder.
    pub frames_rejected: u32,
    /// Whether a pushed model's predictor runs.
    pub model_loaded: bool,
    /// The configured forgetting factor (1 when not configured).
    pub forgetting: f32,
    /// The configured sliding window (0: none).
    pub window: u32,
    /// Effective number of vectors in the statistics: sum of lambda^age (= `windows` without
    /// forgetting; with a window, the vectors in it).
    pub weight: f32,
    /// Solves made by the recursive estimate since the configuration ([`Message::Track`]).
    pub solves: u32,
}

/// An on-device solve of problem (13): regress y_{k+p} on [z_k^p; u_{k+p}] from the
/// statistics' leading block, with the l1 or l2,1 penalty of the core's Lasso.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolveRequest {
    /// lambda as a fraction of lambda_max (0: least squares by coordinate descent).
    pub lambda_ratio: f32,
    /// false: l1 (per entry); true: l2,1 (per column, shared by the outputs).
    pub group: bool,
    /// Penalise standardised coefficients (weights sqrt(G_jj / N)).
    pub standardise: bool,
}

/// Result of a [`Message::Solve`]; the coefficients are pulled with
/// [`Message::PullSolution`] (l x (q + r), row-major).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolveSummary {
    /// Regressor columns q + r.
    pub columns: u32,
    /// Outputs l.
    pub outputs: u8,
    /// lambda used.
    pub lambda: f32,
    /// lambda_max of the statistics.
    pub lambda_max: f32,
    /// Sweeps used.
    pub iterations: u32,
    /// Whether the stopping rule was met.
    pub converged: bool,
    /// Non-zero columns.
    pub active: u32,
    /// Relative KKT violation (certificate).
    pub kkt: f32,
    /// Objective value.
    pub objective: f32,
}

/// The recursive estimate (request [`Message::Track`]): solve every `every` applied samples,
/// warm-started from the last solution, and run the one-step predictor of the solution in
/// force on every new statistic vector.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// Samples between solves (0: tracking off).
    pub every: u32,
    /// The solve to repeat (lambda_ratio 0: the least-squares PBSID/VARX regression of
    /// problem (13)).
    pub solve: SolveRequest,
}

/// The recursive estimate's record (reply to [`Message::GetEstimate`]). The coefficients of
/// the last successful solve are pulled with [`Message::PullSolution`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate<'a> {
    /// Successful tracking solves since the configuration.
    pub solves: u32,
    /// Tracking solves that failed (the previous solution stays in force).
    pub failures: u32,
    /// Stream index of the next sample when the last solve ran (0: none yet).
    pub at_sample: u32,
    /// Summary of the last successful solve (all zero before the first).
    pub summary: SolveSummary,
    /// One-step predictions the previous solution made over its whole interval (between the
    /// last two solves): out of sample, each vector was predicted before a solve saw it.
    pub count: u32,
    /// Their sum of squared errors per output (l floats).
    pub sse: &'a [u8],
    /// The newest one-step prediction error y_{k+p} - Theta [z_k^p; u_{k+p}] per output (l
    /// floats).
    pub last_error: &'a [u8],
}

/// A chunk of a model pushed to the device for its one-step-ahead predictor. The values,
/// in the device's float type, are A^(1..m) (n x n each), B^(1..m) (n x r), K^(1..m)
/// (n x l), then C (l x n) and D (l x r), one matrix each or m each if
/// `scheduled_output`; all row-major. Chunks arrive in order (`offset` = values received).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelChunk<'a> {
    /// State dimension n.
    pub n: u16,
    /// C and D depend on the scheduling (m matrices each).
    pub scheduled_output: bool,
    /// Index of the first value of this chunk.
    pub offset: u32,
    /// Total number of values of the model.
    pub total: u32,
    /// The values, little-endian floats.
    pub values: &'a [u8],
}

/// Rejection of a frame or a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorReply {
    /// Why.
    pub code: ErrorCode,
    /// A number qualifying it (see [`ErrorCode`]).
    pub detail: u32,
}

/// The one-step-ahead predictor's record (reply to [`Message::GetPrediction`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Prediction<'a> {
    /// Samples predicted since the model was loaded or the device reset.
    pub count: u32,
    /// Sum of squared prediction errors per output (l floats).
    pub sse: &'a [u8],
    /// The last prediction yhat_k per output (l floats).
    pub last: &'a [u8],
}

/// Every message of the protocol. Requests go host -> device, the others are replies.
/// Variants are only ever appended (postcard encodes the index).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Message<'a> {
    /// Request: handshake; reply [`Message::Info`].
    Hello {
        /// The host's protocol version.
        version: u8,
    },
    /// Reply: what the device is.
    Info(Info),
    /// Request: set dimensions and layout, clear statistics; reply [`Message::Ack`].
    Configure(Config),
    /// Request: samples `first..first + n`, each [u (r), y (l), p (s)]; reply
    /// [`Message::Status`].
    Samples {
        /// Stream index of the first sample.
        first: u32,
        /// n (r + l + s) little-endian floats.
        values: &'a [u8],
    },
    /// Request: reply [`Message::Status`].
    GetStatus,
    /// Reply: the device's state.
    Status(Status),
    /// Request: `count` values of the packed Gram from `offset`; reply [`Message::Values`]
    /// (possibly fewer values: as many as fit a frame).
    PullStats {
        /// First value.
        offset: u32,
        /// Values wanted.
        count: u16,
    },
    /// Reply: a chunk of values.
    Values {
        /// Index of the first value.
        offset: u32,
        /// Length of the whole vector.
        total: u32,
        /// Little-endian floats.
        values: &'a [u8],
    },
    /// Request: solve on the device; reply [`Message::Solved`].
    Solve(SolveRequest),
    /// Reply: summary of a solve.
    Solved(SolveSummary),
    /// Request: `count` coefficients of the last solve from `offset`; reply
    /// [`Message::Values`].
    PullSolution {
        /// First value.
        offset: u32,
        /// Values wanted.
        count: u16,
    },
    /// Request: a model chunk; reply [`Message::Ack`].
    PushModel(ModelChunk<'a>),
    /// Request: clear statistics, sample index and predictor state (the configuration and
    /// a loaded model stay); reply [`Message::Ack`].
    Reset,
    /// Reply: request applied.
    Ack,
    /// Reply: the request or frame was rejected.
    Error(ErrorReply),
    /// Request: reply [`Message::Prediction`].
    GetPrediction,
    /// Reply: the predictor's record.
    Prediction(Prediction<'a>),
    /// Request (protocol 2): start, change or stop the recursive estimate; reply
    /// [`Message::Ack`].
    Track(Track),
    /// Request (protocol 2): reply [`Message::Estimate`].
    GetEstimate,
    /// Reply (protocol 2): the recursive estimate's record.
    Estimate(Estimate<'a>),
}

impl Message<'_> {
    /// True for messages the host sends.
    pub fn is_request(&self) -> bool {
        matches!(
            self,
            Message::Hello { .. }
                | Message::Configure(_)
                | Message::Samples { .. }
                | Message::GetStatus
                | Message::PullStats { .. }
                | Message::Solve(_)
                | Message::PullSolution { .. }
                | Message::PushModel(_)
                | Message::Reset
                | Message::GetPrediction
                | Message::Track(_)
                | Message::GetEstimate
        )
    }
}

/// A decoded frame: sequence number and message.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Packet<'a> {
    /// Request number (0: unsolicited, see the module docs).
    pub seq: u32,
    /// The message.
    #[serde(borrow)]
    pub msg: Message<'a>,
}

/// Why a frame could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncodeError {
    /// The scratch or output buffer is too small for this message.
    BufferTooSmall,
}

/// Encode `seq` + `msg` as a complete frame (COBS + delimiter) into `out`, using `raw` as
/// scratch for the unstuffed bytes. Returns the frame length.
pub fn encode_frame(
    seq: u32,
    msg: &Message<'_>,
    raw: &mut [u8],
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    encode_frame_version(VERSION, seq, msg, raw, out)
}

/// [`encode_frame`] with another version byte: what a device uses to NAK an older peer in
/// that peer's own framing ([`OLDEST_ANSWERED`]); only messages whose encoding did not
/// change between the versions (the `Error` reply) may be sent this way.
pub fn encode_frame_version(
    version: u8,
    seq: u32,
    msg: &Message<'_>,
    raw: &mut [u8],
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    if raw.len() < FRAME_OVERHEAD + 2 {
        return Err(EncodeError::BufferTooSmall);
    }
    raw[0] = version;
    let avail = raw.len() - 4;
    let body = postcard::to_slice(&Packet { seq, msg: *msg }, &mut raw[1..avail])
        .map_err(|_| EncodeError::BufferTooSmall)?
        .len();
    let n = 1 + body;
    let crc = crc32(&raw[..n]);
    raw[n..n + 4].copy_from_slice(&crc.to_le_bytes());
    let enc = cobs_encode(&raw[..n + 4], out).ok_or(EncodeError::BufferTooSmall)?;
    if enc >= out.len() {
        return Err(EncodeError::BufferTooSmall);
    }
    out[enc] = 0;
    Ok(enc + 1)
}

/// Two peers that speak different protocol versions (a frame with a valid CRC and another
/// version byte): the typed form of [`ErrorCode::WrongVersion`], naming both versions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VersionMismatch {
    /// This side's version ([`VERSION`]).
    pub ours: u8,
    /// The version byte of the peer's frame.
    pub theirs: u8,
}

impl core::fmt::Display for VersionMismatch {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "unsupported protocol version: the peer speaks version {}, this side version {}",
            self.theirs, self.ours
        )
    }
}

/// Why [`decode_frame_checked`] rejected a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejected {
    /// A frame-level reason ([`ErrorCode::is_frame_error`]), never `WrongVersion`.
    Frame(ErrorCode),
    /// A valid frame of another protocol version.
    Version(VersionMismatch),
}

impl Rejected {
    /// The reason as the wire carries it.
    pub fn code(self) -> ErrorCode {
        match self {
            Rejected::Frame(c) => c,
            Rejected::Version(_) => ErrorCode::WrongVersion,
        }
    }
}

/// COBS-decode `buf` in place and check length, CRC and version: the raw length, or why
/// not (for a version mismatch, `buf[0]` then holds the peer's version byte).
fn unstuff_and_check(buf: &mut [u8]) -> Result<usize, ErrorCode> {
    let n = cobs_decode_in_place(buf)?;
    let raw = &buf[..n];
    if n < FRAME_OVERHEAD + 2 {
        return Err(ErrorCode::Truncated);
    }
    let (data, crc) = raw.split_at(n - 4);
    let want = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    if crc32(data) != want {
        return Err(ErrorCode::BadCrc);
    }
    if data[0] != VERSION {
        return Err(ErrorCode::WrongVersion);
    }
    Ok(n)
}

/// The postcard body of a checked frame.
fn parse_body(body: &[u8]) -> Result<Packet<'_>, ErrorCode> {
    // the variant index follows the seq varint: an index past the last known variant is a
    // message of a newer peer, not a corruption (the CRC passed)
    let mut at = 0;
    read_varint(body, &mut at)?;
    if read_varint(body, &mut at)? >= MESSAGE_VARIANTS {
        return Err(ErrorCode::UnknownMessage);
    }
    match postcard::take_from_bytes::<Packet<'_>>(body) {
        Ok((pkt, [])) => Ok(pkt),
        Ok(_) => Err(ErrorCode::Malformed),
        Err(postcard::Error::DeserializeUnexpectedEnd) => Err(ErrorCode::Truncated),
        Err(_) => Err(ErrorCode::Malformed),
    }
}

/// Decode one frame (its COBS bytes, without the delimiter) in place. Every invalid frame
/// is rejected with its reason: [`ErrorCode::BadCobs`], [`ErrorCode::Truncated`],
/// [`ErrorCode::BadCrc`], [`ErrorCode::WrongVersion`], [`ErrorCode::UnknownMessage`] or
/// [`ErrorCode::Malformed`] ([`ErrorCode::Oversize`] comes from the [`Deframer`]).
pub fn decode_frame(buf: &mut [u8]) -> Result<Packet<'_>, ErrorCode> {
    let n = unstuff_and_check(buf)?;
    parse_body(&buf[1..n - 4])
}

/// [`decode_frame`], with a frame of another version reported as a [`VersionMismatch`]
/// naming the peer's version (what a host shows when it meets an older or newer device).
pub fn decode_frame_checked(buf: &mut [u8]) -> Result<Packet<'_>, Rejected> {
    match unstuff_and_check(buf) {
        Ok(n) => parse_body(&buf[1..n - 4]).map_err(Rejected::Frame),
        Err(ErrorCode::WrongVersion) => Err(Rejected::Version(VersionMismatch {
            ours: VERSION,
            theirs: buf[0],
        })),
        Err(c) => Err(Rejected::Frame(c)),
    }
}

/// Number of [`Message`] variants this version knows.
pub const MESSAGE_VARIANTS: u32 = 20;

/// A postcard varint (LEB128, at most 5 bytes for a u32) at `*at`.
fn read_varint(b: &[u8], at: &mut usize) -> Result<u32, ErrorCode> {
    let mut v: u32 = 0;
    for i in 0..5 {
        let byte = *b.get(*at).ok_or(ErrorCode::Truncated)?;
        *at += 1;
        v |= ((byte & 0x7F) as u32) << (7 * i);
        if byte & 0x80 == 0 {
            return Ok(v);
        }
    }
    Err(ErrorCode::Malformed)
}

/// What [`Deframer::push`] found.
#[derive(Debug, PartialEq, Eq)]
pub enum Event<'a> {
    /// Nothing complete yet.
    Pending,
    /// A complete frame (COBS bytes, delimiter removed), valid until the next push.
    Frame(&'a mut [u8]),
    /// A frame overflowed the buffer; its bytes up to the delimiter were dropped.
    Oversize,
}

/// Splits a byte stream at 0x00 delimiters into a fixed buffer of `N` bytes: no
/// allocation, and an over-long frame costs only itself (it is reported once at its
/// delimiter and the next frame starts clean).
#[derive(Debug, Clone)]
pub struct Deframer<const N: usize> {
    buf: [u8; N],
    len: usize,
    overflow: bool,
}

impl<const N: usize> Default for Deframer<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Deframer<N> {
    /// An empty deframer.
    pub const fn new() -> Self {
        Deframer {
            buf: [0; N],
            len: 0,
            overflow: false,
        }
    }

    /// Bytes of the current, incomplete frame.
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Drop the incomplete frame.
    pub fn clear(&mut self) {
        self.len = 0;
        self.overflow = false;
    }

    /// Feed one byte.
    pub fn push(&mut self, b: u8) -> Event<'_> {
        if b == 0 {
            let len = self.len;
            let over = self.overflow;
            self.len = 0;
            self.overflow = false;
            if over {
                return Event::Oversize;
            }
            if len == 0 {
                return Event::Pending;
            }
            return Event::Frame(&mut self.buf[..len]);
        }
        if self.overflow {
            return Event::Pending;
        }
        if self.len < N {
            self.buf[self.len] = b;
            self.len += 1;
        } else {
            self.overflow = true;
        }
        Event::Pending
    }
}

// ---------------------------------------------------------------------------------------
// Values

/// A float the wire carries: [`Real`] plus little-endian byte conversion.
pub trait WireReal: Real {
    /// Write `self` into `out[..Self::BYTES]`.
    fn write_le(self, out: &mut [u8]);
    /// Read from `b[..Self::BYTES]`.
    fn read_le(b: &[u8]) -> Self;
}

impl WireReal for f32 {
    #[inline]
    fn write_le(self, out: &mut [u8]) {
        out[..4].copy_from_slice(&self.to_le_bytes());
    }
    #[inline]
    fn read_le(b: &[u8]) -> Self {
        f32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
}

impl WireReal for f64 {
    #[inline]
    fn write_le(self, out: &mut [u8]) {
        out[..8].copy_from_slice(&self.to_le_bytes());
    }
    #[inline]
    fn read_le(b: &[u8]) -> Self {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[..8]);
        f64::from_le_bytes(a)
    }
}

/// Write `vals` as little-endian floats into `out`; returns the bytes written, or `None`
/// if `out` is too short.
pub fn write_values<T: WireReal>(vals: &[T], out: &mut [u8]) -> Option<usize> {
    let n = vals.len().checked_mul(T::BYTES)?;
    if out.len() < n {
        return None;
    }
    for (v, o) in vals.iter().zip(out.chunks_exact_mut(T::BYTES)) {
        v.write_le(o);
    }
    Some(n)
}

/// Value `i` of a little-endian float slice (the caller checks the length).
#[inline]
pub fn read_value<T: WireReal>(bytes: &[u8], i: usize) -> T {
    T::read_le(&bytes[i * T::BYTES..(i + 1) * T::BYTES])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn cobs_round_trips() {
        let cases: [&[u8]; 6] = [
            &[],
            &[0],
            &[0, 0],
            &[1, 2, 3],
            &[0x11, 0x22, 0x00, 0x33],
            &[0xFF; 600],
        ];
        for c in cases {
            let mut enc = [0u8; 1024];
            let n = cobs_encode(c, &mut enc).unwrap();
            assert!(n <= cobs_max_len(c.len()));
            assert!(!enc[..n].contains(&0));
            let m = cobs_decode_in_place(&mut enc[..n]).unwrap();
            assert_eq!(&enc[..m], c);
        }
        let long: std::vec::Vec<u8> = (0..1000u32).map(|i| (i % 7) as u8).collect();
        let mut enc = [0u8; 1100];
        let n = cobs_encode(&long, &mut enc).unwrap();
        let m = cobs_decode_in_place(&mut enc[..n]).unwrap();
        assert_eq!(&enc[..m], &long[..]);
        assert!(cobs_encode(&long, &mut [0u8; 100]).is_none());
    }

    #[test]
    fn frame_round_trip_and_rejections() {
        let vals = [1.5f32, -2.0, 3.25];
        let mut vb = [0u8; 12];
        write_values(&vals, &mut vb).unwrap();
        let msg = Message::Samples {
            first: 7,
            values: &vb,
        };
        let mut raw = [0u8; 128];
        let mut out = [0u8; 140];
        let n = encode_frame(42, &msg, &mut raw, &mut out).unwrap();
        assert_eq!(out[n - 1], 0);
        let mut f = out[..n - 1].to_vec();
        let pkt = decode_frame(&mut f).unwrap();
        assert_eq!(pkt.seq, 42);
        assert_eq!(pkt.msg, msg);
        // one flipped bit anywhere: rejected
        for i in 0..n - 1 {
            for bit in 0..8 {
                let mut g = out[..n - 1].to_vec();
                g[i] ^= 1 << bit;
                assert!(decode_frame(&mut g).is_err(), "byte {i} bit {bit}");
            }
        }
        // truncated
        let mut g = out[..n - 3].to_vec();
        assert!(decode_frame(&mut g).is_err());
        assert_eq!(decode_frame(&mut [1u8, 1]), Err(ErrorCode::Truncated));
        // wrong version with a valid CRC
        let mut r = [0u8; 64];
        r[0] = VERSION + 1;
        let body = postcard::to_slice(
            &Packet {
                seq: 1,
                msg: Message::Reset,
            },
            &mut r[1..60],
        )
        .unwrap()
        .len();
        let crc = crc32(&r[..1 + body]);
        r[1 + body..5 + body].copy_from_slice(&crc.to_le_bytes());
        let mut e = [0u8; 80];
        let k = cobs_encode(&r[..5 + body], &mut e).unwrap();
        assert_eq!(decode_frame(&mut e[..k]), Err(ErrorCode::WrongVersion));
        // unknown variant with a valid CRC
        let raw_unknown = [VERSION, 1, 99];
        let crc = crc32(&raw_unknown);
        let mut r2 = raw_unknown.to_vec();
        r2.extend_from_slice(&crc.to_le_bytes());
        let k = cobs_encode(&r2, &mut e).unwrap();
        assert_eq!(decode_frame(&mut e[..k]), Err(ErrorCode::UnknownMessage));
    }

    /// The bytes on the wire, as docs/wire.md shows them: a change here is a protocol change.
    #[test]
    fn frame_bytes_are_pinned() {
        let mut raw = [0u8; 64];
        let mut out = [0u8; 64];
        let n = encode_frame(1, &Message::Reset, &mut raw, &mut out).unwrap();
        assert_eq!(
            &out[..n],
            &[0x08, 0x02, 0x01, 0x0c, 0x16, 0x70, 0x68, 0xec, 0x00]
        );
        let n = encode_frame(5, &Message::Hello { version: VERSION }, &mut raw, &mut out).unwrap();
        assert_eq!(
            &out[..n],
            &[0x03, 0x02, 0x05, 0x06, 0x02, 0x50, 0xb4, 0x88, 0x63, 0x00]
        );
        let cfg = Config {
            r: 1,
            l: 1,
            s: 1,
            p: 3,
            layout: Layout::Extended,
            forgetting: 0.5,
            window: 1000,
        };
        // forgetting 0.5 (f32 LE 00 00 00 3f), window 1000 (varint e8 07)
        let n = encode_frame(2, &Message::Configure(cfg), &mut raw, &mut out).unwrap();
        assert_eq!(
            &out[..n],
            &[
                0x09, 0x02, 0x02, 0x02, 0x01, 0x01, 0x01, 0x03, 0x01, 0x01, 0x01, 0x08, 0x3f, 0xe8,
                0x07, 0xbe, 0x74, 0x89, 0x8a, 0x00
            ]
        );
    }

    /// A version-1 frame (as a version-1 host or device writes it: version byte 1, the same
    /// postcard body) reaching this version.
    fn v1_frame(seq: u32, msg: &Message<'_>) -> std::vec::Vec<u8> {
        let mut raw = [0u8; 128];
        let mut out = [0u8; 140];
        let n = encode_frame_version(1, seq, msg, &mut raw, &mut out).unwrap();
        out[..n - 1].to_vec()
    }

    /// Protocol 2 meets protocol 1, both ways: the frame is refused before any field is
    /// read, with a typed error naming both versions.
    #[test]
    fn other_versions_get_a_typed_error_naming_both() {
        // a v1 host's Hello reaching a v2 decoder
        let mut f = v1_frame(7, &Message::Hello { version: 1 });
        let e = decode_frame_checked(&mut f).unwrap_err();
        assert_eq!(e, Rejected::Version(VersionMismatch { ours: 2, theirs: 1 }));
        assert_eq!(e.code(), ErrorCode::WrongVersion);
        let text = std::format!("{}", VersionMismatch { ours: 2, theirs: 1 });
        assert!(
            text.contains("version 1") && text.contains("version 2"),
            "{text}"
        );
        assert!(text.contains("unsupported"), "{text}");
        // the plain decoder gives the wire reason
        let mut f = v1_frame(7, &Message::Hello { version: 1 });
        assert_eq!(decode_frame(&mut f), Err(ErrorCode::WrongVersion));
        // a v1 device's NAK (its version in the frame and in `detail`) reaching a v2 host
        let nak = Message::Error(ErrorReply {
            code: ErrorCode::WrongVersion,
            detail: 1,
        });
        let mut f = v1_frame(0, &nak);
        assert_eq!(
            decode_frame_checked(&mut f),
            Err(Rejected::Version(VersionMismatch {
                ours: VERSION,
                theirs: 1
            }))
        );
        // a newer peer (v3) is named too
        let mut raw = [0u8; 64];
        let mut out = [0u8; 80];
        let n = encode_frame_version(3, 1, &Message::Reset, &mut raw, &mut out).unwrap();
        assert_eq!(
            decode_frame_checked(&mut out[..n - 1]),
            Err(Rejected::Version(VersionMismatch {
                ours: VERSION,
                theirs: 3
            }))
        );
        // the Error reply a v2 device NAKs a v1 host with, framed as version 1: the body
        // decodes with the version-1 layout of `Error` (index 14, code, detail)
        let f = v1_frame(
            0,
            &Message::Error(ErrorReply {
                code: ErrorCode::WrongVersion,
                detail: VERSION as u32,
            }),
        );
        let mut b = f.clone();
        let n = cobs_decode_in_place(&mut b).unwrap();
        assert_eq!(&b[..n - 4], &[1, 0, 14, 4, VERSION]);
    }

    /// Version 2's new messages round-trip, and a Configure with forgetting and a window.
    #[test]
    fn version_two_messages_round_trip() {
        let sum = SolveSummary {
            columns: 21,
            outputs: 1,
            lambda: 0.5,
            lambda_max: 2.0,
            iterations: 7,
            converged: true,
            active: 3,
            kkt: 1e-7,
            objective: -4.0,
        };
        let sse = [0u8, 0, 128, 63];
        let msgs = [
            Message::Track(Track {
                every: 100,
                solve: SolveRequest {
                    lambda_ratio: 0.0,
                    group: false,
                    standardise: true,
                },
            }),
            Message::GetEstimate,
            Message::Estimate(Estimate {
                solves: 3,
                failures: 1,
                at_sample: 300,
                summary: sum,
                count: 99,
                sse: &sse,
                last_error: &sse,
            }),
            Message::Configure(Config {
                r: 1,
                l: 2,
                s: 3,
                p: 4,
                layout: Layout::Plain,
                forgetting: 0.999,
                window: 5000,
            }),
        ];
        for m in msgs {
            let mut raw = [0u8; 128];
            let mut out = [0u8; 140];
            let n = encode_frame(9, &m, &mut raw, &mut out).unwrap();
            let mut f = out[..n - 1].to_vec();
            assert_eq!(decode_frame(&mut f).unwrap().msg, m);
        }
    }

    #[test]
    fn deframer_resyncs_and_reports_oversize() {
        let mut d = Deframer::<8>::new();
        let mut frames = 0;
        let mut over = 0;
        for &b in &[1u8, 2, 0, 0, 9, 9, 9, 9, 9, 9, 9, 9, 9, 9, 0, 3, 3, 0] {
            match d.push(b) {
                Event::Frame(_) => frames += 1,
                Event::Oversize => over += 1,
                Event::Pending => {}
            }
        }
        assert_eq!((frames, over), (2, 1));
        assert_eq!(max_raw(512), 508);
        assert!(cobs_max_len(max_raw(512)) < 512);
    }
}
