"""Notebook 05: sweeps of quality knobs (paired with 05_sweeps.ipynb by pair.py)."""
# %% [markdown]
# # 05 What accuracy costs in time: every representation on one figure
#
# `python -m jskel sweep FILE --out DIR` writes `results.csv` (one row per setting: the varied
# values, warm median seconds, error metrics against a reference). This notebook loads the
# committed sweeps in `docs/` and plots error against time for the relief march, the implicit
# tracers and the cell objects' linear search (with the exact voxel walk as one more point), with
# each Pareto front.

# %%
import csv
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "experiments").is_dir())
SWEEPS = {"relief steps": "sweep_relief_steps_cpu", "implicit method and step": "sweep_implicit_steps_cpu",
          "cells step and voxel walk": "sweep_cells_steps_cpu"}


def pareto(t, e):
    """Indices of the points no other point beats in both time and error."""
    order = np.argsort(t)
    best, keep = np.inf, []
    for i in order:
        if e[i] < best:
            best = e[i]
            keep.append(i)
    return np.array(keep)


# %%
fig, ax = plt.subplots(figsize=(7, 5))
for (label, folder), colour in zip(SWEEPS.items(), ("tab:blue", "tab:orange", "tab:green")):
    rows = list(csv.DictReader((ROOT / "docs" / folder / "results.csv").open()))
    t = np.array([float(r["time_median_s"]) for r in rows])
    e = np.array([float(r["depth_px_p99"]) if r.get("depth_px_p99") not in (None, "") else np.nan for r in rows])
    ok = np.isfinite(e) & (e > 0)
    t, e = t[ok], e[ok]
    ax.scatter(t, e, s=14, color=colour, alpha=0.5)
    f = pareto(t, e)
    ax.plot(t[f], e[f], "-o", color=colour, ms=4, label=f"{label} ({ok.sum()} settings)")
ax.set_xscale("log")
ax.set_yscale("log")
ax.set_xlabel("warm median seconds per frame (CPU)")
ax.set_ylabel("depth error, p99 (pixel footprints)")
ax.set_title("error against time, Pareto fronts")
ax.legend(fontsize=8)
plt.show()
