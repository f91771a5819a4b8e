//! `lpvid._lpvid`: the native half of the Python package `lpvid`.
//!
//! Thin: every computation is the host library's (`lpvid_host::pipeline`, `simulate`,
//! `diagnose`, `statistics`), so a model identified from Python is the model `lpvid pbsid`
//! writes. This module converts numpy arrays to the library's data sets and back, turns the
//! library's errors into Python exceptions with the command line's text, and releases the
//! GIL around long work. The Python half (`python/lpvid/__init__.py`) accepts pandas
//! DataFrames, paths and loose arrays and builds the user-facing objects.

use std::path::Path;

use lpvid::PbsidDims;
use lpvid_host::arx::{ArxOptions, Estimator, LambdaChoice, Precision, SigmaChoice, SigmaData};
use lpvid_host::data::{DataError as HostDataError, Dataset};
use lpvid_host::diagnose;
use lpvid_host::lpvss::{scheduled, LpvSs, Signals};
use lpvid_host::model::{ModelFile, ModelKind};
use lpvid_host::observer::{HinfOptions, ObserverRequest, DEFAULT_MARGIN};
use lpvid_host::pbsid::{
    BpdnScore, Centre, Order, PbsidOptions, Reg, Solver, DEFAULT_SCHED_WEIGHT,
};
use lpvid_host::pipeline::{self, reg_name, DataFile, PbsidSettings};
use lpvid_host::simulate::{score, simulate, Mode, Score};
use lpvid_host::statistics::Statistics;
use nalgebra::{DMatrix, DVector};
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

create_exception!(
    lpvid,
    LpvidError,
    PyException,
    "An lpvid error; str(e) is the message the lpvid command line prints."
);
create_exception!(
    lpvid,
    DataError,
    LpvidError,
    "A data or model problem; attributes file, line (1-based, or None), column (or None), message."
);

/// A `DataError` exception with its location attributes.
fn data_err(py: Python<'_>, e: &HostDataError) -> PyErr {
    let err = DataError::new_err(e.to_string());
    let v = err.value(py);
    let _ = v.setattr("file", e.file.clone());
    let _ = v.setattr("line", e.line);
    let _ = v.setattr("column", e.column.clone());
    let _ = v.setattr("message", e.message.clone());
    err
}

/// The host library's error as a Python exception (same text as the command line).
fn host_err(py: Python<'_>, e: lpvid_host::Error) -> PyErr {
    match &e {
        lpvid_host::Error::Data(d) => data_err(py, d),
        lpvid_host::Error::Diagnose(diagnose::DiagnoseError::Data(d)) => data_err(py, d),
        _ => LpvidError::new_err(e.to_string()),
    }
}

fn invalid(msg: impl Into<String>) -> PyErr {
    LpvidError::new_err(msg.into())
}

