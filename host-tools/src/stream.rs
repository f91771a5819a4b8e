//! Constant memory on large files: the file read in chunks of rows, each chunk parsed by the
//! same CSV parser as a whole file ([`Dataset::parse`], header prepended).
//!
//! - `lpvid pbsid`: the chunks feed the streamed primal fit ([`crate::pbsid::stream`]: pass 1
//!   statistics, pass 2 realization), then a third pass scores the model by free-run
//!   simulation, the state carried across chunks. With the scheduling centre in doubt
//!   (`--centre auto`) the passes carry the fits at 0 and at the mean side by side and the
//!   third keeps the one [`crate::pipeline::identify`] would keep.
//! - `lpvid validate` ([`score_streaming`]) and `lpvid simulate` ([`simulate_streaming`]): an
//!   lpv-ss model run over the chunks in free run or one-step prediction, from the zero
//!   state or from one estimated on the first samples ([`crate::simulate::estimate_x0`] on
//!   the rows held until there are enough), scored from running sums; `simulate` writes
//!   each chunk's rows into the staged output ([`crate::data::stage_writer`]). Delayed
//!   factors of the signal map read the rows kept from the chunk before, and a free run
//!   through own-output feedback the outputs kept from it
//!   ([`crate::simulate::free_run_ss_into`], the in-memory run's loop). Left to the
//!   in-memory path: lpv-arx models, factors on the sample index and smoothed factors
//!   (`"smooth"`, a low-pass over the whole record) (`run_streamable`).
//!
//! All of them run the one simulation step ([`crate::lpvss::Stepper::output_into`] and
//! [`crate::lpvss::Stepper::state_into`], struct `ChunkRun`), so the outputs equal the
//! in-memory ones to the bit and the scores to rounding (Welford sums against two-pass).
//!
//! Nothing here reports a data error of its own: anything the streamed path does not handle
//! — options that need the data (the kernel form, BPDN, `--refine`, `--observer hinf`), a
//! model as above, a pipe, a file whose lines the chunking cannot split safely (blank or
//! over-long lines, a quote), bad data anywhere, a fit that fails — returns `None`, and the
//! caller runs the in-memory path ([`crate::pipeline::identify`],
//! [`crate::simulate::score_from`], [`crate::simulate::run`]), which gives the canonical
//! error with its file, line and column. A streamed run changes no file: `pbsid` writes the
//! model only on success, `simulate` commits its staged output only on success.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::Path;

use serde_json::{json, Value};

use nalgebra::DMatrix;

use crate::data::{stage_writer, DataError, Dataset, StagedWrite, MAX_LINE_BYTES};
use crate::lpvss::{LpvSs, Signals, Stepper};
use crate::model::{Feedback, ModelFile, ModelKind, SignalMap, SAMPLE_INDEX};
use crate::observer;
use crate::pbsid::stream::{streamable, NotStreamed, PassOne, PassTwo};
use crate::pbsid::{Centre, PbsidFit};
use crate::pipeline::{pbsid_fit_record, pbsid_warnings, pick_centre, Identified, PbsidSettings};
use crate::simulate::{estimate_x0, free_run_ss_into, Mode, Score, DIVERGED, X0, X0_SAMPLES};

/// Rows per chunk: the memory of the streamed path is a few chunks, whatever the file.
pub const CHUNK_ROWS: usize = 8192;

/// Training files at least this large are streamed when the options allow; smaller ones are
/// read whole (the same model either way, and a small file costs nothing to hold).
pub const STREAM_MIN_BYTES: u64 = 4 << 20;

/// Whether `lpvid pbsid` streams this training file with these settings.
pub fn should_stream(path: &Path, settings: &PbsidSettings) -> bool {
    should_stream_data(path) && !settings.observer.hinf && streamable(&settings.fit).is_ok()
}

/// The file's rows in chunks, each a [`Dataset`] parsed by [`Dataset::parse`] with the
/// header line prepended; `None` from [`CsvChunks::next`] ends the file, `Err(())` says the
/// streamed reading gives up (the whole-file parser decides).
struct CsvChunks {
    source: String,
    reader: BufReader<File>,
    header: Vec<u8>,
    fnv: u64,
    rows: usize,
    line: Vec<u8>,
    blank_seen: bool,
    done: bool,
    chunk_rows: usize,
}

impl CsvChunks {
    fn open(path: &Path, chunk_rows: usize) -> Result<CsvChunks, ()> {
        let file = File::open(path).map_err(|_| ())?;
        if !file.metadata().map_err(|_| ())?.is_file() {
            return Err(());
        }
        let mut c = CsvChunks {
            source: path.display().to_string(),
            reader: BufReader::with_capacity(1 << 20, file),
            header: Vec::new(),
            fnv: 0xcbf29ce484222325,
            rows: 0,
            line: Vec::new(),
            blank_seen: false,
            done: false,
            chunk_rows: chunk_rows.max(1),
        };
        if !c.read_line()? || is_blank(&c.line) {
            return Err(());
        }
        c.header = c.line.clone();
        Ok(c)
    }

    /// The next line into `self.line` (with its terminator); false at the end of the file.
    fn read_line(&mut self) -> Result<bool, ()> {
        self.line.clear();
        let n = std::io::Read::take(&mut self.reader, MAX_LINE_BYTES as u64 + 2)
            .read_until(b'\n', &mut self.line)
            .map_err(|_| ())?;
        if n > MAX_LINE_BYTES {
            return Err(());
        }
        for b in &self.line {
            self.fnv ^= *b as u64;
            self.fnv = self.fnv.wrapping_mul(0x100000001b3);
        }
        Ok(n > 0)
    }

