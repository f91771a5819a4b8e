//! The device engine without a transport: exactly-once sample accounting, retransmissions
//! answered from the cache, and zero heap allocations while it handles frames (a counting
//! global allocator watches this thread).

use lpvid::device::DefaultDevice;
use lpvid::protocol::{
    decode_frame, encode_frame, write_values, Config, ErrorCode, Layout, Message, ModelChunk,
    SolveRequest,
};

mod common;

use common::counting_alloc::{self, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

type Dev = DefaultDevice<f32>;

/// Encode into fixed arrays (no allocation on the test's side either).
fn frame(seq: u32, msg: &Message<'_>, out: &mut [u8; 600]) -> usize {
    let mut raw = [0u8; 600];
    encode_frame(seq, msg, &mut raw, out).unwrap()
}

/// What the device answered: (seq, reply kind, error code if any) of the last reply.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Seen {
    seq: u32,
    ok: bool,
    code: Option<ErrorCode>,
    next: Option<u32>,
    windows: Option<u64>,
}

fn handle(dev: &mut Dev, bytes: &[u8]) -> Option<Seen> {
    let mut seen = None;
    dev.handle(bytes, |f| {
        let mut buf = [0u8; 600];
        let n = f.len() - 1;
        buf[..n].copy_from_slice(&f[..n]);
        if let Ok(p) = decode_frame(&mut buf[..n]) {
            seen = Some(match p.msg {
                Message::Error(e) => Seen {
                    seq: p.seq,
                    ok: false,
                    code: Some(e.code),
                    next: None,
                    windows: None,
                },
                Message::Status(s) => Seen {
                    seq: p.seq,
                    ok: true,
                    code: None,
                    next: Some(s.next_sample),
                    windows: Some(s.windows),
                },
                _ => Seen {
                    seq: p.seq,
                    ok: true,
                    code: None,
                    next: None,
                    windows: None,
                },
            });
        }
    });
    seen
}

/// A `Samples` frame of 10 samples from stream index `first`.
fn samples_frame(seq: u32, first: usize, out: &mut [u8; 600]) -> usize {
    let mut vb = [0u8; 480];
    let m = samples_bytes(first, 10, &mut vb);
    let msg = Message::Samples {
        first: first as u32,
        values: &vb[..m],
    };
    frame(seq, &msg, out)
}

fn samples_bytes(first: usize, n: usize, out: &mut [u8; 480]) -> usize {
    let mut vals = [0f32; 120];
    for i in 0..n {
        let k = (first + i) as f32;
        vals[3 * i] = (0.7 * k).sin();
        vals[3 * i + 1] = (0.3 * k).cos();
        vals[3 * i + 2] = 0.5 + 0.2 * (0.1 * k).sin();
    }
    write_values(&vals[..3 * n], out).unwrap()
}

