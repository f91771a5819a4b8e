//! `lpvid device`: talk to a device over a serial port (info, stream a file, pull the
//! statistics and identify from them through [`crate::pipeline::identify_from_stats`], solve
//! on the device, push a model, reset, watch the device's recursive estimate).

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::{Args, Subcommand};
use lpvid::protocol::{Info, SolveRequest, Track};
use lpvid::{packed_len, stat_vector_len, PbsidDims, StatsLayout};
use serde_json::{json, Value};

use super::files::{check_paths, Outputs};
use super::{CliError, Ui};
use crate::data::Dataset;
use crate::link::watch::{WatchHistory, WatchRecord};
use crate::link::{
    compare_as_device, extended_gram, open_port, replay_tracking, sample_rows, Accumulation, Link,
    LinkError, LinkOptions, ReplayPoint,
};
use crate::lpvss::Signals;
use crate::model::{ModelFile, ModelKind, SignalMap};
use crate::pbsid::{Order, PbsidOptions, Reg};
use crate::pipeline;

/// `lpvid device`: talk to a device (firmware or emulator) over a serial port.
#[derive(Debug, Args)]
pub struct DeviceArgs {
    /// Serial port (e.g. /dev/ttyACM0, or the /dev/pts/N QEMU prints).
    #[arg(long)]
    port: PathBuf,
    /// Reply timeout in milliseconds before a retransmission, for every request including
    /// the first handshake (default: 500, and 3000 for the first reply of a session, which a
    /// QEMU pseudo-terminal can hold for about a second).
    #[arg(long)]
    timeout_ms: Option<u64>,
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
    /// Configure, start the device's recursive estimate (a solve every --every samples,
    /// warm-started) and stream a file, showing the estimate as it goes: a progress line,
    /// a plot file refreshed now and then, or JSON lines (--json).
    Watch(WatchArgs),
}

/// How the device accumulates (protocol 2).
#[derive(Debug, Args)]
struct AccArgs {
    /// Exponential forgetting factor lambda in (0, 1] per statistic vector (memory about
    /// 1/(1 - lambda) vectors; 1: none).
    #[arg(long, value_name = "LAMBDA", default_value_t = 1.0)]
    forgetting: f32,
    /// Sliding window: keep the last N/2 .. N - 1 statistic vectors (0: the whole stream;
    /// exclusive with --forgetting).
    #[arg(long, value_name = "N", default_value_t = 0)]
    window: u32,
}

impl AccArgs {
    fn accumulation(&self) -> Accumulation {
        Accumulation {
            forgetting: self.forgetting,
            window: self.window,
        }
    }
}

#[derive(Debug, Args)]
struct WatchArgs {
    /// Data file (CSV: u1.., y1.., p1..).
    file: PathBuf,
    /// Past window p.
    #[arg(long, default_value_t = 3)]
    past: usize,
    /// Accumulate the plain statistics of problem (13) only.
    #[arg(long)]
    plain: bool,
    #[command(flatten)]
    acc: AccArgs,
    /// Samples between the device's solves.
    #[arg(long, value_name = "K", default_value_t = 500)]
    every: u32,
    /// lambda as a fraction of lambda_max (0: the least-squares PBSID/VARX regression).
    #[arg(long, default_value_t = 0.0)]
    lambda_ratio: f32,
    /// l2,1 (group) penalty instead of l1.
    #[arg(long)]
    group: bool,
    /// Penalise raw instead of standardised coefficients.
    #[arg(long)]
    raw: bool,
    /// Write an SVG plot of the one-step error and the coefficients here, refreshed every
    /// --plot-every reports and at the end.
    #[arg(long, value_name = "FILE.svg")]
    plot: Option<PathBuf>,
    /// Reports between plot refreshes.
    #[arg(long, default_value_t = 10)]
    plot_every: usize,
    /// Replay the estimate on the host in the device's float type with the core's code and
    /// fail unless every report equals it bit for bit.
    #[arg(long)]
    compare: bool,
    /// Largest number of samples per frame (default: as many as fit).
    #[arg(long, default_value_t = 0)]
    batch: usize,
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
    #[command(flatten)]
    acc: AccArgs,
}

