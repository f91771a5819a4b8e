"""Shared fixtures: the repository root, the `lpvid` binary, simulated LPV experiments."""

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]
FIXTURES = ROOT / "fixtures"


def lpvid_bin():
    """The command line: $LPVID_BIN, target/release/lpvid, target/debug/lpvid, or PATH."""
    for c in (os.environ.get("LPVID_BIN"), ROOT / "target/release/lpvid", ROOT / "target/debug/lpvid",
              shutil.which("lpvid")):
        if c and Path(c).is_file():
            return str(c)
    return None


@pytest.fixture
def cli():
    exe = lpvid_bin()
    if exe is None:
        pytest.skip("the lpvid binary is not built (cargo build --release -p lpvid-host --bin lpvid)")

    def run(*args, check=True):
        return subprocess.run([exe, *map(str, args)], cwd=ROOT, capture_output=True, text=True, check=check)

    return run


@pytest.fixture
def in_root(monkeypatch):
    monkeypatch.chdir(ROOT)
    return ROOT


def simulate_lpv(n, seed, noise=0.01):
    """A 2-state, 1-input, 1-output LPV system with one scheduling signal."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    p = np.sin(np.arange(n) * 2 * np.pi / 97.0 + seed) * 0.8 + 0.1 * rng.standard_normal(n)
    a0 = np.array([[0.6, 0.3], [-0.3, 0.5]])
    a1 = np.array([[0.2, 0.0], [0.1, -0.2]])
    b0 = np.array([1.0, 0.5])
    b1 = np.array([0.3, -0.2])
    c = np.array([1.0, 0.4])
    x = np.zeros(2)
    y = np.empty(n)
    for k in range(n):
        y[k] = c @ x + 0.1 * u[k]
        x = (a0 + p[k] * a1) @ x + (b0 + p[k] * b1) * u[k]
    y += noise * rng.standard_normal(n)
    return u, y, p


@pytest.fixture
def experiments():
    """Six experiments of the system above (different lengths and seeds)."""
    return [simulate_lpv(n, seed) for seed, n in enumerate([700, 900, 500, 1200, 800, 650])]


def rel_diff(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))