    /// The next chunk: Ok(None) at the end of the file, Err(()) when the streamed reading
    /// gives up.
    fn next_chunk(&mut self) -> Result<Option<Dataset>, ()> {
        if self.done {
            return Ok(None);
        }
        let mut bytes = self.header.clone();
        if !bytes.ends_with(b"\n") {
            bytes.push(b'\n');
        }
        let mut count = 0;
        while count < self.chunk_rows {
            if !self.read_line()? {
                self.done = true;
                break;
            }
            // quotes could hold a line break; a blank line is an error unless only blank
            // lines follow: the whole-file parser says so
            if self.line.contains(&b'"') {
                return Err(());
            }
            if is_blank(&self.line) {
                self.blank_seen = true;
                continue;
            }
            if self.blank_seen {
                return Err(());
            }
            bytes.extend_from_slice(&self.line);
            if !self.line.ends_with(b"\n") {
                bytes.push(b'\n');
            }
            count += 1;
        }
        if count == 0 {
            return if self.rows == 0 { Err(()) } else { Ok(None) };
        }
        self.rows += count;
        let ds = Dataset::parse(&self.source, &bytes[..]).map_err(|_| ())?;
        // a lone carriage return ends a line for the parser: the rows would not be counted
        if ds.len() != count {
            return Err(());
        }
        Ok(Some(ds))
    }

    fn fingerprint(&self) -> String {
        format!("{:016x}", self.fnv)
    }
}

/// The chunks in order, each Ok or, once, the Err(()) that ends the reading.
impl Iterator for CsvChunks {
    type Item = Result<Dataset, ()>;

    fn next(&mut self) -> Option<Self::Item> {
        let next = self.next_chunk().transpose();
        if matches!(next, Some(Err(()))) {
            self.done = true;
        }
        next
    }
}

fn is_blank(line: &[u8]) -> bool {
    line.iter().all(u8::is_ascii_whitespace)
}

/// Per-column checks of `training_signals` ([`crate::pipeline::training_signals`]) kept
/// across chunks: the largest magnitude and whether the column varies.
#[derive(Debug, Clone)]
struct ColumnCheck {
    name: String,
    big: f64,
    first: Option<f64>,
    varies: bool,
}

/// Pass over the file: every chunk through `each`; `None` when the streamed reading gives up.
/// With a second core the next chunk is read and parsed on a thread of its own while `each`
/// works on this one (at most [`CHUNKS_AHEAD`] parsed chunks wait: memory stays constant);
/// the chunks, their order and what `each` computes are the same either way. Parsing is
/// about a sixth of a streamed B1 fit's CPU per pass, and passes 2 and 3 run on one thread.
fn for_each_chunk(
    path: &Path,
    chunk_rows: usize,
    mut each: impl FnMut(&Dataset) -> Result<(), ()>,
) -> Option<(usize, String)> {
    let mut chunks = CsvChunks::open(path, chunk_rows).ok()?;
    // every chunk through `each` until the file ends (true) or either gives up (false)
    let mut consume = |all: &mut dyn Iterator<Item = Result<Dataset, ()>>| {
        for next in all {
            if !next.is_ok_and(|ds| each(&ds).is_ok()) {
                return false;
            }
        }
        true
    };
    if crate::linalg::cores() < 2 {
        let ok = consume(&mut chunks);
        return ok.then(|| (chunks.rows, chunks.fingerprint()));
    }
    std::thread::scope(|sc| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Result<Dataset, ()>>(CHUNKS_AHEAD);
        let reader = sc.spawn(move || {
            for next in chunks.by_ref() {
                // a closed channel: `each` gave up, nothing more is read
                if tx.send(next).is_err() {
                    return None;
                }
            }
            Some((chunks.rows, chunks.fingerprint()))
        });
        let ok = consume(&mut rx.iter());
        // the receiver is dropped before the join, so a reader blocked on a full channel ends
        drop(rx);
        let read = reader.join().ok()?;
        read.filter(|_| ok)
    })
}

/// Parsed chunks [`for_each_chunk`]'s reader thread may hold ready beyond the one being used.
const CHUNKS_AHEAD: usize = 1;

/// A state-space model run over a record in chunks, the state carried from one chunk to the
/// next: the free run or the one-step predictor from an initial state x0, and the scores of
/// [`crate::simulate::score_from`] from running sums (VAF and BFR per output over the
/// samples after the first `skip`). The step is the shared allocation-free one
/// ([`Stepper::output_into`], [`Stepper::state_into`]), as in [`LpvSs::run_from`], so the
/// outputs are those of the in-memory run to the bit.
struct ChunkRun<'a> {
    model: &'a LpvSs,
    /// The model laid out for the sample loop.
    step: Stepper,
    predictor: bool,
    /// Leading samples not scored (used for the initial state).
    skip: usize,
    /// The state, its successor, mu_k and u_k, y_k and the innovation y_k - yhat_k: the
    /// step's whole memory.
    x: Vec<f64>,
    xn: Vec<f64>,
    mu: Vec<f64>,
    u: Vec<f64>,
    yk: Vec<f64>,
    ek: Vec<f64>,
    k: usize,
    stopped: bool,
    diverged_at: Option<usize>,
    /// Per output: Welford mean and M2 of y and of y - yhat, and the sum of (y - yhat)^2.
    y: Vec<(f64, f64)>,
    err: Vec<(f64, f64)>,
    sse: Vec<f64>,
    /// The free run through own-output feedback: its last outputs (at most `keep` rows),
    /// which the delayed factors of the next chunk read.
    kept: DMatrix<f64>,
    keep: usize,
}

