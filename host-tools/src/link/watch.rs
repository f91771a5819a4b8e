//! The recursive estimate seen from the host (issue 18; `lpvid device watch` is its command
//! line): stream samples and, whenever the device reports a new tracking solve
//! ([`lpvid::protocol::Status::solves`]), pull its record ([`lpvid::protocol::Estimate`])
//! and coefficients as a [`WatchRecord`]. The estimate is problem (13) of the kernel paper
//! solved on the device's (forgetting or windowed) statistics; the one-step error is the
//! VARX predictor of the same problem. No printing here: the command line prints the
//! progress line, the JSON lines and the plot ([`WatchHistory::svg`]).

use std::io::{Read, Write};

use lpvid::protocol::{SolveSummary, Status};

use super::{EstimateReply, Link, LinkError};
use crate::diagnose::plots::{line_panels_svg, LinePanel};

/// One report of the recursive estimate: what `lpvid device watch --json` prints per line.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct WatchRecord {
    /// Successful solves so far.
    pub solves: u32,
    /// Failed solves so far.
    pub failures: u32,
    /// Stream index of the next sample when the last solve ran.
    pub at_sample: u32,
    /// The last solve's summary.
    pub summary: SolveSummary,
    /// Its coefficients, l x (q + r) row-major (output o regresses y_{k+p}^(o) on
    /// [z_k^p; u_{k+p}]).
    pub theta: Vec<f64>,
    /// One-step predictions of the previous solution over its interval.
    pub interval_count: u32,
    /// Their sum of squared errors per output (as the device reports it).
    pub interval_sse: Vec<f64>,
    /// Their root-mean-square error per output (empty before an interval has finished).
    pub interval_rms: Vec<f64>,
    /// The newest one-step error per output.
    pub last_error: Vec<f64>,
}

impl WatchRecord {
    /// Decode an estimate reply and the coefficients pulled after it; the coefficient count
    /// must be what the summary says (columns x outputs).
    pub fn new(est: &EstimateReply, theta: Vec<f64>) -> Result<Self, LinkError> {
        let want = est.summary.columns as usize * est.summary.outputs as usize;
        if theta.len() != want {
            return Err(LinkError::Protocol(format!(
                "estimate of {} x {} coefficients, {} pulled",
                est.summary.outputs,
                est.summary.columns,
                theta.len()
            )));
        }
        if est.sse.len() != est.last_error.len() {
            return Err(LinkError::Protocol(format!(
                "estimate with {} squared errors and {} last errors",
                est.sse.len(),
                est.last_error.len()
            )));
        }
        let interval_rms = if est.count > 0 {
            est.sse
                .iter()
                .map(|s| (s / est.count as f64).sqrt())
                .collect()
        } else {
            Vec::new()
        };
        Ok(WatchRecord {
            solves: est.solves,
            failures: est.failures,
            at_sample: est.at_sample,
            summary: est.summary,
            theta,
            interval_count: est.count,
            interval_sse: est.sse.clone(),
            interval_rms,
            last_error: est.last_error.clone(),
        })
    }
}

/// The records of a watch, for the plot.
#[derive(Debug, Clone, Default)]
pub struct WatchHistory {
    /// In the order received.
    pub records: Vec<WatchRecord>,
}

impl WatchHistory {
    /// The plot: one-step RMS error per output against the sample index (log scale), and
    /// the coefficients against the sample index (the 8 largest in the last solve), drawn
    /// by the diagnosis plots' SVG renderer.
    pub fn svg(&self) -> String {
        let x: Vec<f64> = self.records.iter().map(|r| r.at_sample as f64).collect();
        let mut err = LinePanel {
            title: "one-step prediction error of the previous solution".into(),
            xlabel: "sample".into(),
            ylabel: "RMS".into(),
            log_y: true,
            series: Vec::new(),
        };
        let l = self
            .records
            .last()
            .map_or(0, |r| r.summary.outputs as usize);
        for o in 0..l {
            let (xs, ys): (Vec<f64>, Vec<f64>) = self
                .records
                .iter()
                .filter_map(|r| {
                    r.interval_rms
                        .get(o)
                        .filter(|v| **v > 0.0)
                        .map(|v| (r.at_sample as f64, *v))
                })
                .unzip();
            err.series.push((format!("y{}", o + 1), xs, ys));
        }
        let mut coef = LinePanel {
            title: "coefficients of the recursive estimate".into(),
            xlabel: "sample".into(),
            ylabel: "theta".into(),
            log_y: false,
            series: Vec::new(),
        };
        if let Some(last) = self.records.last() {
            let mut idx: Vec<usize> = (0..last.theta.len()).collect();
            idx.sort_by(|a, b| last.theta[*b].abs().total_cmp(&last.theta[*a].abs()));
            for j in idx.into_iter().take(8) {
                let ys: Vec<f64> = self
                    .records
                    .iter()
                    .map(|r| r.theta.get(j).copied().unwrap_or(f64::NAN))
                    .collect();
                coef.series.push((format!("theta[{j}]"), x.clone(), ys));
            }
        }
        line_panels_svg(&[err, coef], 1)
    }
}