/// FNV-1a of the arrays' names and row-major f64 bytes (the `fit` record's fingerprint of
/// data given as arrays).
fn array_bytes(names: &[String], data: &[f64]) -> Vec<u8> {
    let mut b = names.join(",").into_bytes();
    b.push(b'\n');
    for v in data {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

/// A data set (a CSV file read by the library, or named columns from numpy).
#[pyclass(name = "_Data", module = "lpvid._lpvid", frozen)]
struct PyData {
    file: DataFile,
}

#[pymethods]
impl PyData {
    /// Read a CSV data file with the library's parser (the command line's errors).
    #[staticmethod]
    fn read(py: Python<'_>, path: String) -> PyResult<PyData> {
        let file = py
            .detach(|| DataFile::read(Path::new(&path)))
            .map_err(|e| data_err(py, &e))?;
        Ok(PyData { file })
    }

    /// Columns `names` of the N x len(names) array `values`; `source` names it in errors
    /// and in the fit record.
    #[staticmethod]
    fn from_array(
        py: Python<'_>,
        names: Vec<String>,
        values: PyReadonlyArray2<'_, f64>,
        source: String,
    ) -> PyResult<PyData> {
        let arr = values.as_array();
        let (n, c) = (arr.nrows(), arr.ncols());
        if c != names.len() {
            return Err(invalid(format!(
                "{source}: {} column names for {c} columns",
                names.len()
            )));
        }
        for (i, a) in names.iter().enumerate() {
            if names[..i].contains(a) {
                return Err(data_err(
                    py,
                    &HostDataError::new(&source, None, Some(a), "duplicate column name"),
                ));
            }
        }
        let mut cols = vec![Vec::with_capacity(n); c];
        let mut flat = Vec::with_capacity(n * c);
        for k in 0..n {
            for (j, col) in cols.iter_mut().enumerate() {
                let v = arr[(k, j)];
                if !v.is_finite() {
                    return Err(data_err(
                        py,
                        &HostDataError::new(
                            &source,
                            None,
                            Some(&names[j]),
                            format!("sample {k} is {v} (NaN and infinite values are not allowed)"),
                        ),
                    ));
                }
                col.push(v);
                flat.push(v);
            }
        }
        let bytes = array_bytes(&names, &flat);
        Ok(PyData {
            file: DataFile {
                path: source.clone().into(),
                data: Dataset {
                    source,
                    names,
                    cols,
                },
                bytes,
            },
        })
    }

    /// Column names.
    #[getter]
    fn names(&self) -> Vec<String> {
        self.file.data.names.clone()
    }

    /// The source name (file path or the name given).
    #[getter]
    fn source(&self) -> String {
        self.file.data.source.clone()
    }

    /// Number of rows.
    fn __len__(&self) -> usize {
        self.file.data.len()
    }

    /// The values, N x columns.
    fn values<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let ds = &self.file.data;
        let (n, c) = (ds.len(), ds.cols.len());
        Array2::from_shape_fn((n, c), |(k, j)| ds.cols[j][k]).into_pyarray(py)
    }

    /// The record the model's `fit` writes for this data (file, rows, fnv1a64).
    fn record(&self) -> String {
        self.file.record().to_string()
    }
}

/// A model file (LPV state space or LPV-ARX) with its signal map and fit record.
#[pyclass(name = "_Model", module = "lpvid._lpvid", frozen)]
struct PyModel {
    model: ModelFile,
}

fn to_matrix(m: &DMatrix<f64>) -> Array2<f64> {
    Array2::from_shape_fn((m.nrows(), m.ncols()), |(i, j)| m[(i, j)])
}

fn stack(ms: &[DMatrix<f64>]) -> Array3<f64> {
    let (r, c) = ms.first().map_or((0, 0), |m| (m.nrows(), m.ncols()));
    Array3::from_shape_fn((ms.len(), r, c), |(k, i, j)| ms[k][(i, j)])
}

/// Free run of `ss` on `sig` from the initial state `x0` (the library's free run starts
/// at 0; this is the same recursion with x0 given, including its divergence guard).
fn free_run_from(ss: &LpvSs, sig: &Signals, x0: &DVector<f64>) -> DMatrix<f64> {
    let (ns, n, l) = (sig.len(), ss.n(), ss.l());
    let mut x = x0.clone();
    let mut out = DMatrix::<f64>::from_element(ns, l, f64::NAN);
    for k in 0..ns {
        let mu = sig.mu(k);
        let u = sig.u.row(k).transpose();
        let yk = scheduled(&ss.c, &mu) * &x + scheduled(&ss.d, &mu) * &u;
        out.set_row(k, &yk.transpose());
        let mut xn = DVector::<f64>::zeros(n);
        for i in 0..ss.m() {
            if mu[i] != 0.0 {
                xn += (&ss.a[i] * &x + &ss.b[i] * &u) * mu[i];
            }
        }
        x = xn;
        if !x.iter().all(|v| v.is_finite()) || x.amax() > 1e150 {
            break;
        }
    }
    out
}

fn score_json(s: &Score) -> String {
    serde_json::to_string(s).expect("a score serialises")
}

#[pymethods]
impl PyModel {
    /// Parse model JSON (the format `lpvid` writes); `source` names it in errors.
    #[staticmethod]
    #[pyo3(signature = (text, source = "model".to_string()))]
    fn from_json(py: Python<'_>, text: &str, source: String) -> PyResult<PyModel> {
        let model = ModelFile::from_json_str(&source, text).map_err(|e| data_err(py, &e))?;
        Ok(PyModel { model })
    }

    /// Read a model file.
    #[staticmethod]
    fn read(py: Python<'_>, path: String) -> PyResult<PyModel> {
        let model = ModelFile::read(Path::new(&path)).map_err(|e| data_err(py, &e))?;
        Ok(PyModel { model })
    }

    /// The model JSON, exactly as `lpvid` writes it.
    fn to_json(&self) -> String {
        self.model.to_json_string()
    }

    /// Validate and write atomically (as `lpvid`).
    fn write(&self, py: Python<'_>, path: String) -> PyResult<()> {
        self.model
            .write(Path::new(&path))
            .map_err(|e| data_err(py, &e))
    }

    /// The fit record as JSON text.
    fn fit_json(&self) -> String {
        self.model.fit.to_string()
    }

    /// "lpv-ss" or "lpv-arx".
    #[getter]
    fn kind(&self) -> &'static str {
        match self.model.kind {
            ModelKind::Ss(_) => "lpv-ss",
            ModelKind::Arx(_) => "lpv-arx",
        }
    }

    /// (inputs, outputs, scheduling basis functions after the constant).
    #[getter]
    fn dims(&self) -> (usize, usize, usize) {
        let s = &self.model.signals;
        (s.inputs.len(), s.outputs.len(), s.m() - 1)
    }

    /// State dimension (None for an ARX model).
    #[getter]
    fn n(&self) -> Option<usize> {
        match &self.model.kind {
            ModelKind::Ss(ss) => Some(ss.n()),
            ModelKind::Arx(_) => None,
        }
    }

    /// The signal map as JSON text ({"inputs", "scheduling", "outputs"} as the model file).
    fn signals_json(&self) -> String {
        let v: serde_json::Value =
            serde_json::from_str(&self.model.to_json_string()).expect("the model JSON parses");
        serde_json::json!({
            "inputs": v["inputs"], "scheduling": v["scheduling"], "outputs": v["outputs"],
        })
        .to_string()
    }

    /// The matrices: A, B, K (m x n x ., one per scheduling basis function), C, D
    /// (mc x l x .); for an ARX model na, nb, a (na x m), b (inputs x (nb+1) x m).
    fn matrices<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        match &self.model.kind {
            ModelKind::Ss(ss) => {
                d.set_item("A", stack(&ss.a).into_pyarray(py))?;
                d.set_item("B", stack(&ss.b).into_pyarray(py))?;
                d.set_item("K", stack(&ss.k).into_pyarray(py))?;
                d.set_item("C", stack(&ss.c).into_pyarray(py))?;
                d.set_item("D", stack(&ss.d).into_pyarray(py))?;
            }
            ModelKind::Arx(a) => {
                let m = a.a.first().map_or(0, Vec::len);
                d.set_item("na", a.na)?;
                d.set_item("nb", a.nb)?;
                let am = Array2::from_shape_fn((a.a.len(), m), |(i, q)| a.a[i][q]);
                d.set_item("a", am.into_pyarray(py))?;
                let bm = Array3::from_shape_fn((a.b.len(), a.nb + 1, m), |(i, j, q)| a.b[i][j][q]);
                d.set_item("b", bm.into_pyarray(py))?;
            }
        }
        Ok(d)
    }

    /// Free run (x0 = 0 unless given; lpv-ss only for x0) on `data`: N x l.
    #[pyo3(signature = (data, x0 = None))]
    fn simulate<'py>(
        &self,
        py: Python<'py>,
        data: &PyData,
        x0: Option<PyReadonlyArray1<'py, f64>>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let ds = &data.file.data;
        let yhat = match x0 {
            None => {
                py.detach(|| simulate(&self.model, ds, Mode::FreeRun))
                    .map_err(|e| data_err(py, &e))?
                    .1
            }
            Some(x0) => {
                let ModelKind::Ss(ss) = &self.model.kind else {
                    return Err(invalid("x0: an LPV-ARX model has no state"));
                };
                let x0 = x0.as_array();
                if x0.len() != ss.n() {
                    return Err(invalid(format!(
                        "x0 has {} values, the model has {} states",
                        x0.len(),
                        ss.n()
                    )));
                }
                let x0 = DVector::from_iterator(x0.len(), x0.iter().copied());
                let sig = self
                    .model
                    .signals
                    .evaluate(ds)
                    .map_err(|e| data_err(py, &e))?;
                py.detach(|| free_run_from(ss, &sig, &x0))
            }
        };
        Ok(to_matrix(&yhat).into_pyarray(py))
    }

    /// One-step-ahead prediction with the measured outputs: N x l.
    fn predict<'py>(&self, py: Python<'py>, data: &PyData) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let (_, yhat) = py
            .detach(|| simulate(&self.model, &data.file.data, Mode::Predictor))
            .map_err(|e| data_err(py, &e))?;
        Ok(to_matrix(&yhat).into_pyarray(py))
    }

    /// VAF/BFR (JSON of the library's Score) of the free run or the predictor.
    #[pyo3(signature = (data, predictor = false))]
    fn score(&self, py: Python<'_>, data: &PyData, predictor: bool) -> PyResult<String> {
        let mode = if predictor {
            Mode::Predictor
        } else {
            Mode::FreeRun
        };
        let s = py
            .detach(|| score(&self.model, &data.file.data, mode))
            .map_err(|e| data_err(py, &e))?;
        Ok(score_json(&s))
    }

    /// The one-paragraph description `lpvid diagnose` prints.
    fn summary(&self) -> String {
        diagnose::report::model_summary(&self.model)
    }
}