#[derive(Debug, Args)]
struct PullArgs {
    /// Write the model identified from the statistics here (JSON).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the raw statistics here (JSON: dimensions, windows, packed Gram).
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Write the statistics here in the mergeable binary encoding (docs/wire.md section 7),
    /// for `lpvid pbsid --stats A --stats B ...` (extended statistics only).
    #[arg(long, value_name = "S.lpvs")]
    stats_out: Option<PathBuf>,
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
    CliError::Lib(e.into())
}

fn w(out: &mut dyn Write, s: String) -> Result<(), CliError> {
    writeln!(out, "{s}")?;
    Ok(())
}

/// What a device command reads from local files, read and checked before the port is
/// opened (a bad file fails at once, not after a handshake).
enum Local {
    None,
    Stream(Dataset, Signals, PbsidDims),
    Watch(Dataset, Signals, PbsidDims),
    Push(ModelFile),
    Pull(Option<(Dataset, Signals)>),
}

/// Read and check the local inputs of `a`, and check its outputs can be written.
fn local_inputs(a: &DeviceArgs) -> Result<Local, CliError> {
    Ok(match &a.action {
        DeviceAction::Stream(s) => {
            let ds = Dataset::read_csv(&s.file)?;
            let map = SignalMap::default_for(&ds)?;
            let sig = map.evaluate(&ds)?;
            let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), s.past)
                .map_err(|e| CliError::Invalid(format!("{}: {e}", ds.source)))?;
            Local::Stream(ds, sig, dims)
        }
        DeviceAction::Watch(wa) => {
            if let Some(plot) = &wa.plot {
                check_paths(
                    &[("--port", a.port.as_path()), ("FILE", wa.file.as_path())],
                    &[("--plot", plot.as_path())],
                )?;
            }
            let ds = Dataset::read_csv(&wa.file)?;
            let map = SignalMap::default_for(&ds)?;
            let sig = map.evaluate(&ds)?;
            let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), wa.past)
                .map_err(|e| CliError::Invalid(format!("{}: {e}", ds.source)))?;
            Local::Watch(ds, sig, dims)
        }
        DeviceAction::Push(p) => {
            let mf = super::diagnose::read_model(&p.model)?;
            let ModelKind::Ss(m) = &mf.kind else {
                return Err(CliError::Invalid(format!(
                    "{}: the device predictor runs lpv-ss models only",
                    p.model.display()
                )));
            };
            m.validate()
                .map_err(|e| CliError::Invalid(format!("{}: {e}", p.model.display())))?;
            if let Some(at) = mf.signals.first_non_standard() {
                return Err(CliError::Invalid(format!(
                    "{}: signal map: {at}: the device predictor reads its frame's channels \
                     u1.., y1.., p1.. unchanged (no power, delay, function, \"smooth\" or \
                     own-output factor); push a model with the plain map, or compute the \
                     signal before it reaches the device",
                    p.model.display()
                )));
            }
            Local::Push(mf)
        }
        DeviceAction::Pull(p) => {
            let mut inputs = vec![("--port", a.port.as_path())];
            if let Some(c) = &p.compare {
                inputs.push(("--compare", c.as_path()));
            }
            let mut outs = Vec::new();
            if let Some(o) = &p.out {
                outs.push(("--out", o.as_path()));
            }
            if let Some(o) = &p.stats {
                outs.push(("--stats", o.as_path()));
            }
            if let Some(o) = &p.stats_out {
                outs.push(("--stats-out", o.as_path()));
            }
            check_paths(&inputs, &outs)?;
            match &p.compare {
                Some(c) => {
                    let ds = Dataset::read_csv(c)?;
                    let sig = SignalMap::default_for(&ds)?.evaluate(&ds)?;
                    Local::Pull(Some((ds, sig)))
                }
                None => Local::Pull(None),
            }
        }
        _ => Local::None,
    })
}

/// The link settings `a` asks for: `--timeout-ms` applies to every wait, the first
/// handshake included.
fn link_options(a: &DeviceArgs) -> LinkOptions {
    let d = LinkOptions::default();
    LinkOptions {
        timeout: a.timeout_ms.map_or(d.timeout, Duration::from_millis),
        first_timeout: a.timeout_ms.map_or(d.first_timeout, Duration::from_millis),
        retries: a.retries,
        batch: match &a.action {
            DeviceAction::Stream(s) => s.batch,
            DeviceAction::Watch(s) => s.batch,
            _ => 0,
        },
    }
}

