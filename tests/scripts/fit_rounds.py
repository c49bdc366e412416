"""Run by hand (not by the suite): one fit of a real mesh with topology edits, as
``experiments/bench_fit_real.yaml`` runs it (its start, solver and edits), printing each round's
joints, the joints its program was compiled for, iterations, seconds and compile seconds.

    JSKEL_CACHE=off python tests/scripts/fit_rounds.py [skeletor:722817260] [SEED] [ROUNDS]

ROUNDS overrides the file's ``edits.rounds`` (docs/fitting.md quotes runs with 5).
"""

import sys
import time

import numpy as np
import trimesh
import yaml

from jskel.fit import contracted_and_fitted
from jskel.peers.skeletonizer import RealFitBenchFile, mesh_path

cfg = RealFitBenchFile.model_validate(yaml.safe_load(open("experiments/bench_fit_real.yaml"))).fit_real
spec = sys.argv[1] if len(sys.argv) > 1 else cfg.meshes[0]
seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
if len(sys.argv) > 3:
    cfg = cfg.model_copy(update={"edits": cfg.edits.model_copy(update={"rounds": int(sys.argv[3])})})
mesh = trimesh.load(mesh_path(spec), process=False)
pts = np.asarray(trimesh.sample.sample_surface(mesh, cfg.points, seed=seed)[0], np.float64)
t = time.perf_counter()
_, (res, _, _), secs = contracted_and_fitted(pts, cfg.start, cfg.solver, cfg.edits, "fit_real")
print(secs, "wall", round(time.perf_counter() - t, 2))
for r in res.rounds:
    print(r)
