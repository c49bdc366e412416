"""Run by hand (not by the suite): what the radii refit (``solver.radii_refit``,
``jskel/fit/_radii.py``) reaches from the TRUE joints of the fit bench's chain, the bound on
what any fit of those points' radii can do with the joints right. The cloud is
``experiments/bench_fit.yaml``'s (its noise, outliers, seed and loss; 100,000 points on a
1,000-segment bent chain by default), the start its perturbed radii; one JSON line: the
start's and the refit's median relative error, share within 5 % and largest error.

    python tests/scripts/radii_refit_bound.py [segments] [points]
"""

import json
import sys
import time

import numpy as np
import yaml

from jskel.fit import perturbed
from jskel.fit._bench import FitBench, _cloud, bent_chain
from jskel.fit._radii import refit_radii


def spread(radii, truth) -> dict:
    e = np.abs(np.asarray(radii) / truth - 1)
    return {"median_rel": round(float(np.median(e)), 4), "within_5pct_share": round(float(np.mean(e < 0.05)), 4),
            "max_rel": round(float(e.max()), 4)}


def main(segments: int = 1000, points: int = 100000) -> dict:
    b = FitBench.model_validate(yaml.safe_load(open("experiments/bench_fit.yaml"))["fit"])
    j, r, p = bent_chain(segments, b.seed)
    pts, _ = _cloud(j, r, p, points, b.noise_sd, b.outliers, np.random.default_rng(b.seed + 1))
    _, r0 = perturbed(j, r, p, b.perturb, np.random.default_rng(b.seed + 2))
    ext = float(np.max(np.ptp(pts, axis=0)))
    t = time.perf_counter()
    got = refit_radii(pts, j, r0, p, b.loss, 0.01 * ext)  # SolverConfig's default scale, as the bench's fits
    return {"segments": segments, "points": points, "loss": b.loss, "noise_sd": b.noise_sd, "outliers": b.outliers,
            "start": spread(r0, r), "refit_from_true_joints": spread(got, r), "seconds": round(time.perf_counter() - t, 3)}


if __name__ == "__main__":
    print(json.dumps(main(*(int(a) for a in sys.argv[1:3]))))