#[allow(clippy::too_many_arguments)]
fn pbsid_options(
    past: usize,
    order: &str,
    reg: &str,
    kernel: bool,
    primal: bool,
    kernel_rows: Option<usize>,
    kernel_tol: f64,
    refine: bool,
    future: Option<usize>,
    feedthrough: bool,
    sched_weight: f64,
    max_order: usize,
    bpdn_score: Option<&str>,
) -> PyResult<PbsidOptions> {
    if kernel && primal {
        return Err(invalid("kernel=True and primal=True exclude each other"));
    }
    if kernel_rows.is_some() && primal {
        return Err(invalid("kernel_rows and primal=True exclude each other"));
    }
    let mut o = PbsidOptions::new(past);
    o.order = order.parse::<Order>().map_err(|e| invalid(e.to_string()))?;
    o.reg = reg.parse::<Reg>().map_err(|e| invalid(e.to_string()))?;
    if let Some(b) = bpdn_score {
        if o.reg != Reg::BpdnSv {
            return Err(invalid(format!(
                "bpdn_score applies to reg='bpdn-sv' only (got reg='{}')",
                reg_name(o.reg)
            )));
        }
        o.bpdn_score = b.parse::<BpdnScore>().map_err(|e| invalid(e.to_string()))?;
    }
    o.feedthrough = feedthrough;
    o.solver = if kernel {
        Solver::Dual
    } else if primal {
        Solver::Primal
    } else {
        Solver::Auto
    };
    o.future = future;
    o.sched_weight = sched_weight;
    o.kernel_rows = kernel_rows;
    o.kernel_tol = kernel_tol;
    o.refine = refine;
    o.max_order = max_order;
    Ok(o)
}

