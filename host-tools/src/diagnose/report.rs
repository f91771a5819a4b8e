//! The human summary of a diagnosis: an engineer's note saying what was wrong, the evidence,
//! what was added and the error before and after.

use std::fmt::Write as _;
use std::path::PathBuf;

use super::residual::ResidualReport;
use super::Report;
use crate::model::{describe, ModelFile, ModelKind};

/// "lpv-ss, n = 2, inputs u1, scheduling 1, p1, outputs y1".
pub fn model_summary(m: &ModelFile) -> String {
    let list = |v: &[Vec<crate::model::Factor>]| {
        v.iter().map(|p| describe(p)).collect::<Vec<_>>().join(", ")
    };
    let kind = match &m.kind {
        ModelKind::Ss(ss) => format!(
            "lpv-ss with {} states{}",
            ss.n(),
            if ss.c.len() > 1 {
                ", scheduled output equation"
            } else {
                ""
            }
        ),
        ModelKind::Arx(a) => format!("lpv-arx with na = {}, nb = {}", a.na, a.nb),
    };
    format!(
        "{kind}; inputs {}; scheduling basis {}; outputs {}",
        list(&m.signals.inputs),
        list(&m.signals.scheduling),
        list(&m.signals.outputs)
    )
}

/// The "not applicable" note of a catalogue variant that was not tried (the report's and the
/// JSON's `not_applicable` entry): "past window 9 (was 7), order 2: not tried, its PBSID
/// regression would have 4000 regressors".
pub fn not_tried(s: &super::catalogue::Skipped) -> String {
    format!(
        "{}: not tried, its PBSID regression would have {} regressors",
        s.cand.detail, s.regressors
    )
}

fn pct(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:.2}"))
        .collect::<Vec<_>>()
        .join(" / ")
}

/// The residual in a few lines: only what fails.
fn residual_lines(r: &ResidualReport, s: &mut String) {
    for w in &r.whiteness {
        if w.p_value < 0.01 {
            let _ = writeln!(
                s,
                "  - output {}: not white: Ljung-Box Q = {:.0} on {} lags (p = {:.1e}), {} of {} autocorrelations outside +-{:.3}",
                w.output,
                w.ljung_box,
                w.dof,
                w.p_value,
                w.excursions,
                w.acf.len() - 1,
                w.band
            );
        } else {
            let _ = writeln!(
                s,
                "  - output {}: white (Ljung-Box p = {:.2})",
                w.output, w.p_value
            );
        }
    }
    for (j, m) in r.mean.iter().enumerate() {
        if r.mean_p[j] < 0.01 {
            let _ = writeln!(
                s,
                "  - output {}: mean {:+.3e} ({:.0} % of the RMS, t = {:.1})",
                j + 1,
                m,
                100.0 * m.abs() / r.rms[j].max(1e-300),
                r.mean_t[j]
            );
        }
    }
    for c in r.cross.iter().filter(|c| c.significant) {
        let _ = writeln!(
            s,
            "  - output {}: correlated with {} {} (|r| = {:.3} at lag {}, beyond the significance bound +-{:.3}; 95 % Bartlett band +-{:.3})",
            c.output, c.kind, c.signal, c.max_abs, c.at_lag, c.bound, c.bartlett_band
        );
    }
    for t in r.nonlinear.iter().filter(|t| t.ratio > 1.0).take(3) {
        let _ = writeln!(
            s,
            "  - output {}: correlated with {} (r = {:+.3} at lag {}, {:.1}x its 99 % bound)",
            t.output, t.regressor, t.r, t.lag, t.ratio
        );
    }
    for sp in &r.spectrum {
        for p in sp.peaks.iter().take(2) {
            let _ = writeln!(
                s,
                "  - output {}: spectral line at {:.4} rad/sample (period {:.2} samples), {:.0}x the local level",
                sp.output, p.omega, p.period, p.ratio
            );
        }
    }
}

