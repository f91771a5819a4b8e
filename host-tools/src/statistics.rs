//! Mergeable statistics of experiments and their versioned byte encoding.
//!
//! [`Statistics`] holds the core's `Extended` second moments (`lpvid::StatsLayout::Extended`:
//! everything [`crate::pbsid::fit_from_stats`] needs to finish the whole fit without data)
//! summed over any number of experiments. Each experiment is windowed on its own (a window
//! never spans two experiments: the first vector of an experiment needs p + 1 of its own
//! samples), so the statistics of a set of experiments are the sum of the statistics of
//! each, in any order and grouping: that is what lets them be computed where the data live
//! (a Dask worker, a device) and reduced in a tree ([`Statistics::merge`]).
//!
//! The byte encoding ([`Statistics::to_bytes`], [`Statistics::from_bytes`]) is versioned and
//! self-describing (magic, version, layout, float type, dimensions, windows, experiments,
//! the packed Gram in the value layout of the device link's `PullStats`, CRC-32):
//! `docs/wire.md` section 7 describes it byte by byte.

use lpvid::{packed_len, stat_vector_len, write_stat_vector, Gram, PbsidDims, Slab, StatsLayout};
use serde_json::{json, Value};

use crate::data::DataError;
use crate::error::Error;
use crate::lpvss::Signals;
use crate::model::ModelFile;
use crate::pbsid::{PbsidFit, PbsidOptions};

/// The first four bytes of an encoding: ASCII "LPVS".
pub const MAGIC: [u8; 4] = *b"LPVS";
/// Encoding version written by [`Statistics::to_bytes`] (and the only one read).
pub const VERSION: u16 = 1;
/// Bytes before the values: magic 4, version 2, layout 1, float bytes 1, r l s p 4 x 4,
/// windows 8, experiments 8, value count 8.
pub const HEADER_LEN: usize = 48;
/// Bytes after the values: the CRC-32.
pub const TRAILER_LEN: usize = 4;

/// Layout byte of the encoding (`lpvid::StatsLayout`): only `Extended` can be fitted.
const LAYOUT_PLAIN: u8 = 0;
const LAYOUT_EXTENDED: u8 = 1;

/// Where decoding errors say they are (the `file` of their [`DataError`]).
const SOURCE: &str = "statistics";

/// Second-moment statistics of LPV-PBSID_opt (extended layout, f64) summed over
/// experiments.
#[derive(Debug, Clone)]
pub struct Statistics {
    dims: PbsidDims,
    gram: Gram<f64, Vec<f64>>,
    experiments: u64,
}

fn data_error(message: impl Into<String>) -> Error {
    Error::Data(DataError::new(SOURCE, None, None, message))
}

impl Statistics {
    /// Empty statistics for r inputs, l outputs, s scheduling signals and past window p.
    pub fn new(dims: PbsidDims) -> Result<Statistics, Error> {
        let len = stat_vector_len(&dims, StatsLayout::Extended)?;
        Ok(Statistics {
            dims,
            gram: Gram::new(len, vec![0.0; packed_len(len)])?,
            experiments: 0,
        })
    }

    /// The dimensions.
    pub fn dims(&self) -> PbsidDims {
        self.dims
    }

    /// Windows accumulated (over all experiments).
    pub fn windows(&self) -> u64 {
        self.gram.count()
    }

    /// Experiments added (directly or through merges).
    pub fn experiments(&self) -> u64 {
        self.experiments
    }

    /// The summed Gram of the extended statistic vectors.
    pub fn gram(&self) -> &Gram<f64, Vec<f64>> {
        &self.gram
    }