impl<'a> ChunkRun<'a> {
    fn new(model: &'a LpvSs, mode: Mode, x0: &[f64], skip: usize) -> ChunkRun<'a> {
        let l = model.l();
        let mut mu = vec![0.0; model.m()];
        mu[0] = 1.0;
        ChunkRun {
            model,
            step: model.stepper(),
            predictor: mode == Mode::Predictor,
            skip,
            x: x0.to_vec(),
            xn: vec![0.0; model.n()],
            mu,
            u: vec![0.0; model.r()],
            yk: vec![0.0; l],
            ek: vec![0.0; l],
            k: 0,
            stopped: false,
            diverged_at: None,
            y: vec![(0.0, 0.0); l],
            err: vec![(0.0, 0.0); l],
            sse: vec![0.0; l],
            kept: DMatrix::zeros(0, l),
            keep: 0,
        }
    }

    /// The next samples; their model outputs into `out` (rows as `sig`, l columns) if given.
    fn update(&mut self, sig: &Signals, out: Option<&mut DMatrix<f64>>) {
        self.update_after(sig, &Feedback::default(), 0, out);
    }

    /// [`ChunkRun::update`] on the rows of `sig` from `h` on (the rows before are the
    /// end of the chunk before, which the delayed factors and the feedback `fb` read): in
    /// the free run through own-output feedback the samples are run by
    /// [`free_run_ss_into`] from the outputs kept of the chunk before, else by the step here.
    fn update_after(
        &mut self,
        sig: &Signals,
        fb: &Feedback,
        h: usize,
        mut out: Option<&mut DMatrix<f64>>,
    ) {
        let m = self.model;
        let (n, l) = (sig.len(), m.l());
        let feedback = !self.predictor && !fb.is_empty();
        // the free run through the feedback: the outputs of the chunk before, then these
        let mut run = DMatrix::<f64>::zeros(if feedback { n } else { 0 }, l);
        if feedback {
            let kept = self.kept.nrows();
            for i in 0..h.min(kept) {
                run.set_row(h - 1 - i, &self.kept.row(kept - 1 - i));
            }
            if self.stopped {
                run.rows_mut(h, n - h).fill(f64::NAN);
            } else if !free_run_ss_into(m, sig, fb, &mut self.x, h, n, &mut run) {
                self.stopped = true;
            }
        }
        let s = sig.p.ncols().min(m.m() - 1);
        for k in h..n {
            for q in 0..s {
                self.mu[q + 1] = sig.p[(k, q)];
            }
            for (j, v) in self.u.iter_mut().enumerate() {
                *v = sig.u[(k, j)];
            }
            if feedback {
                for (j, v) in self.yk.iter_mut().enumerate() {
                    *v = run[(k, j)];
                }
            } else if self.stopped {
                self.yk.iter_mut().for_each(|v| *v = f64::NAN);
            } else {
                self.step
                    .output_into(&self.mu, &self.x, &self.u, &mut self.yk);
            }
            if self.diverged_at.is_none()
                && self.yk.iter().any(|v| !v.is_finite() || v.abs() > DIVERGED)
            {
                self.diverged_at = Some(self.k);
            }
            if let Some(o) = out.as_deref_mut() {
                for (j, v) in self.yk.iter().enumerate() {
                    o[(k - h, j)] = *v;
                }
            }
            let count = (self.k + 1).saturating_sub(self.skip) as f64;
            for j in 0..l {
                let yv = sig.y[(k, j)];
                let e = yv - self.yk[j];
                self.ek[j] = e;
                if self.k >= self.skip {
                    welford(&mut self.y[j], yv, count);
                    welford(&mut self.err[j], e, count);
                    self.sse[j] += e * e;
                }
            }
            if !self.stopped && !feedback {
                let innovation = self.predictor.then_some(&self.ek[..]);
                self.step
                    .state_into(&self.mu, &self.x, &self.u, innovation, &mut self.xn);
                std::mem::swap(&mut self.x, &mut self.xn);
                if self.x.iter().any(|v| !v.is_finite() || v.abs() > 1e150) {
                    self.stopped = true;
                }
            }
            self.k += 1;
        }
        if feedback {
            // the outputs the next chunk's delayed feedback reads
            let keep = self.keep.min(n);
            self.kept = run.rows(n - keep, keep).into_owned();
        }
    }

    /// The normalised free-run error of [`crate::pipeline::held_out_error`] from the running
    /// sums: the mean over outputs of MSE / var y over the samples after `skip`; infinite
    /// when the run diverges or scores at most one sample.
    fn free_run_error(&self) -> f64 {
        let skipped = self.skip.min(self.k);
        if self.k <= skipped + 1 || self.y.is_empty() {
            return f64::INFINITY;
        }
        let n = (self.k - skipped) as f64;
        let total: f64 = (0..self.y.len())
            .map(|j| (self.sse[j] / n) / (self.y[j].1 / n).max(1e-300))
            .sum();
        let e = total / self.y.len() as f64;
        if e.is_finite() {
            e
        } else {
            f64::INFINITY
        }
    }

    fn score(&self, file: &str) -> Score {
        let skipped = self.skip.min(self.k);
        let n = (self.k - skipped) as f64;
        let mut vaf = Vec::new();
        let mut bfr = Vec::new();
        for j in 0..self.y.len() {
            let finite = self.err[j].1.is_finite() && self.sse[j].is_finite();
            let (vy, ve) = (self.y[j].1 / n, self.err[j].1 / n);
            let den = self.y[j].1.sqrt();
            let (v, b) = if finite {
                (
                    crate::metrics::vaf_from_variances(vy, ve),
                    crate::metrics::bfr_from_norms(self.sse[j].sqrt(), den),
                )
            } else {
                (0.0, 0.0)
            };
            vaf.push(v);
            bfr.push(b);
        }
        Score {
            file: file.to_string(),
            mode: if self.predictor {
                "predictor"
            } else {
                "free-run"
            },
            vaf_mean: crate::metrics::mean(&vaf),
            bfr_mean: crate::metrics::mean(&bfr),
            vaf,
            bfr,
            skipped,
            diverged_at: self.diverged_at,
        }
    }
}

/// One Welford step: (mean, M2) with the n-th value `v`.
fn welford(acc: &mut (f64, f64), v: f64, n: f64) {
    let d = v - acc.0;
    acc.0 += d / n;
    acc.1 += d * (v - acc.0);
}

/// [`crate::pipeline::identify`] on a training file read in chunks of [`CHUNK_ROWS`] rows
/// (see the module docs); `None`: use the in-memory path. `val` is scored as `identify`
/// scores it.
pub fn identify_streaming(
    path: &Path,
    val: Option<&Dataset>,
    settings: &PbsidSettings,
) -> Option<Identified> {
    identify_streaming_chunks(path, val, settings, CHUNK_ROWS)
}

/// [`identify_streaming`] with chunks of `chunk_rows` rows.
pub fn identify_streaming_chunks(
    path: &Path,
    val: Option<&Dataset>,
    settings: &PbsidSettings,
    chunk_rows: usize,
) -> Option<Identified> {
    let opts = &settings.fit;
    if settings.observer.hinf || streamable(opts).is_err() {
        return None;
    }
    // pass 1: checks, channel sums, plain statistics, the scheduling box
    let mut map: Option<SignalMap> = None;
    let mut one: Option<PassOne> = None;
    let mut checks: Vec<ColumnCheck> = Vec::new();
    let mut box_lo: Vec<f64> = Vec::new();
    let mut box_hi: Vec<f64> = Vec::new();
    let mut p_sum: Vec<f64> = Vec::new();
    let (rows, fnv) = for_each_chunk(path, chunk_rows, |ds| {
        if map.is_none() {
            let m = SignalMap::default_for(ds).map_err(|_| ())?;
            for prefix in ['u', 'y', 'p'] {
                for name in ds.channels(prefix) {
                    checks.push(ColumnCheck {
                        name,
                        big: 0.0,
                        first: None,
                        varies: prefix == 'y',
                    });
                }
            }
            map = Some(m);
        }
        for c in checks.iter_mut() {
            let col = ds.column(&c.name).ok_or(())?;
            for &v in col {
                c.big = c.big.max(v.abs());
                match c.first {
                    None => c.first = Some(v),
                    Some(f) if f != v => c.varies = true,
                    _ => {}
                }
            }
        }
        let sig = map.as_ref().ok_or(())?.evaluate(ds).map_err(|_| ())?;
        if one.is_none() {
            let (r, l, s) = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
            one = Some(PassOne::new(r, l, s, opts).map_err(|_| ())?);
            box_lo = vec![f64::INFINITY; s];
            box_hi = vec![f64::NEG_INFINITY; s];
            p_sum = vec![0.0; s];
        }
        for j in 0..sig.p.ncols() {
            for &v in sig.p.column(j).iter() {
                box_lo[j] = box_lo[j].min(v);
                box_hi[j] = box_hi[j].max(v);
                p_sum[j] += v;
            }
        }
        one.as_mut().ok_or(())?.update(&sig).map_err(|_| ())
    })?;
    let map = map?;
    let max_mag = crate::data::MAX_MAGNITUDE;
    if checks
        .iter()
        .any(|c| c.big > max_mag || (c.big > 0.0 && c.big < 1.0 / max_mag) || !c.varies)
        || rows < opts.past + 3
    {
        return None;
    }
    // the centre in doubt (`--centre auto`, 0 away from a scheduling signal's mean, the
    // criterion of the in-memory fit on the same channel sums): pass 1 finished at 0 and at
    // the mean, both realized in pass 2, both free runs scored in pass 3, the better kept
    // by the in-memory fit's choice ([`crate::pipeline::pick_centre`])
    let mut one = one?;
    let check = opts.centre == Centre::Auto && one.centre_in_doubt();
    let centres = if check {
        vec![Centre::Zero, Centre::Mean]
    } else {
        vec![opts.centre]
    };
    // (centre, pass 2) of each fit that pass 1 finished; a failed fit drops out, as it does
    // in-memory (`pipeline::choose_centre`); the kernel form's turn leaves it all to that path
    let mut twos = Vec::new();
    for &c in &centres {
        let mut o = opts.clone();
        o.centre = c;
        match one.finish(&o) {
            Ok(t) => twos.push((c, Some(t))),
            Err(NotStreamed::Fit(_)) => {}
            Err(_) => return None,
        }
    }
    drop(one);
    if twos.is_empty() {
        return None;
    }
    // pass 2: the realizations; two centres' on two threads (independent sums, the same
    // bits as one after the other)
    for_each_chunk(path, chunk_rows, |ds| {
        let sig = map.evaluate(ds).map_err(|_| ())?;
        let update = |two: &mut Option<PassTwo>| {
            if two.as_mut().is_some_and(|t| t.update(&sig).is_err()) {
                *two = None;
            }
        };
        match twos.as_mut_slice() {
            [(_, a), (_, b)] if crate::linalg::cores() >= 2 => std::thread::scope(|sc| {
                sc.spawn(|| update(b));
                update(a);
            }),
            all => all.iter_mut().for_each(|(_, two)| update(two)),
        }
        Ok(())
    })?;
    let mut fits: Vec<(Centre, PbsidFit)> = twos
        .into_iter()
        .filter_map(|(c, two)| Some((c, two?.finish().ok()?)))
        .collect();
    if fits.is_empty() {
        return None;
    }
    // pass 3: each fit's free run on the training file from x0 = 0 (the score reported;
    // the streamed observer step keeps the least-squares model, so this is the free run of
    // the model written) and, when the centre is checked, from an initial state estimated
    // on the first samples (the error `pipeline::held_out_error` scores)
    let x0_rows = (rows / 4).min(X0_SAMPLES);
    let FreeRuns {
        scores,
        errors,
        dims,
    } = free_runs(path, chunk_rows, &map, &fits, check, x0_rows)?;
    let (chosen, centre_check) = if check {
        let entry = |c: Centre| {
            let i = fits.iter().position(|f| f.0 == c)?;
            Some((&fits[i].1, errors[i]))
        };
        let (c, record) = pick_centre(entry(Centre::Zero), entry(Centre::Mean))?;
        (c, Some(record))
    } else {
        (opts.centre, None)
    };
    let i = fits.iter().position(|f| f.0 == chosen)?;
    let fit = fits.swap_remove(i).1;
    let train_score = scores.into_iter().nth(i)?;
    let mut chosen_opts = opts.clone();
    chosen_opts.centre = chosen;
    let opts = &chosen_opts;
    let names = map.scheduling_names();
    let mean: Vec<f64> = p_sum.iter().map(|s| s / rows as f64).collect();
    let obs_step = observer::observer_step_streamed(
        &fit.model,
        &names,
        &box_lo,
        &box_hi,
        &mean,
        &settings.observer,
    )
    .ok()?;
    let train_record = json!({
        "file": path.display().to_string(),
        "rows": rows,
        "fnv1a64": fnv,
    });
    let mut record = pbsid_fit_record(opts, &fit, train_record);
    if let (Some(c), Value::Object(m)) = (centre_check, &mut record) {
        m.insert("centre_check".into(), c);
    }
    obs_step.annotate(&mut record);
    let model = ModelFile {
        kind: ModelKind::Ss(obs_step.model.clone()),
        signals: map.clone(),
        fit: record,
    };
    let val_score = match val {
        Some(v) => Some(crate::simulate::score(&model, v, crate::simulate::Mode::FreeRun).ok()?),
        None => None,
    };
    let warnings = pbsid_warnings(opts, &fit, &obs_step, &train_score, val_score.as_ref());
    Some(Identified {
        warnings,
        dims,
        samples: rows,
        model,
        fit,
        train_score,
        val_score,
        observer: obs_step,
    })
}

/// Pass 3 of [`identify_streaming_chunks`]: each of `fits`' models run freely over the
/// file from x0 = 0 (its training score) and, with `estimate`, from an initial state
/// estimated on the first `x0_rows` rows (held until read, as [`run_file`] does), scored by
/// [`ChunkRun::free_run_error`]. Memory: the runs' states and the chunks holding those rows.
fn free_runs(
    path: &Path,
    chunk_rows: usize,
    map: &SignalMap,
    fits: &[(Centre, PbsidFit)],
    estimate: bool,
    x0_rows: usize,
) -> Option<FreeRuns> {
    let file = path.display().to_string();
    let mut zero: Vec<ChunkRun> = fits
        .iter()
        .map(|(_, f)| ChunkRun::new(&f.model, Mode::FreeRun, &vec![0.0; f.model.n()], 0))
        .collect();
    let mut est: Option<Vec<ChunkRun>> = None;
    let mut held: Vec<Dataset> = Vec::new();
    let mut held_rows = 0;
    // the estimated runs from the held rows' head, then those rows through them
    let start = |held: &mut Vec<Dataset>| -> Result<Vec<ChunkRun>, ()> {
        let (hs, hf) = match head_of(held, x0_rows) {
            Some(head) if x0_rows > 0 => (
                Some(map.evaluate(&head).map_err(|_| ())?),
                map.feedback(&head).map_err(|_| ())?,
            ),
            _ => (None, Feedback::default()),
        };
        let mut runs: Vec<ChunkRun> = fits
            .iter()
            .map(|(_, f)| {
                let x = match &hs {
                    Some(hs) => estimate_x0(&f.model, hs, &hf, x0_rows),
                    None => nalgebra::DVector::zeros(f.model.n()),
                };
                ChunkRun::new(&f.model, Mode::FreeRun, x.as_slice(), x0_rows)
            })
            .collect();
        for ds in held.drain(..) {
            let sig = map.evaluate(&ds).map_err(|_| ())?;
            runs.iter_mut().for_each(|r| r.update(&sig, None));
        }
        Ok(runs)
    };
    let mut dims = (0, 0, 0);
    for_each_chunk(path, chunk_rows, |ds| {
        let sig = map.evaluate(ds).map_err(|_| ())?;
        dims = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
        zero.iter_mut().for_each(|r| r.update(&sig, None));
        if !estimate {
            return Ok(());
        }
        match est.as_mut() {
            Some(runs) => runs.iter_mut().for_each(|r| r.update(&sig, None)),
            None => {
                held.push(ds.clone());
                held_rows += ds.len();
                if held_rows >= x0_rows {
                    est = Some(start(&mut held)?);
                }
            }
        }
        Ok(())
    })?;
    let errors = match (estimate, est) {
        (false, _) => vec![f64::INFINITY; fits.len()],
        (true, Some(runs)) => runs.iter().map(ChunkRun::free_run_error).collect(),
        (true, None) => start(&mut held)
            .ok()?
            .iter()
            .map(ChunkRun::free_run_error)
            .collect(),
    };
    let scores = zero.iter().map(|r| r.score(&file)).collect();
    Some(FreeRuns {
        scores,
        errors,
        dims,
    })
}

/// Pass 3's results, per fit in the order given: the score of the free run from x0 = 0,
/// the error from the estimated initial state (infinite when not estimated); and the
/// signals' dimensions (inputs, outputs, scheduling signals).
struct FreeRuns {
    scores: Vec<Score>,
    errors: Vec<f64>,
    dims: (usize, usize, usize),
}

/// Why the streamed validate/simulate hands a model to the in-memory path, if it does:
/// an lpv-arx model (its recursion, [`crate::simulate::arx_run_from`], reads the whole
/// record); a factor on the sample index `k`; a factor with `"smooth"` (its low-pass starts
/// at the record's first sample and runs through every row, which a chunk evaluated after a
/// few kept rows would restart); a delay longer than [`CHUNK_ROWS`] (the rows kept for it)
/// and the chunk.
/// Otherwise the model and the longest delay of its signal map.
fn run_streamable(model: &ModelFile, chunk_rows: usize) -> Option<(&LpvSs, usize)> {
    let ModelKind::Ss(ss) = &model.kind else {
        return None;
    };
    let map = &model.signals;
    let mut delay = 0;
    for f in map
        .inputs
        .iter()
        .chain(&map.scheduling)
        .chain(&map.outputs)
        .flatten()
    {
        if f.col == SAMPLE_INDEX || f.smooth.is_some() {
            return None;
        }
        delay = delay.max(f.delay);
    }
    (delay <= chunk_rows.max(CHUNK_ROWS)).then_some((ss, delay))
}

/// A model's signals chunk by chunk: each chunk evaluated by [`SignalMap::evaluate`] after
/// the last `delay` rows before it, so a delayed factor reads what it reads in the whole
/// record; the own-output feedback ([`SignalMap::feedback`]) on the same rows (empty when
/// the map has none; its errors fall back as the in-memory run would give them).
struct ChunkSignals<'a> {
    map: &'a SignalMap,
    delay: usize,
    history: Option<Dataset>,
}

