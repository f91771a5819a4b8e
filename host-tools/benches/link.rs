//! Throughput of the device link (docs/bench-device.md): samples per second from the host's
//! `Link` through a pseudo-terminal pair into
//! - `pty/engine`: the core's device engine (f32, extended statistics, p = 3), updating its
//!   statistics for every sample;
//! - `pty/ack-only`: a responder that decodes the same frames and acknowledges them without
//!   touching any statistics (the cost of the transport and the framing alone);
//! - `in-process/engine`: the engine fed the same encoded frames directly, no transport (the
//!   cost of decoding and updating alone).
//!
//! Run: `cargo bench -p lpvid-host --bench link`.

use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lpvid::device::DefaultDevice;
use lpvid::protocol::{
    decode_frame, encode_frame, max_raw, Deframer, Event, Info, Message, Status, VERSION,
};
use lpvid::{PbsidDims, StatsLayout};
use lpvid_host::link::{f64_to_values, serve, Link, LinkOptions};
use serialport::{SerialPort, TTYPort};

const N: usize = 2000;
const P: usize = 3;

fn rows() -> Vec<f64> {
    (0..N)
        .flat_map(|k| {
            let t = k as f64;
            [
                (0.7 * t).sin(),
                (0.3 * t).cos() + 0.1 * (1.3 * t).sin(),
                (0.2 * std::f64::consts::PI * t).cos() + 0.2,
            ]
        })
        .collect()
}

/// Acknowledge every request without any statistics: the framing and transport alone.
fn ack_only(port: &mut TTYPort, stop: &AtomicBool) {
    let mut d = Box::new(Deframer::<512>::new());
    let mut raw = [0u8; 512];
    let mut tx = [0u8; 512];
    let mut buf = [0u8; 4096];
    let mut next = 0u32;
    while !stop.load(Ordering::Relaxed) {
        let n = match port.read(&mut buf) {
            Ok(n) => n,
            Err(_) => continue,
        };
        for &b in &buf[..n] {
            let Event::Frame(f) = d.push(b) else { continue };
            let Ok(pkt) = decode_frame(f) else { continue };
            let reply = match pkt.msg {
                Message::Hello { .. } => Message::Info(Info {
                    version: VERSION,
                    float_bytes: 4,
                    max_frame: max_raw(512) as u16,
                    window_cap: 0,
                    gram_cap: 0,
                    vector_cap: 0,
                    solver_cap: 0,
                    model_cap: 0,
                    max_channels: 32,
                    capabilities: 0,
                }),
                Message::Samples { first, values } => {
                    next = first + (values.len() / 12) as u32;
                    Message::Status(Status {
                        configured: true,
                        r: 1,
                        l: 1,
                        s: 1,
                        p: P as u8,
                        next_sample: next,
                        windows: 0,
                        gram_len: 0,
                        duplicate_samples: 0,
                        frames_ok: 0,
                        frames_rejected: 0,
                        model_loaded: false,
                        forgetting: 1.0,
                        window: 0,
                        weight: 0.0,
                        solves: 0,
                    })
                }
                Message::Reset => {
                    next = 0;
                    Message::Ack
                }
                _ => Message::Ack,
            };
            let _ = next;
            if let Ok(k) = encode_frame(pkt.seq, &reply, &mut raw, &mut tx) {
                let _ = port.write_all(&tx[..k]);
            }
        }
    }
}

fn pty_link(engine: bool) -> (Link<TTYPort>, Arc<AtomicBool>, std::thread::JoinHandle<()>) {
    let (mut host, mut far) = TTYPort::pair().expect("pseudo-terminal pair");
    host.set_timeout(Duration::from_millis(5)).unwrap();
    far.set_timeout(Duration::from_millis(5)).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let h = std::thread::Builder::new()
        .stack_size(8 << 20)
        .spawn(move || {
            if engine {
                let mut dev = Box::new(DefaultDevice::<f32>::new());
                let _ = serve(&mut far, &mut *dev, &s);
            } else {
                ack_only(&mut far, &s);
            }
        })
        .unwrap();
    let mut link = Link::new(host, LinkOptions::default());
    link.hello().unwrap();
    link.configure(&PbsidDims::new(1, 1, 1, P).unwrap(), StatsLayout::Extended)
        .unwrap();
    (link, stop, h)
}

fn bench_link(c: &mut Criterion) {
    let data = rows();
    let mut g = c.benchmark_group("device-link");
    g.throughput(Throughput::Elements(N as u64));
    g.sample_size(20);
    g.measurement_time(Duration::from_secs(6));
    for (name, engine) in [("pty/engine", true), ("pty/ack-only", false)] {
        let (mut link, stop, h) = pty_link(engine);
        g.bench_function(name, |b| {
            b.iter(|| {
                link.reset().unwrap();
                link.stream(&data, 3, 0, |_| {}).unwrap()
            })
        });
        stop.store(true, Ordering::Relaxed);
        drop(link);
        let _ = h.join();
    }
    // the engine alone: the same frames, no transport
    let mut frames = Vec::new();
    let mut raw = [0u8; 512];
    let mut out = [0u8; 512];
    let bs = (max_raw(512) - lpvid::protocol::MESSAGE_HEADROOM) / 12;
    let mut vals = Vec::new();
    let mut seq = 10;
    let cfg = lpvid::protocol::Config {
        r: 1,
        l: 1,
        s: 1,
        p: P as u8,
        layout: lpvid::protocol::Layout::Extended,
        forgetting: 1.0,
        window: 0,
    };
    let n = encode_frame(1, &Message::Configure(cfg), &mut raw, &mut out).unwrap();
    let configure = out[..n].to_vec();
    let mut first = 0;
    while first < N {
        let k = bs.min(N - first);
        f64_to_values(&data[first * 3..(first + k) * 3], 4, &mut vals);
        let n = encode_frame(
            seq,
            &Message::Samples {
                first: first as u32,
                values: &vals,
            },
            &mut raw,
            &mut out,
        )
        .unwrap();
        frames.extend_from_slice(&out[..n]);
        seq += 1;
        first += k;
    }
    let mut dev = Box::new(DefaultDevice::<f32>::new());
    g.bench_function("in-process/engine", |b| {
        b.iter(|| {
            dev.handle(&configure, |_| {});
            let mut replies = 0;
            dev.handle(&frames, |_| replies += 1);
            assert_eq!(dev.status().next_sample as usize, N);
            replies
        })
    });
    g.finish();
}

criterion_group!(benches, bench_link);
criterion_main!(benches);
