//! Data files (DESIGN.md section 5): CSV with one header line and one row per sample;
//! `u1..ur` inputs, `y1..yl` outputs, `p1..ps` scheduling, any other column carried along.
//! Every problem gives one [`DataError`] naming file, line and column; writes are atomic.

use std::fmt;
use std::fs;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use crate::lpvss::Signals;

/// An error in a data or model file: where it is (file, 1-based line, column) and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DataError {
    /// The file name (as given by the caller), always set.
    pub file: String,
    /// 1-based line in the file (the CSV header is line 1), when known.
    pub line: Option<usize>,
    /// The CSV column name concerned, when there is one.
    pub column: Option<String>,
    /// What is wrong, in words.
    pub message: String,
}

impl DataError {
    /// An error with every location part given explicitly.
    pub fn new(
        file: impl Into<String>,
        line: Option<usize>,
        column: Option<&str>,
        message: impl Into<String>,
    ) -> DataError {
        DataError {
            file: file.into(),
            line,
            column: column.map(str::to_owned),
            message: message.into(),
        }
    }
}

impl fmt::Display for DataError {
    /// `file:line: column 'name': message`, leaving out the parts that are unknown. The
    /// column is not repeated when the message already starts by naming it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        match &self.column {
            Some(c) if !self.message.starts_with(&format!("column '{c}'")) => {
                write!(f, ": column '{c}': {}", self.message)
            }
            _ => write!(f, ": {}", self.message),
        }
    }
}

impl std::error::Error for DataError {}

/// A data file in memory: named columns of finite numbers, all of the same length.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// The file name used in error messages.
    pub source: String,
    /// Column names, in file order.
    pub names: Vec<String>,
    /// Column-major values, one `Vec` per name.
    pub cols: Vec<Vec<f64>>,
}

/// Parse one CSV field as a finite number, or say why it is not one.
fn parse_number(text: &str) -> Result<f64, String> {
    if text.is_empty() {
        return Err("empty field where a number is expected".into());
    }
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!(
            "\"{text}\" is not finite (NaN and infinite values are not allowed)"
        )),
        Err(_) => Err(format!("\"{text}\" is not a number")),
    }
}

impl Dataset {
    /// Read and check a CSV data file; errors name the file as `path` displays.
    pub fn read_csv(path: &Path) -> Result<Dataset, DataError> {
        let source = path.display().to_string();
        let file = fs::File::open(path)
            .map_err(|e| DataError::new(&source, None, None, format!("cannot open: {e}")))?;
        Dataset::parse(&source, std::io::BufReader::new(file))
    }

    /// Parse CSV text from `reader`; `source` is the file name used in errors.
    pub fn parse(source: &str, mut reader: impl Read) -> Result<Dataset, DataError> {
        let err = |line: Option<usize>, col: Option<&str>, msg: String| {
            DataError::new(source, line, col, msg)
        };
        // Read it all: line numbers are counted from byte offsets (the csv crate's own line
        // count skips blank lines).
        let mut bytes = Vec::new();
        reader
            .read_to_end(&mut bytes)
            .map_err(|e| err(None, None, format!("cannot read: {e}")))?;
        let body = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(&bytes);
        let lines = std::cell::RefCell::new(LineCounter::new(body));
        let line_of = |pos: Option<&csv::Position>| {
            pos.map(|p| lines.borrow_mut().line_at(p.byte() as usize))
        };
        let mut rdr = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .trim(csv::Trim::All)
            .from_reader(body);
        let mut records = rdr.records();
        let csv_err = |e: csv::Error| {
            let line = line_of(e.position());
            let msg = match e.kind() {
                csv::ErrorKind::Utf8 { .. } => "invalid UTF-8 text".to_string(),
                csv::ErrorKind::Io(io) => format!("cannot read: {io}"),
                _ => e.to_string(),
            };
            DataError::new(source, line, None, msg)
        };
        // Header: the first record that is not a blank line.
        let header = loop {
            match records.next() {
                None => {
                    return Err(err(
                        Some(1),
                        None,
                        "empty file: expected a header line such as u1,y1,p1".into(),
                    ))
                }
                Some(Err(e)) => return Err(csv_err(e)),
                Some(Ok(r)) if is_blank(&r) => continue,
                Some(Ok(r)) => break r,
            }
        };
        let header_line = line_of(header.position()).unwrap_or(1);
        let mut names: Vec<String> = Vec::with_capacity(header.len());
        for (i, name) in header.iter().enumerate() {
            let name = name.trim();
            if name.is_empty() {
                return Err(err(
                    Some(header_line),
                    None,
                    format!(
                        "the header's field {} is empty: every column needs a name",
                        i + 1
                    ),
                ));
            }
            if let Some(j) = names.iter().position(|n| n == name) {
                return Err(err(
                    Some(header_line),
                    Some(name),
                    format!(
                        "duplicate column name (fields {} and {} of the header)",
                        j + 1,
                        i + 1
                    ),
                ));
            }
            names.push(name.to_owned());
        }
        if names.iter().all(|n| parse_number(n).is_ok()) {
            return Err(err(
                Some(header_line),
                None,
                format!(
                    "the first line \"{}\" looks like data, not a header: expected column names \
                     such as u1,y1,p1",
                    names.join(",")
                ),
            ));
        }
        let width = names.len();
        let mut cols: Vec<Vec<f64>> = vec![Vec::new(); width];
        for rec in records {
            let rec = rec.map_err(csv_err)?;
            if is_blank(&rec) {
                continue;
            }
            let line = line_of(rec.position());
            if rec.len() != width {
                let col = names.get(rec.len()).map(String::as_str);
                let what = if rec.len() < width {
                    "missing values"
                } else {
                    "too many values"
                };
                return Err(err(
                    line,
                    col,
                    format!(
                        "expected {width} fields, found {} ({what}; the header is {})",
                        rec.len(),
                        names.join(",")
                    ),
                ));
            }
            for ((field, name), col) in rec.iter().zip(&names).zip(cols.iter_mut()) {
                let v = parse_number(field).map_err(|m| err(line, Some(name), m))?;
                col.push(v);
            }
        }
        if cols[0].is_empty() {
            return Err(err(
                Some(header_line),
                None,
                "no data rows after the header".into(),
            ));
        }
        Ok(Dataset {
            source: source.to_owned(),
            names,
            cols,
        })
    }

