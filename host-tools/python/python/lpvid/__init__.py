"""lpvid: LPV system identification from Python.

The same library as the ``lpvid`` command line (LPV-PBSID_opt, LPV-ARX, ``diagnose``,
mergeable statistics), with the command line's option names and defaults:

>>> import lpvid
>>> model = lpvid.pbsid(u, y, p, past=3)            # numpy arrays, N x r / N x l / N x s
>>> model = lpvid.pbsid(df, past=3)                 # or a DataFrame with u1.., y1.., p1..
>>> model = lpvid.pbsid("train.csv", past=3)        # or a CSV file (as ``lpvid pbsid``)
>>> model.validate(u_val, y_val, p_val)             # Score: VAF and BFR per output
>>> yhat = model.simulate(u_val, p_val)
>>> text = model.to_json()                          # the model file ``lpvid`` reads

Data arguments: ``u, y, p`` as arrays (1-D for one channel, or N x channels; ``p`` may be
omitted when there is no scheduling signal), or a single pandas DataFrame / dict of columns
(named as in the CSV files: ``u1.., y1.., p1..``; other columns are carried along), or a
path to a CSV file. Errors raise :class:`LpvidError` (``str(e)`` is the command line's
message); data problems raise its subclass :class:`DataError` with ``file``, ``line``,
``column`` attributes. Long computations release the GIL.
"""

from __future__ import annotations

import html
import json
import os
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from . import _lpvid
from ._lpvid import DataError, LpvidError

__version__ = _lpvid.__version__

__all__ = [
    "DataError",
    "LpvidError",
    "Model",
    "Score",
    "Report",
    "Finding",
    "Statistics",
    "pbsid",
    "arx",
    "diagnose",
    "fit_from_statistics",
    "read_csv",
    "read_model",
]

DEFAULT_SCHED_WEIGHT = _lpvid.DEFAULT_SCHED_WEIGHT
DEFAULT_LMI_MARGIN = _lpvid.DEFAULT_LMI_MARGIN


# ---------------------------------------------------------------------------------------
# data in


def _is_frame(x: Any) -> bool:
    return hasattr(x, "columns") and hasattr(x, "to_numpy") and hasattr(x, "dtypes")


def _as_2d(name: str, x: Any) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise LpvidError(f"{name}: expected a 1-D or 2-D array, got {a.ndim} dimensions")
    return a


def _frame_columns(df: Any) -> Dict[str, np.ndarray]:
    out = {}
    for c in df.columns:
        col = df[c]
        if getattr(col.dtype, "kind", "O") in "biuf":
            out[str(c)] = col.to_numpy(dtype=np.float64)
    return out


def _columns_data(cols: Mapping[str, Any], source: str) -> "_lpvid._Data":
    names = [str(k) for k in cols]
    arrays = [np.asarray(cols[k], dtype=np.float64).reshape(-1) for k in cols]
    n = {len(a) for a in arrays}
    if len(n) > 1:
        lens = ", ".join(f"{k}: {len(a)}" for k, a in zip(names, arrays))
        raise LpvidError(f"{source}: columns of different lengths ({lens})")
    values = np.ascontiguousarray(
        np.column_stack(arrays) if arrays else np.zeros((0, 0)), dtype=np.float64
    )
    return _lpvid._Data.from_array(names, values, source)