impl ChunkSignals<'_> {
    /// The signals and the feedback of the rows kept and this chunk, and how many rows
    /// were kept (the chunk's rows are those after them).
    fn evaluate(&mut self, ds: &Dataset) -> Result<(Signals, Feedback, usize), ()> {
        let joined;
        let (src, h) = match self.history.take() {
            Some(mut prev) if self.delay > 0 => {
                let h = prev.len();
                for (c, add) in prev.cols.iter_mut().zip(&ds.cols) {
                    c.extend_from_slice(add);
                }
                joined = prev;
                (&joined, h)
            }
            _ => (ds, 0),
        };
        if src.names != ds.names {
            return Err(());
        }
        let sig = self.map.evaluate(src).map_err(|_| ())?;
        let fb = self.map.feedback(src).map_err(|_| ())?;
        if self.delay > 0 {
            let keep = self.delay.min(src.len());
            self.history = Some(Dataset {
                source: src.source.clone(),
                names: src.names.clone(),
                cols: src
                    .cols
                    .iter()
                    .map(|c| c[c.len() - keep..].to_vec())
                    .collect(),
            });
        }
        Ok((sig, fb, h))
    }
}

/// The rows of `chunks` (same columns) as one data set, the first `rows` only.
fn head_of(chunks: &[Dataset], rows: usize) -> Option<Dataset> {
    let first = chunks.first()?;
    let mut head = Dataset {
        source: first.source.clone(),
        names: first.names.clone(),
        cols: vec![Vec::new(); first.cols.len()],
    };
    for ds in chunks {
        for (c, add) in head.cols.iter_mut().zip(&ds.cols) {
            let take = rows.saturating_sub(c.len()).min(add.len());
            c.extend_from_slice(&add[..take]);
        }
    }
    Some(head)
}

