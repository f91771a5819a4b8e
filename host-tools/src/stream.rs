//! `lpvid pbsid` in constant memory: the training file read in chunks of rows, each chunk
//! parsed by the same CSV parser as a whole file ([`Dataset::parse`], header prepended) and
//! fed to the streamed primal fit ([`crate::pbsid::stream`]: pass 1 statistics, pass 2
//! realization), then a third pass scores the model by free-run simulation (the same
//! recursion as [`crate::lpvss::LpvSs::simulate`], the state carried across chunks).
//!
//! Nothing here reports an error of its own: anything the streamed path does not handle —
//! options that need the data (the kernel form, BPDN, `--refine`, `--observer hinf`), a pipe,
//! a file whose lines the chunking cannot split safely (blank or over-long lines, a quote),
//! bad data anywhere, a fit that fails — returns `None`, and the caller runs the in-memory
//! [`crate::pipeline::identify`], which gives the canonical error with its file, line and
//! column. A streamed run writes nothing; the caller writes the model only on success.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::Path;

use serde_json::json;

use crate::data::{Dataset, MAX_LINE_BYTES};
use crate::lpvss::{LpvSs, Signals};
use crate::model::{describe, ModelFile, ModelKind, SignalMap};
use crate::observer;
use crate::pbsid::stream::{streamable, PassOne};
use crate::pipeline::{pbsid_fit_record, pbsid_warnings, Identified, PbsidSettings};
use crate::simulate::{Score, DIVERGED};

/// Rows per chunk: the memory of the streamed path is a few chunks, whatever the file.
pub const CHUNK_ROWS: usize = 8192;

/// Training files at least this large are streamed when the options allow; smaller ones are
/// read whole (the same model either way, and a small file costs nothing to hold).
pub const STREAM_MIN_BYTES: u64 = 4 << 20;

/// Whether `lpvid pbsid` streams this training file with these settings.
pub fn should_stream(path: &Path, settings: &PbsidSettings) -> bool {
    let big = std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() >= STREAM_MIN_BYTES);
    big && !settings.observer.hinf && streamable(&settings.fit).is_ok()
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

    fn next(&mut self) -> Result<Option<Dataset>, ()> {
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
fn for_each_chunk(
    path: &Path,
    chunk_rows: usize,
    mut each: impl FnMut(&Dataset) -> Result<(), ()>,
) -> Option<(usize, String)> {
    let mut chunks = CsvChunks::open(path, chunk_rows).ok()?;
    loop {
        match chunks.next() {
            Ok(Some(ds)) => each(&ds).ok()?,
            Ok(None) => break,
            Err(()) => return None,
        }
    }
    Some((chunks.rows, chunks.fingerprint()))
}

/// Free-run simulation from x0 = 0 carried across chunks, and the scores of
/// [`crate::simulate::score`] from running sums (VAF and BFR per output).
struct FreeRun<'a> {
    model: &'a LpvSs,
    /// The state, its successor, mu_k and u_k, y_k: the step's whole memory
    /// ([`LpvSs::output_into`], [`LpvSs::state_into`]).
    x: Vec<f64>,
    xn: Vec<f64>,
    mu: Vec<f64>,
    u: Vec<f64>,
    yk: Vec<f64>,
    k: usize,
    stopped: bool,
    diverged_at: Option<usize>,
    /// Per output: Welford mean and M2 of y and of y - yhat, and the sum of (y - yhat)^2.
    y: Vec<(f64, f64)>,
    err: Vec<(f64, f64)>,
    sse: Vec<f64>,
}

impl<'a> FreeRun<'a> {
    fn new(model: &'a LpvSs) -> FreeRun<'a> {
        let l = model.l();
        let mut mu = vec![0.0; model.m()];
        mu[0] = 1.0;
        FreeRun {
            model,
            x: vec![0.0; model.n()],
            xn: vec![0.0; model.n()],
            mu,
            u: vec![0.0; model.r()],
            yk: vec![0.0; l],
            k: 0,
            stopped: false,
            diverged_at: None,
            y: vec![(0.0, 0.0); l],
            err: vec![(0.0, 0.0); l],
            sse: vec![0.0; l],
        }
    }

    fn update(&mut self, sig: &Signals) {
        let m = self.model;
        let s = sig.p.ncols().min(m.m() - 1);
        for k in 0..sig.len() {
            let n = (self.k + 1) as f64;
            for q in 0..s {
                self.mu[q + 1] = sig.p[(k, q)];
            }
            for (j, v) in self.u.iter_mut().enumerate() {
                *v = sig.u[(k, j)];
            }
            if self.stopped {
                self.yk.iter_mut().for_each(|v| *v = f64::NAN);
            } else {
                m.output_into(&self.mu, &self.x, &self.u, &mut self.yk);
            }
            if self.diverged_at.is_none()
                && self.yk.iter().any(|v| !v.is_finite() || v.abs() > DIVERGED)
            {
                self.diverged_at = Some(self.k);
            }
            for j in 0..m.l() {
                let yv = sig.y[(k, j)];
                let e = yv - self.yk[j];
                welford(&mut self.y[j], yv, n);
                welford(&mut self.err[j], e, n);
                self.sse[j] += e * e;
            }
            if !self.stopped {
                m.state_into(&self.mu, &self.x, &self.u, None, &mut self.xn);
                std::mem::swap(&mut self.x, &mut self.xn);
                if self.x.iter().any(|v| !v.is_finite() || v.abs() > 1e150) {
                    self.stopped = true;
                }
            }
            self.k += 1;
        }
    }

    fn score(&self, file: &str) -> Score {
        let n = self.k as f64;
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
            mode: "free-run",
            vaf_mean: crate::metrics::mean(&vaf),
            bfr_mean: crate::metrics::mean(&bfr),
            vaf,
            bfr,
            skipped: 0,
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
    let mut two = one?.finish(opts).ok()?;
    // pass 2: the realization
    for_each_chunk(path, chunk_rows, |ds| {
        let sig = map.evaluate(ds).map_err(|_| ())?;
        two.update(&sig).map_err(|_| ())
    })?;
    let fit = two.finish().ok()?;
    let names: Vec<String> = map.scheduling.iter().skip(1).map(|p| describe(p)).collect();
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
    obs_step.annotate(&mut record);
    let model = ModelFile {
        kind: ModelKind::Ss(obs_step.model.clone()),
        signals: map.clone(),
        fit: record,
    };
    // pass 3: the free-run score on the training file
    let ModelKind::Ss(ss) = &model.kind else {
        return None;
    };
    let mut run = FreeRun::new(ss);
    let mut dims = (0, 0, 0);
    for_each_chunk(path, chunk_rows, |ds| {
        let sig = model.signals.evaluate(ds).map_err(|_| ())?;
        dims = (sig.u.ncols(), sig.y.ncols(), sig.p.ncols());
        run.update(&sig);
        Ok(())
    })?;
    let train_score = run.score(&path.display().to_string());
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn free_run_scores_equal_the_whole_record_ones() {
        let m = crate::systems::b1_truth();
        let exp = crate::systems::b1(700, 0.05, 5);
        let mut run = FreeRun::new(&m);
        for k in (0..700).step_by(64) {
            run.update(&exp.train.slice(k, 64.min(700 - k)));
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
