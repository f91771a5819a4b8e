"""lpvid.dask on a LocalCluster with 2 worker processes: the model equals the
single-process fit and only the statistics reach the client."""

import numpy as np
import pandas as pd
import pytest

import lpvid
import lpvid.dask

dask = pytest.importorskip("dask")
distributed = pytest.importorskip("dask.distributed")
import dask.bag as db  # noqa: E402
import dask.dataframe as dd  # noqa: E402
from conftest import rel_diff, simulate_lpv  # noqa: E402

PAST = 2


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


def frames(count=8, n=1500):
    out = []
    for i in range(count):
        u, y, p = simulate_lpv(n + 37 * i, 100 + i)
        out.append(pd.DataFrame({"u1": u, "y1": y, "p1": p}))
    return out


def single_process(parts):
    st = lpvid.Statistics(past=PAST, inputs=1, outputs=1, scheduling=1)
    for df in parts:
        st.update(df)
    return st


def assert_same_model(a, b):
    assert a.order == b.order
    for k in "ABKCD":
        assert rel_diff(getattr(a, k), getattr(b, k)) < 1e-9, k


def test_dataframe_partitions_are_experiments(client):
    parts = frames()
    ddf = dd.concat([dd.from_pandas(df, npartitions=1) for df in parts])
    assert ddf.npartitions == len(parts)
    raw = lpvid.dask.statistics_bytes(ddf, past=PAST, split_every=3)
    ref = single_process(parts)
    got = lpvid.Statistics.from_bytes(raw)
    assert got.experiments == len(parts) and got.windows == ref.windows
    assert rel_diff(got.packed(), ref.packed()) < 1e-12
    # the client receives the statistics, not the data
    data_bytes = sum(df.memory_usage(index=False).sum() for df in parts)
    assert len(raw) == ref.nbytes
    assert len(raw) < data_bytes / 10, (len(raw), data_bytes)
    assert_same_model(lpvid.dask.pbsid(ddf, past=PAST, order=2),
                      lpvid.fit_from_statistics(ref, order=2))


def test_bag_of_experiments(client):
    parts = frames(count=6, n=1000)
    exps = [(df.u1.to_numpy(), df.y1.to_numpy(), df.p1.to_numpy()) for df in parts]
    bag = db.from_sequence(exps, npartitions=4)
    model = lpvid.dask.pbsid(bag, past=PAST, order=2, split_every=2)
    ref = lpvid.fit_from_statistics(single_process(parts), order=2)
    assert_same_model(model, ref)
    assert model.fit["source"]["statistics"]["experiments"] == 6
    u, y, p = simulate_lpv(2000, 999)
    assert model.validate(u, y, p).vaf_mean > 99


def test_bag_of_dataframes_and_errors(client):
    parts = frames(count=3, n=800)
    st = lpvid.dask.statistics(db.from_sequence(parts, npartitions=3), past=PAST)
    assert st.experiments == 3
    with pytest.raises(lpvid.LpvidError):
        lpvid.dask.statistics([1, 2], past=PAST)
    with pytest.raises(Exception, match="experiment"):
        lpvid.dask.statistics(db.from_sequence([42], npartitions=1), past=PAST)