def _data(
    u: Any,
    y: Any = None,
    p: Any = None,
    *,
    source: Optional[str] = None,
    outputs: Optional[int] = None,
) -> "_lpvid._Data":
    """Anything the API accepts as data -> the library's data set.

    ``outputs``: when ``y`` is missing (simulation), add that many zero output columns so
    that the model's signal map finds y1..yl (they are not used by a free run)."""
    if isinstance(u, _lpvid._Data):
        return u
    if isinstance(u, Data):
        if outputs is None:
            return u._d
        u = u.to_dict()
    single = isinstance(u, (str, os.PathLike)) or _is_frame(u) or isinstance(u, Mapping)
    if single and (y is not None or p is not None):
        raise LpvidError("give either one data set (DataFrame, dict or CSV path) or arrays u, y, p")
    if isinstance(u, (str, os.PathLike)):
        if outputs is not None:
            u = read_csv(u, frame=False).to_dict()
        else:
            return _lpvid._Data.read(os.fspath(u))
    if isinstance(u, tuple) and y is None and p is None and 2 <= len(u) <= 3:
        return _data(*u, source=source, outputs=outputs)
    if _is_frame(u) or isinstance(u, Mapping):
        cols = _frame_columns(u) if _is_frame(u) else dict(u)
        if outputs is not None:
            n = len(next(iter(cols.values()))) if cols else 0
            for j in range(1, outputs + 1):
                cols.setdefault(f"y{j}", np.zeros(n))
        return _columns_data(cols, source or ("DataFrame" if _is_frame(u) else "dict"))
    cols: Dict[str, np.ndarray] = {}
    n = None
    for prefix, x in (("u", u), ("y", y), ("p", p)):
        if x is None:
            continue
        a = _as_2d(prefix, x)
        if n is not None and a.shape[0] != n:
            raise LpvidError(
                f"{prefix} has {a.shape[0]} samples, the arrays before it {n}"
            )
        n = a.shape[0]
        for j in range(a.shape[1]):
            cols[f"{prefix}{j + 1}"] = a[:, j]
    if y is None and outputs is not None:
        for j in range(1, outputs + 1):
            cols[f"y{j}"] = np.zeros(n or 0)
    return _columns_data(cols, source or "arrays")


class Data:
    """A data set as the library sees it (from :func:`read_csv` with ``frame=False``)."""

    def __init__(self, native: "_lpvid._Data"):
        self._d = native

    @property
    def names(self) -> List[str]:
        return list(self._d.names)

    @property
    def source(self) -> str:
        return self._d.source

    def __len__(self) -> int:
        return len(self._d)

    def to_dict(self) -> Dict[str, np.ndarray]:
        v = self._d.values()
        return {n: v[:, j].copy() for j, n in enumerate(self._d.names)}

    def __getitem__(self, name: str) -> np.ndarray:
        return self._d.values()[:, self._d.names.index(name)]

    def __repr__(self) -> str:
        return f"Data({self.source!r}: {len(self)} rows, columns {', '.join(self.names)})"


def read_csv(path: "str | os.PathLike", frame: bool = True) -> Any:
    """Read a data file with lpvid's own parser (errors name file, line and column).

    Returns a pandas DataFrame when pandas is installed and ``frame`` is true, else a
    :class:`Data` (``.to_dict()`` gives numpy columns)."""
    d = _lpvid._Data.read(os.fspath(path))
    if frame:
        try:
            import pandas as pd
        except ImportError:
            pass
        else:
            return pd.DataFrame(d.values(), columns=list(d.names))
    return Data(d)


# ---------------------------------------------------------------------------------------
# scores, models


class Score:
    """VAF and BFR (percent) per output and their means, of a free run or a predictor."""

    def __init__(self, d: Mapping[str, Any]):
        self.file: str = d["file"]
        self.mode: str = d["mode"]
        self.vaf = np.asarray(d["vaf"], dtype=float)
        self.bfr = np.asarray(d["bfr"], dtype=float)
        self.vaf_mean: float = float(d["vaf_mean"])
        self.bfr_mean: float = float(d["bfr_mean"])

    def to_dict(self) -> Dict[str, Any]:
        return {
            "file": self.file,
            "mode": self.mode,
            "vaf": self.vaf.tolist(),
            "bfr": self.bfr.tolist(),
            "vaf_mean": self.vaf_mean,
            "bfr_mean": self.bfr_mean,
        }

    def __repr__(self) -> str:
        f = lambda v, d: "[" + ", ".join(f"{x:.{d}f}" for x in v) + "]"  # noqa: E731
        return (
            f"Score({self.file} ({self.mode}): VAF {f(self.vaf, 3)} % (mean {self.vaf_mean:.3f}), "
            f"BFR {f(self.bfr, 2)} % (mean {self.bfr_mean:.2f}))"
        )

    def _repr_html_(self) -> str:
        rows = "".join(
            f"<tr><td>y{j + 1}</td><td>{v:.3f}</td><td>{b:.2f}</td></tr>"
            for j, (v, b) in enumerate(zip(self.vaf, self.bfr))
        )
        return (
            f"<table><caption>{html.escape(self.file)} ({self.mode})</caption>"
            "<tr><th>output</th><th>VAF %</th><th>BFR %</th></tr>"
            f"{rows}<tr><th>mean</th><th>{self.vaf_mean:.3f}</th><th>{self.bfr_mean:.2f}</th></tr>"
            "</table>"
        )