/// What the handshake waits for, in words.
fn waiting_note(port: &std::path::Path, o: &LinkOptions) -> String {
    let (first, next) = (o.first_timeout.as_millis(), o.timeout.as_millis());
    let schedule = if first == next {
        format!("{next} ms x {} attempts", o.retries + 1)
    } else {
        format!(
            "first reply up to {first} ms, then {next} ms x {} retries",
            o.retries
        )
    };
    format!(
        "waiting for the device on {} (handshake, {schedule}; --timeout-ms and --retries \
         change this)",
        port.display()
    )
}

/// Run `lpvid device ...`.
pub(super) fn run(a: &DeviceArgs, ui: Ui, out: &mut dyn Write) -> Result<(), CliError> {
    let local = local_inputs(a)?;
    let opts = link_options(a);
    let port = open_port(&a.port).map_err(link_err)?;
    let mut link = Link::new(port, opts);
    if !a.json {
        ui.note(&waiting_note(&a.port, &opts));
    }
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
        DeviceAction::Stream(s) => {
            let Local::Stream(ds, sig, dims) = local else {
                unreachable!("stream reads its file first")
            };
            stream_cmd(&mut link, s, (&ds, &sig, dims), a.json || !ui.progress())
        }
        DeviceAction::Pull(p) => {
            let Local::Pull(cmp) = local else {
                unreachable!("pull reads its --compare file first")
            };
            pull_cmd(&mut link, p, &info, cmp.as_ref())
        }
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
            let Local::Push(mf) = local else {
                unreachable!("push reads its model first")
            };
            let ModelKind::Ss(m) = &mf.kind else {
                unreachable!("checked by local_inputs")
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
        DeviceAction::Watch(wa) => {
            let Local::Watch(ds, sig, dims) = local else {
                unreachable!("watch reads its file first")
            };
            watch_cmd(&mut link, wa, &info, (&ds, &sig, dims), a.json, ui, out)
        }
    }?;
    let ls = link.stats();
    let mut result = result;
    result["link"] = serde_json::to_value(ls).unwrap_or(Value::Null);
    if a.json && matches!(a.action, DeviceAction::Watch(_)) {
        // JSON lines: the summary is the last line
        w(out, serde_json::to_string(&result).unwrap_or_default())?;
    } else if a.json {
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
    (ds, sig, dims): (&Dataset, &Signals, PbsidDims),
    no_bar: bool,
) -> Result<Value, CliError> {
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
            return Err(CliError::Invalid(
                "--resume: the device is not configured for this file's dimensions".into(),
            ));
        }
        st.next_sample
    } else {
        link.configure_with(&dims, layout, s.acc.accumulation())
            .map_err(link_err)?;
        0
    };
    let rows = sample_rows(sig);
    let per = dims.r + dims.l + dims.s;
    let n = sig.len();
    let skip = (first as usize).min(n);
    let bar = if !no_bar {
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
    compare: Option<&(Dataset, Signals)>,
) -> Result<Value, CliError> {
    let mut outputs = Outputs::default();
    let (st, vals) = link.pull_stats().map_err(link_err)?;
    let dims = PbsidDims::new(st.r as usize, st.l as usize, st.s as usize, st.p as usize)
        .map_err(|e| CliError::Invalid(format!("device dimensions: {e}")))?;
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
        outputs.bytes(
            path,
            serde_json::to_string(&v).unwrap_or_default().as_bytes(),
        )?;
        res["stats_file"] = json!(path.display().to_string());
    }
    if let Some(path) = &p.stats_out {
        if layout != StatsLayout::Extended {
            return Err(CliError::Invalid(
                "--stats-out needs the extended statistics: stream without --plain".into(),
            ));
        }
        if st.forgetting != 1.0 || st.window != 0 {
            return Err(CliError::Invalid(
                "--stats-out writes mergeable sums: statistics with forgetting or a sliding \
                 window do not merge by addition (stream with --forgetting 1 --window 0)"
                    .into(),
            ));
        }
        let merged = crate::statistics::Statistics::from_packed(dims, &vals, st.windows, 1)?;
        outputs.bytes(path, &merged.to_bytes())?;
        res["stats_out"] = json!(path.display().to_string());
    }
    if let Some(path) = &p.out {
        if layout != StatsLayout::Extended {
            return Err(CliError::Invalid(
                "a model needs the extended statistics: stream without --plain".into(),
            ));
        }
        let gram = extended_gram(&vals, st.windows, &dims).map_err(crate::Error::from)?;
        let (mf, fit) = pipeline::identify_from_stats(
            &gram,
            &dims,
            &opts,
            json!({
                "what": "device statistics (lpvid device pull)",
                "float": if info.float_bytes == 4 {"f32"} else {"f64"},
            }),
        )?;
        outputs.model(&mf, path)?;
        res["model"] = json!({"out": path.display().to_string(), "order": fit.order,
            "singular_values": fit.singular_values});
    }
    if let (Some(path), Some((_, sig))) = (&p.compare, compare) {
        let with_model = if layout == StatsLayout::Extended {
            Some(&opts)
        } else {
            None
        };
        // the host replays the device's accumulation: its forgetting, window and storage
        let acc = Accumulation {
            forgetting: st.forgetting,
            window: st.window,
        };
        let cmp = compare_as_device(
            &vals,
            st.windows,
            info.float_bytes,
            sig,
            &dims,
            layout,
            with_model,
            acc,
            2 * info.gram_cap as usize,
        )
        .map_err(crate::Error::from)?;
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
            return Err(CliError::Invalid(format!(
                "device statistics do not match {}: {}",
                path.display(),
                bad.join("; ")
            )));
        }
    }
    outputs.commit()?;
    Ok(res)
}