/// The chunks' model outputs go here (chunk rows, their outputs); an error stops the calls.
type Sink<'s> = &'s mut dyn FnMut(&Dataset, &DMatrix<f64>) -> Result<(), DataError>;

/// A streamed run over a file: the run (its score), the rows read, and the first error of
/// the sink (not called after it, nor from the sample where the run diverged).
struct FileRun<'a> {
    run: ChunkRun<'a>,
    rows: usize,
    sink_error: Option<DataError>,
}

/// `model` run over the file at `path` in chunks of `chunk_rows` rows from the initial state
/// `x0`: with [`X0::Estimate`] the chunks are held until the first `samples` rows are read,
/// the state is estimated from them by [`estimate_x0`] (the in-memory run's function, on
/// the same rows) and the run starts (so the memory is a chunk and those rows). `None`: the
/// in-memory path decides (a model `run_streamable` refuses, anything the chunked reading
/// gives up on, bad data).
fn run_file<'a>(
    model: &'a ModelFile,
    path: &Path,
    mode: Mode,
    x0: X0,
    chunk_rows: usize,
    mut sink: Option<Sink<'_>>,
) -> Option<FileRun<'a>> {
    let (ss, delay) = run_streamable(model, chunk_rows)?;
    let samples = match x0 {
        X0::Zero => 0,
        X0::Estimate { samples } => samples,
    };
    let mut sigs = ChunkSignals {
        map: &model.signals,
        delay,
        history: None,
    };
    let mut run = (samples == 0).then(|| {
        let mut r = ChunkRun::new(ss, mode, &vec![0.0; ss.n()], 0);
        r.keep = delay;
        r
    });
    let mut pending: Vec<Dataset> = Vec::new();
    let mut pending_rows = 0;
    let mut out = DMatrix::<f64>::zeros(0, ss.l());
    let mut sink_error: Option<DataError> = None;
    let mut step = |run: &mut ChunkRun<'a>, ds: &Dataset| -> Result<(), ()> {
        let (sig, fb, h) = sigs.evaluate(ds)?;
        let write = sink.is_some() && sink_error.is_none() && run.diverged_at.is_none();
        if write {
            out.resize_mut(sig.len() - h, ss.l(), 0.0);
        }
        run.update_after(&sig, &fb, h, write.then_some(&mut out));
        if let (true, None, Some(f)) = (write, run.diverged_at, sink.as_deref_mut()) {
            sink_error = f(ds, &out).err();
        }
        Ok(())
    };
    // the initial state from the held rows, then those rows through the run
    let start = |pending: &mut Vec<Dataset>,
                 step: &mut dyn FnMut(&mut ChunkRun<'a>, &Dataset) -> Result<(), ()>|
     -> Result<ChunkRun<'a>, ()> {
        let head = head_of(pending, samples).ok_or(())?;
        let hs = model.signals.evaluate(&head).map_err(|_| ())?;
        let hf = model.signals.feedback(&head).map_err(|_| ())?;
        let x = estimate_x0(ss, &hs, &hf, samples);
        let mut r = ChunkRun::new(ss, mode, x.as_slice(), samples);
        r.keep = delay;
        for ds in pending.drain(..) {
            step(&mut r, &ds)?;
        }
        Ok(r)
    };
    let (rows, _) = for_each_chunk(path, chunk_rows, |ds| {
        if let Some(r) = run.as_mut() {
            return step(r, ds);
        }
        pending.push(ds.clone());
        pending_rows += ds.len();
        if pending_rows >= samples {
            run = Some(start(&mut pending, &mut step)?);
        }
        Ok(())
    })?;
    let run = match run {
        Some(r) => r,
        None => start(&mut pending, &mut step).ok()?,
    };
    Some(FileRun {
        run,
        rows,
        sink_error,
    })
}

