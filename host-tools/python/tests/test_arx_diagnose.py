"""lpvid.arx and lpvid.diagnose, and the notebook example."""

import os
import runpy
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import lpvid
from conftest import FIXTURES, ROOT, rel_diff

SMART = next((Path(c) / "smart-rotor-370rpm.csv" for c in
              (os.environ.get("LPVID_DATA"), ROOT.parent / "shared" / "data", "/work/shared/data")
              if c and (Path(c) / "smart-rotor-370rpm.csv").is_file()), None)


def test_arx_matches_the_cli(cli, tmp_path, in_root):
    out = tmp_path / "arx.json"
    cli("arx", "--train", "fixtures/b6-train.csv", "--calib", "fixtures/b6-calib.csv",
        "--na", "2", "--nb", "1", "--ng", "1", "--out", out)
    m = lpvid.arx("fixtures/b6-train.csv", calib="fixtures/b6-calib.csv", na=2, nb=1, ng=1)
    assert m.kind == "lpv-arx" and m.order is None
    assert m.to_json() == out.read_text()
    assert m.a.shape == (2, 2) and m.b.shape == (1, 2, 2)
    ls = lpvid.arx(pd.read_csv(FIXTURES / "b6-train.csv"), na=2, nb=1, ng=1, estimator="ls",
                   val=pd.read_csv(FIXTURES / "b6-val.csv"))
    assert ls.fit["estimator"] == "ls" and ls.val_score is not None
    assert ls.validate(FIXTURES / "b6-val.csv").vaf_mean == pytest.approx(ls.val_score.vaf_mean)
    with pytest.raises(lpvid.LpvidError, match="estimator"):
        lpvid.arx(FIXTURES / "b6-train.csv", na=2, nb=1, ng=1, estimator="magic")


def test_diagnose_report_objects():
    m = lpvid.pbsid(FIXTURES / "b2-train.csv", past=3)
    rep = lpvid.diagnose(m, FIXTURES / "b2-train.csv", FIXTURES / "b2-val.csv", fix=False)
    assert isinstance(rep.before, lpvid.Score) and rep.after is None
    assert rep.model.to_json() == m.to_json()
    assert "Stopped" in repr(rep) or "nothing" in repr(rep)
    assert "<table>" in rep._repr_html_()
    with pytest.raises(lpvid.LpvidError, match="lpvid.Model"):
        lpvid.diagnose("model.json", FIXTURES / "b2-train.csv", FIXTURES / "b2-val.csv")
    val = pd.read_csv(FIXTURES / "b2-val.csv").drop(columns=["p1"])
    with pytest.raises(lpvid.DataError, match="p1"):
        lpvid.diagnose(m, FIXTURES / "b2-train.csv", val)


def test_notebook_example_finds_and_fixes_on_the_smart_rotor(tmp_path, monkeypatch):
    """The notebook example, run in this process (its cells as a script): its plots and models
    are written, and its diagnosis of the smart rotor (first 5000 rows to identify, the rest to
    validate, `fix=True`) names an effect and applies it. One run of the notebook's diagnosis
    serves both checks (it is the slowest call of this suite)."""
    script = ROOT / "host-tools/python/examples/smart_rotor_notebook.py"
    monkeypatch.setattr(sys, "argv", [str(script), str(tmp_path)])
    if SMART is None:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(str(script), run_name="__main__")
        assert done.value.code == 0
        return
    cells = runpy.run_path(str(script), run_name="__main__")
    m, rep = cells["model"], cells["report"]
    assert rep.findings, rep.text
    f = rep.findings[0]
    assert f.effect and f.detail and f.evidence and 0 < f.explained <= 1
    assert rep.applied and rep.after_one_step is not None
    assert rep.after_one_step.vaf_mean > rep.before_one_step.vaf_mean
    # the applied effect is in the model's structure: more states (order-too-low) or more
    # input channels (the rotor harmonics, an unused signal, a nonlinearity)
    assert rep.model.order > m.order or rep.model.inputs > m.inputs
    for name in ("validation.png", "singular_values.png", "residual_autocorrelation.png",
                 "smart-rotor-370.json"):
        assert (tmp_path / name).stat().st_size > 0, name
