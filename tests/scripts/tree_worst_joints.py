"""Run by hand (not by the suite): one grown tree of ``experiments/bench_fit_trees.yaml`` (its
first draw) fitted as that file does, printing the fitted joints furthest from the true axes
(degree, radius against the true radius there, parent, segment length) and the bench's measures.

    JSKEL_CACHE=off python tests/scripts/tree_worst_joints.py SEGMENTS [ROUNDS] [LATER_LOSS]
"""

import sys

import numpy as np
import yaml
from scipy.spatial import cKDTree

from jskel.fit._points import sample_surface
from jskel.fit._run import contracted_and_fitted
from jskel.fit._tree_bench import TreeBenchFile, _axis_samples, _degrees, compared, grown_tree

b = TreeBenchFile.model_validate(yaml.safe_load(open("experiments/bench_fit_trees.yaml"))).fit_trees
size = int(sys.argv[1])
edits = {"rounds": int(sys.argv[2])} if len(sys.argv) > 2 else {}
if len(sys.argv) > 3:
    edits["later_loss"] = sys.argv[3]
b = b.model_copy(update={"edits": b.edits.model_copy(update=edits)})
j, r, p = (np.asarray(x, np.float64) for x in grown_tree(size, b.seed))
p = p.astype(np.int64)
rng = np.random.default_rng(b.seed)
n = b.points_per_segment * int(np.sum(p >= 0))
pts = sample_surface(j, r, p, n, rng) + rng.normal(0.0, b.noise, (n, 3))
k = int(round(b.outliers * n))
lo, hi = pts.min(0), pts.max(0)
pts[rng.choice(n, k, replace=False)] = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (k, 3))
_, (res, _, _), _ = contracted_and_fitted(pts, b.start, b.solver, b.edits, "fit_trees")
ax, ar = _axis_samples(j, r, p)
d, near = cKDTree(ax).query(res.joints)
deg = _degrees(res.parents)
for i in np.argsort(d)[::-1][:5]:
    q = res.parents[i]
    print(f"joint {i}: {d[i]:.3f} off the axes, degree {deg[i]}, radius {res.radii[i]:.3f} (true {ar[near[i]]:.3f}), parent {q}, "
          f"segment {np.linalg.norm(res.joints[i] - res.joints[q]) if q >= 0 else 0.0:.3f}")
print(compared(j, r, p, res.joints, res.radii, res.parents))