/// Whether `lpvid validate`/`simulate` read this data file in chunks: a regular file of at
/// least [`STREAM_MIN_BYTES`] (the model decides the rest: [`score_streaming`]).
pub fn should_stream_data(path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() >= STREAM_MIN_BYTES)
}

/// [`crate::simulate::score_from`] of `model` on the data file at `path`, read in chunks of
/// [`CHUNK_ROWS`] rows (constant memory), with the number of rows; `None`: use the
/// in-memory path (lpv-arx models, a factor on the sample index, bad data:
/// `run_streamable`, module docs).
pub fn score_streaming(
    model: &ModelFile,
    path: &Path,
    mode: Mode,
    x0: X0,
) -> Option<(Score, usize)> {
    score_streaming_chunks(model, path, mode, x0, CHUNK_ROWS)
}

/// [`score_streaming`] with chunks of `chunk_rows` rows.
pub fn score_streaming_chunks(
    model: &ModelFile,
    path: &Path,
    mode: Mode,
    x0: X0,
    chunk_rows: usize,
) -> Option<(Score, usize)> {
    let f = run_file(model, path, mode, x0, chunk_rows, None)?;
    Some((f.run.score(&path.display().to_string()), f.rows))
}

/// A streamed `lpvid simulate` output, staged, not yet in place.
#[derive(Debug)]
pub struct Simulated {
    /// The output file, complete in its temporary file ([`crate::data::StagedWrite::commit`]).
    pub staged: StagedWrite,
    /// Rows written.
    pub rows: usize,
    /// Simulated output columns.
    pub outputs: usize,
}

