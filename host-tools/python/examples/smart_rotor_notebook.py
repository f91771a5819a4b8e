# %% [markdown]
# # lpvid in a notebook: the smart rotor
#
# A wind-tunnel "smart rotor" (TU Delft) at 370 rpm: two trailing-edge flap voltages in
# (u1, u2), two blade-root strain signals out (y1, y2), sampled at 100 Hz; the data are in
# `smart-rotor-370rpm.csv` of the project's measured-data directory (`../shared/data` next to
# the checkout, or `$LPVID_DATA`). The rotor speed is constant, so the model is LTI
# (no scheduling column): LPV-PBSID_opt with m = 1.
#
# Cells (`# %%`) run in Jupyter / VS Code, or as a script:
# `python smart_rotor_notebook.py [output directory]` (plots go there; a temporary directory
# by default). The pytest suite runs it.

# %%
import os
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed; in a notebook remove this line
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

import lpvid  # noqa: E402

HERE = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
candidates = [os.environ.get("LPVID_DATA"), HERE.parents[2].parent / "shared" / "data",
              Path("/work/shared/data")]
DATA = next((Path(c) for c in candidates if c and (Path(c) / "smart-rotor-370rpm.csv").is_file()), None)
if DATA is None:
    print("smart rotor example skipped: smart-rotor-370rpm.csv not found in $LPVID_DATA, "
          "../shared/data next to the checkout or /work/shared/data")
    sys.exit(0)
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 and not sys.argv[1].startswith("-") else Path(
    tempfile.mkdtemp(prefix="lpvid-smart-rotor-"))
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## Data: first half to identify, second half to validate

# %%
df = lpvid.read_csv(DATA / "smart-rotor-370rpm.csv")  # lpvid's own CSV parser
train, val = df.iloc[:5000].reset_index(drop=True), df.iloc[5000:].reset_index(drop=True)
print(df.describe().loc[["mean", "std"]])

# %% [markdown]
# ## Identify: LPV-PBSID_opt with the command line's defaults (order from the singular values)

# %%
model = lpvid.pbsid(train, past=8, val=val)
print(model)
print("order:", model.order, "--", model.fit["order_reason"])

# %% [markdown]
# ## Validate: free run and one-step predictor on the held-out half

# %%
free = model.validate(val)
pred = model.validate(val, predictor=True)
print(free)
print(pred)
u_val = val[["u1", "u2"]].to_numpy()
y_val = val[["y1", "y2"]].to_numpy()
yhat = model.simulate(u_val)          # free run from x0 = 0 (no scheduling signal)
yone = model.predict(u_val, y_val)    # one-step-ahead

# %% [markdown]
# ## Diagnose: what does the residual still contain? (`lpvid diagnose --fix`)

# %%
report = lpvid.diagnose(model, train, val, fix=True)
for f in report.findings:
    print(f)
    for e in f.evidence[:3]:
        print("    ", e)
print("validation VAF before", report.before.vaf_mean,
      "after", None if report.after is None else report.after.vaf_mean)
print("one-step VAF before", report.before_one_step.vaf_mean,
      "after", None if report.after_one_step is None else report.after_one_step.vaf_mean)
fixed = report.model

# %% [markdown]
# ## Plots (the ones `lpvid` writes, drawn from the returned arrays)

# %%
t = val["t"].to_numpy() if "t" in val else np.arange(len(val)) * 0.01
fig, axes = plt.subplots(2, 1, sharex=True, figsize=(9, 5))
for j, ax in enumerate(axes):
    ax.plot(t, y_val[:, j], "k", lw=0.6, label="measured")
    ax.plot(t, yhat[:, j], "C0", lw=0.8, label=f"free run (VAF {free.vaf[j]:.1f} %)")
    ax.plot(t, yone[:, j], "C1--", lw=0.6, label=f"one-step (VAF {pred.vaf[j]:.1f} %)")
    ax.set_ylabel(f"y{j + 1}")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xlim(t[0], t[0] + 10)
axes[-1].set_xlabel("t [s]")
fig.suptitle("smart rotor 370 rpm: validation half")
fig.tight_layout()
fig.savefig(OUT / "validation.png", dpi=100)

fig, ax = plt.subplots(figsize=(5, 3.5))
sv = model.singular_values
ax.semilogy(np.arange(1, len(sv) + 1), sv, "o-", ms=3)
ax.axvline(model.order, color="C3", lw=0.8, label=f"order {model.order}")
ax.set_xlabel("index")
ax.set_ylabel("singular value of Gamma K Z")
ax.legend()
fig.tight_layout()
fig.savefig(OUT / "singular_values.png", dpi=100)

res = y_val - yone
fig, axes = plt.subplots(1, 2, figsize=(9, 3))
for j, ax in enumerate(axes):
    r = res[:, j] - res[:, j].mean()
    ac = np.correlate(r, r, "full")[len(r) - 1:len(r) + 40] / (r @ r)
    ax.stem(np.arange(len(ac)), ac)
    band = 1.96 / np.sqrt(len(r))
    ax.axhspan(-band, band, color="0.85")
    ax.set_title(f"one-step residual y{j + 1}: autocorrelation")
fig.tight_layout()
fig.savefig(OUT / "residual_autocorrelation.png", dpi=100)
plt.close("all")

# %% [markdown]
# ## Save the models (read them back with `lpvid validate --model ...`)

# %%
model.write(OUT / "smart-rotor-370.json")
fixed.write(OUT / "smart-rotor-370-fixed.json")
assert lpvid.Model.read(OUT / "smart-rotor-370.json").to_json() == model.to_json()
print("plots and models in", OUT)
for p in sorted(OUT.iterdir()):
    print("  ", p.name)