impl<P: Read + Write> Link<P> {
    /// [`Link::stream`] in frames, and after every acknowledged frame whose status shows
    /// new tracking solves, the estimate and coefficients as a [`WatchRecord`] for
    /// `on_record` (several solves within one frame show as the newest). `progress(done,
    /// status)` follows every frame. The device must be configured and tracking
    /// ([`Link::track`]).
    pub fn watch(
        &mut self,
        rows: &[f64],
        per: usize,
        first: u32,
        mut progress: impl FnMut(usize, &Status),
        mut on_record: impl FnMut(&WatchRecord),
    ) -> Result<Status, LinkError> {
        self.ensure_hello()?;
        if per == 0 || rows.len() % per != 0 {
            return Err(LinkError::Protocol("sample rows of unequal length".into()));
        }
        let n = rows.len() / per;
        let chunk = self.batch_size(per).max(1);
        let mut done = 0usize;
        let mut solves = self.status()?.solves;
        let mut last = None;
        while done < n {
            let k = chunk.min(n - done);
            let st = self.stream(
                &rows[done * per..(done + k) * per],
                per,
                first + done as u32,
                |_| {},
            )?;
            done += k;
            if st.solves != solves {
                solves = st.solves;
                let est = self.estimate()?;
                let theta = self.solution(est.summary.columns, est.summary.outputs)?;
                on_record(&WatchRecord::new(&est, theta)?);
            }
            progress(done, &st);
            last = Some(st);
        }
        match last {
            Some(s) => Ok(s),
            None => self.status(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::{replay_tracking, sample_rows, Accumulation, LinkOptions};
    use crate::lpvss::Signals;
    use lpvid::device::DefaultDevice;
    use lpvid::protocol::{SolveRequest, Track};
    use lpvid::{PbsidDims, StatsLayout};
    use nalgebra::DMatrix;
    use std::collections::VecDeque;
    use std::time::Duration;

    /// A port that hands every write to an in-process f32 device engine and reads back its
    /// replies: the link and the engine without threads or a terminal.
    struct Loopback {
        dev: Box<DefaultDevice<f32>>,
        rx: VecDeque<u8>,
    }

    impl Read for Loopback {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(self.rx.len());
            for b in buf.iter_mut().take(n) {
                *b = self.rx.pop_front().unwrap_or(0);
            }
            Ok(n)
        }
    }

    impl Write for Loopback {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            let rx = &mut self.rx;
            self.dev.handle(buf, |f| rx.extend(f.iter().copied()));
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// A drifting LPV-ARX plant with a little output noise (r = l = s = 1).
    fn drifting(n: usize) -> Signals {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let (mut u, mut y, mut p) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        for k in 0..n {
            u[k] = 2.0 * rnd();
            p[k] = (k as f64 * 0.01).sin();
            if k >= 2 {
                // the input gain drifts by 20 % over the record
                let g = 1.0 + 0.2 * k as f64 / n as f64;
                y[k] = (0.5 + 0.3 * p[k - 1]) * y[k - 1] + g * u[k - 1] - 0.2 * u[k - 2]
                    + 0.01 * rnd();
            }
        }
        Signals {
            u: DMatrix::from_column_slice(n, 1, &u),
            y: DMatrix::from_column_slice(n, 1, &y),
            p: DMatrix::from_column_slice(n, 1, &p),
        }
    }

    /// The watch decodes every report the engine makes into a record equal to the host's
    /// replay of the same estimate bit for bit, with the one-step error of the noise level.
    #[test]
    fn watch_decodes_the_estimate_reports() {
        let sig = drifting(2000);
        let dims = PbsidDims::new(1, 1, 1, 2).unwrap();
        let acc = Accumulation {
            forgetting: 0.995,
            window: 0,
        };
        let track = Track {
            every: 250,
            solve: SolveRequest {
                lambda_ratio: 0.0,
                group: false,
                standardise: true,
            },
        };
        let port = Loopback {
            dev: Box::new(DefaultDevice::new()),
            rx: VecDeque::new(),
        };
        let opts = LinkOptions {
            timeout: Duration::from_millis(50),
            first_timeout: Duration::from_millis(50),
            retries: 2,
            batch: 0,
        };
        let mut link = Link::new(port, opts);
        let info = link.hello().unwrap();
        link.configure_with(&dims, StatsLayout::Extended, acc)
            .unwrap();
        link.track(track).unwrap();
        let mut recs = Vec::new();
        let mut frames = 0;
        link.watch(
            &sample_rows(&sig),
            3,
            0,
            |_, _| frames += 1,
            |r| recs.push(r.clone()),
        )
        .unwrap();
        let host = replay_tracking::<f32>(
            &sig,
            2,
            StatsLayout::Extended,
            acc,
            2 * info.gram_cap as usize,
            info.solver_cap as usize,
            &track,
        )
        .unwrap();
        assert_eq!(host.len(), 8);
        assert!(frames > recs.len());
        // a report per solve (the frames are shorter than K), each equal to the replay
        assert_eq!(recs.len(), 8);
        for (r, h) in recs.iter().zip(&host) {
            assert_eq!((r.solves, r.at_sample), (h.solves, h.at_sample));
            assert_eq!(r.theta, h.theta);
            assert_eq!(r.interval_count, h.interval_count);
            assert_eq!(r.interval_sse, h.interval_sse);
            assert_eq!(r.theta.len(), r.summary.columns as usize);
        }
        // from the second report on, the interval's one-step RMS (the first interval has no
        // solution yet): above the noise (0.01 uniform: std 0.0029) since the plant drifts
        // (the input gain by 0.2 over the record), and the estimate follows the drift: over
        // the last three intervals its error is well below that of the same recursive
        // estimate without forgetting (whose gain lags about half the record behind)
        assert!(recs[0].interval_rms.is_empty());
        for r in &recs[1..] {
            assert_eq!(r.interval_count, 250);
            assert!(r.interval_rms[0] > 0.0029, "{:?}", r.interval_rms);
        }
        let plain = replay_tracking::<f32>(
            &sig,
            2,
            StatsLayout::Extended,
            Accumulation::default(),
            2 * info.gram_cap as usize,
            info.solver_cap as usize,
            &track,
        )
        .unwrap();
        let tail = |sse: &mut dyn Iterator<Item = (f64, u32)>| {
            let (s, n) = sse.fold((0.0, 0u32), |(a, b), (s, n)| (a + s, b + n));
            (s / n as f64).sqrt()
        };
        let forget = tail(
            &mut recs[5..]
                .iter()
                .map(|r| (r.interval_sse[0], r.interval_count)),
        );
        let long = tail(
            &mut plain[5..]
                .iter()
                .map(|p| (p.interval_sse[0], p.interval_count)),
        );
        println!("one-step RMS over the last 3 intervals: forgetting {forget:.4}, none {long:.4}");
        assert!(forget < 0.75 * long, "forgetting {forget}, none {long}");
        // the JSON line keys and the plot
        let v = serde_json::to_value(&recs[3]).unwrap();
        for k in [
            "solves",
            "at_sample",
            "theta",
            "interval_rms",
            "last_error",
            "summary",
        ] {
            assert!(v.get(k).is_some(), "{k}");
        }
        let hist = WatchHistory { records: recs };
        let svg = hist.svg();
        assert!(svg.starts_with("<svg") && svg.contains("theta[") && svg.contains("<path"));
    }

    #[test]
    fn a_record_with_the_wrong_coefficient_count_is_refused() {
        let est = EstimateReply {
            solves: 1,
            failures: 0,
            at_sample: 10,
            summary: SolveSummary {
                columns: 3,
                outputs: 2,
                lambda: 0.0,
                lambda_max: 1.0,
                iterations: 1,
                converged: true,
                active: 3,
                kkt: 0.0,
                objective: 0.0,
            },
            count: 4,
            sse: vec![4.0, 16.0],
            last_error: vec![0.5, -1.0],
        };
        assert!(WatchRecord::new(&est, vec![0.0; 5]).is_err());
        let r = WatchRecord::new(&est, vec![0.0; 6]).unwrap();
        assert_eq!(r.interval_rms, vec![1.0, 2.0]);
    }
}