/// LPV-PBSID_opt (`lpvid pbsid`) through `pipeline::identify`. Returns the model and a
/// JSON summary (the `--json` summary's fields).
#[pyfunction]
#[pyo3(signature = (train, past, order = "auto", reg = "tikhonov-gcv", kernel = false,
    primal = false, kernel_rows = None, kernel_tol = 0.0, refine = false, future = None,
    feedthrough = true, sched_weight = DEFAULT_SCHED_WEIGHT, max_order = 20, bpdn_score = None,
    observer = "ls", scheduling_range = Vec::new(), lmi_margin = DEFAULT_MARGIN, val = None,
    centre = "auto"))]
#[allow(clippy::too_many_arguments)]
fn pbsid(
    py: Python<'_>,
    train: &PyData,
    past: usize,
    order: &str,
    reg: &str,
    kernel: bool,
    primal: bool,
    kernel_rows: Option<usize>,
    kernel_tol: f64,
    refine: bool,
    future: Option<usize>,
    feedthrough: bool,
    sched_weight: f64,
    max_order: usize,
    bpdn_score: Option<&str>,
    observer: &str,
    scheduling_range: Vec<String>,
    lmi_margin: f64,
    val: Option<&PyData>,
    centre: &str,
) -> PyResult<(PyModel, String)> {
    let mut fit = pbsid_options(
        past,
        order,
        reg,
        kernel,
        primal,
        kernel_rows,
        kernel_tol,
        refine,
        future,
        feedthrough,
        sched_weight,
        max_order,
        bpdn_score,
    )?;
    fit.centre = centre.parse::<Centre>().map_err(|e| invalid(e.to_string()))?;
    let hinf = match observer {
        "ls" => false,
        "hinf" => true,
        other => {
            return Err(invalid(format!(
                "observer must be 'ls' or 'hinf', got '{other}'"
            )))
        }
    };
    let settings = PbsidSettings {
        fit,
        observer: ObserverRequest {
            hinf,
            ranges: scheduling_range,
            opts: HinfOptions {
                margin: lmi_margin,
                ..Default::default()
            },
        },
    };
    let run = py
        .detach(|| pipeline::identify(&train.file, val.map(|v| &v.file.data), &settings))
        .map_err(|e| host_err(py, e))?;
    let summary = serde_json::json!({
        "order": run.fit.order,
        "order_reason": run.fit.order_reason,
        "singular_values": run.fit.singular_values,
        "solver": run.model.fit["solver"].clone(),
        "solver_reason": run.fit.solver_reason,
        "warnings": run.warnings,
        "lambda": run.fit.lambda,
        "train": run.train_score,
        "val": run.val_score,
        "observer": run.observer.used,
        "observer_lines": run.observer.lines,
        "stability_region": run.observer.stability_json(),
        "samples": run.samples,
        "dims": run.dims,
    });
    Ok((PyModel { model: run.model }, summary.to_string()))
}

