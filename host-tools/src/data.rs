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
        Err(_) if text.contains([';', '\t', ',']) => Err(format!(
            "\"{text}\" is not a number: the separator or the decimal point looks wrong (lpvid \
             reads ',' as the separator and '.' as the decimal point)"
        )),
        Err(_) => Err(format!("\"{text}\" is not a number")),
    }
}

/// Longest line a data or model file may have (a file that never ends, such as
/// `/dev/zero`, is stopped here instead of filling the memory).
pub const MAX_LINE_BYTES: usize = 1 << 20;

/// Most bytes read from a pipe (a regular file's size is known; a pipe could run forever).
pub const MAX_PIPE_BYTES: u64 = 1 << 30;

/// The separator a one-field header uses instead of a comma (`;`, a tab), if it looks so.
fn foreign_separator(header: &csv::StringRecord) -> Option<&'static str> {
    if header.len() != 1 {
        return None;
    }
    let h = &header[0];
    if h.contains(';') {
        Some("';'")
    } else if h.contains('\t') {
        Some("a tab")
    } else if h.contains('|') {
        Some("'|'")
    } else if h.trim().contains(' ') && h.split_whitespace().count() > 1 {
        Some("spaces")
    } else {
        None
    }
}

/// The signal columns (`u`, `y`, `p` followed by a number without a leading zero) must be
/// numbered from 1 without gaps: `u2` without `u1`, or `u1,u3`, would otherwise silently
/// drop a signal. Returns the offending column and the message.
fn check_numbering(names: &[String]) -> Result<(), (String, String)> {
    for (prefix, what) in [('u', "input"), ('y', "output"), ('p', "scheduling signal")] {
        let mut nums: Vec<(u64, &str)> = names
            .iter()
            .filter_map(|n| {
                let rest = n.strip_prefix(prefix)?;
                if rest.starts_with('0') || !rest.bytes().all(|b| b.is_ascii_digit()) {
                    return None;
                }
                rest.parse::<u64>().ok().map(|k| (k, n.as_str()))
            })
            .collect();
        nums.sort_unstable();
        for (i, &(k, name)) in nums.iter().enumerate() {
            let want = i as u64 + 1;
            if k != want {
                let msg = if i == 0 {
                    format!(
                        "column '{name}': {what} columns are numbered from {prefix}1 without gaps, \
                         but there is no {prefix}1 (rename the columns {prefix}1, {prefix}2, ...; \
                         a logged signal that is not an {what} needs another name)"
                    )
                } else {
                    format!(
                        "column '{name}': {what} columns are numbered from {prefix}1 without gaps, \
                         but {prefix}{want} is missing (found {}; rename them {prefix}1..{prefix}{}, \
                         a logged signal needs another name)",
                        nums.iter().map(|n| n.1).collect::<Vec<_>>().join(","),
                        nums.len()
                    )
                };
                return Err((name.to_owned(), msg));
            }
        }
    }
    Ok(())
}

/// The first whitespace-only line after `header_line` that has a non-blank line after it
/// (1-based), as [`LineCounter`] counts lines.
fn inner_blank_line(body: &[u8], header_line: usize) -> Option<usize> {
    let (mut line, mut start) = (1usize, 0usize);
    let mut first_blank: Option<usize> = None;
    loop {
        let mut j = start;
        while j < body.len() && body[j] != b'\n' && body[j] != b'\r' {
            j += 1;
        }
        let at_end = j >= body.len();
        let blank = body[start..j].iter().all(u8::is_ascii_whitespace);
        if line > header_line {
            if !blank {
                if first_blank.is_some() {
                    return first_blank;
                }
            } else if !at_end && first_blank.is_none() {
                first_blank = Some(line);
            }
        }
        if at_end {
            return None;
        }
        start = if body[j] == b'\r' && body.get(j + 1) == Some(&b'\n') {
            j + 2
        } else {
            j + 1
        };
        line += 1;
    }
}

/// Bytes read per call in [`read_bounded`]; [`Dataset::parse_bytes`] checks bytes already
/// in memory in chunks of the same size, so both stop at the same line.
const READ_CHUNK: usize = 64 * 1024;

/// The line-length check of [`read_bounded`], one chunk at a time: the current line number
/// and the length of its part seen so far.
struct LineLimit {
    line: usize,
    line_len: usize,
}

impl LineLimit {
    fn new() -> Self {
        LineLimit {
            line: 1,
            line_len: 0,
        }
    }