/// `lpvid device watch`: configure, start tracking, stream, report every new solve.
#[allow(clippy::too_many_arguments)]
fn watch_cmd(
    link: &mut Link<serialport::TTYPort>,
    wa: &WatchArgs,
    info: &Info,
    (ds, sig, dims): (&Dataset, &Signals, PbsidDims),
    json_lines: bool,
    ui: Ui,
    out: &mut dyn Write,
) -> Result<Value, CliError> {
    let layout = if wa.plain {
        StatsLayout::Plain
    } else {
        StatsLayout::Extended
    };
    let acc = wa.acc.accumulation();
    if wa.every == 0 {
        return Err(CliError::Invalid("--every must be at least 1".into()));
    }
    let track = Track {
        every: wa.every,
        solve: SolveRequest {
            lambda_ratio: wa.lambda_ratio,
            group: wa.group,
            standardise: !wa.raw,
        },
    };
    // the host's replay first: a configuration the device cannot hold fails here too
    let replay: Option<Vec<ReplayPoint>> = if wa.compare {
        let (g, x) = (2 * info.gram_cap as usize, info.solver_cap as usize);
        let pts = if info.float_bytes == 4 {
            replay_tracking::<f32>(sig, dims.p, layout, acc, g, x, &track)
        } else {
            replay_tracking::<f64>(sig, dims.p, layout, acc, g, x, &track)
        }
        .map_err(crate::Error::from)?;
        Some(pts)
    } else {
        None
    };
    link.configure_with(&dims, layout, acc).map_err(link_err)?;
    link.track(track).map_err(link_err)?;
    let rows = sample_rows(sig);
    let per = dims.r + dims.l + dims.s;
    let n = sig.len();
    let bar = if !json_lines && ui.progress() {
        let b = indicatif::ProgressBar::new(n as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} samples {per_sec} | {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut history = WatchHistory::default();
    let mut mismatches: Vec<String> = Vec::new();
    let mut compared = 0usize;
    let mut io_err: Option<CliError> = None;
    let t0 = Instant::now();
    let st = link
        .watch(
            &rows,
            per,
            0,
            |d, _| bar.set_position(d as u64),
            |rec: &WatchRecord| {
                bar.set_message(record_line(rec));
                if let Some(pts) = &replay {
                    compared += 1;
                    if let Some(why) = differs(rec, pts) {
                        mismatches.push(why);
                    }
                }
                if json_lines {
                    let mut v = serde_json::to_value(rec).unwrap_or(Value::Null);
                    v["event"] = json!("estimate");
                    if let Err(e) = w(out, serde_json::to_string(&v).unwrap_or_default()) {
                        io_err.get_or_insert(e);
                    }
                }
                history.records.push(rec.clone());
                if let Some(path) = &wa.plot {
                    if history.records.len() % wa.plot_every.max(1) == 0 {
                        if let Err(e) = crate::data::write_atomic(path, history.svg().as_bytes()) {
                            io_err.get_or_insert(CliError::Lib(e.into()));
                        }
                    }
                }
            },
        )
        .map_err(link_err)?;
    bar.finish_and_clear();
    if let Some(e) = io_err {
        return Err(e);
    }
    if let Some(path) = &wa.plot {
        crate::data::write_atomic(path, history.svg().as_bytes())
            .map_err(|e| CliError::Lib(e.into()))?;
    }
    let est = link.estimate().map_err(link_err)?;
    let secs = t0.elapsed().as_secs_f64();
    let mut res = json!({
        "command": "device watch",
        "file": ds.source,
        "samples": n,
        "seconds": secs,
        "samples_per_second": n as f64 / secs.max(1e-9),
        "every": wa.every,
        "forgetting": acc.forgetting,
        "window": acc.window,
        "reports": history.records.len(),
        "solves": est.solves,
        "failures": est.failures,
        "status": st,
        "last": history.records.last(),
    });
    if let Some(pts) = &replay {
        res["compare"] = json!({
            "host_solves": pts.len(),
            "reports_compared": compared,
            "identical": compared - mismatches.len(),
        });
        if pts.len() != est.solves as usize {
            mismatches.push(format!(
                "{} solves on the device, {} in the host replay",
                est.solves,
                pts.len()
            ));
        }
        if !mismatches.is_empty() {
            return Err(CliError::Invalid(format!(
                "the device's recursive estimate differs from the host's replay: {}",
                mismatches.join("; ")
            )));
        }
    }
    if let Some(path) = &wa.plot {
        res["plot"] = json!(path.display().to_string());
    }
    Ok(res)
}

/// The progress line's message for a report.
fn record_line(r: &WatchRecord) -> String {
    let rms: Vec<String> = r.interval_rms.iter().map(|v| format!("{v:.3e}")).collect();
    format!(
        "solve {} at sample {}: one-step RMS [{}], {} active, {} sweeps",
        r.solves,
        r.at_sample,
        rms.join(" "),
        r.summary.active,
        r.summary.iterations
    )
}

/// Why a device report differs from the host replay's point of the same solve count (bit
/// for bit: the device and the host run the same core code in the same float type).
fn differs(rec: &WatchRecord, pts: &[ReplayPoint]) -> Option<String> {
    let Some(p) = pts.iter().find(|p| p.solves == rec.solves) else {
        return Some(format!("solve {} has no host counterpart", rec.solves));
    };
    if p.at_sample != rec.at_sample {
        return Some(format!(
            "solve {} at sample {} on the device, {} on the host",
            rec.solves, rec.at_sample, p.at_sample
        ));
    }
    if p.theta != rec.theta {
        let d = p
            .theta
            .iter()
            .zip(&rec.theta)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        return Some(format!(
            "solve {}: coefficients differ by up to {d:.3e}",
            rec.solves
        ));
    }
    if p.interval_count != rec.interval_count || p.interval_sse != rec.interval_sse {
        return Some(format!(
            "solve {}: one-step errors differ ({} predictions, SSE {:?} on the device; {}, {:?} on the host)",
            rec.solves, rec.interval_count, rec.interval_sse, p.interval_count, p.interval_sse
        ));
    }
    None
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
        "device watch" => {
            w(out, format!(
                "watched {} samples of {}: {} solves every {} samples ({} failed), forgetting {}, window {}",
                v["samples"], v["file"].as_str().unwrap_or("?"), v["solves"], v["every"], v["failures"],
                v["forgetting"], v["window"]
            ))?;
            if let Some(l) = v.get("last").filter(|l| !l.is_null()) {
                w(out, format!(
                    "  last solve at sample {}: one-step RMS of the previous solution {}, coefficients {}",
                    l["at_sample"], l["interval_rms"], l["theta"]
                ))?;
            }
            if let Some(p) = v.get("plot") {
                w(out, format!("  plot: {}", p.as_str().unwrap_or("?")))?;
            }
            if let Some(c) = v.get("compare") {
                w(
                    out,
                    format!(
                        "  host replay: {} of {} reports identical bit for bit",
                        c["identical"], c["reports_compared"]
                    ),
                )?;
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