    /// Add one experiment: `rows` holds its samples row-major `[u (r), y (l), p (s)]` (the
    /// sample layout of the wire and of the core's `Streaming::update_block`); `source`
    /// names it in errors. Its windows start at its own first sample. The statistic vectors
    /// are the core's (`write_stat_vector`, extended layout) accumulated with the core's
    /// batched Gram update, so the result is that of `lpvid::PbsidStats` fed the same samples
    /// (up to the summation order). An experiment shorter than p + 1 samples adds no window
    /// but counts as an experiment. A rejected experiment (a non-finite value, a
    /// dimension mismatch, an overflow) changes nothing. Returns the windows added.
    pub fn add_experiment(&mut self, rows: &[f64], source: &str) -> Result<u64, Error> {
        let d = self.dims;
        let w = d.r + d.l + d.s;
        if rows.len() % w != 0 {
            return Err(Error::Data(DataError::new(
                source,
                None,
                None,
                format!(
                    "{} values are not whole samples of {w} (r = {}, l = {}, s = {})",
                    rows.len(),
                    d.r,
                    d.l,
                    d.s
                ),
            )));
        }
        let n = rows.len() / w;
        for (k, row) in rows.chunks_exact(w).enumerate() {
            if let Some(j) = row.iter().position(|v| !v.is_finite()) {
                let name = column_name(&d, j);
                return Err(Error::Data(DataError::new(
                    source,
                    None,
                    Some(&name),
                    format!(
                        "sample {k} is {} (NaN and infinite values are not allowed)",
                        row[j]
                    ),
                )));
            }
        }
        if n <= d.p {
            self.experiments += 1;
            return Ok(0);
        }
        // [u, y, 1, p] rows: the core's Slab (mu = [1, p])
        let m = d.m();
        let mut slab_rows = Vec::with_capacity(n * (d.r + d.l + m));
        for row in rows.chunks_exact(w) {
            slab_rows.extend_from_slice(&row[..d.r + d.l]);
            slab_rows.push(1.0);
            slab_rows.extend_from_slice(&row[d.r + d.l..]);
        }
        let slab = Slab::new(&slab_rows, d.r, d.l, m)?;
        let len = self.gram.dim();
        let windows = n - d.p;
        let mut gram = Gram::new(len, vec![0.0; packed_len(len)])?;
        let row = |k: usize, dst: &mut [f64]| {
            write_stat_vector(&d, StatsLayout::Extended, &slab, k, dst);
        };
        crate::linalg::gram_add_rows(&mut gram, 0..windows, &row).map_err(|e| {
            Error::Data(DataError::new(
                source,
                None,
                None,
                format!("windows 0..{windows}: {e}"),
            ))
        })?;
        self.gram.merge(&gram)?;
        self.experiments += 1;
        Ok(windows as u64)
    }

    /// Add one experiment given as signals (u N x r, y N x l, p N x s).
    pub fn add_signals(&mut self, sig: &Signals, source: &str) -> Result<u64, Error> {
        let d = self.dims;
        if sig.u.ncols() != d.r || sig.y.ncols() != d.l || sig.p.ncols() != d.s {
            return Err(Error::Data(DataError::new(
                source,
                None,
                None,
                format!(
                    "the experiment has {} inputs, {} outputs, {} scheduling signals; the statistics are for {}, {}, {}",
                    sig.u.ncols(),
                    sig.y.ncols(),
                    sig.p.ncols(),
                    d.r,
                    d.l,
                    d.s
                ),
            )));
        }
        let mut rows = Vec::with_capacity(sig.len() * (d.r + d.l + d.s));
        for k in 0..sig.len() {
            rows.extend(sig.u.row(k).iter());
            rows.extend(sig.y.row(k).iter());
            rows.extend(sig.p.row(k).iter());
        }
        self.add_experiment(&rows, source)
    }

    /// Add `other`'s statistics (the experiments of both). Dimensions must agree; on error
    /// nothing changes.
    pub fn merge(&mut self, other: &Statistics) -> Result<(), Error> {
        if self.dims != other.dims {
            return Err(data_error(format!(
                "cannot merge statistics of {} with statistics of {}",
                dims_text(&other.dims),
                dims_text(&self.dims)
            )));
        }
        self.gram.merge(&other.gram)?;
        self.experiments += other.experiments;
        Ok(())
    }

    /// Size of the encoding for `dims` (bytes).
    pub fn encoded_len(dims: &PbsidDims) -> Result<usize, Error> {
        let len = stat_vector_len(dims, StatsLayout::Extended)?;
        Ok(HEADER_LEN + 8 * packed_len(len) + TRAILER_LEN)
    }