class Model:
    """An identified model (LPV state space ``lpv-ss`` or ``lpv-arx``), in the model file
    format of the ``lpvid`` command line.

    Attributes: ``fit`` (the fit record, a dict), ``singular_values``, ``order``, ``kind``,
    ``A, B, K, C, D`` (numpy arrays stacked over the scheduling basis functions, m x rows x
    cols), ``train_score`` / ``val_score`` (:class:`Score` when the fit computed them)."""

    def __init__(self, native: "_lpvid._Model", summary: Optional[Mapping[str, Any]] = None):
        self._m = native
        self.summary: Dict[str, Any] = dict(summary or {})
        self._fit: Optional[Dict[str, Any]] = None
        self._mats: Optional[Dict[str, Any]] = None

    # --- files
    @classmethod
    def from_json(cls, text: str, source: str = "model") -> "Model":
        """Parse model JSON as ``lpvid`` writes it."""
        return cls(_lpvid._Model.from_json(text, source))

    @classmethod
    def read(cls, path: "str | os.PathLike") -> "Model":
        """Read a model file (``lpvid pbsid --out``)."""
        return cls(_lpvid._Model.read(os.fspath(path)))

    def to_json(self) -> str:
        """The model file's text, exactly as ``lpvid`` writes it."""
        return self._m.to_json()

    def write(self, path: "str | os.PathLike") -> None:
        """Validate and write the model file atomically."""
        self._m.write(os.fspath(path))

    save = write

    def __reduce__(self):
        return (_model_from_state, (self.to_json(), self.summary))

    # --- what it is
    @property
    def kind(self) -> str:
        return self._m.kind

    @property
    def fit(self) -> Dict[str, Any]:
        """The fit record (settings, what the fit chose, data fingerprints)."""
        if self._fit is None:
            self._fit = json.loads(self._m.fit_json())
        return self._fit

    @property
    def singular_values(self) -> np.ndarray:
        return np.asarray(self.fit.get("singular_values") or [], dtype=float)

    @property
    def order(self) -> Optional[int]:
        """State dimension n (None for an LPV-ARX model)."""
        return self._m.n

    @property
    def inputs(self) -> int:
        return self._m.dims[0]

    @property
    def outputs(self) -> int:
        return self._m.dims[1]

    @property
    def scheduling(self) -> int:
        """Scheduling basis functions besides the constant (s for a plain model)."""
        return self._m.dims[2]

    @property
    def signals(self) -> Dict[str, Any]:
        """What each input, scheduling function and output is, as in the model file."""
        return json.loads(self._m.signals_json())

    @property
    def matrices(self) -> Dict[str, Any]:
        if self._mats is None:
            self._mats = dict(self._m.matrices())
        return self._mats

    def __getattr__(self, name: str) -> Any:
        if name in ("A", "B", "K", "C", "D", "a", "b", "na", "nb"):
            mats = self.matrices
            if name in mats:
                return mats[name]
        raise AttributeError(name)

    @property
    def train_score(self) -> Optional[Score]:
        t = self.summary.get("train")
        return Score(t) if t else None

    @property
    def val_score(self) -> Optional[Score]:
        v = self.summary.get("val")
        return Score(v) if v else None

    # --- use
    def simulate(self, u: Any, p: Any = None, x0: Any = None) -> np.ndarray:
        """Free-run outputs (N x l) driven by inputs ``u`` and scheduling ``p`` from the
        initial state ``x0`` (zero by default; lpv-ss only). ``u`` may be a DataFrame."""
        d = _data(u, None, p, outputs=self.outputs)
        if x0 is not None:
            x0 = np.ascontiguousarray(np.asarray(x0, dtype=np.float64).reshape(-1))
        return self._m.simulate(d, x0)

    def predict(self, u: Any, y: Any = None, p: Any = None) -> np.ndarray:
        """One-step-ahead predictions (N x l) using the measured outputs ``y``."""
        return self._m.predict(_data(u, y, p))

    def validate(self, u: Any, y: Any = None, p: Any = None, predictor: bool = False) -> Score:
        """VAF and BFR of the free run (or of the one-step predictor) on data."""
        return Score(json.loads(self._m.score(_data(u, y, p), predictor)))

    # --- display
    def _headline(self) -> str:
        f = self.fit
        if self.kind == "lpv-ss":
            head = (
                f"LPV state-space model: n = {self.order}, {self.inputs} inputs, "
                f"{self.outputs} outputs, {self.scheduling} scheduling"
            )
        else:
            head = f"LPV-ARX model: na = {self.na}, nb = {self.nb}, {self.inputs} inputs"
        how = f.get("method")
        if how:
            bits = [how]
            for k in ("past", "reg", "order_rule", "estimator"):
                if f.get(k) is not None:
                    bits.append(f"{k} {f[k]}")
            head += " (" + ", ".join(bits) + ")"
        return head

    def __repr__(self) -> str:
        lines = [self._headline()]
        sv = self.singular_values
        if len(sv):
            lines.append(
                "  singular values: " + " ".join(f"{v:.3g}" for v in sv[: min(len(sv), 12)])
                + (" ..." if len(sv) > 12 else "")
            )
        if self.fit.get("order_reason"):
            lines.append(f"  order: {self.fit['order_reason']}")
        for s in (self.train_score, self.val_score):
            if s is not None:
                lines.append(f"  {s!r}")
        return "<lpvid.Model " + "\n".join(lines) + ">"

    def _repr_html_(self) -> str:
        out = [f"<b>{html.escape(self._headline())}</b>"]
        sv = self.singular_values
        if len(sv):
            top = max(sv[0], 1e-300)
            rows = []
            for i, v in enumerate(sv[:20]):
                width = max(0.0, (np.log10(max(v, 1e-300) / top) * 6 + 60)) * 2
                mark = " &larr; order" if self.order == i + 1 else ""
                rows.append(
                    f"<tr><td>{i + 1}</td><td>{v:.4e}</td><td><div style='background:#4a7;"
                    f"height:8px;width:{width:.0f}px'></div></td><td>{mark}</td></tr>"
                )
            out.append("<table><tr><th>#</th><th>singular value</th><th></th><th></th></tr>"
                       + "".join(rows) + "</table>")
        if self.fit.get("order_reason"):
            out.append(f"<p>order: {html.escape(str(self.fit['order_reason']))}</p>")
        for s in (self.train_score, self.val_score):
            if s is not None:
                out.append(s._repr_html_())
        return "<div>" + "".join(out) + "</div>"


