"""Notebook 02: relief in a shell over frusta (paired with 02_relief.ipynb by pair.py)."""
# %% [markdown]
# # 02 Relief-mapped frusta (Bhagvat et al. 2009, Sec. 3)
#
# A height field lives in a shell of `thickness` over the frusta and is found by a linear march
# of `steps` samples and a bisection (Sec. 3). Here: the column of `experiments/relief_column.yaml`,
# the depth error of the march against a 256-step reference as the step count grows, and
# close-ups side by side.

# %%
import os
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import jskel
from jskel.measure import compare
from jskel.render import render

SMALL = os.environ.get("JSKEL_NOTEBOOK_SMALL") == "1"  # CI runs every notebook at a reduced size
ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "experiments").is_dir())
S = 64 if SMALL else 256
STEPS = [2, 8, 32] if SMALL else [2, 4, 8, 16, 32, 64]
plt.rcParams["figure.dpi"] = 60  # the stored close-ups stay small


def run(steps):
    exp = jskel.load(ROOT / "experiments" / "relief_column.yaml",
                     [f"camera.width={S}", f"camera.height={S}", f"object.relief.steps={steps}", "render.progress=false"])
    return render(exp, progress=False)


# %% [markdown]
# ## Steps against error

# %%
ref = run(256)
rows = []
for n in STEPS:
    r = run(n)
    m = compare(r.hits, ref.hits, r.rgb, ref.rgb)
    rows.append((n, m["depth_rmse"], m["hit_miss_pct"], r.run["render_s"], r))
fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
ax[0].loglog([r[0] for r in rows], [r[1] for r in rows], "-o")
ax[0].set_xlabel("march steps")
ax[0].set_ylabel("depth RMSE vs 256 steps")
ax[1].plot([r[0] for r in rows], [r[3] for r in rows], "-o")
ax[1].set_xscale("log")
ax[1].set_xlabel("march steps")
ax[1].set_ylabel("render seconds")
plt.show()

# %% [markdown]
# ## Close-ups at several step counts (a grazing part of the column)

# %%
c = slice(S // 4, S // 4 + S // 3)
fig, axs = plt.subplots(1, len(rows) + 1, figsize=(3 * (len(rows) + 1), 3.2))
for a, (n, err, miss, secs, r) in zip(axs, rows):
    a.imshow(r.image[c, c])
    a.set_title(f"{n} steps\nRMSE {err:.4f}, {miss:.2f}% hit/miss")
axs[-1].imshow(ref.image[c, c])
axs[-1].set_title("256 steps (reference)")
for a in axs:
    a.axis("off")
plt.show()