/// LPV-ARX (`lpvid arx`) through `pipeline::identify_arx`.
#[pyfunction]
#[pyo3(signature = (train, na, nb, ng, estimator = "bciv", sigma_p = None, lambda_ = "cv",
    sigma_grid = None, sigma_data = "all", plain_l1 = false, no_debias = false,
    min_cost = false, no_refine = false, refit_train_only = false, max_iter = 10, f32 = false,
    noise_ratios = None, calib = None, val = None))]
#[allow(clippy::too_many_arguments)]
fn arx(
    py: Python<'_>,
    train: &PyData,
    na: usize,
    nb: usize,
    ng: usize,
    estimator: &str,
    sigma_p: Option<&str>,
    lambda_: &str,
    sigma_grid: Option<Vec<f64>>,
    sigma_data: &str,
    plain_l1: bool,
    no_debias: bool,
    min_cost: bool,
    no_refine: bool,
    refit_train_only: bool,
    max_iter: usize,
    f32: bool,
    noise_ratios: Option<Vec<f64>>,
    calib: Option<&PyData>,
    val: Option<&PyData>,
) -> PyResult<(PyModel, String)> {
    let mut o = ArxOptions::new(na, nb, ng);
    o.estimator = estimator
        .parse::<Estimator>()
        .map_err(|e| invalid(e.to_string()))?;
    o.sigma = match sigma_p {
        Some(s) => s
            .parse::<SigmaChoice>()
            .map_err(|e| invalid(e.to_string()))?,
        None if o.estimator == Estimator::Bciv => SigmaChoice::Auto,
        None => SigmaChoice::Fixed(0.0),
    };
    o.lambda = lambda_
        .parse::<LambdaChoice>()
        .map_err(|e| invalid(e.to_string()))?;
    o.sigma_grid = sigma_grid;
    o.sigma_data = sigma_data
        .parse::<SigmaData>()
        .map_err(|e| invalid(e.to_string()))?;
    o.adaptive = !plain_l1;
    o.debias = !no_debias;
    o.one_se = !min_cost;
    o.refine_sigma = !no_refine;
    o.refit_all = !refit_train_only;
    o.max_iter = max_iter;
    o.precision = if f32 { Precision::F32 } else { Precision::F64 };
    if let Some(r) = &noise_ratios {
        if let Some(v) = r.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(invalid(format!(
                "noise_ratios: {v} is not a finite number >= 0"
            )));
        }
    }
    o.noise_ratios = noise_ratios;
    let run = py
        .detach(|| {
            pipeline::identify_arx(
                &train.file,
                calib.map(|c| &c.file),
                val.map(|v| &v.file.data),
                &o,
            )
        })
        .map_err(|e| host_err(py, e))?;
    let summary = serde_json::json!({
        "train": run.train_score,
        "train_diverged": run.train_diverged,
        "val": run.val_score,
        "sigma_grid": run.grid,
    });
    Ok((PyModel { model: run.model }, summary.to_string()))
}