def _model_from_state(text: str, summary: Mapping[str, Any]) -> Model:
    return Model(_lpvid._Model.from_json(text, "model"), summary)


def read_model(path: "str | os.PathLike") -> Model:
    """Read a model file written by ``lpvid`` or :meth:`Model.write`."""
    return Model.read(path)


# ---------------------------------------------------------------------------------------
# identification


def _order_text(order: Any) -> str:
    if isinstance(order, (int, np.integer)) and not isinstance(order, bool):
        return str(int(order))
    if isinstance(order, str):
        return order
    raise LpvidError(f"order must be a positive integer or 'auto', got {order!r}")


def _positive_int(name: str, v: Any, minimum: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise LpvidError(f"{name} must be an integer >= {minimum}, got {v!r}")
    return int(v)


def _ranges(r: Any) -> List[str]:
    if r is None:
        return []
    if isinstance(r, str):
        return [x for x in r.split(",") if x]
    if isinstance(r, Mapping):
        return [f"{k}={lo}:{hi}" for k, (lo, hi) in r.items()]
    return [str(x) for x in r]


def pbsid(
    u: Any,
    y: Any = None,
    p: Any = None,
    *,
    past: int,
    order: "int | str" = "auto",
    reg: str = "tikhonov-gcv",
    kernel: bool = False,
    primal: bool = False,
    kernel_rows: Optional[int] = None,
    kernel_tol: float = 0.0,
    observer: str = "ls",
    scheduling_range: Any = None,
    lmi_margin: float = DEFAULT_LMI_MARGIN,
    refine: bool = False,
    future: Optional[int] = None,
    no_feedthrough: bool = False,
    sched_weight: float = DEFAULT_SCHED_WEIGHT,
    max_order: int = 20,
    bpdn_score: Optional[str] = None,
    val: Any = None,
    name: Optional[str] = None,
    centre: str = "auto",
) -> Model:
    """LPV-PBSID_opt, as ``lpvid pbsid`` (same options, same defaults, same model).

    ``val``: validation data (scored by free run; used by ``reg='bpdn-sv'``), any data form
    the API accepts (a tuple ``(u, y, p)`` for arrays). ``name`` names array data in the fit
    record and in errors. ``centre``: where the scheduling signals are centred in the fit
    (``auto``, ``zero`` or ``mean``, as ``--centre``). Returns a :class:`Model` with
    ``train_score`` / ``val_score``."""
    past = _positive_int("past", past)
    train = _data(u, y, p, source=name)
    v = _data(val) if val is not None else None
    native, summary = _lpvid.pbsid(
        train,
        past,
        order=_order_text(order),
        reg=str(reg),
        kernel=bool(kernel),
        primal=bool(primal),
        kernel_rows=None if kernel_rows is None else _positive_int("kernel_rows", kernel_rows),
        kernel_tol=float(kernel_tol),
        refine=bool(refine),
        future=None if future is None else _positive_int("future", future),
        feedthrough=not no_feedthrough,
        sched_weight=float(sched_weight),
        max_order=_positive_int("max_order", max_order),
        bpdn_score=bpdn_score,
        observer=str(observer),
        scheduling_range=_ranges(scheduling_range),
        lmi_margin=float(lmi_margin),
        val=v,
        centre=str(centre),
    )
    return Model(native, json.loads(summary))


def arx(
    u: Any,
    y: Any = None,
    p: Any = None,
    *,
    na: int,
    nb: int,
    ng: int,
    estimator: str = "bciv",
    sigma_p: "float | str | None" = None,
    lambda_: "float | str" = "cv",
    sigma_grid: Optional[Sequence[float]] = None,
    sigma_data: str = "all",
    plain_l1: bool = False,
    no_debias: bool = False,
    min_cost: bool = False,
    no_refine: bool = False,
    refit_train_only: bool = False,
    max_iter: int = 10,
    f32: bool = False,
    noise_ratios: Optional[Sequence[float]] = None,
    calib: Any = None,
    val: Any = None,
    name: Optional[str] = None,
) -> Model:
    """LPV-ARX (LS, refined IV, BC-IV, BC-IV-LASSO), as ``lpvid arx`` (``lambda_`` is
    ``--lambda``; ``sigma_grid`` a list of numbers)."""
    train = _data(u, y, p, source=name)
    native, summary = _lpvid.arx(
        train,
        _positive_int("na", na, 0),
        _positive_int("nb", nb, 0),
        _positive_int("ng", ng, 0),
        estimator=str(estimator),
        sigma_p=None if sigma_p is None else str(sigma_p),
        lambda_=str(lambda_),
        sigma_grid=None if sigma_grid is None else [float(x) for x in sigma_grid],
        sigma_data=str(sigma_data),
        plain_l1=bool(plain_l1),
        no_debias=bool(no_debias),
        min_cost=bool(min_cost),
        no_refine=bool(no_refine),
        refit_train_only=bool(refit_train_only),
        max_iter=_positive_int("max_iter", max_iter),
        f32=bool(f32),
        noise_ratios=None if noise_ratios is None else [float(x) for x in noise_ratios],
        calib=_data(calib) if calib is not None else None,
        val=_data(val) if val is not None else None,
    )
    return Model(native, json.loads(summary))


# ---------------------------------------------------------------------------------------
# diagnosis


class Finding:
    """One effect the residual of the model points to: ``effect`` (its name), ``detail``
    (what the best variant adds), ``explained`` (fraction of the held-out error it
    explains), ``evidence`` (the residual tests, in words), ``p_value``, ``significant``."""

    def __init__(self, d: Mapping[str, Any]):
        self.raw = dict(d)
        self.effect: str = d.get("effect", "")
        self.detail: str = d.get("detail", "")
        x = d.get("explained")
        self.explained: float = float("nan") if x is None else float(x)
        self.evidence: List[str] = list(d.get("evidence") or [])
        self.residual: Optional[str] = d.get("residual")
        self.p_value: Optional[float] = d.get("p_value")
        self.significant: bool = bool(d.get("significant", True))
        self.vaf: Optional[float] = d.get("vaf")

    def __repr__(self) -> str:
        sig = "" if self.significant else ", not significant"
        return (
            f"Finding({self.effect}: {self.detail}; explains {100 * self.explained:.1f} % "
            f"of the {self.residual or ''} error{sig})"
        )


class Report:
    """What ``lpvid diagnose`` reports: ``findings`` (:class:`Finding`), ``applied``
    (the fixes made, as :class:`Finding` with ``vaf_before`` / ``vaf_after`` in ``raw``),
    ``before`` / ``after`` (:class:`Score` on the validation data, free run),
    ``before_one_step`` / ``after_one_step``, ``refined`` (with ``fix``, when no effect
    was missing but the structure refined by output error predicts better: its ``step``,
    ``explained``, ``p_value``, ``mse_before`` / ``mse_after``; else None), ``model`` (the
    final :class:`Model`: the given one when nothing changed), ``text`` (the command
    line's summary)."""

    def __init__(self, model: Model, report: Mapping[str, Any], text: str):
        self.raw = dict(report)
        self.model = model
        self.text = text
        self.findings = [Finding(f) for f in report.get("findings", [])]
        self.applied = [Finding(a) for a in report.get("applied", [])]
        self.refined: Optional[Dict[str, Any]] = report.get("refined")
        sc = lambda k: Score(report[k]) if report.get(k) else None  # noqa: E731
        self.before: Score = sc("before")
        self.after: Optional[Score] = sc("after")
        self.before_one_step: Score = sc("before_one_step")
        self.after_one_step: Optional[Score] = sc("after_one_step")
        self.stopped: str = report.get("stopped", "")
        self.notes: List[str] = list(report.get("notes", []))

    def __repr__(self) -> str:
        return self.text

    def _repr_html_(self) -> str:
        rows = "".join(
            f"<tr><td>{html.escape(f.effect)}</td><td>{html.escape(f.detail)}</td>"
            f"<td>{100 * f.explained:.1f} %</td><td>{'yes' if f.significant else 'no'}</td>"
            f"<td>{html.escape('; '.join(f.evidence))}</td></tr>"
            for f in self.findings
        )
        after = (
            f"{self.after.vaf_mean:.2f}" if self.after is not None else "(nothing applied)"
        )
        return (
            f"<div><b>diagnose</b>: validation VAF {self.before.vaf_mean:.2f} % before, "
            f"{after} after"
            "<table><tr><th>effect</th><th>detail</th><th>explained</th><th>significant</th>"
            f"<th>evidence</th></tr>{rows}</table>"
            f"<details><summary>report</summary><pre>{html.escape(self.text)}</pre></details></div>"
        )


def diagnose(
    model: Model,
    train: Any,
    val: Any,
    fix: bool = True,
    max_steps: int = 1,
    threads: int = 0,
) -> Report:
    """``lpvid diagnose``: test the model's residual on ``val`` for missing effects; with
    ``fix`` add the best one and refit on ``train`` (up to ``max_steps`` times).
    ``train``/``val``: a DataFrame, dict, CSV path or tuple ``(u, y, p)``."""
    if not isinstance(model, Model):
        raise LpvidError(f"diagnose needs a lpvid.Model, got {type(model).__name__}")
    native, report, text = _lpvid.diagnose_model(
        model._m,
        _data(train, source="train"),
        _data(val, source="val"),
        fix=bool(fix),
        max_steps=_positive_int("max_steps", max_steps),
        threads=_positive_int("threads", threads, 0),
    )
    return Report(Model(native), json.loads(report), text)


# ---------------------------------------------------------------------------------------
# statistics


def _experiment_rows(
    u: Any, y: Any, p: Any, dims: "tuple[int, int, int]", source: str
) -> np.ndarray:
    r, l, s = dims
    if isinstance(u, (str, os.PathLike)):
        u = read_csv(u, frame=False).to_dict()
    elif isinstance(u, Data):
        u = u.to_dict()
    if _is_frame(u) or isinstance(u, Mapping):
        if y is not None or p is not None:
            raise LpvidError("give either one data set (DataFrame or dict) or arrays u, y, p")
        cols = _frame_columns(u) if _is_frame(u) else u
        names = [f"u{j}" for j in range(1, r + 1)] + [f"y{j}" for j in range(1, l + 1)]
        names += [f"p{j}" for j in range(1, s + 1)]
        missing = [n for n in names if n not in cols]
        if missing:
            raise DataError(
                f"{source}: no column {', '.join(missing)} (the statistics are for "
                f"{r} inputs, {l} outputs, {s} scheduling signals; columns: {', '.join(map(str, cols))})"
            )
        return np.ascontiguousarray(
            np.column_stack([np.asarray(cols[n], dtype=np.float64) for n in names])
            if names else np.zeros((0, 0))
        )
    if isinstance(u, tuple) and y is None and p is None and 2 <= len(u) <= 3:
        u, y, p = (tuple(u) + (None,))[:3]
    parts = []
    n = None
    for prefix, x, want in (("u", u, r), ("y", y, l), ("p", p, s)):
        if x is None:
            a = np.zeros((n or 0, 0))
        else:
            a = _as_2d(prefix, x)
        if a.shape[1] != want:
            raise LpvidError(
                f"{source}: {prefix} has {a.shape[1]} channels, the statistics are for {want}"
            )
        if n is not None and a.shape[0] != n and a.shape[1]:
            raise LpvidError(f"{source}: {prefix} has {a.shape[0]} samples, u {n}")
        if a.shape[1]:
            n = a.shape[0]
        parts.append(a)
    n = n or 0
    parts = [a if a.shape[1] else np.zeros((n, 0)) for a in parts]
    return np.ascontiguousarray(np.hstack(parts), dtype=np.float64)


class Statistics:
    """Mergeable LPV-PBSID_opt statistics of experiments (extended layout, f64).

    ``update(u, y, p)`` adds one experiment (its windows start at its own first sample:
    windows never span two experiments); ``merge(other)`` adds another's experiments;
    ``to_bytes()`` / ``Statistics.from_bytes(b)`` is the versioned encoding of
    docs/wire.md section 7; :func:`fit_from_statistics` fits a model from them. The
    statistics of a set of experiments do not depend on how they were grouped or merged
    (up to rounding), so they can be computed where the data are and reduced in a tree
    (:mod:`lpvid.dask`)."""

    def __init__(self, past: int, inputs: int, outputs: int, scheduling: int = 0):
        self._s = _lpvid._Statistics(
            _positive_int("past", past),
            _positive_int("inputs", inputs, 0),
            _positive_int("outputs", outputs),
            _positive_int("scheduling", scheduling, 0),
        )

    @classmethod
    def _wrap(cls, native: "_lpvid._Statistics") -> "Statistics":
        st = cls.__new__(cls)
        st._s = native
        return st

    @classmethod
    def for_data(cls, data: Any, past: int) -> "Statistics":
        """Empty statistics with the channels (u*, y*, p*) of a DataFrame or dict."""
        cols = _frame_columns(data) if _is_frame(data) else dict(data)
        count = lambda c: sum(1 for k in cols if str(k)[:1] == c and str(k)[1:].isdigit())  # noqa: E731
        return cls(past, count("u"), count("y"), count("p"))

    def update(self, u: Any, y: Any = None, p: Any = None, name: Optional[str] = None) -> int:
        """Add one experiment; returns the windows it added."""
        _, r, l, s = self._s.dims
        source = name or f"experiment {self._s.experiments + 1}"
        rows = _experiment_rows(u, y, p, (r, l, s), source)
        return self._s.update(rows, source)

    def merge(self, other: "Statistics") -> "Statistics":
        """Add ``other``'s statistics into these; returns self."""
        if isinstance(other, (bytes, bytearray, memoryview)):
            other = Statistics.from_bytes(other)
        if not isinstance(other, Statistics):
            raise LpvidError(f"cannot merge a {type(other).__name__} into Statistics")
        self._s.merge(other._s)
        return self

    def copy(self) -> "Statistics":
        return Statistics.from_bytes(self.to_bytes())

    def __iadd__(self, other: "Statistics") -> "Statistics":
        return self.merge(other)

    def __add__(self, other: "Statistics") -> "Statistics":
        return self.copy().merge(other)

    def to_bytes(self) -> bytes:
        return self._s.to_bytes()

    @classmethod
    def from_bytes(cls, data: "bytes | bytearray | memoryview") -> "Statistics":
        return cls._wrap(_lpvid._Statistics.from_bytes(bytes(data)))

    def __reduce__(self):
        return (Statistics.from_bytes, (self.to_bytes(),))

    @property
    def past(self) -> int:
        return self._s.dims[0]

    @property
    def inputs(self) -> int:
        return self._s.dims[1]

    @property
    def outputs(self) -> int:
        return self._s.dims[2]

    @property
    def scheduling(self) -> int:
        return self._s.dims[3]

    @property
    def windows(self) -> int:
        return self._s.windows

    @property
    def experiments(self) -> int:
        return self._s.experiments

    @property
    def nbytes(self) -> int:
        """Size of the encoding (bytes): fixed by the dimensions, not by the data."""
        return self._s.nbytes

    def packed(self) -> np.ndarray:
        """The packed upper triangle of the Gram (docs/wire.md section 5)."""
        return self._s.packed()

    def __repr__(self) -> str:
        return (
            f"Statistics(past={self.past}, inputs={self.inputs}, outputs={self.outputs}, "
            f"scheduling={self.scheduling}: {self.experiments} experiments, {self.windows} "
            f"windows, {self.nbytes} bytes)"
        )


def fit_from_statistics(
    stats: "Statistics | bytes",
    order: "int | str" = "auto",
    reg: str = "tikhonov-gcv",
    future: Optional[int] = None,
    no_feedthrough: bool = False,
    sched_weight: float = DEFAULT_SCHED_WEIGHT,
    max_order: int = 20,
) -> Model:
    """LPV-PBSID_opt from statistics alone (the library's ``identify_from_stats``: the same
    regression and realization as :func:`pbsid` with ``primal=True``; K is the least-squares
    gain and there is no data to score on)."""
    if isinstance(stats, (bytes, bytearray, memoryview)):
        stats = Statistics.from_bytes(stats)
    if not isinstance(stats, Statistics):
        raise LpvidError(f"fit_from_statistics needs Statistics, got {type(stats).__name__}")
    native, summary = stats._s.fit(
        order=_order_text(order),
        reg=str(reg),
        future=None if future is None else _positive_int("future", future),
        feedthrough=not no_feedthrough,
        sched_weight=float(sched_weight),
        max_order=_positive_int("max_order", max_order),
    )
    return Model(native, json.loads(summary))
