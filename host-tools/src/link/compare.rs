//! Device statistics checked against a data file: the host accumulates the same samples
//! with the core's code (in the device's float type and in f64), compares the packed Grams
//! and the models fitted from them ([`compare_with_file`]); `make device-test` relies on it.

use lpvid::device::{device_summation, solve_statistics, OneStep};
use lpvid::protocol::{SolveSummary, Track};
use lpvid::sliding::{rebase_gram, HalfWindow};
use lpvid::{packed_len, stat_vector_len, Gram, PbsidDims, PbsidStats, StatsLayout};

use super::Accumulation;

use crate::lpvss::{LpvSs, Signals};
use crate::pbsid::{self, FitError, PbsidFit, PbsidOptions, Solver};

/// Statistics accumulated on the host (storage in `Vec`s).
pub type HostStats<T> = PbsidStats<T, Vec<T>, Vec<T>, Vec<T>>;

/// Why statistics could not be compared or fitted.
#[derive(Debug, thiserror::Error)]
pub enum CompareError {
    /// The core rejected the dimensions or a sample.
    #[error(transparent)]
    Core(#[from] lpvid::Error),
    /// The pulled statistics do not have the size these dimensions give.
    #[error(
        "the device holds {pulled} statistic values, the host computes {host} for these dimensions"
    )]
    Size {
        /// Values pulled.
        pulled: usize,
        /// Values the host computes.
        host: usize,
    },
    /// The pulled values do not load as an extended Gram.
    #[error("pulled statistics do not fit the extended layout of these dimensions: {0}")]
    Layout(lpvid::Error),
    /// The device cannot hold this configuration (the host replays the device's storage).
    #[error("a device with {gram_values} Gram values cannot hold {what}")]
    DeviceCapacity {
        /// The device's Gram storage (values).
        gram_values: usize,
        /// What does not fit.
        what: &'static str,
    },
    /// A fit failed (`what`: which one).
    #[error("{what}: {source}")]
    Fit {
        /// "file fit", "fit from device statistics", "fit from host statistics".
        what: &'static str,
        /// The fit's error.
        source: FitError,
    },
}

/// Extended (or plain) statistics of `sig` accumulated on the host with the core's code in
/// float type `T` (f32: exactly what an f32 device computes from the same samples).
pub fn host_stats<T: lpvid::Real>(
    sig: &Signals,
    p: usize,
    layout: StatsLayout,
) -> Result<HostStats<T>, lpvid::Error> {
    let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), p)?;
    let len = stat_vector_len(&dims, layout)?;
    let mut st = PbsidStats::with_storage(
        dims,
        layout,
        vec![T::ZERO; lpvid::window_storage_len(dims.r, dims.l, dims.s, p)],
        // compensated sums, as on the device (lpvid::device::sizes::G)
        vec![T::ZERO; lpvid::gram_storage_len(len)],
        vec![T::ZERO; len],
    )?;
    for k in 0..sig.len() {
        let row =
            |m: &nalgebra::DMatrix<f64>| -> Vec<T> { m.row(k).iter().map(|v| T::of(*v)).collect() };
        st.update(&row(&sig.u), &row(&sig.y), &row(&sig.p))?;
    }
    Ok(st)
}

/// [`host_stats`] as a device with `gram_values` Gram storage values accumulates under
/// `acc` (protocol 2): the same summation ([`device_summation`]), forgetting
/// ([`Gram::set_forgetting`]) and sliding window (the snapshot in the Gram's spare storage,
/// rebased by [`rebase_gram`] every half window), so an f32 host equals an f32 device bit
/// for bit. With `Accumulation::default()` and a device's storage this is [`host_stats`].
pub fn host_stats_as_device<T: lpvid::Real>(
    sig: &Signals,
    p: usize,
    layout: StatsLayout,
    acc: Accumulation,
    gram_values: usize,
) -> Result<HostStats<T>, CompareError> {
    let mut run = HostRun::<T>::new(sig, p, layout, acc, gram_values)?;
    for k in 0..sig.len() {
        run.sample(sig, k)?;
    }
    Ok(run.st)
}

/// The device's accumulation replayed on the host, one sample at a time.
struct HostRun<T: lpvid::Real> {
    st: HostStats<T>,
    win: Option<HalfWindow>,
}