    /// The versioned encoding (`docs/wire.md` section 7).
    pub fn to_bytes(&self) -> Vec<u8> {
        let values = self.gram.packed();
        let mut out = Vec::with_capacity(HEADER_LEN + 8 * values.len() + TRAILER_LEN);
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.push(LAYOUT_EXTENDED);
        out.push(8);
        for v in [self.dims.r, self.dims.l, self.dims.s, self.dims.p] {
            out.extend_from_slice(&(v as u32).to_le_bytes());
        }
        out.extend_from_slice(&self.gram.count().to_le_bytes());
        out.extend_from_slice(&self.experiments.to_le_bytes());
        out.extend_from_slice(&(values.len() as u64).to_le_bytes());
        for v in values {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let crc = lpvid::protocol::crc32(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Decode [`Statistics::to_bytes`]' encoding (values in f64, or f32 as an f32 device
    /// accumulates them, widened). Every field is checked; the error says which is wrong.
    pub fn from_bytes(bytes: &[u8]) -> Result<Statistics, Error> {
        if bytes.len() < HEADER_LEN + TRAILER_LEN {
            return Err(data_error(format!(
                "{} bytes: too short for statistics (the header alone is {HEADER_LEN} bytes)",
                bytes.len()
            )));
        }
        if bytes[..4] != MAGIC {
            return Err(data_error(format!(
                "not lpvid statistics: the bytes start with {:02x?}, not \"LPVS\"",
                &bytes[..4]
            )));
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
        let version = u16_at(4);
        if version != VERSION {
            return Err(data_error(format!(
                "statistics encoding version {version}; this lpvid reads version {VERSION}"
            )));
        }
        match bytes[6] {
            LAYOUT_EXTENDED => {}
            LAYOUT_PLAIN => {
                return Err(data_error(
                    "plain-layout statistics: a fit from statistics needs the extended layout",
                ))
            }
            other => return Err(data_error(format!("unknown statistics layout {other}"))),
        }
        let fb = bytes[7] as usize;
        if fb != 8 && fb != 4 {
            return Err(data_error(format!(
                "float size {fb} bytes: statistics values are f64 (8) or f32 (4)"
            )));
        }
        let [r, l, s, p] = [8, 12, 16, 20].map(|o| u32_at(o) as usize);
        let dims = PbsidDims::new(r, l, s, p).map_err(|e| {
            data_error(format!(
                "bad dimensions r = {r}, l = {l}, s = {s}, p = {p}: {e}"
            ))
        })?;
        let windows = u64_at(24);
        let experiments = u64_at(32);
        let count = u64_at(40);
        let len = stat_vector_len(&dims, StatsLayout::Extended)?;
        let expected = packed_len(len);
        if count != expected as u64 {
            return Err(data_error(format!(
                "{count} values, but {} has {expected}",
                dims_text(&dims)
            )));
        }
        let total = HEADER_LEN + fb * expected + TRAILER_LEN;
        if bytes.len() != total {
            return Err(data_error(format!(
                "{} bytes, but {} in {}-byte floats encode as {total}",
                bytes.len(),
                dims_text(&dims),
                fb
            )));
        }
        let body = &bytes[..total - TRAILER_LEN];
        let crc = u32_at(total - TRAILER_LEN);
        let computed = lpvid::protocol::crc32(body);
        if crc != computed {
            return Err(data_error(format!(
                "CRC-32 mismatch (stored {crc:08x}, computed {computed:08x}): the bytes were damaged"
            )));
        }
        let values: Vec<f64> = body[HEADER_LEN..]
            .chunks_exact(fb)
            .map(|c| {
                if fb == 8 {
                    f64::from_le_bytes(c.try_into().expect("8 bytes"))
                } else {
                    f32::from_le_bytes(c.try_into().expect("4 bytes")) as f64
                }
            })
            .collect();
        Statistics::from_packed(dims, &values, windows, experiments)
    }

    /// Statistics from a packed extended Gram as a device holds them (`lpvid device pull`):
    /// `windows` windows of `experiments` experiments.
    pub fn from_packed(
        dims: PbsidDims,
        values: &[f64],
        windows: u64,
        experiments: u64,
    ) -> Result<Statistics, Error> {
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(data_error(format!("value {i} is not finite")));
        }
        let mut st = Statistics::new(dims)?;
        st.gram.load(values, windows)?;
        st.experiments = experiments;
        Ok(st)
    }

    /// LPV-PBSID_opt from these statistics ([`crate::pipeline::identify_from_stats`]): the
    /// model file (its `fit` record's `source` says how many experiments and windows) and
    /// the fit. `opts.past` must be the statistics' past window.
    pub fn identify(&self, opts: &PbsidOptions) -> Result<(ModelFile, PbsidFit), Error> {
        crate::pipeline::identify_from_stats(&self.gram, &self.dims, opts, self.source_record())
    }

    /// `{"statistics": {...}}` as the `fit` record's `source`.
    pub fn source_record(&self) -> Value {
        json!({
            "statistics": {
                "encoding_version": VERSION,
                "layout": "extended",
                "experiments": self.experiments,
                "windows": self.windows(),
                "bytes": HEADER_LEN + 8 * self.gram.packed().len() + TRAILER_LEN,
            }
        })
    }
}

/// The data column of value `j` of a sample row `[u, y, p]` (u1.., y1.., p1..).
fn column_name(d: &PbsidDims, j: usize) -> String {
    if j < d.r {
        format!("u{}", j + 1)
    } else if j < d.r + d.l {
        format!("y{}", j - d.r + 1)
    } else {
        format!("p{}", j - d.r - d.l + 1)
    }
}

fn dims_text(d: &PbsidDims) -> String {
    format!("r = {}, l = {}, s = {}, p = {}", d.r, d.l, d.s, d.p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Dataset;
    use crate::link::compare::host_stats;
    use crate::model::ModelKind;
    use crate::pipeline::training_signals;

    fn b1() -> Signals {
        let ds = Dataset::parse(
            "fixtures/b1-train.csv",
            &include_bytes!("../../fixtures/b1-train.csv")[..],
        )
        .unwrap();
        training_signals(&ds, 3).unwrap().1
    }

    fn dims_of(sig: &Signals, p: usize) -> PbsidDims {
        PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), p).unwrap()
    }

    #[test]
    fn one_experiment_equals_pbsid_stats() {
        let sig = b1();
        let mut st = Statistics::new(dims_of(&sig, 3)).unwrap();
        st.add_signals(&sig, "b1").unwrap();
        let core = host_stats::<f64>(&sig, 3, StatsLayout::Extended).unwrap();
        assert_eq!(st.windows(), core.gram().count());
        let diff = crate::link::compare::gram_difference(st.gram().packed(), core.gram());
        assert!(diff < 1e-12, "{diff}");
    }

    #[test]
    fn experiments_windowed_apart_and_merge_in_any_grouping() {
        let sig = b1();
        let n = sig.len();
        let parts = [(0, n / 3), (n / 3, n / 3), (2 * n / 3, n - 2 * n / 3)];
        let d = dims_of(&sig, 3);
        let mut seq = Statistics::new(d).unwrap();
        let mut each = Vec::new();
        for &(a, len) in &parts {
            let part = sig.slice(a, len);
            seq.add_signals(&part, "part").unwrap();
            let mut one = Statistics::new(d).unwrap();
            one.add_signals(&part, "part").unwrap();
            each.push(one);
        }
        // windows never cross experiments: 3 experiments lose 2 x p windows
        assert_eq!(seq.windows() as usize, n - 3 * 3);
        assert_eq!(seq.experiments(), 3);
        let mut tree = each[2].clone();
        let mut left = each[0].clone();
        left.merge(&each[1]).unwrap();
        tree.merge(&left).unwrap();
        assert_eq!(tree.windows(), seq.windows());
        assert_eq!(tree.experiments(), 3);
        let diff = crate::link::compare::gram_difference(tree.gram().packed(), seq.gram());
        assert!(diff < 1e-13, "{diff}");
    }

    #[test]
    fn bytes_round_trip_exactly_and_fit() {
        let sig = b1();
        let mut st = Statistics::new(dims_of(&sig, 3)).unwrap();
        st.add_signals(&sig, "b1").unwrap();
        let bytes = st.to_bytes();
        assert_eq!(bytes.len(), Statistics::encoded_len(&st.dims()).unwrap());
        assert_eq!(&bytes[..4], b"LPVS");
        let back = Statistics::from_bytes(&bytes).unwrap();
        assert_eq!(back.gram().packed(), st.gram().packed());
        assert_eq!(back.windows(), st.windows());
        assert_eq!(back.experiments(), 1);
        let (model, fit) = back.identify(&PbsidOptions::new(3)).unwrap();
        assert_eq!(fit.order, 4);
        assert!(matches!(model.kind, ModelKind::Ss(_)));
        assert_eq!(model.fit["source"]["statistics"]["experiments"], 1);
    }

    #[test]
    fn bad_bytes_say_what_is_wrong() {
        let sig = b1();
        let mut st = Statistics::new(dims_of(&sig, 2)).unwrap();
        st.add_signals(&sig, "b1").unwrap();
        let good = st.to_bytes();
        let msg = |b: &[u8]| Statistics::from_bytes(b).unwrap_err().to_string();
        assert!(msg(&good[..10]).contains("too short"));
        let mut m = good.clone();
        m[0] = b'X';
        assert!(msg(&m).contains("not lpvid statistics"));
        let mut v = good.clone();
        v[4] = 9;
        assert!(msg(&v).contains("version 9"));
        let mut c = good.clone();
        let last = HEADER_LEN + 3;
        c[last] ^= 0x55;
        assert!(msg(&c).contains("CRC-32"));
        assert!(msg(&good[..good.len() - 1]).contains("bytes, but"));
    }

    #[test]
    fn bad_samples_are_refused_whole() {
        let sig = b1();
        let d = dims_of(&sig, 2);
        let mut st = Statistics::new(d).unwrap();
        let w = d.r + d.l + d.s;
        let mut rows = vec![0.5; 10 * w];
        rows[3 * w + d.r] = f64::NAN;
        let e = st.add_experiment(&rows, "exp7").unwrap_err().to_string();
        assert!(e.starts_with("exp7: column 'y1'"), "{e}");
        assert_eq!(st.experiments(), 0);
        assert_eq!(st.windows(), 0);
        let e = st.add_experiment(&rows[..w + 1], "exp8").unwrap_err();
        assert!(e.to_string().contains("whole samples"));
        let other = Statistics::new(PbsidDims::new(d.r, d.l, d.s, 3).unwrap()).unwrap();
        assert!(st
            .merge(&other)
            .unwrap_err()
            .to_string()
            .contains("cannot merge"));
    }
}