/// `lpvid diagnose` through `diagnose::diagnose`: the final model, the report (JSON) and
/// the command line's summary text.
#[pyfunction]
#[pyo3(signature = (model, train, val, fix = true, max_steps = 1, threads = 0))]
fn diagnose_model(
    py: Python<'_>,
    model: &PyModel,
    train: &PyData,
    val: &PyData,
    fix: bool,
    max_steps: usize,
    threads: usize,
) -> PyResult<(PyModel, String, String)> {
    let opts = diagnose::Options {
        fix,
        max_steps,
        threads,
    };
    let out = py
        .detach(|| diagnose::diagnose(&model.model, &train.file.data, &val.file.data, &opts))
        .map_err(|e| host_err(py, lpvid_host::Error::Diagnose(e)))?;
    let summary = diagnose::report::summary(&out.report, &[]);
    let mut report = serde_json::to_value(&out.report).expect("the report serialises");
    report["singular_values_before"] = serde_json::json!(out.singular_values.0);
    report["singular_values_after"] = serde_json::json!(out.singular_values.1);
    Ok((PyModel { model: out.model }, report.to_string(), summary))
}

/// Mergeable statistics of experiments (`lpvid_host::statistics::Statistics`).
#[pyclass(name = "_Statistics", module = "lpvid._lpvid")]
struct PyStatistics {
    st: Statistics,
}

#[pymethods]
impl PyStatistics {
    #[new]
    fn new(
        py: Python<'_>,
        past: usize,
        inputs: usize,
        outputs: usize,
        scheduling: usize,
    ) -> PyResult<Self> {
        let dims = PbsidDims::new(inputs, outputs, scheduling, past)
            .map_err(|e| invalid(format!("statistics: {e}")))?;
        let st = Statistics::new(dims).map_err(|e| host_err(py, e))?;
        Ok(PyStatistics { st })
    }

