"""pbsid, the model file round trip with the command line, simulate/predict/validate."""

import json

import numpy as np
import pandas as pd
import pytest

import lpvid
from conftest import FIXTURES, rel_diff


def b1(name="b1-train.csv"):
    return pd.read_csv(FIXTURES / name)


def test_pbsid_from_csv_writes_the_cli_model_byte_for_byte(cli, in_root, tmp_path):
    out = tmp_path / "cli.json"
    cli("pbsid", "--train", "fixtures/b1-train.csv", "--past", "3", "--out", out)
    m = lpvid.pbsid("fixtures/b1-train.csv", past=3)
    assert m.to_json() == out.read_text()
    assert m.order == 4
    assert m.fit["train"]["file"] == "fixtures/b1-train.csv"


def test_model_written_by_python_is_read_by_cli_and_back(cli, tmp_path):
    df = b1()
    m = lpvid.pbsid(df, past=3, name="b1 frame")
    path = tmp_path / "py.json"
    m.write(path)
    r = cli("validate", "--model", path, "--data", FIXTURES / "b1-val.csv", "--json")
    cli_score = json.loads(r.stdout)["score"]
    py_score = m.validate(FIXTURES / "b1-val.csv")
    np.testing.assert_allclose(py_score.vaf, cli_score["vaf"], rtol=1e-12)
    np.testing.assert_allclose(py_score.bfr, cli_score["bfr"], rtol=1e-12)
    # a CLI model read by Python
    out = tmp_path / "cli.json"
    cli("pbsid", "--train", FIXTURES / "b1-train.csv", "--past", "2", "--order", "3", "--out", out)
    back = lpvid.Model.read(out)
    assert back.order == 3 and back.fit["past"] == 2
    assert lpvid.Model.from_json(out.read_text()).to_json() == out.read_text()


def test_arrays_dataframe_and_path_give_the_same_model():
    df = b1()
    u = df[["u1", "u2"]].to_numpy()
    y = df[["y1", "y2", "y3"]].to_numpy()
    p = df[["p1", "p2", "p3"]].to_numpy()
    a = lpvid.pbsid(u, y, p, past=3)
    f = lpvid.pbsid(df, past=3)
    c = lpvid.pbsid(str(FIXTURES / "b1-train.csv"), past=3)
    for k in "ABKCD":
        assert rel_diff(getattr(a, k), getattr(c, k)) < 1e-12
        assert rel_diff(getattr(f, k), getattr(c, k)) < 1e-12
    assert a.A.shape == (4, 4, 4)  # m = 4 local models of n x n
    assert a.fit["train"]["file"] == "arrays"


def test_settings_reach_the_fit():
    df = b1()
    m = lpvid.pbsid(df, past=2, order=3, reg="none", future=2, no_feedthrough=True,
                    val=b1("b1-val.csv"))
    assert m.order == 3
    assert m.fit["reg"] == "none" and m.fit["feedthrough"] is False
    assert np.all(m.D == 0)
    assert m.val_score is not None and m.val_score.vaf_mean > 90
    assert len(m.singular_values) >= 3
    k = lpvid.pbsid(df, past=2, kernel=True)
    assert k.fit["solver"] == "kernel"
    assert "lpv-pbsid-opt" in repr(m) and "<table>" in m._repr_html_()


def test_simulate_predict_validate():
    train, val = b1(), b1("b1-val.csv")
    m = lpvid.pbsid(train, past=3, val=val)
    u = val[["u1", "u2"]].to_numpy()
    y = val[["y1", "y2", "y3"]].to_numpy()
    p = val[["p1", "p2", "p3"]].to_numpy()
    yhat = m.simulate(u, p)
    assert yhat.shape == y.shape
    assert rel_diff(m.simulate(val), yhat) == 0.0
    assert rel_diff(m.simulate(u, p, x0=np.zeros(m.order)), yhat) < 1e-14
    x0 = np.ones(m.order)
    assert rel_diff(m.simulate(u, p, x0=x0), yhat) > 1e-6
    # the effect of x0 dies out (the model is stable)
    assert np.max(np.abs(m.simulate(u, p, x0=x0)[-50:] - yhat[-50:])) < 1e-6
    s = m.validate(u, y, p)
    assert s.mode == "free-run"
    np.testing.assert_allclose(s.vaf, m.val_score.vaf, rtol=1e-12)
    pred = m.predict(u, y, p)
    assert pred.shape == y.shape
    sp = m.validate(val, predictor=True)
    assert sp.mode == "predictor" and sp.vaf_mean >= s.vaf_mean - 1e-9
    assert "VAF" in repr(s) and "<table>" in s._repr_html_()


def test_pickle_round_trip():
    import pickle

    m = lpvid.pbsid(b1(), past=2)
    back = pickle.loads(pickle.dumps(m))
    assert back.to_json() == m.to_json()


def test_pbsid_centre_is_the_cli_option(cli, in_root, tmp_path):
    # B1's rho has 0 away from its mean: auto fits at 0 and at the mean and keeps 0, as the
    # command line does; centre="mean" fixes the centre and compares nothing
    out = tmp_path / "cli.json"
    cli("pbsid", "--train", "fixtures/b1-train.csv", "--past", "3", "--centre", "mean", "--out", out)
    m = lpvid.pbsid("fixtures/b1-train.csv", past=3, centre="mean")
    assert m.to_json() == out.read_text()
    assert m.fit["centre"] == "mean"
    assert "centre_check" not in m.fit
    auto = lpvid.pbsid("fixtures/b1-train.csv", past=3)
    assert auto.fit["centre_check"]["chosen"] == "zero"
    with pytest.raises(lpvid.LpvidError, match="scheduling centre"):
        lpvid.pbsid("fixtures/b1-train.csv", past=3, centre="middle")
