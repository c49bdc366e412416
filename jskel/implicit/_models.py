"""Procedural implicit models (host side). Each returns (a (P,3), b (P,3), ra (P,), rb (P,)).

* ``gecko``: 66 metaballs in the spirit of Rouiller's Figure 5 (spine, head, eyes, tail, four
  legs with three toes each), lying in the x-z plane, y up;
* ``blob_grid``: ``n`` metaballs at seeded random positions in a slab, for scaling studies.
"""

from __future__ import annotations

import math

import numpy as np


def _check(name, options, allowed):
    out = dict(allowed)
    for k, v in options.items():
        if k not in allowed:
            raise ValueError(f"object.options.{k}: unknown option for {name} (got {v!r}; known: {', '.join(sorted(allowed)) or 'none'})")
        out[k] = v
    return out


def gecko(seed: int, options: dict):
    _check("gecko", options, {})
    balls = []  # (centre, R)
    for i in range(10):  # spine
        x = -0.9 + 0.2 * i
        balls.append(((x, 0.25, 0.04 * math.sin(2 * x)), 0.42 - 0.015 * abs(i - 5)))
    for i, (x, r) in enumerate([(1.05, 0.36), (1.3, 0.34), (1.5, 0.28), (1.66, 0.2)]):  # head
        balls.append(((x, 0.28 - 0.02 * i, 0.0), r))
    for s in (-1, 1):  # eyes
        balls.append(((1.38, 0.42, 0.17 * s), 0.13))
    for i in range(14):  # tail
        f = i / 13
        balls.append(((-1.1 - 1.6 * f, 0.22 - 0.08 * f, 0.35 * math.sin(3.0 * f)), 0.34 * (1 - 0.7 * f)))
    for (x, s) in [(0.65, 1), (0.65, -1), (-0.6, 1), (-0.6, -1)]:  # legs: 2 balls + 3 toes x 2 balls
        hip = np.array([x, 0.2, 0.25 * s])
        knee = hip + np.array([0.1, -0.05, 0.35 * s])
        foot = knee + np.array([0.12, -0.15, 0.15 * s])
        balls.append((tuple(knee), 0.2))
        balls.append((tuple(foot), 0.18))
        for t in (-1, 0, 1):
            d = np.array([math.cos(0.6 * t + 0.3 * s), 0.0, 0.6 * s * math.sin(0.6 * t + 0.8)])
            d /= np.linalg.norm(d)
            balls.append((tuple(foot + 0.14 * d + [0, -0.04, 0]), 0.12))
            balls.append((tuple(foot + 0.26 * d + [0, -0.05, 0]), 0.1))
    for i, x in enumerate((1.8, 1.86)):  # snout tip
        balls.append(((x, 0.2, 0.0), 0.12 - 0.03 * i))
    for x in (0.25, -0.35):  # belly
        balls.append(((x, 0.12, 0.0), 0.3))
    c = np.array([b[0] for b in balls], np.float64)
    r = np.array([b[1] for b in balls], np.float64) * 1.6  # effective radius R: kernel support
    return c, c.copy(), r, r.copy()


def blob_grid(seed: int, options: dict):
    o = _check("blob_grid", options, {"n": 500.0, "radius": 0.25})
    n = int(o["n"])
    if n < 1:
        raise ValueError(f"object.options.n: need at least 1 (got {n})")
    rng = np.random.default_rng(seed)
    side = math.sqrt(n) * 0.3
    c = np.stack([rng.uniform(-side, side, n), rng.uniform(0, 0.4, n), rng.uniform(-side, side, n)], 1)
    r = np.full(n, float(o["radius"])) * rng.uniform(0.8, 1.2, n)
    return c, c.copy(), r, r.copy()


MODELS = {"gecko": gecko, "blob_grid": blob_grid}
