//! Pictures of a diagnosis as SVG files (plain text, no font or image library needed, labels
//! included): validation fit before/after, residual autocorrelation and cross-correlations
//! with their bounds, residual spectrum with the found peaks, singular values.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::data::{write_atomic, DataError};
use crate::simulate::Mode;

use super::Outcome;

const W: f64 = 520.0;
const H: f64 = 240.0;
const ML: f64 = 62.0;
const MR: f64 = 14.0;
const MT: f64 = 26.0;
const MB: f64 = 38.0;

/// How a series is drawn.
#[derive(Debug, Clone, Copy)]
enum Kind {
    Line,
    Stem,
    Dots,
}

struct Series {
    x: Vec<f64>,
    y: Vec<f64>,
    color: &'static str,
    label: String,
    kind: Kind,
    width: f64,
}

struct Panel {
    title: String,
    xlabel: String,
    ylabel: String,
    series: Vec<Series>,
    /// Horizontal lines (y, colour, dashed).
    hlines: Vec<(f64, &'static str, bool)>,
    /// Legend entries of the horizontal lines (colour, label), drawn dashed.
    hline_labels: Vec<(&'static str, String)>,
    log_y: bool,
}

impl Panel {
    fn new(title: impl Into<String>, xlabel: &str, ylabel: &str) -> Panel {
        Panel {
            title: title.into(),
            xlabel: xlabel.into(),
            ylabel: ylabel.into(),
            series: vec![],
            hlines: vec![],
            hline_labels: vec![],
            log_y: false,
        }
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    let span = (hi - lo).abs().max(1e-300);
    let raw = span / n as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let mut t = (lo / step).ceil() * step;
    let mut out = vec![];
    while t <= hi + 1e-9 * span {
        out.push(if t.abs() < 1e-12 * span { 0.0 } else { t });
        t += step;
    }
    out
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 1e4 || v.abs() < 1e-3 {
        format!("{v:.1e}")
    } else {
        let s = format!("{v:.4}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

fn draw_panel(p: &Panel, ox: f64, oy: f64, s: &mut String) {
    let tr = |v: f64| if p.log_y { v.max(1e-300).log10() } else { v };
    let mut xs = (f64::INFINITY, f64::NEG_INFINITY);
    let mut ys = (f64::INFINITY, f64::NEG_INFINITY);
    let ymax = p
        .series
        .iter()
        .flat_map(|se| se.y.iter().copied())
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let floor = if p.log_y {
        ymax * 1e-12
    } else {
        f64::NEG_INFINITY
    };
    for se in &p.series {
        for (&x, &y) in se.x.iter().zip(&se.y) {
            if x.is_finite() && y.is_finite() && (!p.log_y || y > floor) {
                xs = (xs.0.min(x), xs.1.max(x));
                ys = (ys.0.min(tr(y)), ys.1.max(tr(y)));
            }
        }
    }
    for &(y, _, _) in &p.hlines {
        if y.is_finite() && (!p.log_y || y > 0.0) {
            ys = (ys.0.min(tr(y)), ys.1.max(tr(y)));
        }
    }
    if !xs.0.is_finite() {
        xs = (0.0, 1.0);
    }
    if !ys.0.is_finite() {
        ys = (0.0, 1.0);
    }
    if xs.1 <= xs.0 {
        xs.1 = xs.0 + 1.0;
    }
    if ys.1 <= ys.0 {
        ys = (ys.0 - 0.5, ys.1 + 0.5);
    }
    let pad = 0.05 * (ys.1 - ys.0);
    ys = (ys.0 - pad, ys.1 + pad);
    let (pw, ph) = (W - ML - MR, H - MT - MB);
    let px = |x: f64| ox + ML + (x - xs.0) / (xs.1 - xs.0) * pw;
    let py = |y: f64| oy + MT + (1.0 - (tr(y) - ys.0) / (ys.1 - ys.0)) * ph;
    let _ = writeln!(
        s,
        r##"<rect x="{:.1}" y="{:.1}" width="{pw:.1}" height="{ph:.1}" fill="white" stroke="#444"/>"##,
        ox + ML,
        oy + MT
    );
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="{:.1}" font-size="12" font-weight="bold">{}</text>"#,
        ox + ML,
        oy + 16.0,
        esc(&p.title)
    );
    for t in nice_ticks(xs.0, xs.1, 6) {
        let x = px(t);
        let _ = writeln!(
            s,
            r##"<line x1="{x:.1}" y1="{:.1}" x2="{x:.1}" y2="{:.1}" stroke="#ddd"/><text x="{x:.1}" y="{:.1}" font-size="10" text-anchor="middle">{}</text>"##,
            oy + MT,
            oy + MT + ph,
            oy + MT + ph + 13.0,
            fmt_tick(t)
        );
    }
    for t in nice_ticks(ys.0, ys.1, 5) {
        let y = oy + MT + (1.0 - (t - ys.0) / (ys.1 - ys.0)) * ph;
        let label = if p.log_y {
            format!("1e{}", fmt_tick(t))
        } else {
            fmt_tick(t)
        };
        let _ = writeln!(
            s,
            r##"<line x1="{:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" font-size="10" text-anchor="end">{label}</text>"##,
            ox + ML,
            ox + ML + pw,
            ox + ML - 4.0,
            y + 3.0
        );
    }
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="{:.1}" font-size="11" text-anchor="middle">{}</text>"#,
        ox + ML + pw / 2.0,
        oy + H - 6.0,
        esc(&p.xlabel)
    );
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="{:.1}" font-size="11" text-anchor="middle" transform="rotate(-90 {:.1} {:.1})">{}</text>"#,
        ox + 14.0,
        oy + MT + ph / 2.0,
        ox + 14.0,
        oy + MT + ph / 2.0,
        esc(&p.ylabel)
    );
    let clip_y = |y: f64| y.clamp(oy + MT, oy + MT + ph);
    for &(y, c, dashed) in &p.hlines {
        if !y.is_finite() || (p.log_y && y <= 0.0) {
            continue;
        }
        let yy = clip_y(py(y));
        let _ = writeln!(
            s,
            r#"<line x1="{:.1}" y1="{yy:.1}" x2="{:.1}" y2="{yy:.1}" stroke="{c}" stroke-width="1"{}/>"#,
            ox + ML,
            ox + ML + pw,
            if dashed {
                r#" stroke-dasharray="4 3""#
            } else {
                ""
            }
        );
    }
    let zero = if p.log_y {
        py(10f64.powf(ys.0))
    } else {
        clip_y(py(0.0))
    };
    for se in &p.series {
        match se.kind {
            Kind::Line => {
                let mut path = String::new();
                let mut pen = false;
                for (&x, &y) in se.x.iter().zip(&se.y) {
                    if !(x.is_finite() && y.is_finite()) || (p.log_y && y <= floor) {
                        pen = false;
                        continue;
                    }
                    let _ = write!(
                        path,
                        "{}{:.1},{:.1} ",
                        if pen { "L" } else { "M" },
                        px(x),
                        clip_y(py(y))
                    );
                    pen = true;
                }
                let _ = writeln!(
                    s,
                    r#"<path d="{path}" fill="none" stroke="{}" stroke-width="{}"/>"#,
                    se.color, se.width
                );
            }
            Kind::Stem => {
                for (&x, &y) in se.x.iter().zip(&se.y) {
                    if y.is_finite() {
                        let _ = writeln!(
                            s,
                            r#"<line x1="{:.1}" y1="{zero:.1}" x2="{:.1}" y2="{:.1}" stroke="{}" stroke-width="2"/>"#,
                            px(x),
                            px(x),
                            clip_y(py(y)),
                            se.color
                        );
                    }
                }
            }
            Kind::Dots => {
                for (&x, &y) in se.x.iter().zip(&se.y) {
                    if y.is_finite() && (!p.log_y || y > 0.0) {
                        let _ = writeln!(
                            s,
                            r#"<circle cx="{:.1}" cy="{:.1}" r="3.5" fill="none" stroke="{}" stroke-width="1.5"/>"#,
                            px(x),
                            clip_y(py(y)),
                            se.color
                        );
                    }
                }
            }
        }
    }
    // legend: in the top right corner, as wide as its longest label
    let longest = p
        .series
        .iter()
        .map(|se| se.label.chars().count())
        .chain(p.hline_labels.iter().map(|h| h.1.chars().count()))
        .max()
        .unwrap_or(0) as f64;
    let lx = ox + ML + pw - (24.0 + 5.6 * longest).min(pw - 10.0);
    let mut ly = oy + MT + 12.0;
    let entries = p
        .series
        .iter()
        .filter(|se| !se.label.is_empty())
        .map(|se| (se.color, se.label.as_str(), "2", ""))
        .chain(
            p.hline_labels
                .iter()
                .map(|(c, l)| (*c, l.as_str(), "1", r#" stroke-dasharray="4 3""#)),
        );
    for (color, label, width, dash) in entries {
        let _ = writeln!(
            s,
            r#"<line x1="{:.1}" y1="{:.1}" x2="{:.1}" y2="{:.1}" stroke="{color}" stroke-width="{width}"{dash}/><text x="{:.1}" y="{:.1}" font-size="10">{}</text>"#,
            lx,
            ly - 3.0,
            lx + 16.0,
            ly - 3.0,
            lx + 20.0,
            ly,
            esc(label)
        );
        ly += 13.0;
    }
}

fn render_svg(panels: &[Panel], cols: usize) -> String {
    // a figure is as wide as the panels it has (a single panel is not drawn on a two-wide canvas)
    let cols = cols.min(panels.len()).max(1);
    let rows = panels.len().div_ceil(cols).max(1);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{}" height="{}" font-family="sans-serif">"#,
        W * cols as f64,
        H * rows as f64
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    for (i, p) in panels.iter().enumerate() {
        draw_panel(p, W * (i % cols) as f64, H * (i / cols) as f64, &mut s);
    }
    s.push_str("</svg>\n");
    s
}

fn series(x: Vec<f64>, y: Vec<f64>, color: &'static str, label: &str, kind: Kind) -> Series {
    Series {
        x,
        y,
        color,
        label: label.into(),
        kind,
        width: 1.0,
    }
}

/// Write every picture of `res` into `dir`; returns the files written.
pub fn write_all(dir: &Path, res: &Outcome) -> Result<Vec<PathBuf>, DataError> {
    let mut written = Vec::new();
    for (path, text) in render_all(dir, res) {
        write_atomic(&path, text.as_bytes())?;
        written.push(path);
    }
    Ok(written)
}

/// The figures [`write_all`] writes, as (path in `dir`, SVG text), without writing them
/// (so that a command can write them together with its other outputs).
pub fn render_all(dir: &Path, res: &Outcome) -> Vec<(PathBuf, String)> {
    let mut figures = Vec::new();
    let be = &res.before_eval;
    let (n, l) = (be.y.nrows(), be.y.ncols());
    let show = n.min(300);
    let start = n - show;
    let ks: Vec<f64> = (start..n).map(|k| k as f64).collect();
    // 1. fit before/after
    let mut panels = Vec::new();
    for j in 0..l {
        let mut p = Panel::new(
            if show < n {
                format!(
                    "validation output {}: measured and simulated (free run), last {show} of {n} samples",
                    j + 1
                )
            } else {
                format!(
                    "validation output {}: measured and simulated (free run)",
                    j + 1
                )
            },
            "sample",
            &format!("y{}", j + 1),
        );
        let col = |m: &nalgebra::DMatrix<f64>| (start..n).map(|k| m[(k, j)]).collect::<Vec<_>>();
        let mut meas = series(ks.clone(), col(&be.y), "#999", "measured", Kind::Line);
        meas.width = 3.0;
        p.series.push(meas);
        p.series.push(series(
            ks.clone(),
            col(&be.yhat_free),
            "#d62728",
            &format!("before (VAF {:.1} %)", res.report.before.vaf[j]),
            Kind::Line,
        ));
        if let (Some(ae), Some(af)) = (&res.after_eval, &res.report.after) {
            p.series.push(series(
                ks.clone(),
                col(&ae.yhat_free),
                "#1f77b4",
                &format!("after (VAF {:.1} %)", af.vaf[j]),
                Kind::Line,
            ));
        }
        panels.push(p);
    }
    figures.push((dir.join("fit.svg"), render_svg(&panels, 1)));
    // 2. residual autocorrelation
    let mut panels = Vec::new();
    for (rep, name) in [
        (&res.report.residual.free_run, "free-run"),
        (&res.report.residual.one_step, "one-step"),
    ] {
        for w in &rep.whiteness {
            let mut p = Panel::new(
                format!(
                    "{name} residual {} autocorrelation (Ljung-Box p = {:.1e})",
                    w.output, w.p_value
                ),
                "lag",
                "r",
            );
            p.series.push(series(
                (0..w.acf.len()).map(|k| k as f64).collect(),
                w.acf.clone(),
                "#1f77b4",
                "",
                Kind::Stem,
            ));
            p.hlines.push((w.band, "#d62728", true));
            p.hlines.push((-w.band, "#d62728", true));
            p.hline_labels
                .push(("#d62728", "+-1.96/sqrt(N): 95 % band".into()));
            panels.push(p);
        }
    }
    figures.push((dir.join("autocorrelation.svg"), render_svg(&panels, 2)));
    // 3. cross-correlations
    let mut panels = Vec::new();
    for c in &res.report.residual.free_run.cross {
        let lags = c.r.len() / 2;
        let mut p = Panel::new(
            format!(
                "residual {} vs {} {} ({})",
                c.output,
                c.kind,
                c.signal,
                if c.significant {
                    "significant"
                } else {
                    "within bounds"
                }
            ),
            "lag (positive: signal leads)",
            "r",
        );
        p.series.push(series(
            (0..c.r.len()).map(|k| k as f64 - lags as f64).collect(),
            c.r.clone(),
            "#1f77b4",
            "",
            Kind::Stem,
        ));
        p.hlines.push((c.band, "#999", true));
        p.hlines.push((-c.band, "#999", true));
        p.hlines.push((c.bartlett_band, "#d62728", true));
        p.hlines.push((-c.bartlett_band, "#d62728", true));
        p.hlines.push((c.bound, "#000", true));
        p.hlines.push((-c.bound, "#000", true));
        p.hline_labels
            .push(("#999", "+-1.96/sqrt(N): 95 %, white".into()));
        p.hline_labels
            .push(("#d62728", "Bartlett 95 % band".into()));
        p.hline_labels.push(("#000", "significance bound".into()));
        panels.push(p);
    }
    if !panels.is_empty() {
        figures.push((dir.join("cross-correlation.svg"), render_svg(&panels, 2)));
    }
    // 4. spectrum
    let mut panels = Vec::new();
    for sp in &res.report.residual.free_run.spectrum {
        let mut p = Panel::new(
            format!(
                "free-run residual {} periodogram and significant lines",
                sp.output
            ),
            "frequency (rad/sample)",
            "power",
        );
        p.log_y = true;
        let step = (sp.omega.len() / 2000).max(1);
        let pick = |v: &[f64]| v.iter().skip(1).step_by(step).copied().collect::<Vec<_>>();
        p.series.push(series(
            pick(&sp.omega),
            pick(&sp.power),
            "#1f77b4",
            "periodogram",
            Kind::Line,
        ));
        // no line is tested at the lowest two Fourier bins (trends): no threshold there
        let (lim_w, lim): (Vec<f64>, Vec<f64>) = pick(&sp.omega)
            .into_iter()
            .zip(pick(&sp.limit))
            .filter(|(_, v)| v.is_finite())
            .unzip();
        p.series
            .push(series(lim_w, lim, "#d62728", "threshold", Kind::Line));
        let peaks_x: Vec<f64> = sp.peaks.iter().map(|q| q.omega).collect();
        let peaks_y: Vec<f64> = sp
            .peaks
            .iter()
            .map(|q| {
                super::stats::dtft_power(&residual_col(res, Mode::FreeRun, sp.output - 1), q.omega)
            })
            .collect();
        p.series.push(series(
            peaks_x,
            peaks_y,
            "#2ca02c",
            "found lines",
            Kind::Dots,
        ));
        panels.push(p);
    }
    figures.push((dir.join("spectrum.svg"), render_svg(&panels, 1)));
    // 5. singular values
    let (a, b) = &res.singular_values;
    if !a.is_empty() {
        let mut p = Panel::new("singular values of Gamma K Z", "index", "singular value");
        p.log_y = true;
        p.series.push(series(
            (1..=a.len()).map(|k| k as f64).collect(),
            a.clone(),
            "#d62728",
            "model as given (refit)",
            Kind::Dots,
        ));
        if !res.report.applied.is_empty() && !b.is_empty() {
            p.series.push(series(
                (1..=b.len()).map(|k| k as f64).collect(),
                b.clone(),
                "#1f77b4",
                "after the fix",
                Kind::Line,
            ));
        }
        figures.push((dir.join("singular-values.svg"), render_svg(&[p], 1)));
    }
    figures
}

fn residual_col(res: &Outcome, mode: Mode, j: usize) -> Vec<f64> {
    res.before_eval
        .residual(mode)
        .column(j)
        .iter()
        .copied()
        .collect()
}

/// A panel of line series for other front ends (`lpvid device watch`), drawn by this
/// module's renderer: series are (label, x, y).
#[derive(Debug, Clone, Default)]
pub struct LinePanel {
    /// Title above the panel.
    pub title: String,
    /// x axis label.
    pub xlabel: String,
    /// y axis label.
    pub ylabel: String,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// (label, x, y) per series.
    pub series: Vec<(String, Vec<f64>, Vec<f64>)>,
}

/// An SVG figure of `panels`, `cols` per row, in the diagnosis pictures' style (colours
/// cycle through a fixed palette).
pub fn line_panels_svg(panels: &[LinePanel], cols: usize) -> String {
    const PALETTE: [&str; 8] = [
        "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    ];
    let drawn: Vec<Panel> = panels
        .iter()
        .map(|lp| {
            let mut p = Panel::new(lp.title.clone(), &lp.xlabel, &lp.ylabel);
            p.log_y = lp.log_y;
            for (i, (label, x, y)) in lp.series.iter().enumerate() {
                p.series.push(series(
                    x.clone(),
                    y.clone(),
                    PALETTE[i % PALETTE.len()],
                    label,
                    Kind::Line,
                ));
            }
            p
        })
        .collect();
    render_svg(&drawn, cols)
}
