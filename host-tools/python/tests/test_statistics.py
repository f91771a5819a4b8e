"""Mergeable statistics: experiments windowed apart, merge, bytes, fit."""

import numpy as np
import pandas as pd
import pytest

import lpvid
from conftest import rel_diff, simulate_lpv


def test_one_experiment_fit_equals_the_primal_file_fit():
    u, y, p = simulate_lpv(3000, 1)
    st = lpvid.Statistics(past=3, inputs=1, outputs=1, scheduling=1)
    assert st.update(u, y, p) == 3000 - 3
    ms = lpvid.fit_from_statistics(st, order=2)
    mf = lpvid.pbsid(u, y, p, past=3, order=2, primal=True)
    assert ms.order == mf.order == 2
    yhat_s = ms.simulate(u, p)
    yhat_f = mf.simulate(u, p)
    assert rel_diff(yhat_s, yhat_f) < 1e-7
    assert ms.fit["source"]["statistics"]["windows"] == 2997
    assert ms.validate(u, y, p).vaf_mean > 99


def test_windows_never_cross_experiments(experiments):
    st = lpvid.Statistics(past=2, inputs=1, outputs=1, scheduling=1)
    total = 0
    for u, y, p in experiments:
        total += st.update(u, y, p)
    assert total == sum(len(e[0]) - 2 for e in experiments)
    assert st.windows == total and st.experiments == len(experiments)
    # one long experiment would have 2 x (count - 1) more windows
    cat = [np.concatenate([e[i] for e in experiments]) for i in range(3)]
    one = lpvid.Statistics(past=2, inputs=1, outputs=1, scheduling=1)
    one.update(*cat)
    assert one.windows == total + 2 * (len(experiments) - 1)


def test_merge_in_any_grouping_and_bytes(experiments):
    def stats(exps):
        st = lpvid.Statistics(past=2, inputs=1, outputs=1, scheduling=1)
        for e in exps:
            st.update(*e)
        return st

    seq = stats(experiments)
    a, b, c = stats(experiments[:2]), stats(experiments[2:3]), stats(experiments[3:])
    tree = c.merge(lpvid.Statistics.from_bytes(a.to_bytes()).merge(b))
    assert tree.windows == seq.windows and tree.experiments == 6
    assert rel_diff(tree.packed(), seq.packed()) < 1e-14
    data = seq.to_bytes()
    assert len(data) == seq.nbytes and data[:4] == b"LPVS"
    back = lpvid.Statistics.from_bytes(data)
    assert np.array_equal(back.packed(), seq.packed())
    assert (back.past, back.inputs, back.outputs, back.scheduling) == (2, 1, 1, 1)
    assert "6 experiments" in repr(back)
    m1 = lpvid.fit_from_statistics(seq, order=2)
    m2 = lpvid.fit_from_statistics(data, order=2)
    assert m1.to_json() == m2.to_json()
    both = a + b
    assert both.experiments == 3 and a.experiments == 2


def test_dataframe_experiments_use_column_names():
    u, y, p = simulate_lpv(600, 3)
    df = pd.DataFrame({"t": np.arange(600.0), "p1": p, "y1": y, "u1": u})
    st = lpvid.Statistics.for_data(df, past=2)
    assert (st.inputs, st.outputs, st.scheduling) == (1, 1, 1)
    st.update(df)
    ref = lpvid.Statistics(past=2, inputs=1, outputs=1, scheduling=1)
    ref.update(u, y, p)
    assert np.array_equal(st.packed(), ref.packed())


def test_statistics_errors():
    st = lpvid.Statistics(past=2, inputs=1, outputs=1, scheduling=1)
    u, y, p = simulate_lpv(100, 0)
    y[5] = np.inf
    with pytest.raises(lpvid.DataError) as e:
        st.update(u, y, p, name="run 3")
    assert e.value.column == "y1" and e.value.file == "run 3"
    assert st.experiments == 0 and st.windows == 0
    with pytest.raises(lpvid.LpvidError, match="channels"):
        st.update(np.zeros((10, 2)), y, p)
    with pytest.raises(lpvid.DataError, match="no column p1"):
        st.update(pd.DataFrame({"u1": u, "y1": y}))
    other = lpvid.Statistics(past=3, inputs=1, outputs=1, scheduling=1)
    with pytest.raises(lpvid.DataError, match="cannot merge"):
        st.merge(other)
    good = other.to_bytes()
    with pytest.raises(lpvid.DataError, match="not lpvid statistics"):
        lpvid.Statistics.from_bytes(b"XXXX" + good[4:])
    with pytest.raises(lpvid.DataError, match="CRC-32"):
        lpvid.Statistics.from_bytes(good[:60] + bytes([good[60] ^ 1]) + good[61:])
    with pytest.raises(lpvid.DataError, match="too short"):
        lpvid.Statistics.from_bytes(b"LPVS")
    with pytest.raises(lpvid.LpvidError, match="windows|samples"):
        lpvid.fit_from_statistics(other)
    with pytest.raises(lpvid.LpvidError, match="past must be"):
        lpvid.Statistics(past=0, inputs=1, outputs=1)