/// The note printed on stdout.
pub fn summary(r: &Report, plots: &[PathBuf]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "lpvid diagnose: {} ({})\n  trained on {}, validated on {} ({} samples)",
        r.model, r.model_summary, r.train, r.val, r.residual.free_run.samples
    );
    let _ = writeln!(
        s,
        "Before: free-run VAF {} % (BFR {} %), one-step VAF {} %{}.",
        pct(&r.before.vaf),
        pct(&r.before.bfr),
        pct(&r.before_one_step.vaf),
        if r.before.skipped > 0 {
            format!(
                " (every model's initial state estimated on the first {} validation samples, which are not scored)",
                r.before.skipped
            )
        } else {
            String::new()
        }
    );
    let _ = writeln!(s, "Free-run residual on the validation data:");
    residual_lines(&r.residual.free_run, &mut s);
    let _ = writeln!(s, "One-step residual:");
    for w in &r.residual.one_step.whiteness {
        let _ = writeln!(
            s,
            "  - output {}: Ljung-Box Q = {:.0} on {} lags (p = {:.1e})",
            w.output, w.ljung_box, w.dof, w.p_value
        );
    }
    for st in &r.steps {
        let lead = if r.steps.len() > 1 {
            format!("Step {}: ", st.step)
        } else {
            String::new()
        };
        match st.findings.first() {
            Some(f) if f.significant => {
                let _ = writeln!(
                    s,
                    "{lead}what is missing: {} -- {}: {} explains {:.1} % of the held-out {} error (t = {:.1}, p = {:.1e}, {} variant{} tried).",
                    f.effect,
                    super::effects::Effect::ALL
                        .iter()
                        .find(|e| e.name() == f.effect)
                        .map_or("", |e| e.lacks()),
                    f.detail,
                    100.0 * f.explained,
                    f.residual,
                    f.t,
                    f.p_value,
                    f.variants,
                    if f.variants == 1 { "" } else { "s" }
                );
                let _ = writeln!(s, "  Evidence:");
                for e in f.evidence.iter().take(6) {
                    let _ = writeln!(s, "    - {e}");
                }
            }
            _ => {
                let _ = writeln!(
                    s,
                    "{lead}nothing explains the residual above the noise threshold ({} variants tried).",
                    st.variants
                );
            }
        }
        // one line per candidate that was not applied, with the rule that blocked it (the
        // same text as the JSON's `blocked_by`)
        let applied_here = r.applied.iter().any(|a| a.step == st.step);
        let skip = usize::from(applied_here);
        let others: Vec<String> = st
            .findings
            .iter()
            .skip(skip)
            .take(5)
            .map(|f| {
                let why = match &f.blocked_by {
                    Some(b) => format!("not a finding because {b}"),
                    None if applied_here => {
                        "above the noise threshold; not applied because one effect is added per step (the best first)".to_string()
                    }
                    None => format!("above the noise threshold; not applied because {}", r.stopped),
                };
                format!(
                    "    - {} explains {:.1} % ({}): {why}",
                    f.effect,
                    100.0 * f.explained,
                    f.detail
                )
            })
            .collect();
        if !others.is_empty() {
            let _ = writeln!(
                s,
                "  {} (not applied, with the rule that blocked each):",
                if skip == 1 {
                    "Next candidates"
                } else {
                    "Best candidates"
                }
            );
            for o in &others {
                let _ = writeln!(s, "{o}");
            }
        }
        for a in r.applied.iter().filter(|a| a.step == st.step) {
            let _ = writeln!(
                s,
                "  Added: {} -- {}; refit with the model's own settings. Held-out {} MSE/var(y) {:.4e} -> {:.4e} ({:.1}x lower), mean VAF {:.2} % -> {:.2} %.",
                a.effect,
                a.detail,
                a.residual,
                a.mse_before,
                a.mse_after,
                a.mse_before / a.mse_after.max(1e-300),
                a.vaf_before,
                a.vaf_after
            );
        }
    }
    if let Some(f) = &r.refined {
        let _ = writeln!(
            s,
            "Refined: no effect is a finding at step {}, but the structure's subspace estimate is biased: the structure refined by output error (as `lpvid pbsid --refine` does) explains {:.1} % of the held-out free-run error of its refit (p = {:.1e}) and is the model written. Held-out free-run MSE/var(y) {:.4e} -> {:.4e} ({:.1}x lower), mean VAF {:.2} % -> {:.2} %.",
            f.step,
            100.0 * f.explained,
            f.p_value,
            f.mse_before,
            f.mse_after,
            f.mse_before / f.mse_after.max(1e-300),
            f.vaf_before,
            f.vaf_after
        );
    }
    if let (Some(af), Some(ao)) = (&r.after, &r.after_one_step) {
        let _ = writeln!(
            s,
            "After: free-run VAF {} % (before {} %), BFR {} % (before {} %), one-step VAF {} % (before {} %).",
            pct(&af.vaf),
            pct(&r.before.vaf),
            pct(&af.bfr),
            pct(&r.before.bfr),
            pct(&ao.vaf),
            pct(&r.before_one_step.vaf)
        );
    }
    let _ = writeln!(s, "Stopped: {}.", r.stopped);
    for n in &r.notes {
        let _ = writeln!(s, "Note: {n}.");
    }
    if let Some(o) = &r.out {
        let _ = writeln!(s, "Model written to {o}.");
    }
    if !plots.is_empty() {
        let names: Vec<String> = plots.iter().map(|p| p.display().to_string()).collect();
        let _ = writeln!(s, "Plots: {}.", names.join(", "));
    }
    s
}