#[test]
fn exactly_once_and_zero_allocations() {
    let mut dev = Box::new(Dev::new());
    let mut buf = [0u8; 600];
    let cfg = Config {
        r: 1,
        l: 1,
        s: 1,
        p: 3,
        layout: Layout::Extended,
        forgetting: 1.0,
        window: 0,
    };

    counting_alloc::start();
    let n = frame(7, &Message::Hello { version: 1 }, &mut buf);
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    let n = frame(8, &Message::Configure(cfg), &mut buf);
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);

    // 40 samples in 4 frames
    let mut seq = 9;
    for b in 0..4 {
        let n = samples_frame(seq, 10 * b, &mut buf);
        let s = handle(&mut dev, &buf[..n]).unwrap();
        assert_eq!(s.next, Some(10 * (b as u32 + 1)));
        // the same frame again (a retransmission): answered from the cache, not applied
        let s2 = handle(&mut dev, &buf[..n]).unwrap();
        assert_eq!(s, s2);
        seq += 1;
    }
    assert_eq!(dev.status().next_sample, 40);
    assert_eq!(dev.status().windows, 37);
    // the last batch as a new request: duplicates acknowledged, not re-applied
    let n = samples_frame(seq, 30, &mut buf);
    seq += 1;
    let s = handle(&mut dev, &buf[..n]).unwrap();
    assert_eq!((s.next, s.windows), (Some(40), Some(37)));
    assert_eq!(dev.status().duplicate_samples, 10);
    // a gap is an error, not hidden
    let n = samples_frame(seq, 50, &mut buf);
    seq += 1;
    assert_eq!(
        handle(&mut dev, &buf[..n]).unwrap().code,
        Some(ErrorCode::Gap)
    );
    assert_eq!(dev.status().next_sample, 40);

    // corrupted, truncated and garbage frames: NAKs with reasons, nothing changes
    let n = samples_frame(seq, 40, &mut buf);
    let mut bad = buf;
    bad[n / 2] ^= 0x10;
    let s = handle(&mut dev, &bad[..n]).unwrap();
    assert_eq!((s.seq, s.ok), (0, false));
    let mut cut = buf;
    cut[n / 2] = 0;
    handle(&mut dev, &cut[..n / 2 + 1]);
    handle(&mut dev, &[0x13, 0x37, 0xFF, 0x00, 0x00, 0x42, 0x00]);
    assert_eq!(dev.status().next_sample, 40);
    // the intact frame after all that
    let s = handle(&mut dev, &buf[..n]).unwrap();
    assert_eq!(s.next, Some(50));
    seq += 1;

    // pull, solve, model, prediction, reset: no allocation either
    let n = frame(
        seq,
        &Message::PullStats {
            offset: 100,
            count: 50,
        },
        &mut buf,
    );
    seq += 1;
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    let n = frame(
        seq,
        &Message::Solve(SolveRequest {
            lambda_ratio: 0.05,
            group: true,
            standardise: true,
        }),
        &mut buf,
    );
    seq += 1;
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    let n = frame(
        seq,
        &Message::PullSolution {
            offset: 0,
            count: 100,
        },
        &mut buf,
    );
    seq += 1;
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    // n = 1, r = l = 1, m = 2: A (2), B (2), K (2), C, D
    let model = [0.5f32, 0.1, 1.0, 0.2, 0.3, 0.0, 1.0, 0.0];
    let mut mb = [0u8; 32];
    write_values(&model, &mut mb).unwrap();
    let n = frame(
        seq,
        &Message::PushModel(ModelChunk {
            n: 1,
            scheduled_output: false,
            offset: 0,
            total: 8,
            values: &mb,
        }),
        &mut buf,
    );
    seq += 1;
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    assert!(dev.status().model_loaded);
    let n = samples_frame(seq, 50, &mut buf);
    seq += 1;
    assert_eq!(handle(&mut dev, &buf[..n]).unwrap().next, Some(60));
    let n = frame(seq, &Message::GetPrediction, &mut buf);
    seq += 1;
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    let n = frame(seq, &Message::Reset, &mut buf);
    assert!(handle(&mut dev, &buf[..n]).unwrap().ok);
    let allocs = counting_alloc::stop();

    assert_eq!(dev.status().next_sample, 0);
    assert_eq!(dev.status().windows, 0);
    assert_eq!(allocs, 0, "the device engine allocated");
}

#[test]
fn configuration_errors_are_values() {
    let mut dev = Box::new(Dev::new());
    let mut buf = [0u8; 600];
    let bad = [
        (
            Config {
                r: 1,
                l: 0,
                s: 1,
                p: 3,
                layout: Layout::Plain,
                forgetting: 1.0,
                window: 0,
            },
            ErrorCode::BadConfig,
        ),
        (
            Config {
                r: 1,
                l: 1,
                s: 1,
                p: 9,
                layout: Layout::Extended,
                forgetting: 1.0,
                window: 0,
            },
            ErrorCode::Capacity,
        ),
        (
            Config {
                r: 1,
                l: 1,
                s: 1,
                p: 2,
                layout: Layout::Extended,
                forgetting: 1.5,
                window: 0,
            },
            ErrorCode::Unsupported,
        ),
        (
            // protocol 2: forgetting and a sliding window are alternatives
            Config {
                r: 1,
                l: 1,
                s: 1,
                p: 2,
                layout: Layout::Extended,
                forgetting: 0.99,
                window: 100,
            },
            ErrorCode::Unsupported,
        ),
        (
            Config {
                r: 1,
                l: 1,
                s: 1,
                p: 2,
                layout: Layout::Extended,
                forgetting: 1.0,
                window: 1,
            },
            ErrorCode::Unsupported,
        ),
    ];
    for (i, (cfg, code)) in bad.iter().enumerate() {
        let n = frame(i as u32 + 1, &Message::Configure(*cfg), &mut buf);
        assert_eq!(handle(&mut dev, &buf[..n]).unwrap().code, Some(*code));
    }
    assert!(!dev.status().configured);
    let n = frame(9, &Message::Reset, &mut buf);
    assert_eq!(
        handle(&mut dev, &buf[..n]).unwrap().code,
        Some(ErrorCode::NotConfigured)
    );
    // a reply-type message sent to the device
    let n = frame(10, &Message::Ack, &mut buf);
    assert_eq!(
        handle(&mut dev, &buf[..n]).unwrap().code,
        Some(ErrorCode::UnexpectedMessage)
    );
}
