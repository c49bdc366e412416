"""Notebook 06: fitting a skeleton to a point cloud (paired with 06_fitting.ipynb by pair.py)."""
# %% [markdown]
# # 06 Fitting frusta to a noisy point cloud
#
# Points are sampled on a known bent branch, with Gaussian noise and outliers; a skeleton of the
# same topology, started 10 % off, is fitted with Levenberg-Marquardt (jaxopt) on Cauchy-robust
# signed distances to the frusta surface (`jskel.fit`).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np

from jskel.fit import fit_points, perturbed, sample_surface
from jskel.fit._config import SolverConfig

SMALL = os.environ.get("JSKEL_NOTEBOOK_SMALL") == "1"  # CI runs every notebook at a reduced size
N = 600 if SMALL else 3000

# %% [markdown]
# ## A noisy cloud around a known branch

# %%
rng = np.random.default_rng(0)
joints = np.array([[0, 0, 0], [0, 1, 0], [-0.57, 1.82, 0], [-0.78, 2.8, 0], [-0.78, 3.75, -0.32], [-0.6, 4.66, -0.7]])
radii = np.array([0.5, 0.46, 0.42, 0.38, 0.34, 0.3])
parents = np.arange(-1, 5)
length = np.sum(np.linalg.norm(np.diff(joints, axis=0), axis=1))
points = sample_surface(joints, radii, parents, N, rng) + rng.normal(0, 0.01 * length, (N, 3))
out = rng.choice(N, N // 20, replace=False)
points[out] = rng.uniform(points.min(0) - 0.5, points.max(0) + 0.5, (len(out), 3))
j0, r0 = perturbed(joints, radii, parents, 0.1, np.random.default_rng(3))

# %% [markdown]
# ## Fit

# %%
res = fit_points(points, j0, r0, parents, SolverConfig(name="lm", loss="cauchy", scale=0.01, maxiter=100))
print(f"{res.iterations} iterations in {res.seconds:.2f} s (compile {res.compile_s:.1f} s); converged: {res.converged}")
print(f"joint error: {np.max(np.linalg.norm(res.joints - joints, axis=1)) / length:.2%} of the length; "
      f"radius error: {np.max(np.abs(res.radii / radii - 1)):.1%}")

# %% [markdown]
# ## Loss curve, and the fitted skeleton over the points

# %%
fig = plt.figure(figsize=(12, 4.5))
ax0 = fig.add_subplot(1, 2, 1)
ax0.semilogy(res.history)
ax0.set_xlabel("iteration")
ax0.set_ylabel("loss")
ax0.set_title("Levenberg-Marquardt")
ax1 = fig.add_subplot(1, 2, 2, projection="3d")
ax1.scatter(*points.T, s=1, c="0.6")
for name, jj, col in (("start", j0, "tab:orange"), ("fitted", res.joints, "tab:red"), ("truth", joints, "k")):
    ax1.plot(*jj.T, "-o", color=col, ms=3, label=name)
ax1.legend()
plt.show()