    /// Number of samples (rows).
    pub fn len(&self) -> usize {
        self.cols.first().map_or(0, Vec::len)
    }

    /// True when there is no sample.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values of column `name`, if present.
    pub fn column(&self, name: &str) -> Option<&[f64]> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| self.cols[i].as_slice())
    }

    /// The names `prefix1, prefix2, ...` present contiguously from 1 (`u1,u2,u4` gives `u1,u2`).
    pub fn channels(&self, prefix: char) -> Vec<String> {
        (1..)
            .map(|i| format!("{prefix}{i}"))
            .take_while(|n| self.names.contains(n))
            .collect()
    }

    /// A dataset with columns u1..ur, y1..yl, p1..ps holding the signals of `sig`.
    pub fn from_signals(sig: &Signals, source: &str) -> Dataset {
        let mut names = Vec::new();
        let mut cols = Vec::new();
        for (prefix, m) in [('u', &sig.u), ('y', &sig.y), ('p', &sig.p)] {
            for j in 0..m.ncols() {
                names.push(format!("{prefix}{}", j + 1));
                cols.push(m.column(j).iter().copied().collect());
            }
        }
        Dataset {
            source: source.to_owned(),
            names,
            cols,
        }
    }

    /// Write as CSV (full f64 precision), atomically: a temporary file in the same
    /// directory renamed over `path`, so a failure never leaves a half-written file.
    pub fn write_csv(&self, path: &Path) -> Result<(), DataError> {
        let file = path.display().to_string();
        if self.cols.len() != self.names.len() || self.cols.iter().any(|c| c.len() != self.len()) {
            return Err(DataError::new(
                &file,
                None,
                None,
                "not written: columns and names disagree or columns differ in length",
            ));
        }
        for (name, col) in self.names.iter().zip(&self.cols) {
            if let Some(k) = col.iter().position(|v| !v.is_finite()) {
                return Err(DataError::new(
                    &file,
                    Some(k + 2),
                    Some(name),
                    format!("not written: value {} is not finite", col[k]),
                ));
            }
        }
        let mut w = csv::WriterBuilder::new().from_writer(Vec::new());
        let io = |e: csv::Error| DataError::new(&file, None, None, format!("cannot write: {e}"));
        w.write_record(&self.names).map_err(io)?;
        let mut row = Vec::with_capacity(self.names.len());
        for k in 0..self.len() {
            row.clear();
            row.extend(self.cols.iter().map(|c| format!("{}", c[k])));
            w.write_record(&row).map_err(io)?;
        }
        let bytes = w
            .into_inner()
            .map_err(|e| DataError::new(&file, None, None, format!("cannot write: {e}")))?;
        write_atomic(path, &bytes)
    }

    /// Error unless column `name` exists and varies: a constant regressor carries no
    /// information and makes a least-squares fit rank deficient.
    pub fn check_not_constant(&self, name: &str) -> Result<(), DataError> {
        let col = self.column(name).ok_or_else(|| {
            DataError::new(
                &self.source,
                Some(1),
                Some(name),
                format!(
                    "column '{name}' is missing (columns are: {})",
                    self.names.join(", ")
                ),
            )
        })?;
        match col.first() {
            Some(&v0) if col.iter().all(|&v| v == v0) => Err(DataError::new(
                &self.source,
                None,
                Some(name),
                format!(
                    "column '{name}' is constant (value {v0}): it carries no information and \
                     makes the regression rank deficient"
                ),
            )),
            _ => Ok(()),
        }
    }
}