impl<T: lpvid::Real> HostRun<T> {
    fn new(
        sig: &Signals,
        p: usize,
        layout: StatsLayout,
        acc: Accumulation,
        gram_values: usize,
    ) -> Result<Self, CompareError> {
        let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), p)?;
        let len = stat_vector_len(&dims, layout)?;
        let win = if acc.window > 0 {
            Some(HalfWindow::new(acc.window as u64)?)
        } else {
            None
        };
        let summation = device_summation(len, win.is_some(), gram_values).ok_or(
            CompareError::DeviceCapacity {
                gram_values,
                what: "these statistics",
            },
        )?;
        let mut st = PbsidStats::with_storage(
            dims,
            layout,
            vec![T::ZERO; lpvid::window_storage_len(dims.r, dims.l, dims.s, p)],
            vec![T::ZERO; packed_len(len)],
            vec![T::ZERO; len],
        )?;
        *st.gram_mut() = Gram::with_summation(len, vec![T::ZERO; gram_values], summation)?;
        st.set_forgetting(T::of(acc.forgetting as f64))?;
        Ok(HostRun { st, win })
    }

    /// Feed sample `k`; true when it completed a statistic vector.
    fn sample(&mut self, sig: &Signals, k: usize) -> Result<bool, CompareError> {
        let row =
            |m: &nalgebra::DMatrix<f64>| -> Vec<T> { m.row(k).iter().map(|v| T::of(*v)).collect() };
        let done = self.st.update(&row(&sig.u), &row(&sig.y), &row(&sig.p))?;
        if done {
            if let Some(w) = self.win.as_mut() {
                if w.added() {
                    rebase_gram(self.st.gram_mut(), None, w.half())?;
                }
            }
        }
        Ok(done)
    }
}

/// One solve of a recursive estimate replayed on the host ([`replay_tracking`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ReplayPoint {
    /// Stream index of the next sample when the solve ran.
    pub at_sample: u32,
    /// Successful solves so far (this one included).
    pub solves: u32,
    /// The solve's summary.
    pub summary: SolveSummary,
    /// The coefficients, l x (q + r).
    pub theta: Vec<f64>,
    /// One-step predictions of the previous solution over its interval.
    pub interval_count: u32,
    /// Their sum of squared errors per output.
    pub interval_sse: Vec<f64>,
}

/// The device's recursive estimate replayed on the host in float type `T` with the core's
/// functions (statistics as [`host_stats_as_device`], [`solve_statistics`] warm-started every
/// `track.every` samples, [`OneStep`] between solves): the points an f32 device reports,
/// bit for bit. `solver_values`: the device's solver storage.
pub fn replay_tracking<T: lpvid::Real>(
    sig: &Signals,
    p: usize,
    layout: StatsLayout,
    acc: Accumulation,
    gram_values: usize,
    solver_values: usize,
    track: &Track,
) -> Result<Vec<ReplayPoint>, CompareError> {
    let mut run = HostRun::<T>::new(sig, p, layout, acc, gram_values)?;
    let dims = run.st.dims();
    let l = dims.l;
    let cols = dims.q()? + dims.r;
    let mut solver = vec![T::ZERO; solver_values];
    let mut rec = OneStep::<T>::new();
    let mut solved = false;
    let mut points = Vec::new();
    let mut since = 0u32;
    let mut solves = 0u32;
    for k in 0..sig.len() {
        if run.sample(sig, k)? && solved {
            rec.add(run.st.last_vector(), &solver, cols, l);
        }
        if track.every == 0 {
            continue;
        }
        since += 1;
        if since >= track.every {
            since = 0;
            if let Ok(sum) = solve_statistics(run.st.gram(), &dims, &track.solve, &mut solver, true)
            {
                solved = true;
                solves += 1;
                points.push(ReplayPoint {
                    at_sample: (k + 1) as u32,
                    solves,
                    summary: sum,
                    theta: solver[..l * cols].iter().map(|v| v.to_f64()).collect(),
                    interval_count: rec.count,
                    interval_sse: rec.sse[..l].iter().map(|v| v.to_f64()).collect(),
                });
                rec = OneStep::new();
            }
        }
    }
    Ok(points)
}

/// Samples of `sig` row-major [u, y, p], the order the wire carries them.
pub fn sample_rows(sig: &Signals) -> Vec<f64> {
    let mut rows = Vec::with_capacity(sig.len() * (sig.u.ncols() + sig.y.ncols() + sig.p.ncols()));
    for k in 0..sig.len() {
        rows.extend(sig.u.row(k).iter());
        rows.extend(sig.y.row(k).iter());
        rows.extend(sig.p.row(k).iter());
    }
    rows
}

/// Largest difference between two packed Grams, each entry relative to
/// sqrt(G_ii G_jj) of `reference` (the scale of a sum of products: what rounding in
/// the accumulation is proportional to).
pub fn gram_difference(pulled: &[f64], reference: &Gram<f64, Vec<f64>>) -> f64 {
    let dim = reference.dim();
    let mut worst: f64 = 0.0;
    let mut off = 0;
    for i in 0..dim {
        for j in i..dim {
            let a = pulled.get(off + j - i).copied().unwrap_or(f64::NAN);
            let b = reference.get(i, j);
            let scale = (reference.get(i, i) * reference.get(j, j))
                .sqrt()
                .max(1e-300);
            let d = (a - b).abs() / scale;
            worst = if d.is_nan() {
                f64::INFINITY
            } else {
                worst.max(d)
            };
        }
        off += dim - i;
    }
    worst
}

/// Largest difference of two models' free-run outputs on `sig`, relative to max |y|.
pub fn model_difference(a: &LpvSs, b: &LpvSs, sig: &Signals) -> f64 {
    let ya = a.simulate(sig, None);
    let yb = b.simulate(sig, None);
    let d = (ya - &yb).amax() / sig.y.amax().max(1e-300);
    if d.is_nan() {
        f64::INFINITY
    } else {
        d
    }
}

