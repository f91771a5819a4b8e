"""Measure the statistics reduction of lpvid.dask against one process (docs/scale.md).

    python scale_benchmark.py [samples ...]        # default 1e6 1e7

For each total sample count: 20 experiments of an LPV system (r = l = s = 1, past 3) are
generated on the workers of a LocalCluster(n_workers=2, processes=True) (the data never
leave them), reduced to statistics by lpvid.dask and fitted on the client; the same
experiments are then reduced in this one process. Prints the times, the bytes the client
received, the data size and the largest relative difference of the two models' matrices.
"""

import platform
import sys
import time

import numpy as np
import pandas as pd

import lpvid
import lpvid.dask

EXPERIMENTS = 20
PAST = 3

TRUE_MODEL = None


def true_model():
    """A 2-state LPV model (identified once from a short simulated record)."""
    global TRUE_MODEL
    if TRUE_MODEL is None:
        rng = np.random.default_rng(0)
        n = 4000
        u = rng.standard_normal(n)
        p = np.sin(np.arange(n) * 2 * np.pi / 97.0) * 0.8
        x = np.zeros(2)
        y = np.empty(n)
        a0 = np.array([[0.6, 0.3], [-0.3, 0.5]])
        a1 = np.array([[0.2, 0.0], [0.1, -0.2]])
        for k in range(n):
            y[k] = x[0] + 0.4 * x[1] + 0.1 * u[k]
            x = (a0 + p[k] * a1) @ x + np.array([1.0 + 0.3 * p[k], 0.5 - 0.2 * p[k]]) * u[k]
        TRUE_MODEL = lpvid.pbsid(u, y, p, past=3, order=2)
    return TRUE_MODEL


def experiment(seed, n, model_json):
    """One experiment: random input, slowly varying scheduling, the model's output + noise."""
    m = lpvid.Model.from_json(model_json)
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    p = 0.8 * np.sin(np.arange(n) * 2 * np.pi / (50.0 + seed) + seed)
    y = m.simulate(u, p)[:, 0] + 0.01 * rng.standard_normal(n)
    return pd.DataFrame({"u1": u, "y1": y, "p1": p})


def main(totals):
    import dask
    import dask.dataframe as dd
    from dask.distributed import Client, LocalCluster, wait

    mj = true_model().to_json()
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, "
          f"{time.strftime('%Y-%m-%d')}, lpvid {lpvid.__version__}, dask {dask.__version__}")
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    try:
        for total in totals:
            n = total // EXPERIMENTS
            meta = pd.DataFrame({"u1": [0.0], "y1": [0.0], "p1": [0.0]}).iloc[:0]
            parts = [dask.delayed(experiment)(seed, n, mj) for seed in range(EXPERIMENTS)]
            ddf = dd.from_delayed(parts, meta=meta).persist()
            wait(ddf)
            data_bytes = EXPERIMENTS * n * 3 * 8
            t0 = time.perf_counter()
            raw = lpvid.dask.statistics_bytes(ddf, past=PAST, split_every=4)
            t_dask = time.perf_counter() - t0
            t0 = time.perf_counter()
            m_dask = lpvid.fit_from_statistics(raw, order=2)
            t_fit = time.perf_counter() - t0
            # one process: the same experiments, here (generation not timed)
            frames = [experiment(seed, n, mj) for seed in range(EXPERIMENTS)]
            t0 = time.perf_counter()
            st = lpvid.Statistics(past=PAST, inputs=1, outputs=1, scheduling=1)
            for df in frames:
                st.update(df)
            t_one = time.perf_counter() - t0
            m_one = lpvid.fit_from_statistics(st, order=2)
            diff = max(
                float(np.max(np.abs(getattr(m_dask, k) - getattr(m_one, k)))
                      / max(np.max(np.abs(getattr(m_one, k))), 1e-300))
                for k in "ABKCD"
            )
            got = lpvid.Statistics.from_bytes(raw)
            g_diff = float(np.max(np.abs(got.packed() - st.packed())) / np.max(np.abs(st.packed())))
            uu, yy, pp = frames[0].u1.to_numpy(), frames[0].y1.to_numpy(), frames[0].p1.to_numpy()
            y_diff = float(np.max(np.abs(m_dask.simulate(uu, pp) - m_one.simulate(uu, pp)))
                           / np.max(np.abs(yy)))
            per = {k: float(np.max(np.abs(getattr(m_dask, k) - getattr(m_one, k)))
                            / max(np.max(np.abs(getattr(m_one, k))), 1e-300)) for k in "ABKCD"}
            print("   statistics difference %.1e, free-run output difference %.1e, per matrix %s"
                  % (g_diff, y_diff, ", ".join(f"{k} {v:.1e}" for k, v in per.items())))
            print(f"samples {EXPERIMENTS * n:>9}: dask 2 workers {t_dask:7.2f} s, one process "
                  f"{t_one:7.2f} s, fit {t_fit * 1e3:6.1f} ms; client received {len(raw)} bytes "
                  f"(statistics {st.nbytes}), data {data_bytes / 1e6:.0f} MB; per worker sends "
                  f"<= {EXPERIMENTS} x {st.nbytes} bytes; model difference {diff:.1e}")
            del ddf, frames
    finally:
        client.close()
        cluster.close()


if __name__ == "__main__":
    args = [int(float(a)) for a in sys.argv[1:]] or [1_000_000, 10_000_000]
    main(args)
