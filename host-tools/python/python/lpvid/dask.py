"""lpvid on Dask: statistics computed where the data are, reduced in a tree, fitted on the
client.

Each experiment (a partition of a Dask DataFrame, or an element of a Dask bag) becomes
:class:`lpvid.Statistics` on the worker that holds it; the workers send the statistics'
bytes (:meth:`lpvid.Statistics.to_bytes`, a size fixed by the dimensions: see
docs/scale.md), never the data; a tree reduction (``Bag.reduction`` with ``split_every``)
merges them on the workers; only the merged statistics reach the client, which fits the
model (:func:`lpvid.fit_from_statistics`).

>>> from dask.distributed import Client
>>> client = Client("tcp://scheduler:8786")        # or LocalCluster(); nothing else changes
>>> import lpvid.dask
>>> model = lpvid.dask.pbsid(ddf, past=3)           # ddf: one partition per experiment
>>> model = lpvid.dask.pbsid(bag, past=3)           # bag: one element per experiment

An experiment in a bag is a pandas DataFrame or dict of columns (u1.., y1.., p1..), or a
tuple ``(u, y, p)`` of arrays. Windows never cross experiments (nor partitions).
"""

from __future__ import annotations

from typing import Any, Iterable, Optional

from . import LpvidError, Statistics, Model, fit_from_statistics, _is_frame, _frame_columns

__all__ = ["statistics_bytes", "statistics", "pbsid", "experiment_bytes"]


def _dims_of(exp: Any) -> "tuple[int, int, int]":
    if _is_frame(exp) or isinstance(exp, dict):
        cols = _frame_columns(exp) if _is_frame(exp) else exp
        names = [str(c) for c in cols]
        count = lambda c: sum(1 for k in names if k[:1] == c and k[1:].isdigit())  # noqa: E731
        return count("u"), count("y"), count("p")
    if isinstance(exp, (tuple, list)) and 2 <= len(exp) <= 3:
        import numpy as np

        def ch(x: Any) -> int:
            if x is None:
                return 0
            a = np.asarray(x)
            return 1 if a.ndim == 1 else a.shape[1]

        u, y, p = (tuple(exp) + (None,))[:3]
        return ch(u), ch(y), ch(p)
    raise LpvidError(
        f"an experiment is a DataFrame, a dict of columns or a tuple (u, y, p), got {type(exp).__name__}"
    )


def experiment_bytes(experiments: Iterable[Any], past: int) -> bytes:
    """Statistics of ``experiments`` (each one windowed on its own) as bytes; ``b""`` when
    there is none (an empty partition). Runs on a worker."""
    st: Optional[Statistics] = None
    for exp in experiments:
        if _is_frame(exp) and len(exp) == 0:
            continue
        if st is None:
            r, l, s = _dims_of(exp)
            st = Statistics(past, r, l, s)
        st.update(exp)
    return b"" if st is None else st.to_bytes()


def _merge_bytes(parts: Iterable[bytes]) -> bytes:
    """Merge encodings (empty ones skipped): the reduction's combine step."""
    acc: Optional[Statistics] = None
    for b in parts:
        if not b:
            continue
        if acc is None:
            acc = Statistics.from_bytes(b)
        else:
            acc.merge(Statistics.from_bytes(b))
    return b"" if acc is None else acc.to_bytes()


def _partition_bytes(df: Any, past: int) -> list:
    return [experiment_bytes([df], past)]


def _to_bag(collection: Any, past: int):
    """A bag whose elements are statistics bytes (one per DataFrame partition) or the
    experiments themselves (a bag given)."""
    import dask.bag as db

    if hasattr(collection, "to_delayed") and hasattr(collection, "npartitions") and hasattr(
        collection, "columns"
    ):
        from dask import delayed

        parts = [delayed(_partition_bytes)(d, past) for d in collection.to_delayed()]
        return db.from_delayed(parts), True
    if isinstance(collection, db.Bag):
        return collection, False
    raise LpvidError(
        f"expected a dask DataFrame (one partition per experiment) or a dask bag of experiments, got {type(collection).__name__}"
    )


def statistics_bytes(collection: Any, past: int, split_every: int = 8, **compute: Any) -> bytes:
    """The merged statistics' bytes as they reach the client (the only data the client
    receives). ``split_every``: fan-in of the tree reduction. ``compute`` goes to
    ``dask.compute`` (e.g. ``scheduler=``)."""
    if past < 1:
        raise LpvidError(f"past must be an integer >= 1, got {past!r}")
    bag, reduced = _to_bag(collection, past)
    if reduced:
        item = bag.reduction(_merge_bytes, _merge_bytes, split_every=split_every)
    else:
        item = bag.reduction(
            lambda exps: experiment_bytes(exps, past),
            _merge_bytes,
            split_every=split_every,
        )
    out = item.compute(**compute)
    if not out:
        raise LpvidError("no experiment in the collection: nothing to fit")
    return out


def statistics(collection: Any, past: int, split_every: int = 8, **compute: Any) -> Statistics:
    """:func:`statistics_bytes` decoded."""
    return Statistics.from_bytes(statistics_bytes(collection, past, split_every, **compute))


def pbsid(
    collection: Any,
    past: int,
    order: "int | str" = "auto",
    reg: str = "tikhonov-gcv",
    split_every: int = 8,
    **fit: Any,
) -> Model:
    """LPV-PBSID_opt of all experiments of a Dask DataFrame (partition = experiment) or bag:
    statistics on the workers, tree reduction, fit on the client
    (:func:`lpvid.fit_from_statistics`; ``fit`` takes its other options)."""
    st = statistics(collection, past, split_every)
    return fit_from_statistics(st, order=order, reg=reg, **fit)