    /// Add one experiment: rows N x (r + l + s), columns [u, y, p]. Returns its windows.
    fn update(
        &mut self,
        py: Python<'_>,
        rows: PyReadonlyArray2<'_, f64>,
        source: String,
    ) -> PyResult<u64> {
        let d = self.st.dims();
        let arr = rows.as_array();
        if arr.ncols() != d.r + d.l + d.s {
            return Err(invalid(format!(
                "{source}: {} columns, but the statistics are for {} inputs + {} outputs + {} scheduling signals",
                arr.ncols(),
                d.r,
                d.l,
                d.s
            )));
        }
        let owned;
        let flat: &[f64] = match rows.as_slice() {
            Ok(s) => s,
            Err(_) => {
                owned = arr.iter().copied().collect::<Vec<f64>>();
                &owned
            }
        };
        let st = &mut self.st;
        py.detach(|| st.add_experiment(flat, &source))
            .map_err(|e| host_err(py, e))
    }

    /// Add `other`'s statistics.
    fn merge(&mut self, py: Python<'_>, other: &PyStatistics) -> PyResult<()> {
        self.st.merge(&other.st).map_err(|e| host_err(py, e))
    }

    /// The versioned encoding (docs/wire.md section 7).
    fn to_bytes<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        PyBytes::new(py, &self.st.to_bytes())
    }

    /// Decode `to_bytes`' encoding.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<PyStatistics> {
        let st = Statistics::from_bytes(data).map_err(|e| host_err(py, e))?;
        Ok(PyStatistics { st })
    }

    /// Size of the encoding in bytes.
    #[getter]
    fn nbytes(&self) -> PyResult<usize> {
        Statistics::encoded_len(&self.st.dims()).map_err(|e| invalid(e.to_string()))
    }

    /// (past, inputs, outputs, scheduling).
    #[getter]
    fn dims(&self) -> (usize, usize, usize, usize) {
        let d = self.st.dims();
        (d.p, d.r, d.l, d.s)
    }

    #[getter]
    fn windows(&self) -> u64 {
        self.st.windows()
    }

    #[getter]
    fn experiments(&self) -> u64 {
        self.st.experiments()
    }

    /// The packed upper triangle of the Gram.
    fn packed<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        Array1::from_vec(self.st.gram().packed().to_vec()).into_pyarray(py)
    }

    /// LPV-PBSID_opt from the statistics (`pipeline::identify_from_stats`).
    #[pyo3(signature = (order = "auto", reg = "tikhonov-gcv", future = None, feedthrough = true,
        sched_weight = DEFAULT_SCHED_WEIGHT, max_order = 20))]
    #[allow(clippy::too_many_arguments)]
    fn fit(
        &self,
        py: Python<'_>,
        order: &str,
        reg: &str,
        future: Option<usize>,
        feedthrough: bool,
        sched_weight: f64,
        max_order: usize,
    ) -> PyResult<(PyModel, String)> {
        let d = self.st.dims();
        let opts = pbsid_options(
            d.p,
            order,
            reg,
            false,
            true,
            None,
            0.0,
            false,
            future,
            feedthrough,
            sched_weight,
            max_order,
            None,
        )?;
        let st = &self.st;
        let (model, fit) = py
            .detach(|| st.identify(&opts))
            .map_err(|e| host_err(py, e))?;
        let summary = serde_json::json!({
            "order": fit.order,
            "order_reason": fit.order_reason,
            "singular_values": fit.singular_values,
            "lambda": fit.lambda,
            "windows": fit.windows,
        });
        Ok((PyModel { model }, summary.to_string()))
    }
}

/// The native module.
#[pymodule]
fn _lpvid(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("LpvidError", py.get_type::<LpvidError>())?;
    m.add("DataError", py.get_type::<DataError>())?;
    m.add("DEFAULT_SCHED_WEIGHT", DEFAULT_SCHED_WEIGHT)?;
    m.add("DEFAULT_LMI_MARGIN", DEFAULT_MARGIN)?;
    m.add("STATISTICS_VERSION", lpvid_host::statistics::VERSION)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<PyData>()?;
    m.add_class::<PyModel>()?;
    m.add_class::<PyStatistics>()?;
    m.add_function(wrap_pyfunction!(pbsid, m)?)?;
    m.add_function(wrap_pyfunction!(arx, m)?)?;
    m.add_function(wrap_pyfunction!(diagnose_model, m)?)?;
    Ok(())
}
