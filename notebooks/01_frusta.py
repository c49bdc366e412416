"""Notebook 01: conical frusta (paired with 01_frusta.ipynb by pair.py)."""
# %% [markdown]
# # 01 Conical frusta (Bhagvat et al. 2009)
#
# A skeleton of joints, radii and parents is skinned by cones cut by planes at the joints
# (Sec. 2.1-2.2, Eq. 3-5) and ray cast analytically (Sec. 2.4-2.5). This notebook builds a small
# skeleton, draws its cutting planes, renders it with the (u, v) parametrisation of Eq. 6-7 and
# the normals of Eq. 8 as images, then changes a radius and renders again (no recompilation:
# radii are traced values), and ends with `jskel.view`: the render with controls.

# %%
import os
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from jskel import frusta
from jskel.config import validate
from jskel.render import render

SMALL = os.environ.get("JSKEL_NOTEBOOK_SMALL") == "1"  # CI runs every notebook at a reduced size
ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "experiments").is_dir())
W, H = (96, 72) if SMALL else (360, 270)

# %% [markdown]
# ## A skeleton and its cutting planes
# `frusta_from_skeleton` validates the skeleton (every bad field is named) and builds the frusta
# on the host in float64; `rim_points` samples the ellipses where the cutting planes meet the cones.

# %%
joints = np.array([[0, 0, 0], [0, 1.2, 0], [0.6, 2.1, 0.1], [0.8, 3.0, 0.5], [-0.7, 1.9, -0.2]])
radii = np.array([0.45, 0.4, 0.3, 0.12, 0.15])
parents = [-1, 0, 1, 2, 1]
arrays, topo, info = frusta.frusta_from_skeleton(joints, radii, parents)
rims = frusta.rim_points(arrays)
fig = plt.figure(figsize=(5, 5))
ax = fig.add_subplot(projection="3d")
for i, p in enumerate(parents):
    if p >= 0:
        ax.plot(*np.stack([joints[p], joints[i]]).T, "k-", lw=2)
ax.scatter(*rims.reshape(-1, 3).T, s=1, c="tab:green")
ax.set_title(f"{len(arrays.h)} segments: axes and cut ellipses")
plt.show()

# %% [markdown]
# ## Render: image, (u, v) and normals
# An experiment is a dict (or YAML file) validated by pydantic; `render` returns the hits (AOVs)
# and the shaded image.

# %%
raw = {
    "object": {"type": "frusta", "skeleton": {"joints": joints.tolist(), "radii": radii.tolist(), "parents": parents}},
    "camera": {"eye": [3.5, 2.5, 5.0], "target": [0.1, 1.4, 0.0], "fov_deg": 40, "width": W, "height": H},
}
exp = validate(raw)
res = render(exp, progress=False)
hit = np.isfinite(res.hits.t).reshape(H, W)
uv = res.hits.uv.reshape(H, W, 2)
nrm = res.hits.normal.reshape(H, W, 3)
fig, axs = plt.subplots(1, 4, figsize=(16, 3.4))
axs[0].imshow(res.image)
axs[0].set_title(f"render ({res.run['render_s']:.3f} s, compile {res.run['compile_s']:.2f} s)")
axs[1].imshow(np.where(hit, uv[..., 0], np.nan), cmap="twilight")
axs[1].set_title("u (around the axis)")
axs[2].imshow(np.where(hit, uv[..., 1], np.nan), cmap="viridis")
axs[2].set_title("v (along each chain)")
axs[3].imshow(np.where(hit[..., None], 0.5 + 0.5 * nrm, 1.0))
axs[3].set_title("normals (Eq. 8)")
for a in axs:
    a.axis("off")
plt.show()

# %% [markdown]
# ## Change a radius and render again
# Radii are traced values of the same shapes, so the second render reuses the compiled program
# (`compile_s` is 0).

# %%
radii2 = radii.copy()
radii2[1] = 0.6
raw["object"]["skeleton"]["radii"] = radii2.tolist()
res2 = render(validate(raw), progress=False)
fig, axs = plt.subplots(1, 2, figsize=(8, 3.4))
axs[0].imshow(res.image)
axs[0].set_title("radius[1] = 0.4")
axs[1].imshow(res2.image)
axs[1].set_title(f"radius[1] = 0.6 (compile {res2.run['compile_s']:.2f} s)")
for a in axs:
    a.axis("off")
plt.show()
assert res2.run["compile_s"] == 0.0

# %% [markdown]
# ## Explore with controls
# `jskel.view` shows the render with ipywidgets controls: orbit and zoom, the AOV shown (image,
# depth, normals, uv, ids, flags), the representation's quality knobs and the object's traced
# parameters (here a scale of every radius and an offset of the last joint). Moving a control
# renders again with the programs already compiled; the status line counts the programs each
# render handed to XLA. Here two controls are set from code, as moving them does; a page of
# the documentation shows the image as it was left.

# %%
import jskel

v = jskel.view(raw, width=W, height=H)
v.sliders["radius scale"].value = 1.25
v.sliders["azimuth"].value = 40.0
assert v.programs == 0, "a traced change compiled a program"
v