/// 1-based line numbers of byte offsets, for offsets asked in increasing order.
struct LineCounter<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> LineCounter<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        LineCounter {
            bytes,
            pos: 0,
            line: 1,
        }
    }

    /// The line holding byte `offset` (a `\n`, or a `\r` not followed by `\n`, ends a line).
    fn line_at(&mut self, offset: usize) -> usize {
        let mut offset = offset.min(self.bytes.len());
        // a record's position is where the parser started, before any blank lines it skipped
        while offset < self.bytes.len() && matches!(self.bytes[offset], b'\n' | b'\r') {
            offset += 1;
        }
        if offset < self.pos {
            self.pos = 0;
            self.line = 1;
        }
        for i in self.pos..offset {
            match self.bytes[i] {
                b'\n' => self.line += 1,
                b'\r' if self.bytes.get(i + 1) != Some(&b'\n') => self.line += 1,
                _ => {}
            }
        }
        self.pos = offset;
        self.line
    }
}

/// A record that is a blank (or whitespace-only) line.
fn is_blank(r: &csv::StringRecord) -> bool {
    r.is_empty() || (r.len() == 1 && r[0].is_empty())
}

/// Write `bytes` to `path` through a temporary file in the same directory and a rename, so
/// readers see either the old file or the complete new one.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let file = path.display().to_string();
    let fail = |what: &str, e: std::io::Error| {
        DataError::new(&file, None, None, format!("cannot write ({what}): {e}"))
    };
    let name = path
        .file_name()
        .ok_or_else(|| DataError::new(&file, None, None, "cannot write: not a file name"))?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    static COUNTER: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let unique = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    tmp_name.push(format!(".{}-{unique}.tmp", std::process::id()));
    let tmp = dir.join(tmp_name);
    let result = (|| {
        let mut f = fs::File::create(&tmp).map_err(|e| fail("create temporary file", e))?;
        f.write_all(bytes).map_err(|e| fail("write", e))?;
        f.sync_all().map_err(|e| fail("sync", e))?;
        drop(f);
        fs::rename(&tmp, path).map_err(|e| fail("rename temporary file", e))
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    fn parse(text: &str) -> Result<Dataset, DataError> {
        Dataset::parse("d.csv", text.as_bytes())
    }

    fn parse_err(text: &str) -> DataError {
        let e = parse(text).expect_err("expected an error");
        assert_eq!(e.file, "d.csv");
        assert!(e.to_string().starts_with("d.csv"), "{e}");
        e
    }

    #[test]
    fn parses_columns_whitespace_scientific_and_bom() {
        let ds = parse("\u{feff}t, u1 ,y1,p1\n0, 1e-3 , -2.5E+2, .5\n\n1,2,3,4\n").unwrap();
        assert_eq!(ds.names, ["t", "u1", "y1", "p1"]);
        assert_eq!(ds.len(), 2);
        assert_eq!(ds.column("u1").unwrap(), &[1e-3, 2.0]);
        assert_eq!(ds.column("y1").unwrap(), &[-250.0, 3.0]);
        assert_eq!(ds.column("p1").unwrap(), &[0.5, 4.0]);
        assert!(ds.column("u2").is_none());
        assert_eq!(ds.source, "d.csv");
    }

    #[test]
    fn channels_are_contiguous_from_one() {
        let ds = parse("u1,u2,u4,y1,p2,q_ref\n1,2,3,4,5,6\n").unwrap();
        assert_eq!(ds.channels('u'), ["u1", "u2"]);
        assert_eq!(ds.channels('y'), ["y1"]);
        assert!(ds.channels('p').is_empty());
    }

    #[test]
    fn empty_file() {
        for text in ["", "\n\n", "  \n"] {
            let e = parse_err(text);
            assert_eq!(e.line, Some(1));
            assert!(e.message.contains("empty file"), "{e}");
        }
    }

    #[test]
    fn duplicate_column() {
        let e = parse_err("u1,y1,u1\n1,2,3\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("u1")));
        assert_eq!(
            e.to_string(),
            "d.csv:1: column 'u1': duplicate column name (fields 1 and 3 of the header)"
        );
    }

    #[test]
    fn empty_header_name_and_numeric_header() {
        let e = parse_err("u1,,y1\n1,2,3\n");
        assert_eq!(e.line, Some(1));
        assert!(e.message.contains("field 2"), "{e}");
        let e = parse_err("1,2\n3,4\n");
        assert!(e.message.contains("looks like data"), "{e}");
    }

    #[test]
    fn ragged_rows() {
        let e = parse_err("u1,y1,p1\n1,2,3\n1,2\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("p1")));
        assert!(e.message.contains("expected 3 fields, found 2"), "{e}");
        assert!(e
            .to_string()
            .starts_with("d.csv:3: column 'p1': expected 3 fields"));
        let e = parse_err("u1,y1\n1,2\n\n1,2,3\n");
        assert_eq!(e.line, Some(4));
        assert!(e.message.contains("expected 2 fields, found 3"), "{e}");
        let e = parse_err("u1,y1\r\n1,2\r\n\r\n  \r\n\r\n1,x\r\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(6), Some("y1")));
        let e = parse_err("\n\nu1,y1\n1,2,3\n");
        assert_eq!(e.line, Some(4));
    }

    #[test]
    fn not_a_number() {
        let e = parse_err("u1,y1\n1,2\n3,abc\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("y1")));
        assert_eq!(
            e.to_string(),
            "d.csv:3: column 'y1': \"abc\" is not a number"
        );
        let e = parse_err("u1,y1\n1, \n");
        assert_eq!((e.line, e.column.as_deref()), (Some(2), Some("y1")));
        assert!(e.message.contains("empty field"), "{e}");
    }

    #[test]
    fn non_finite_values() {
        for bad in [
            "nan",
            "NaN",
            "inf",
            "-inf",
            "Infinity",
            "-INFINITY",
            "1e999",
        ] {
            let e = parse_err(&format!("u1,y1\n1,2\n{bad},3\n"));
            assert_eq!(
                (e.line, e.column.as_deref()),
                (Some(3), Some("u1")),
                "{bad}"
            );
            assert!(e.message.contains("not finite"), "{e}");
            assert!(e.message.contains(bad), "{e}");
        }
    }

    #[test]
    fn no_data_rows() {
        let e = parse_err("u1,y1\n");
        assert_eq!(e.line, Some(1));
        assert!(e.message.contains("no data rows"), "{e}");
    }

    #[test]
    fn invalid_utf8() {
        let e = Dataset::parse("d.csv", &b"u1,y1\n1,\xff\n"[..]).unwrap_err();
        assert_eq!(e.line, Some(2));
        assert!(e.message.contains("UTF-8"), "{e}");
    }

    #[test]
    fn constant_column() {
        let ds = parse("u1,u2,y1\n1,0.5,1\n2,0.5,3\n").unwrap();
        ds.check_not_constant("u1").unwrap();
        let e = ds.check_not_constant("u2").unwrap_err();
        assert_eq!(e.column.as_deref(), Some("u2"));
        assert_eq!(
            e.to_string(),
            "d.csv: column 'u2' is constant (value 0.5): it carries no information and makes \
             the regression rank deficient"
        );
        let e = ds.check_not_constant("p1").unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("p1")));
    }

    #[test]
    fn signals_round_trip_through_a_file() {
        let sig = Signals {
            u: DMatrix::from_row_slice(3, 2, &[0.1, 1.0 / 3.0, -2.0, 5e-300, 1e300, 7.0]),
            y: DMatrix::from_row_slice(3, 1, &[std::f64::consts::PI, -0.0, 2.5]),
            p: DMatrix::from_row_slice(3, 1, &[0.3, 0.2, 0.1]),
        };
        let ds = Dataset::from_signals(&sig, "mem");
        assert_eq!(ds.names, ["u1", "u2", "y1", "p1"]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        ds.write_csv(&path).unwrap();
        let back = Dataset::read_csv(&path).unwrap();
        assert_eq!(back.names, ds.names);
        assert_eq!(back.cols, ds.cols);
        assert_eq!(back.source, path.display().to_string());
        // only the final file is left behind
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn write_refuses_non_finite_and_keeps_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        std::fs::write(&path, "old").unwrap();
        let ds = Dataset {
            source: "mem".into(),
            names: vec!["u1".into(), "y1".into()],
            cols: vec![vec![1.0, 2.0], vec![3.0, f64::NAN]],
        };
        let e = ds.write_csv(&path).unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("y1")));
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
    }

    #[test]
    fn quoted_names_survive_writing() {
        let ds = Dataset {
            source: "mem".into(),
            names: vec!["u1".into(), "y1".into(), "note, with comma".into()],
            cols: vec![vec![1.0], vec![2.0], vec![3.0]],
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("q.csv");
        ds.write_csv(&path).unwrap();
        let back = Dataset::read_csv(&path).unwrap();
        assert_eq!(back.names, ds.names);
    }

    #[test]
    fn missing_file() {
        let e = Dataset::read_csv(Path::new("/nonexistent/x.csv")).unwrap_err();
        assert_eq!(e.file, "/nonexistent/x.csv");
        assert!(e.message.contains("cannot open"), "{e}");
    }
}
