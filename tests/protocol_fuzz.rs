//! Property tests of the frame decoder and the device engine (DESIGN.md section 7, "every
//! parser and decoder is fuzzed"): no panic, no out-of-bounds access, every invalid frame
//! rejected with a reason, valid frames round-trip, and the engine resynchronises after
//! any garbage.
//!
//! CI runs a few thousand cases per property. The documented long run (docs/bench-device.md):
//! `PROPTEST_CASES=1000000 cargo test --release -p lpvid --test protocol_fuzz`.

use lpvid::device::DefaultDevice;
use lpvid::protocol::{
    cobs_decode_in_place, decode_frame, encode_frame, Config, Deframer, ErrorCode, ErrorReply,
    Event, Layout, Message, ModelChunk, Packet, SolveRequest, Status, MESSAGE_VARIANTS,
};
use proptest::prelude::*;

fn cases(ci: u32) -> ProptestConfig {
    let n = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(ci);
    ProptestConfig {
        cases: n,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// Decoder rejections: only the frame-level reasons.
fn is_frame_reason(c: ErrorCode) -> bool {
    c.is_frame_error()
}

/// Messages with arbitrary fields (value slices from `bytes`).
fn message(kind: u8, a: u32, b: u16, f: f32, bytes: &[u8]) -> Message<'_> {
    match kind % 20 {
        0 => Message::Hello { version: a as u8 },
        1 => Message::GetStatus,
        2 => Message::Configure(Config {
            r: a as u8,
            l: (a >> 8) as u8,
            s: (a >> 16) as u8,
            p: b as u8,
            layout: if a & 1 == 0 {
                Layout::Plain
            } else {
                Layout::Extended
            },
            forgetting: f,
            window: 0,
        }),
        3 => Message::Samples {
            first: a,
            values: bytes,
        },
        4 => Message::PullStats {
            offset: a,
            count: b,
        },
        5 => Message::Values {
            offset: a,
            total: a ^ b as u32,
            values: bytes,
        },
        6 => Message::Solve(SolveRequest {
            lambda_ratio: f,
            group: a & 1 == 1,
            standardise: a & 2 == 2,
        }),
        7 => Message::PullSolution {
            offset: a,
            count: b,
        },
        8 => Message::PushModel(ModelChunk {
            n: b,
            scheduled_output: a & 1 == 1,
            offset: a,
            total: a.wrapping_mul(3),
            values: bytes,
        }),
        9 => Message::Reset,
        10 => Message::Ack,
        11 => Message::Error(ErrorReply {
            code: ErrorCode::Gap,
            detail: a,
        }),
        12 => Message::GetPrediction,
        13 => Message::Status(Status {
            configured: a & 1 == 1,
            r: 1,
            l: 2,
            s: 3,
            p: 4,
            next_sample: a,
            windows: a as u64 * 7,
            gram_len: b as u32,
            duplicate_samples: 0,
            frames_ok: a,
            frames_rejected: b as u32,
            model_loaded: false,
            forgetting: f,
            window: b as u32,
            weight: f,
            solves: a,
        }),
        14 => Message::Prediction(lpvid::protocol::Prediction {
            count: a,
            sse: bytes,
            last: bytes,
        }),
        15 => Message::Solved(lpvid::protocol::SolveSummary {
            columns: a,
            outputs: b as u8,
            lambda: f,
            lambda_max: f,
            iterations: a,
            converged: true,
            active: b as u32,
            kkt: f,
            objective: f,
        }),
        16 => Message::Track(lpvid::protocol::Track {
            every: a,
            solve: SolveRequest {
                lambda_ratio: f,
                group: a & 1 == 1,
                standardise: a & 2 == 2,
            },
        }),
        17 => Message::GetEstimate,
        18 => Message::Estimate(lpvid::protocol::Estimate {
            solves: a,
            failures: b as u32,
            at_sample: a ^ 5,
            summary: lpvid::protocol::SolveSummary {
                columns: a,
                outputs: b as u8,
                lambda: f,
                lambda_max: f,
                iterations: a,
                converged: false,
                active: b as u32,
                kkt: f,
                objective: f,
            },
            count: a,
            sse: bytes,
            last_error: bytes,
        }),
        _ => Message::Info(lpvid::protocol::Info {
            version: 1,
            float_bytes: 4,
            max_frame: b,
            window_cap: a,
            gram_cap: a,
            vector_cap: a,
            solver_cap: a,
            model_cap: a,
            max_channels: b,
            capabilities: a,
        }),
    }
}

fn encode(seq: u32, msg: &Message<'_>) -> Vec<u8> {
    let mut raw = vec![0u8; 2048];
    let mut out = vec![0u8; 2100];
    let n = encode_frame(seq, msg, &mut raw, &mut out).unwrap();
    out.truncate(n);
    out
}

/// NaN-tolerant equality of packets (a NaN float field round-trips bit-exactly).
fn same(a: &Packet<'_>, b: &Packet<'_>) -> bool {
    format!("{a:?}") == format!("{b:?}")
}

#[test]
fn variant_count_matches_the_decoder() {
    // the last variant encodes as index MESSAGE_VARIANTS - 1 (the decoder's bound)
    let f = encode(
        1,
        &Message::Estimate(lpvid::protocol::Estimate {
            solves: 0,
            failures: 0,
            at_sample: 0,
            summary: lpvid::protocol::SolveSummary {
                columns: 0,
                outputs: 0,
                lambda: 0.0,
                lambda_max: 0.0,
                iterations: 0,
                converged: false,
                active: 0,
                kkt: 0.0,
                objective: 0.0,
            },
            count: 0,
            sse: &[],
            last_error: &[],
        }),
    );
    let mut body = f[..f.len() - 1].to_vec();
    let n = cobs_decode_in_place(&mut body).unwrap();
    assert_eq!(body[2] as u32, MESSAGE_VARIANTS - 1);
    assert!(n > 3);
}

proptest! {
    #![proptest_config(cases(2000))]

    /// Valid frames round-trip.
    #[test]
    fn valid_frames_round_trip(seq: u32, kind: u8, a: u32, b: u16, f: f32,
                               bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let msg = message(kind, a, b, f, &bytes);
        let frame = encode(seq, &msg);
        prop_assert_eq!(*frame.last().unwrap(), 0);
        prop_assert!(!frame[..frame.len() - 1].contains(&0));
        let mut body = frame[..frame.len() - 1].to_vec();
        let pkt = decode_frame(&mut body).unwrap();
        let want = Packet { seq, msg };
        prop_assert!(same(&pkt, &want));
    }

    /// Arbitrary bytes: never a panic, and a rejection always carries a frame-level reason.
    #[test]
    fn arbitrary_bytes_never_panic(mut bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        if let Err(code) = decode_frame(&mut bytes) {
            prop_assert!(is_frame_reason(code), "{:?}", code);
        }
    }

    /// A valid frame with random damage (bit flips, deletions, insertions, truncation,
    /// duplicated bytes): rejected with a reason, or decoded to exactly the original.
    #[test]
    fn damaged_frames_are_rejected(seq: u32, kind: u8, a: u32, b: u16, f: f32,
                                   bytes in proptest::collection::vec(any::<u8>(), 0..200),
                                   edits in proptest::collection::vec((0u8..5, any::<u32>(), any::<u8>()), 1..4)) {
        let msg = message(kind, a, b, f, &bytes);
        let frame = encode(seq, &msg);
        let mut body = frame[..frame.len() - 1].to_vec();
        let original = body.clone();
        for (op, at, v) in edits {
            let i = at as usize % body.len().max(1);
            match op {
                0 if !body.is_empty() => body[i] ^= 1 << (v % 8),
                1 if !body.is_empty() => { body.remove(i); }
                2 => body.insert(i.min(body.len()), v),
                3 => body.truncate(i),
                _ if !body.is_empty() => { let x = body[i]; body.insert(i, x); }
                _ => {}
            }
        }
        let changed = body != original;
        match decode_frame(&mut body) {
            Err(code) => prop_assert!(is_frame_reason(code)),
            Ok(pkt) => {
                prop_assert!(same(&pkt, &Packet { seq, msg }), "damaged frame accepted as something else");
                let _ = changed;
            }
        }
    }

    /// One flipped bit anywhere is always caught (CRC-32 detects all 1-3 bit errors here).
    #[test]
    fn single_bit_flips_are_always_caught(seq: u32, kind: u8, a: u32, b: u16, f: f32,
                                          bytes in proptest::collection::vec(any::<u8>(), 0..300),
                                          at: u32, bit in 0u8..8) {
        let msg = message(kind, a, b, f, &bytes);
        let frame = encode(seq, &msg);
        let mut body = frame[..frame.len() - 1].to_vec();
        let i = at as usize % body.len();
        body[i] ^= 1 << bit;
        if body[i] != 0 {
            prop_assert!(decode_frame(&mut body).is_err());
        }
    }

    /// The deframer never overruns and reports an over-long frame once.
    #[test]
    fn deframer_bounds(bytes in proptest::collection::vec(any::<u8>(), 0..2000)) {
        let mut d = Deframer::<64>::new();
        for b in bytes {
            match d.push(b) {
                Event::Frame(f) => prop_assert!(!f.is_empty() && f.len() <= 64),
                Event::Oversize | Event::Pending => {}
            }
            prop_assert!(d.pending() <= 64);
        }
    }
}

proptest! {
    #![proptest_config(cases(300))]

    /// The device engine on arbitrary input: no panic, and afterwards a delimiter plus a
    /// valid Hello always gets its Info reply (resynchronisation).
    #[test]
    fn device_survives_garbage_and_resyncs(garbage in proptest::collection::vec(any::<u8>(), 0..3000),
                                           seq in 1u32..u32::MAX) {
        let mut dev = Box::new(DefaultDevice::<f32>::new());
        let mut replies = 0usize;
        dev.handle(&garbage, |_| replies += 1);
        let mut frame = vec![0u8];
        frame.extend(encode(seq, &Message::Hello { version: 1 }));
        let mut got = None;
        dev.handle(&frame, |f| {
            let mut body = f[..f.len() - 1].to_vec();
            if let Ok(p) = decode_frame(&mut body) {
                if p.seq == seq {
                    got = Some(matches!(p.msg, Message::Info(_)));
                }
            }
        });
        prop_assert_eq!(got, Some(true));
    }

    /// Valid frames with arbitrary contents (any message, any field values) against a
    /// configured device: no panic, and a reply for every request.
    #[test]
    fn device_survives_arbitrary_requests(reqs in proptest::collection::vec(
        (any::<u8>(), any::<u32>(), any::<u16>(), any::<f32>(), proptest::collection::vec(any::<u8>(), 0..300)), 1..20)) {
        let mut dev = Box::new(DefaultDevice::<f32>::new());
        let cfg = encode(1, &Message::Configure(Config { r: 1, l: 1, s: 1, p: 2, layout: Layout::Extended, forgetting: 1.0, window: 0 }));
        dev.handle(&cfg, |_| {});
        for (i, (kind, a, b, f, bytes)) in reqs.iter().enumerate() {
            let msg = message(*kind, *a, *b, *f, bytes);
            let frame = encode(i as u32 + 2, &msg);
            let mut n = 0;
            dev.handle(&frame, |_| n += 1);
            prop_assert_eq!(n, 1);
        }
    }
}