/// The outcome of comparing a device's statistics with the same file on the host.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Comparison {
    /// Windows the device accumulated / the host.
    pub windows: (u64, u64),
    /// Max relative Gram difference, device vs host f64 accumulation.
    pub stats_vs_f64: f64,
    /// Max absolute Gram difference, device vs host accumulation in the device's float type
    /// (0 when both round identically).
    pub stats_vs_same_type: f64,
    /// Max relative free-run output difference: model from the device's statistics vs the
    /// file-based (primal) fit of the same data.
    pub model_vs_file_fit: Option<f64>,
    /// Same, model from the host's f64 statistics vs the file fit (the f64 floor).
    pub host_stats_model_vs_file_fit: Option<f64>,
    /// Orders chosen (device statistics, file fit).
    pub orders: Option<(usize, usize)>,
}

/// Compare pulled statistics with the host's accumulation of `sig`, and (with `opts`) the
/// model fitted from them with the file-based fit.
pub fn compare_with_file(
    pulled: &[f64],
    windows: u64,
    float_bytes: u8,
    sig: &Signals,
    dims: &PbsidDims,
    layout: StatsLayout,
    opts: Option<&PbsidOptions>,
) -> Result<Comparison, CompareError> {
    let g = lpvid::gram_storage_len(stat_vector_len(dims, layout)?);
    let acc = Accumulation::default();
    compare_as_device(
        pulled,
        windows,
        float_bytes,
        sig,
        dims,
        layout,
        opts,
        acc,
        g,
    )
}

/// [`compare_with_file`] for a device that accumulated under `acc` (forgetting, window) in
/// `gram_values` Gram storage values: the host replays the same accumulation
/// ([`host_stats_as_device`]) in f64 and in the device's float type. The model comparisons
/// against the file fit are made only for plain sums (a forgetting or windowed fit is not
/// the file's).
#[allow(clippy::too_many_arguments)]
pub fn compare_as_device(
    pulled: &[f64],
    windows: u64,
    float_bytes: u8,
    sig: &Signals,
    dims: &PbsidDims,
    layout: StatsLayout,
    opts: Option<&PbsidOptions>,
    acc: Accumulation,
    gram_values: usize,
) -> Result<Comparison, CompareError> {
    let h64 = host_stats_as_device::<f64>(sig, dims.p, layout, acc, gram_values)?;
    if h64.gram().packed().len() != pulled.len() {
        return Err(CompareError::Size {
            pulled: pulled.len(),
            host: h64.gram().packed().len(),
        });
    }
    let same: Vec<f64> = if float_bytes == 4 {
        let h32 = host_stats_as_device::<f32>(sig, dims.p, layout, acc, gram_values)?;
        h32.gram().packed().iter().map(|v| *v as f64).collect()
    } else {
        h64.gram().packed().to_vec()
    };
    let opts = if acc == Accumulation::default() {
        opts
    } else {
        None
    };
    let stats_vs_same_type = pulled
        .iter()
        .zip(&same)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let stats_vs_f64 = gram_difference(pulled, h64.gram());
    let mut cmp = Comparison {
        windows: (windows, h64.gram().count()),
        stats_vs_f64,
        stats_vs_same_type,
        model_vs_file_fit: None,
        host_stats_model_vs_file_fit: None,
        orders: None,
    };
    if let (Some(o), StatsLayout::Extended) = (opts, layout) {
        let mut fo = o.clone();
        fo.solver = Solver::Primal;
        let file = pbsid::fit(sig, &fo).map_err(|e| CompareError::Fit {
            what: "file fit",
            source: e,
        })?;
        let dev = fit_pulled(pulled, windows, dims, o)?;
        let host = pbsid::fit_from_stats(h64.gram(), dims, o).map_err(|e| CompareError::Fit {
            what: "fit from host statistics",
            source: e,
        })?;
        cmp.model_vs_file_fit = Some(model_difference(&dev.model, &file.model, sig));
        cmp.host_stats_model_vs_file_fit = Some(model_difference(&host.model, &file.model, sig));
        cmp.orders = Some((dev.order, file.order));
    }
    Ok(cmp)
}

/// Load a packed extended Gram as pulled from a device (upper triangle, row-major) with
/// its window count, checked against the dimensions.
pub fn extended_gram(
    packed: &[f64],
    windows: u64,
    dims: &PbsidDims,
) -> Result<Gram<f64, Vec<f64>>, CompareError> {
    let len = stat_vector_len(dims, StatsLayout::Extended)?;
    let mut g = Gram::new(len, vec![0.0; packed_len(len)])?;
    g.load(packed, windows).map_err(CompareError::Layout)?;
    Ok(g)
}

/// Fit a model from pulled (extended) statistics with [`pbsid::fit_from_stats`].
pub fn fit_pulled(
    pulled: &[f64],
    windows: u64,
    dims: &PbsidDims,
    opts: &PbsidOptions,
) -> Result<PbsidFit, CompareError> {
    let g = extended_gram(pulled, windows, dims)?;
    pbsid::fit_from_stats(&g, dims, opts).map_err(|e| CompareError::Fit {
        what: "fit from device statistics",
        source: e,
    })
}
