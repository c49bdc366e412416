"""Notebook 04: cell-based objects (paired with 04_cells.ipynb by pair.py)."""
# %% [markdown]
# # 04 Cell-based objects (Nürnberg 2011)
#
# A tileable 3D Voronoi tile map fills a base shape; each split cell's membership (inside,
# outside, intersected) is precomputed per tile (Ch. 4) and packed 2 bits a cell; rays are traced
# by the thesis' linear search and bisection (Alg. 3.1), with self-reflection and refraction
# (Alg. 3.2-3.3). jskel's default is an exact walk through the tile map's voxels
# (`search: voxels`); this notebook shows the thesis' search, then both searches' steps per ray.

# %%
import os
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import jskel
from jskel import cells
from jskel.cells._membership import unpack
from jskel.render import render

SMALL = os.environ.get("JSKEL_NOTEBOOK_SMALL") == "1"  # CI runs every notebook at a reduced size
ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "experiments").is_dir())
W, H = (96, 72) if SMALL else (320, 240)
TILES = 8 if SMALL else 32
plt.rcParams["figure.dpi"] = 60  # the stored renders stay small
SMALLER = ["object.search=linear", f"object.tiles={TILES}", "object.tile_map.resolution=16" if SMALL else "object.tile_map.resolution=32",
           f"camera.width={W}", f"camera.height={H}"]

# %% [markdown]
# ## The tile map and the membership map

# %%
exp = jskel.load(ROOT / "experiments" / "torus_cells.yaml", SMALLER)
co = cells.precompute(exp.objects[0].shape)
res = co.split.shape[0]
slots = len(co.split_cell) - 1
codes = unpack(co.words, slots).reshape(TILES, TILES, TILES, slots)  # 0 outside, 1 inside, 2 intersected (per split cell)
fig, axs = plt.subplots(1, 3, figsize=(13, 4))
axs[0].imshow(co.split[:, :, res // 2], cmap="tab20", interpolation="nearest")
axs[0].set_title("tile map: split cells on a slice")
axs[1].imshow((codes == 1).sum(-1)[:, :, TILES // 2], cmap="Greens", interpolation="nearest")
axs[1].set_title("inside cells per tile (middle slice)")
axs[2].imshow((codes == 2).sum(-1)[:, :, TILES // 2], cmap="Oranges", interpolation="nearest")
axs[2].set_title("intersected cells per tile")
plt.show()

# %% [markdown]
# ## First hit, self-reflection, refraction

# %%
fig, axs = plt.subplots(1, 3, figsize=(13, 3.6))
for a, mode in zip(axs, ("first_hit", "reflection", "refraction")):
    r = render(jskel.load(ROOT / "experiments" / "torus_cells.yaml", SMALLER + [f"object.mode={mode}"]), progress=False)
    a.imshow(r.image)
    a.set_title(f"{mode}: {r.run['render_s']:.2f} s")
    a.axis("off")
plt.show()

# %% [markdown]
# ## Steps per ray: the voxel walk and the linear search
#
# `render.steps: true` writes each camera ray's primary-search steps as an AOV (`steps.npy`,
# `RenderResult.aovs["steps"]`): the voxels and skipped tiles or blocks of the walk (the
# default, crossing runs of empty tiles one pyramid block at a time), the same walk tile by
# tile (`object.pyramid: false`), and the samples of the linear search at 1/256 of a tile (the
# gallery's step), on the same object and rays.

# %%
fig, axs = plt.subplots(1, 3, figsize=(15, 3.8))
settings = (["object.search=voxels"], ["object.search=voxels", "object.pyramid=false"], ["object.search=linear"])
for a, extra, title in zip(axs, settings, ("walk, pyramid", "walk, tile by tile", "linear, 1/256 tile")):
    e = jskel.load(ROOT / "experiments" / "torus_cells.yaml", SMALLER + extra + ["render.steps=true"])
    steps = render(e, progress=False).aovs["steps"].reshape(H, W)
    im = a.imshow(steps, cmap="magma")
    a.set_title(f"{title}: {steps.mean():.0f} mean, {steps.max()} max")
    a.axis("off")
    fig.colorbar(im, ax=a, shrink=0.8)
plt.show()