    /// Account for the next `chunk`, or the error naming the line longer than
    /// [`MAX_LINE_BYTES`].
    fn check(&mut self, source: &str, chunk: &[u8]) -> Result<(), DataError> {
        let n = chunk.len();
        // a line only grows past the limit across chunk boundaries (chunks are smaller)
        let (grows, rest) = match (
            chunk.iter().position(|&b| b == b'\n'),
            chunk.iter().rposition(|&b| b == b'\n'),
        ) {
            (Some(first), Some(last)) => (first, Some(n - last - 1)),
            _ => (n, None),
        };
        if self.line_len + grows > MAX_LINE_BYTES {
            return Err(DataError::new(
                source,
                Some(self.line),
                None,
                format!(
                    "line longer than {} MiB: not a data file (a binary file or a device that \
                     never ends?)",
                    MAX_LINE_BYTES >> 20
                ),
            ));
        }
        match rest {
            Some(r) => {
                self.line += count_newlines(chunk);
                self.line_len = r;
            }
            None => self.line_len += n,
        }
        Ok(())
    }
}

/// Number of '\n' in `bytes`, counted in byte-wide sums over blocks of 255 (which cannot
/// overflow) that the compiler vectorises 16 or 32 bytes at a time.
fn count_newlines(bytes: &[u8]) -> usize {
    bytes
        .chunks(255)
        .map(|block| {
            let in_block = block
                .iter()
                .fold(0u8, |acc, &b| acc.wrapping_add(u8::from(b == b'\n')));
            usize::from(in_block)
        })
        .sum()
}

/// Read `reader` to its end, stopping with an error naming the line when a line is longer
/// than [`MAX_LINE_BYTES`] or the whole is longer than `limit` bytes.
fn read_bounded(source: &str, reader: &mut dyn Read, limit: u64) -> Result<Vec<u8>, DataError> {
    let mut bytes = Vec::new();
    let mut buf = vec![0u8; READ_CHUNK];
    let mut lines = LineLimit::new();
    loop {
        let n = match reader.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => {
                return Err(DataError::new(
                    source,
                    None,
                    None,
                    format!("cannot read: {e}"),
                ))
            }
        };
        lines.check(source, &buf[..n])?;
        bytes.extend_from_slice(&buf[..n]);
        if bytes.len() as u64 > limit {
            return Err(DataError::new(
                source,
                None,
                None,
                format!(
                    "more than {} MiB from a pipe: stopped reading (write the data to a file)",
                    limit >> 20
                ),
            ));
        }
    }
    Ok(bytes)
}

/// Read an input file whole, refusing what would never end: a regular file is read (lines
/// at most [`MAX_LINE_BYTES`]), a pipe (FIFO, `/dev/stdin` from a pipe) at most
/// [`MAX_PIPE_BYTES`]; a directory, a character or block device (`/dev/zero`,
/// `/dev/urandom`) or a socket is refused before reading.
pub fn read_input(path: &Path) -> Result<Vec<u8>, DataError> {
    use std::os::unix::fs::FileTypeExt;
    let source = path.display().to_string();
    let meta = fs::metadata(path)
        .map_err(|e| DataError::new(&source, None, None, format!("cannot open: {e}")))?;
    let ft = meta.file_type();
    let refuse = |what: &str| {
        Err(DataError::new(
            &source,
            None,
            None,
            format!(
                "is {what}, not a regular file: lpvid reads inputs from regular files or pipes"
            ),
        ))
    };
    if ft.is_dir() {
        return refuse("a directory");
    }
    if ft.is_char_device() {
        return refuse("a character device (it may never end)");
    }
    if ft.is_block_device() {
        return refuse("a block device");
    }
    if ft.is_socket() {
        return refuse("a socket");
    }
    let limit = if ft.is_fifo() {
        MAX_PIPE_BYTES
    } else {
        u64::MAX
    };
    let mut file = fs::File::open(path)
        .map_err(|e| DataError::new(&source, None, None, format!("cannot open: {e}")))?;
    read_bounded(&source, &mut file, limit)
}

impl Dataset {
    /// Read and check a CSV data file; errors name the file as `path` displays.
    pub fn read_csv(path: &Path) -> Result<Dataset, DataError> {
        let source = path.display().to_string();
        let bytes = read_input(path)?;
        Dataset::parse_read_input(&source, &bytes)
    }

    /// Parse CSV text from `reader`; `source` is the file name used in errors.
    pub fn parse(source: &str, mut reader: impl Read) -> Result<Dataset, DataError> {
        // Read it all: line numbers are counted from byte offsets (the csv crate's own line
        // count skips blank lines).
        let bytes = read_bounded(source, &mut reader, u64::MAX)?;
        Self::parse_checked(source, &bytes)
    }

    /// [`Dataset::parse`] of bytes already in memory, without copying them: the same checks
    /// (the line length in the same chunks first), the same data set or error.
    pub fn parse_bytes(source: &str, bytes: &[u8]) -> Result<Dataset, DataError> {
        let mut lines = LineLimit::new();
        for chunk in bytes.chunks(READ_CHUNK) {
            lines.check(source, chunk)?;
        }
        Self::parse_checked(source, bytes)
    }