/// Why a streamed `lpvid simulate` wrote nothing, when the data were read to the end.
#[derive(Debug)]
pub enum SimulateFailure {
    /// The model's output is not finite or beyond [`DIVERGED`] from this sample (0-based).
    Diverged(usize),
    /// Writing the output failed.
    Write(DataError),
}

/// The model's outputs on the data file at `path` ([`crate::simulate::run`]): the data
/// columns plus `yhat1..` (a name taken by the data gets `_` appended), written chunk by
/// chunk into a staged output ([`crate::data::stage_writer`]) for `out`, the same bytes as
/// the in-memory [`Dataset::to_csv_bytes`]. `None`: use the in-memory path (as
/// [`score_streaming`]); the data are read to the end before a divergence or a write
/// failure is reported, so a bad row anywhere falls back and gets its canonical error.
pub fn simulate_streaming(
    model: &ModelFile,
    path: &Path,
    mode: Mode,
    x0: X0,
    out: &Path,
) -> Option<Result<Simulated, SimulateFailure>> {
    simulate_streaming_chunks(model, path, mode, x0, out, CHUNK_ROWS)
}

/// [`simulate_streaming`] with chunks of `chunk_rows` rows.
pub fn simulate_streaming_chunks(
    model: &ModelFile,
    path: &Path,
    mode: Mode,
    x0: X0,
    out: &Path,
    chunk_rows: usize,
) -> Option<Result<Simulated, SimulateFailure>> {
    run_streamable(model, chunk_rows)?;
    // a destination that cannot be staged fails the in-memory path too, after its reading
    let mut writer = Some(stage_writer(out).ok()?);
    let mut names: Option<Vec<String>> = None;
    let mut sink = |ds: &Dataset, yhat: &DMatrix<f64>| -> Result<(), DataError> {
        let header = names.is_none();
        let names = names.get_or_insert_with(|| {
            let mut all = ds.names.clone();
            for j in 0..yhat.ncols() {
                let mut name = format!("yhat{}", j + 1);
                while all.contains(&name) {
                    name.push('_');
                }
                all.push(name);
            }
            all
        });
        let mut cols = ds.cols.clone();
        cols.extend((0..yhat.ncols()).map(|j| yhat.column(j).iter().copied().collect()));
        let chunk = Dataset {
            source: ds.source.clone(),
            names: names.clone(),
            cols,
        };
        let bytes = chunk.csv_bytes(out, header)?;
        writer
            .as_mut()
            .ok_or_else(|| DataError::new(out.display().to_string(), None, None, "cannot write"))?
            .write(&bytes)
    };
    let f = run_file(model, path, mode, x0, chunk_rows, Some(&mut sink))?;
    if let Some(k) = f.run.diverged_at {
        return Some(Err(SimulateFailure::Diverged(k)));
    }
    if let Some(e) = f.sink_error {
        return Some(Err(SimulateFailure::Write(e)));
    }
    let staged = match writer.take()?.finish() {
        Ok(s) => s,
        Err(e) => return Some(Err(SimulateFailure::Write(e))),
    };
    Some(Ok(Simulated {
        staged,
        rows: f.rows,
        outputs: model.signals.outputs.len(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chunks a pass sees, in order, with the prefetching reader: every row once; a
    /// pass that gives up, or a line the streamed reading cannot take, ends it with None
    /// (the reader then stops, nothing hangs).
    #[test]
    fn a_pass_sees_every_chunk_in_order_and_stops_on_give_up() {
        let dir = tempfile::tempdir().expect("temporary directory");
        let path = dir.path().join("d.csv");
        let mut text = String::from("u1,y1\n");
        for k in 0..1000 {
            text.push_str(&format!("{k},{}\n", 2 * k));
        }
        std::fs::write(&path, &text).expect("written");
        let mut seen = Vec::new();
        let (rows, _) = for_each_chunk(&path, 64, |ds| {
            seen.extend_from_slice(ds.column("u1").ok_or(())?);
            Ok(())
        })
        .expect("a full pass");
        assert_eq!(rows, 1000);
        assert!(seen.iter().enumerate().all(|(k, v)| *v == k as f64));
        assert_eq!(seen.len(), 1000);
        let mut calls = 0;
        let gave_up = for_each_chunk(&path, 64, |_| {
            calls += 1;
            if calls == 3 {
                Err(())
            } else {
                Ok(())
            }
        });
        assert!(gave_up.is_none());
        assert_eq!(calls, 3);
        // a quoted field in the middle: the whole-file reader decides
        std::fs::write(&path, text.replacen("500,1000", "\"500\",1000", 1)).expect("written");
        let mut chunks = 0;
        assert!(for_each_chunk(&path, 64, |_| {
            chunks += 1;
            Ok(())
        })
        .is_none());
        assert_eq!(chunks, 7);
    }

    #[test]
    fn free_run_scores_equal_the_whole_record_ones() {
        let m = crate::systems::b1_truth();
        let exp = crate::systems::b1(700, 0.05, 5);
        let mut run = ChunkRun::new(&m, Mode::FreeRun, &[0.0; 4], 0);
        for k in (0..700).step_by(64) {
            run.update(&exp.train.slice(k, 64.min(700 - k)), None);
        }
        let s = run.score("t");
        let yhat = m.simulate(&exp.train, None);
        let vaf = crate::metrics::vaf_per_output(&exp.train.y, &yhat, 0);
        let bfr = crate::metrics::bfr_per_output(&exp.train.y, &yhat, 0);
        for j in 0..3 {
            assert!((s.vaf[j] - vaf[j]).abs() < 1e-9, "{} {}", s.vaf[j], vaf[j]);
            assert!((s.bfr[j] - bfr[j]).abs() < 1e-9, "{} {}", s.bfr[j], bfr[j]);
        }
        assert_eq!(s.diverged_at, crate::simulate::diverged_at(&yhat));
    }
}
