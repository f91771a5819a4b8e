"""Bad inputs raise LpvidError / DataError with the command line's text."""

import numpy as np
import pytest

import lpvid
from conftest import FIXTURES


def test_bad_csv_gives_file_line_column(cli, tmp_path):
    bad = tmp_path / "bad.csv"
    text = (FIXTURES / "b1-train.csv").read_text().splitlines()
    cells = text[5].split(",")
    cells[3] = "abc"
    text[5] = ",".join(cells)
    bad.write_text("\n".join(text) + "\n")
    with pytest.raises(lpvid.DataError) as e:
        lpvid.pbsid(bad, past=3)
    err = e.value
    assert err.file == str(bad) and err.line == 6 and err.column == "y2"
    r = cli("pbsid", "--train", bad, "--past", "3", "--out", tmp_path / "m.json", check=False)
    assert r.returncode != 0
    assert str(err) in r.stderr
    assert isinstance(err, lpvid.LpvidError)


def test_nan_in_arrays_names_the_column():
    u, y, p = np.random.default_rng(0).standard_normal((3, 200))
    y[17] = np.nan
    with pytest.raises(lpvid.DataError) as e:
        lpvid.pbsid(u, y, p, past=2)
    assert e.value.column == "y1" and "sample 17" in str(e.value) and e.value.line is None


def test_bad_options_carry_the_cli_message():
    u, y, p = np.random.default_rng(0).standard_normal((3, 300))
    with pytest.raises(lpvid.LpvidError, match="unknown regularisation|tikhonov"):
        lpvid.pbsid(u, y, p, past=2, reg="ridge")
    with pytest.raises(lpvid.LpvidError, match="order must be a positive integer or 'auto'"):
        lpvid.pbsid(u, y, p, past=2, order="many")
    with pytest.raises(lpvid.LpvidError, match="past must be an integer >= 1"):
        lpvid.pbsid(u, y, p, past=0)
    with pytest.raises(lpvid.LpvidError, match="bpdn_score applies to reg='bpdn-sv' only"):
        lpvid.pbsid(u, y, p, past=2, bpdn_score="paper")
    with pytest.raises(lpvid.LpvidError, match="observer must be 'ls' or 'hinf'"):
        lpvid.pbsid(u, y, p, past=2, observer="kalman")
    with pytest.raises(lpvid.LpvidError, match="samples"):
        lpvid.pbsid(u, y[:100], p, past=2)
    with pytest.raises(lpvid.DataError, match="a past window of 2 needs at least 5"):
        lpvid.pbsid(u[:4], y[:4], p[:4], past=2)


def test_bad_model_json_gives_the_line():
    with pytest.raises(lpvid.DataError) as e:
        lpvid.Model.from_json('{\n  "type": "lpv-ss",\n  "A": [[1]\n}', source="m.json")
    assert e.value.file == "m.json" and e.value.line is not None


def test_model_needs_its_columns():
    m = lpvid.pbsid(str(FIXTURES / "b1-train.csv"), past=2)
    with pytest.raises(lpvid.DataError, match="p3|column"):
        m.validate({"u1": np.zeros(50), "u2": np.zeros(50), "y1": np.ones(50),
                    "y2": np.ones(50), "y3": np.ones(50), "p1": np.zeros(50), "p2": np.zeros(50)})
    with pytest.raises(lpvid.LpvidError, match="x0 has 3 values"):
        m.simulate(str(FIXTURES / "b1-val.csv"), x0=[0, 0, 0])