    /// [`Dataset::parse_bytes`] of what [`read_input`] returned: its lines were checked
    /// while it read them (the check's outcome does not depend on how the bytes were split
    /// into reads: a line within one read is shorter than the limit), so it is not repeated.
    pub fn parse_read_input(source: &str, bytes: &[u8]) -> Result<Dataset, DataError> {
        Self::parse_checked(source, bytes)
    }

    /// The parse after the line-length check.
    fn parse_checked(source: &str, bytes: &[u8]) -> Result<Dataset, DataError> {
        let err = |line: Option<usize>, col: Option<&str>, msg: String| {
            DataError::new(source, line, col, msg)
        };
        let body = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(bytes);
        if let Some(ds) = plain_file(source, body) {
            return Ok(ds);
        }
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
        if let Some(sep) = foreign_separator(&header) {
            return Err(err(
                Some(header_line),
                None,
                format!(
                    "the header \"{}\" is one field: the separator looks like {sep}, but lpvid \
                     reads comma-separated files (separator ',', decimal point '.', e.g. \
                     u1,y1,p1 and 0.5,-1.25,0.3)",
                    header.iter().collect::<Vec<_>>().join(",")
                ),
            ));
        }
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
        check_numbering(&names).map_err(|(col, m)| err(Some(header_line), Some(&col), m))?;
        let width = names.len();
        // the common case, plain numbers in plain lines, without the csv crate's records;
        // anything else (an error to report, quotes, non-ASCII) takes the general path
        let mut rows_at = records.reader().position().byte() as usize;
        if rows_at > 0 && body.get(rows_at - 1) == Some(&b'\r') && body.get(rows_at) == Some(&b'\n')
        {
            rows_at += 1;
        }
        if let Some(cols) = body.get(rows_at..).and_then(|rows| plain_rows(rows, width)) {
            return Ok(Dataset {
                source: source.to_owned(),
                names,
                cols,
            });
        }
        let mut cols: Vec<Vec<f64>> = vec![Vec::new(); width];
        // a blank line is an error unless only blank lines follow it (the end of the file)
        let blank_at = inner_blank_line(body, header_line);
        for rec in records {
            let rec = rec.map_err(csv_err)?;
            if is_blank(&rec) {
                continue;
            }
            let line = line_of(rec.position());
            if let Some(b) = blank_at.filter(|&b| line.is_some_and(|l| l > b)) {
                return Err(err(
                    Some(b),
                    None,
                    format!(
                        "blank line in the middle of the data (the next row is line {}): \
                         remove it (blank lines are allowed only at the end of the file)",
                        line.map_or("?".into(), |l| l.to_string())
                    ),
                ));
            }
            if rec.len() != width {
                let col = names.get(rec.len()).map(String::as_str);
                let what = if rec.len() < width {
                    "missing values"
                } else if rec.len() % width == 0
                    || rec.iter().any(|f| f.contains(';') || f.contains('\t'))
                {
                    "too many values: a decimal comma? lpvid reads ',' as the separator and \
                     '.' as the decimal point"
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
        let bytes = self.to_csv_bytes(path)?;
        write_atomic(path, &bytes)
    }

    /// The CSV text [`Dataset::write_csv`] writes (`path` names the file in errors).
    pub fn to_csv_bytes(&self, path: &Path) -> Result<Vec<u8>, DataError> {
        self.csv_bytes(path, true)
    }

    /// [`Dataset::to_csv_bytes`] with or without the header line: the rows of a file
    /// written in chunks (`lpvid simulate` on a large file), the header with the first.
    pub fn csv_bytes(&self, path: &Path, header: bool) -> Result<Vec<u8>, DataError> {
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
        if header {
            w.write_record(&self.names).map_err(io)?;
        }
        let mut row = Vec::with_capacity(self.names.len());
        for k in 0..self.len() {
            row.clear();
            row.extend(self.cols.iter().map(|c| fmt_number(c[k])));
            w.write_record(&row).map_err(io)?;
        }
        let bytes = w
            .into_inner()
            .map_err(|e| DataError::new(&file, None, None, format!("cannot write: {e}")))?;
        Ok(bytes)
    }

    /// Error when column `name` (if present) holds values whose squares overflow or
    /// underflow in f64 (magnitudes above [`MAX_MAGNITUDE`], or all non-zero ones below
    /// its inverse): a scale problem, reported as such rather than as a constant column or a
    /// failed fit.
    pub fn check_scale(&self, name: &str) -> Result<(), DataError> {
        let Some(col) = self.column(name) else {
            return Ok(());
        };
        let (k, big) = col.iter().enumerate().fold((0, 0.0f64), |(kb, b), (k, v)| {
            if v.abs() > b {
                (k, v.abs())
            } else {
                (kb, b)
            }
        });
        if big > MAX_MAGNITUDE {
            return Err(DataError::new(
                &self.source,
                Some(k + 2),
                Some(name),
                format!(
                    "column '{name}': value {:e} is too large: the fit squares the data and \
                     values above {MAX_MAGNITUDE:e} overflow; rescale the column (e.g. divide it \
                     by 1e{})",
                    col[k],
                    big.log10().floor() as i32
                ),
            ));
        }
        if big > 0.0 && big < 1.0 / MAX_MAGNITUDE {
            return Err(DataError::new(
                &self.source,
                None,
                Some(name),
                format!(
                    "column '{name}': every value is below {:e} in magnitude (largest {big:e}): \
                     their squares underflow to zero; rescale the column (e.g. multiply it by \
                     1e{})",
                    1.0 / MAX_MAGNITUDE,
                    -(big.log10().floor() as i32)
                ),
            ));
        }
        Ok(())
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

/// A number as a data file writes it: the shortest text that reads back exactly, in plain
/// notation between 1e-5 and 1e16 in magnitude (as `{}` prints it) and in exponent notation
/// outside (`{}` would print 1e95 as 96 digits).
pub fn fmt_number(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || (1e-5..1e16).contains(&a) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Largest magnitude a fitted column may have: the fits form squares and products of the
/// data, and above about 1e150 they overflow (below 1e-150 they underflow to zero).
pub const MAX_MAGNITUDE: f64 = 1e150;

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

/// The data set of a plain file, read without building the csv crate's reader (its set-up
/// costs more than parsing a short file): the first line a header of names made of ASCII
/// letters, digits, '_' and spaces between commas that passes every check of the general
/// path (no foreign separator, no empty or duplicate name, not all numbers, signals numbered
/// from 1), then [`plain_rows`]. For such a header the csv reader's record is the same
/// trimmed fields, so the result is the general path's; `None` for anything else, which the
/// general path then reads or reports.
fn plain_file(source: &str, body: &[u8]) -> Option<Dataset> {
    let end = body.iter().position(|&b| b == b'\n')?;
    let line = &body[..end];
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    let plain = |b: &u8| b.is_ascii_alphanumeric() || matches!(b, b'_' | b',' | b' ');
    if line.trim_ascii().is_empty() || !line.iter().all(plain) {
        return None;
    }
    let line = std::str::from_utf8(line).ok()?;
    let mut names: Vec<String> = Vec::new();
    for name in line.split(',').map(str::trim) {
        if name.is_empty() || names.iter().any(|n| n == name) {
            return None;
        }
        names.push(name.to_owned());
    }
    let header = csv::StringRecord::from(names.clone());
    if foreign_separator(&header).is_some()
        || names.iter().all(|n| parse_number(n).is_ok())
        || check_numbering(&names).is_err()
    {
        return None;
    }
    let cols = plain_rows(&body[end + 1..], names.len())?;
    Some(Dataset {
        source: source.to_owned(),
        names,
        cols,
    })
}

/// The data rows of a CSV body (after its header) when every row is plain: ASCII without
/// quotes, lines ending in LF or CRLF, `width` comma-separated fields (surrounding
/// whitespace trimmed), each a finite number, blank lines only at the end, at least one row.
/// Such rows are read exactly as the csv crate's records are ([`Dataset::parse`]: the same
/// fields, the same `str::parse::<f64>`); `None` for anything else, which the general path
/// then reads or reports.
fn plain_rows(rows: &[u8], width: usize) -> Option<Vec<Vec<f64>>> {
    if width == 0 || !rows.is_ascii() || rows.contains(&b'"') {
        return None;
    }
    // ASCII: validated once as a whole, its lines and fields are then `str` slices (split at
    // ASCII bytes, so at character boundaries), found by memchr, not validated again
    let text = std::str::from_utf8(rows).ok()?;
    let estimate = rows.len() / (8 * width).max(1) + 1;
    let mut cols: Vec<Vec<f64>> = (0..width).map(|_| Vec::with_capacity(estimate)).collect();
    let mut blank_seen = false;
    for line in text.split('\n') {
        let line = line.strip_suffix('\r').unwrap_or(line);
        if line.contains('\r') {
            return None;
        }
        if line.trim_ascii().is_empty() {
            blank_seen = true;
            continue;
        }
        if blank_seen {
            return None;
        }
        let mut fields = line.split(',');
        for col in cols.iter_mut() {
            let field = fields.next()?.trim_ascii();
            if field.is_empty() {
                return None;
            }
            let v: f64 = field.parse().ok()?;
            if !v.is_finite() {
                return None;
            }
            col.push(v);
        }
        if fields.next().is_some() {
            return None;
        }
    }
    if cols[0].is_empty() {
        return None;
    }
    Some(cols)
}

/// A record that is a blank (or whitespace-only) line.
fn is_blank(r: &csv::StringRecord) -> bool {
    r.is_empty() || (r.len() == 1 && r[0].is_empty())
}

/// Write `bytes` to `path` through a temporary file in the same directory and a rename, so
/// readers see either the old file or the complete new one. A destination that exists and
/// is not a regular file (`/dev/null`, `/dev/full`, a FIFO, a terminal) is written through
/// instead, never replaced; a symbolic link is followed (its target is replaced, not the
/// link).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    stage_write(path, bytes)?.commit()
}

/// A write prepared by [`stage_write`]: for a regular destination the complete temporary
/// file next to it, for a non-regular one the bytes to write through. Nothing at the
/// destination has changed until [`StagedWrite::commit`] (or [`commit_all`]); dropping it
/// removes the temporary file.
#[derive(Debug)]
pub struct StagedWrite {
    /// The path as the caller gave it (for messages).
    shown: String,
    /// Where the bytes go (symbolic links resolved).
    target: PathBuf,
    /// The temporary file, or the bytes for a write-through destination.
    kind: Staged,
}

#[derive(Debug)]
enum Staged {
    Temp(Option<PathBuf>),
    Through(Vec<u8>),
}

/// The destination `path` resolves to (a symbolic link's target) and whether it is an
/// existing non-regular file that must be written through.
fn resolve_destination(path: &Path) -> (PathBuf, bool) {
    match fs::metadata(path) {
        Ok(m) => {
            let target = fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
            (target, !m.file_type().is_file())
        }
        Err(_) => (path.to_path_buf(), false),
    }
}

/// The directory a temporary file for `target` goes into.
fn dir_of(target: &Path) -> PathBuf {
    match target.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// A fresh temporary name next to `target`.
fn temp_path(target: &Path) -> Option<PathBuf> {
    static COUNTER: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let name = target.file_name()?;
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    let unique = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    tmp_name.push(format!(".{}-{unique}.tmp", std::process::id()));
    Some(dir_of(target).join(tmp_name))
}

/// Check, before any work, that `path` can be written: not a directory, and for a regular
/// (or new) file an existing directory where a file can be created (probed by creating
/// and removing a temporary file). A non-regular destination is accepted as it is.
pub fn check_destination(path: &Path) -> Result<(), DataError> {
    let file = path.display().to_string();
    let bad = |m: String| Err(DataError::new(&file, None, None, m));
    if path.file_name().is_none() {
        return bad("cannot write: not a file name".into());
    }
    if let Ok(m) = fs::metadata(path) {
        if m.is_dir() {
            return bad("cannot write: is a directory".into());
        }
    }
    let (target, through) = resolve_destination(path);
    if through {
        return Ok(());
    }
    let dir = dir_of(&target);
    match fs::metadata(&dir) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => {
            return bad(format!(
                "cannot write: {} is not a directory",
                dir.display()
            ))
        }
        Err(e) => {
            return bad(format!(
                "cannot write: directory {} does not exist ({e})",
                dir.display()
            ))
        }
    }
    let Some(probe) = temp_path(&target) else {
        return bad("cannot write: not a file name".into());
    };
    match fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => bad(format!(
            "cannot write: cannot create a file in {} ({e})",
            dir.display()
        )),
    }
}

/// Prepare writing `bytes` to `path` (see [`StagedWrite`]): a regular destination gets its
/// complete temporary file now (synced when it replaces a file: [`StagedWriter::finish`]),
/// so a later [`StagedWrite::commit`] is a rename.
pub fn stage_write(path: &Path, bytes: &[u8]) -> Result<StagedWrite, DataError> {
    let mut w = stage_writer(path)?;
    w.write(bytes)?;
    w.finish()
}

/// A [`StagedWrite`] being written piece by piece ([`stage_writer`]): what a command that
/// streams its output (`lpvid simulate` on a large file) writes through, so the temporary
/// file, not the output, grows; dropping it unfinished removes the temporary file.
#[derive(Debug)]
pub struct StagedWriter {
    // dropped first: flushed before the staged write removes the temporary file
    file: Option<std::io::BufWriter<fs::File>>,
    staged: StagedWrite,
    /// The destination exists: the temporary file is synced before the rename may replace it.
    sync: bool,
}

/// Start a [`StagedWrite`] to `path` written in pieces ([`StagedWriter::write`], then
/// [`StagedWriter::finish`]): the temporary file is created now; a write-through destination
/// (a device, a FIFO) collects the bytes and gets them at commit, as [`stage_write`] does.
pub fn stage_writer(path: &Path) -> Result<StagedWriter, DataError> {
    let shown = path.display().to_string();
    if path.file_name().is_none() {
        return Err(DataError::new(
            &shown,
            None,
            None,
            "cannot write: not a file name",
        ));
    }
    let (target, through) = resolve_destination(path);
    if through {
        return Ok(StagedWriter {
            staged: StagedWrite {
                shown,
                target,
                kind: Staged::Through(Vec::new()),
            },
            file: None,
            sync: false,
        });
    }
    let tmp = temp_path(&target)
        .ok_or_else(|| DataError::new(&shown, None, None, "cannot write: not a file name"))?;
    let staged = StagedWrite {
        shown,
        target,
        kind: Staged::Temp(Some(tmp.clone())),
    };
    let sync = fs::metadata(&staged.target).is_ok();
    let f = fs::File::create(&tmp).map_err(|e| staged.fail("create temporary file", e))?;
    Ok(StagedWriter {
        staged,
        file: Some(std::io::BufWriter::with_capacity(1 << 16, f)),
        sync,
    })
}

impl StagedWriter {
    /// Append `bytes`.
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), DataError> {
        match (&mut self.file, &mut self.staged.kind) {
            (Some(f), _) => f.write_all(bytes).map_err(|e| self.staged.fail("write", e)),
            (None, Staged::Through(buf)) => {
                buf.extend_from_slice(bytes);
                Ok(())
            }
            (None, Staged::Temp(_)) => Ok(()),
        }
    }

    /// The complete staged write: the temporary file flushed, and synced when it is to
    /// replace an existing file.
    ///
    /// What a failed run must not do, change a file, rests on the rename alone: until
    /// [`StagedWrite::commit`] the destination is untouched, and after it every reader sees
    /// the complete new file (rename(2) is atomic; the bytes are in the page cache). The
    /// sync adds durability against a power loss or kernel crash, which matters only when
    /// an existing file is replaced: without it some file systems (XFS; ext4 mounted with
    /// `noauto_da_alloc`) may commit the rename before the data, leaving an empty file
    /// where the user's old one was. A new destination has nothing to lose (after a crash
    /// it is absent, or empty, as if the run had not finished), so it is not synced: the
    /// sync costs 0.7-16 ms of waiting on the disk (strace -T, B2 model file), more than
    /// the whole fit of a small record. The directory was never synced, so the rename
    /// itself was not durable before either.
    pub fn finish(mut self) -> Result<StagedWrite, DataError> {
        if let Some(f) = self.file.take() {
            let f = f
                .into_inner()
                .map_err(|e| self.staged.fail("write", e.into_error()))?;
            if self.sync {
                f.sync_all().map_err(|e| self.staged.fail("sync", e))?;
            }
        }
        Ok(self.staged)
    }
}

impl StagedWrite {
    fn fail(&self, what: &str, e: std::io::Error) -> DataError {
        DataError::new(
            &self.shown,
            None,
            None,
            format!("cannot write ({what}): {e}"),
        )
    }

    /// The destination as the caller gave it.
    pub fn path(&self) -> &str {
        &self.shown
    }

    /// Put the bytes in place: rename the temporary file over the destination, or write
    /// through to a non-regular destination (a write error there, e.g. `/dev/full`, is an
    /// error).
    pub fn commit(mut self) -> Result<(), DataError> {
        let fail = |what: &str, e: std::io::Error| {
            DataError::new(
                &self.shown,
                None,
                None,
                format!("cannot write ({what}): {e}"),
            )
        };
        match &mut self.kind {
            Staged::Through(bytes) => {
                let mut f = fs::OpenOptions::new()
                    .write(true)
                    .truncate(true)
                    .open(&self.target)
                    .map_err(|e| fail("open", e))?;
                f.write_all(bytes).map_err(|e| fail("write", e))?;
                f.flush().map_err(|e| fail("write", e))?;
                Ok(())
            }
            Staged::Temp(tmp) => {
                let t = tmp
                    .take()
                    .expect("a staged temporary file is committed once");
                fs::rename(&t, &self.target).map_err(|e| {
                    let _ = fs::remove_file(&t);
                    fail("rename temporary file", e)
                })
            }
        }
    }

    fn is_through(&self) -> bool {
        matches!(self.kind, Staged::Through(_))
    }
}

impl Drop for StagedWrite {
    fn drop(&mut self) {
        if let Staged::Temp(Some(t)) = &self.kind {
            let _ = fs::remove_file(t);
        }
    }
}

/// Commit several staged writes together: the write-through destinations first (they can
/// fail, e.g. `/dev/full`), then the renames; on the first failure the remaining
/// temporary files are removed and their destinations left as they were.
pub fn commit_all(staged: Vec<StagedWrite>) -> Result<(), DataError> {
    let (through, renames): (Vec<_>, Vec<_>) = staged.into_iter().partition(|s| s.is_through());
    for s in through.into_iter().chain(renames) {
        s.commit()?;
    }
    Ok(())
}

/// Whether `a` and `b` name the same file: the same device and inode when both exist (hard
/// links, symbolic links, `./x` and `x`), else the same absolute path.
pub fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (fs::metadata(a), fs::metadata(b)) {
        (Ok(ma), Ok(mb)) => ma.dev() == mb.dev() && ma.ino() == mb.ino(),
        _ => {
            let abs = |p: &Path| {
                let p = if p.is_absolute() {
                    p.to_path_buf()
                } else {
                    std::env::current_dir().unwrap_or_default().join(p)
                };
                // resolve the directory part when it exists (the file itself may not)
                match (
                    p.parent().and_then(|d| fs::canonicalize(d).ok()),
                    p.file_name(),
                ) {
                    (Some(d), Some(n)) => d.join(n),
                    _ => p,
                }
            };
            abs(a) == abs(b)
        }
    }
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
        let ds = parse("\u{feff}t, u1 ,y1,p1\n0, 1e-3 , -2.5E+2, .5\n1,2,3,4\n\n \n").unwrap();
        assert_eq!(ds.names, ["t", "u1", "y1", "p1"]);
        assert_eq!(ds.len(), 2);
        assert_eq!(ds.column("u1").unwrap(), &[1e-3, 2.0]);
        assert_eq!(ds.column("y1").unwrap(), &[-250.0, 3.0]);
        assert_eq!(ds.column("p1").unwrap(), &[0.5, 4.0]);
        assert!(ds.column("u2").is_none());
        assert_eq!(ds.source, "d.csv");
    }

    #[test]
    fn plain_rows_read_as_the_csv_records_do() {
        // the fast path (plain rows, LF or CRLF, trailing blank lines) and the general path
        // (a quoted field sends the whole file there) give the same data set
        let plain = "u1, y1,p1\r\n0.5,-1.25e-3 , 3\r\n+.25,7.,-0\r\n\r\n  \n";
        let quoted = "u1, y1,p1\r\n0.5,-1.25e-3 , 3\r\n\"+.25\",7.,-0\r\n\r\n  \n";
        let (a, b) = (parse(plain).unwrap(), parse(quoted).unwrap());
        assert_eq!(a, b);
        // the header without the csv reader (plain_file) and with it (a quoted name)
        let quoted_header = "\"u1\", y1,p1\r\n0.5,-1.25e-3 , 3\r\n+.25,7.,-0\r\n\r\n  \n";
        assert!(plain_file("d.csv", plain.as_bytes()).is_some());
        assert!(plain_file("d.csv", quoted_header.as_bytes()).is_none());
        assert_eq!(parse(quoted_header).unwrap(), a);
        // bytes in memory: the same data set, and the same error for an endless line
        assert_eq!(Dataset::parse_bytes("d.csv", plain.as_bytes()).unwrap(), a);
        let mut long = b"u1,y1\n1,2\n".to_vec();
        long.extend(std::iter::repeat_n(b'1', MAX_LINE_BYTES + 10));
        let (e1, e2) = (
            Dataset::parse("l.csv", &long[..]).unwrap_err(),
            Dataset::parse_bytes("l.csv", &long).unwrap_err(),
        );
        assert_eq!((e1.line, e1.message), (e2.line, e2.message));
        let text = "a\nb\n".repeat(300) + "c";
        assert_eq!(count_newlines(text.as_bytes()), 600);
        assert_eq!(count_newlines(&[b'\n'; 1000]), 1000);
        assert_eq!(a.cols[1], [-1.25e-3, 7.0]);
        let body = b"1,2\n3,4\n";
        assert_eq!(
            plain_rows(body, 2),
            Some(vec![vec![1.0, 3.0], vec![2.0, 4.0]])
        );
        // anything the general path must judge is left to it
        for bad in [
            &b"1,2\n\n3,4\n"[..],
            b"1,2,\n",
            b"1\n",
            b"1,nan\n",
            b"1,2\r3,4\n",
            b"\n",
        ] {
            assert_eq!(plain_rows(bad, 2), None, "{:?}", std::str::from_utf8(bad));
        }
    }

    #[test]
    fn channels_are_contiguous_from_one() {
        let ds = parse("u1,u2,y1,q_ref,u01,p1x\n1,2,3,4,5,6\n").unwrap();
        assert_eq!(ds.channels('u'), ["u1", "u2"]);
        assert_eq!(ds.channels('y'), ["y1"]);
        assert!(ds.channels('p').is_empty());
    }

    #[test]
    fn signal_numbering_with_a_gap_is_an_error() {
        let e = parse_err("u2,y1,p1\n1,2,3\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(1), Some("u2")));
        assert!(e.message.contains("no u1"), "{e}");
        let e = parse_err("u1,u3,y1,y2,p1\n1,2,3,4,5\n");
        assert_eq!(e.column.as_deref(), Some("u3"));
        assert!(e.message.contains("u2 is missing"), "{e}");
        let e = parse_err("u1,y1,p2\n1,2,3\n");
        assert_eq!(e.column.as_deref(), Some("p2"));
    }

    #[test]
    fn blank_line_in_the_middle_is_an_error() {
        let e = parse_err("u1,y1\n1,2\n\n3,4\n");
        assert_eq!(e.line, Some(3));
        assert!(e.message.contains("blank line"), "{e}");
        let e = parse_err("u1,y1\r\n1,2\r\n  \r\n3,4\r\n");
        assert_eq!(e.line, Some(3));
        // trailing blank lines and leading ones before the header are fine
        assert_eq!(parse("\n\nu1,y1\n1,2\n3,4\n\n\n  \n").unwrap().len(), 2);
    }

    #[test]
    fn foreign_separators_are_named() {
        let e = parse_err("u1;y1;p1\n0,5;1,2;0,3\n");
        assert_eq!(e.line, Some(1));
        assert!(e.message.contains("separator"), "{e}");
        let e = parse_err("u1\ty1\n1\t2\n");
        assert!(e.message.contains("separator"), "{e}");
        // a decimal comma in a comma-separated file
        let e = parse_err("u1,y1,p1\n0,5,1,25,0,3\n");
        assert!(e.message.contains("separator"), "{e}");
        let e = parse_err("u1,y1\n1,\"2,5\"\n");
        assert!(e.message.contains("separator"), "{e}");
    }

    #[test]
    fn endless_lines_are_stopped() {
        let zeros = std::io::repeat(0).take(3 * MAX_LINE_BYTES as u64);
        let e = Dataset::parse("z.csv", zeros).unwrap_err();
        assert_eq!(e.line, Some(1));
        assert!(e.message.contains("line longer than"), "{e}");
        let mut long = b"u1,y1\n1,2\n".to_vec();
        long.extend(std::iter::repeat_n(b'1', MAX_LINE_BYTES + 10));
        let e = Dataset::parse("l.csv", &long[..]).unwrap_err();
        assert_eq!(e.line, Some(3), "{e}");
        // exactly at the limit is fine
        let mut ok = b"u1,y1\n".to_vec();
        ok.extend(std::iter::repeat_n(b' ', MAX_LINE_BYTES - 4));
        ok.extend(b"1,2\n");
        assert_eq!(Dataset::parse("ok.csv", &ok[..]).unwrap().len(), 1);
        let e = read_input(Path::new("/dev/zero")).unwrap_err();
        assert!(e.message.contains("character device"), "{e}");
        let e = read_input(Path::new("/")).unwrap_err();
        assert!(e.message.contains("directory"), "{e}");
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
        let e = parse_err("u1,y1\n1,2\n1,2,3\n");
        assert_eq!(e.line, Some(3));
        assert!(e.message.contains("expected 2 fields, found 3"), "{e}");
        let e = parse_err("u1,y1\r\n1,2\r\n1,x\r\n");
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("y1")));
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
    fn scale_problems_are_named() {
        let ds = parse("u1,y1,p1\n1,2e300,0.5\n2,-3e300,0.25\n").unwrap();
        ds.check_scale("u1").unwrap();
        let e = ds.check_scale("y1").unwrap_err();
        assert_eq!((e.line, e.column.as_deref()), (Some(3), Some("y1")));
        assert!(
            e.message.contains("too large") && !e.message.contains("constant"),
            "{e}"
        );
        let ds = parse("u1,y1\n1e-200,0\n-2e-190,1\n").unwrap();
        let e = ds.check_scale("u1").unwrap_err();
        assert!(e.message.contains("underflow"), "{e}");
        ds.check_scale("y1").unwrap();
    }

    #[test]
    fn numbers_are_written_short() {
        assert_eq!(fmt_number(1e95), "1e95");
        assert_eq!(fmt_number(-2.5e-300), "-2.5e-300");
        assert_eq!(fmt_number(0.1), "0.1");
        assert_eq!(fmt_number(-3.0), "-3");
        assert_eq!(fmt_number(0.0), "0");
        for v in [
            1e95,
            1.0 / 3.0,
            123456789.123,
            7e-6,
            1e16,
            f64::MAX,
            f64::MIN_POSITIVE,
        ] {
            assert_eq!(fmt_number(v).parse::<f64>().unwrap(), v);
            assert!(fmt_number(v).len() < 26, "{}", fmt_number(v));
        }
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
