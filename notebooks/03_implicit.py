"""Notebook 03: skeletal implicit surfaces (paired with 03_implicit.ipynb by pair.py)."""
# %% [markdown]
# # 03 Skeletal implicit surfaces (Rouiller 2011)
#
# Metaballs and metatubes sum kernels f(r) = (1 - r^2/R^2)^2 into a field F; the surface is
# F = T (Sec. 3). Here: the field of a small model on a slice, the three tracers of Sec. 4 (naive
# march, the inside-point bisection of Alg. 2, and the Lipschitz-guaranteed march) and the exact
# tracer side by side with their misses highlighted, and a strip of an animated model (bones,
# Sec. 5).

# %%
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jskel
from jskel import implicit
from jskel.config import validate
from jskel.render import render

SMALL = os.environ.get("JSKEL_NOTEBOOK_SMALL") == "1"  # CI runs every notebook at a reduced size
ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "experiments").is_dir())
W, H = (96, 72) if SMALL else (320, 240)

model = {"type": "implicit", "threshold": 0.5,
         "balls": [{"center": [0, 0, 0], "radius": 1.2}, {"center": [1.0, 0.3, 0], "radius": 0.9},
                   {"center": [-0.9, 0.5, 0.2], "radius": 0.7}],
         "tubes": [{"a": [0.2, 0.3, 0], "b": [0.2, 1.8, 0.1], "radius_a": 0.6, "radius_b": 0.25}]}

# %% [markdown]
# ## The field on the slice z = 0

# %%
built = implicit.build(validate({"object": model}).objects[0].shape)
n = 100 if SMALL else 300
xs, ys = np.meshgrid(np.linspace(-2.2, 2.2, n), np.linspace(-1.2, 2.4, n))
pts = np.stack([xs, ys, np.zeros_like(xs)], -1).reshape(-1, 3) - built.anchor
F = np.asarray(jax.vmap(lambda x: implicit.field(built.params.prims, x))(jnp.asarray(pts, jnp.float32))).reshape(n, n)
fig, ax = plt.subplots(figsize=(6, 5))
im = ax.imshow(F, origin="lower", extent=(-2.2, 2.2, -1.2, 2.4), cmap="magma")
ax.contour(xs, ys, F, levels=[0.5], colors="cyan")
fig.colorbar(im, ax=ax, label="F")
ax.set_title("F on z = 0; the surface F = T = 0.5 in cyan")
plt.show()

# %% [markdown]
# ## Four tracers, misses highlighted
# A naive march with a coarse step skips thin parts; Alg. 2's inside points can bracket a later
# crossing; the Lipschitz march cannot step over a surface (Sec. 4 and `jskel/implicit/_trace.py`);
# the exact tracer solves the field's polynomial on each interval between the primitives'
# breakpoints (`jskel/implicit/_exact.py`), with no step to choose. Red: pixels the reference
# (Lipschitz, tiny eps) hits and the method misses; each title gives the render's time,
# warm (a second render of the same program; at CI's reduced size, the first, compile included).

# %%
cam = {"eye": [0.5, 1.5, 6.0], "target": [0.0, 0.5, 0.0], "fov_deg": 40, "width": W, "height": H}
def trace(**kw):
    return render(validate({"object": {**model, **kw}, "camera": cam}), progress=False)

ref = trace(method="lipschitz", eps=1e-4)
methods = {"naive, step 0.3": dict(method="naive", step=0.3, bisection=8),
           "bisection (Alg. 2)": dict(method="bisection", bisection=12),
           "lipschitz, eps 1e-3": dict(method="lipschitz", eps=1e-3),
           "exact": dict(method="exact")}
fig, axs = plt.subplots(1, 4, figsize=(18, 3.6))
for a, (name, kw) in zip(axs, methods.items()):
    if not SMALL:
        trace(**kw)  # the first render compiles (CI's reduced run times it with its compile)
    t0 = time.perf_counter()
    r = trace(**kw)
    sec = time.perf_counter() - t0
    miss = (np.isfinite(ref.hits.t) & ~np.isfinite(r.hits.t)).reshape(H, W)
    both = np.isfinite(ref.hits.t) & np.isfinite(r.hits.t)
    err = np.max(np.abs(r.hits.t[both] - ref.hits.t[both])) if both.any() else 0.0
    img = r.image.copy()
    img[miss] = [255, 0, 0]
    a.imshow(img)
    a.set_title(f"{name}: {miss.sum()} missed, max |dt| {err:.1e}, {sec:.2f} s", fontsize=9)
    a.axis("off")
plt.show()

# %% [markdown]
# ## An animation strip: the spider walks (bones posed per frame)

# %%
frames = [0, 12, 24] if SMALL else [0, 6, 12, 18, 24, 30]
fig, axs = plt.subplots(1, len(frames), figsize=(3 * len(frames), 2.6))
for a, f in zip(axs, frames):
    exp = jskel.load(ROOT / "experiments" / "spider.yaml", [f"camera.width={W}", f"camera.height={H}", f"object.frame={f}"])
    a.imshow(render(exp, progress=False).image)
    a.set_title(f"frame {f}")
    a.axis("off")
plt.show()
