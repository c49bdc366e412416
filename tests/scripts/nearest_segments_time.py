"""Run by hand (not by the suite): one pass of ``_topology.nearest_segments`` (the radii refit's
and the topology edits' host search) on the fit bench's 1,000-segment chain and 100,000 points,
through the k-d tree of segment centres and by the exhaustive search (``NEAR_FROM`` raised past
the segment count), with whether the two agree. One JSON line; seconds are single runs.

    python tests/scripts/nearest_segments_time.py [segments] [points]
"""

import json
import sys
import time

import numpy as np

from jskel.fit import _topology as T
from jskel.fit._bench import _cloud, bent_chain


def main(segments: int = 1000, points: int = 100000) -> dict:
    j, r, p = bent_chain(segments, 0)
    pts, _ = _cloud(j, r, p, points, 0.05, 0.05, np.random.default_rng(1))
    out = {"segments": segments, "points": points}
    got = {}
    for name, near_from in (("kd_tree", T.NEAR_FROM), ("exhaustive", 10**9)):
        keep, T.NEAR_FROM = T.NEAR_FROM, near_from
        t = time.perf_counter()
        got[name] = T.nearest_segments(pts, j, r * 1.1, p)
        out[f"{name}_s"] = round(time.perf_counter() - t, 3)
        T.NEAR_FROM = keep
    out["same"] = bool(np.array_equal(got["kd_tree"][0], got["exhaustive"][0]) and np.array_equal(got["kd_tree"][1], got["exhaustive"][1]))
    return out


if __name__ == "__main__":
    print(json.dumps(main(*(int(a) for a in sys.argv[1:3]))))
