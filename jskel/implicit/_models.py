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


def _tube_bone(name, parent, head, tail, ra, rb, keys=()):
    return {"name": name, "parent": parent, "head": list(map(float, head)), "tail": list(map(float, tail)),
            "tube": [float(ra), float(rb)], "keys": [{"frame": float(f), "rotate": list(map(float, r))} for f, r in keys]}


def spider(seed: int, options: dict):
    """A spider (Fig. 1) rigged the Fig. 9 way: 16 leg bones are metatubes; a body bone carries
    three metaballs. Frames 0-48 walk: femurs swing about the vertical, tibias bend."""
    _check("spider", options, {})
    bones = [{"name": "body", "parent": None, "head": [0.0, 0.7, -0.8], "tail": [0.0, 0.7, 0.8],
              "keys": [{"frame": f, "rotate": [0.0, 0.0, 4.0 * math.sin(f / 48 * 4 * math.pi)]} for f in range(0, 49, 6)]}]
    balls = [{"center": [0.0, 0.75, -0.6], "radius": 1.0, "bone": "body"},
             {"center": [0.0, 0.7, 0.45], "radius": 0.75, "bone": "body"},
             {"center": [0.0, 0.72, 0.95], "radius": 0.45, "bone": "body"}]
    for side in (-1, 1):
        for i, z in enumerate((0.75, 0.35, -0.05, -0.45)):
            hip = np.array([0.3 * side, 0.7, z])
            out = np.array([side * 1.0, 0.0, (z - 0.15) * 0.9])
            out /= np.linalg.norm(out)
            knee = hip + 1.0 * out + np.array([0, 0.65, 0])
            foot = knee + 1.1 * out + np.array([0, -1.35, 0])
            phase = (i % 2) * math.pi + (side > 0) * math.pi
            swing = [(f, (0.0, 18.0 * math.sin(f / 48 * 4 * math.pi + phase), 0.0)) for f in range(0, 49, 6)]
            bend = [(f, (0.0, 0.0, side * 10.0 * math.cos(f / 48 * 4 * math.pi + phase))) for f in range(0, 49, 6)]
            tag = f"{'l' if side < 0 else 'r'}{i}"
            bones.append(_tube_bone(f"femur_{tag}", "body", hip, knee, 0.24, 0.17, swing))
            bones.append(_tube_bone(f"tibia_{tag}", f"femur_{tag}", knee, foot, 0.17, 0.09, bend))
    return {"balls": balls, "tubes": [], "bones": bones}


def dinosaur(seed: int, options: dict):
    """A biped dinosaur rigged the Fig. 9 way: spine, neck, tail, legs and arms are metatube
    bones; metaballs give the head, belly and feet. Frames 0-48: a walk with a tail swing."""
    _check("dinosaur", options, {})
    def k(amp, axis, phase=0.0):
        return [(f, tuple(amp * math.sin(f / 48 * 2 * math.pi * 2 + phase) if j == axis else 0.0 for j in range(3))) for f in range(0, 49, 6)]
    bones = [
        _tube_bone("hips", None, (0, 1.6, -0.3), (0, 1.8, 0.6), 0.55, 0.5),
        _tube_bone("chest", "hips", (0, 1.8, 0.6), (0, 2.1, 1.3), 0.5, 0.4),
        _tube_bone("neck", "chest", (0, 2.1, 1.3), (0, 2.7, 1.8), 0.32, 0.26, k(8, 0)),
        _tube_bone("tail1", "hips", (0, 1.6, -0.3), (0, 1.5, -1.3), 0.45, 0.32, k(12, 1)),
        _tube_bone("tail2", "tail1", (0, 1.5, -1.3), (0, 1.3, -2.3), 0.32, 0.2, k(12, 1, 0.5)),
        _tube_bone("tail3", "tail2", (0, 1.3, -2.3), (0, 1.1, -3.2), 0.2, 0.08, k(12, 1, 1.0)),
    ]
    for side, ph in ((-1, 0.0), (1, math.pi)):
        s = "l" if side < 0 else "r"
        bones.append(_tube_bone(f"thigh_{s}", "hips", (0.45 * side, 1.5, 0.1), (0.55 * side, 0.8, 0.4), 0.3, 0.2, k(25, 0, ph)))
        bones.append(_tube_bone(f"shin_{s}", f"thigh_{s}", (0.55 * side, 0.8, 0.4), (0.55 * side, 0.15, 0.1), 0.2, 0.14, k(15, 0, ph + 1.0)))
        bones.append(_tube_bone(f"arm_{s}", "chest", (0.4 * side, 1.8, 1.2), (0.55 * side, 1.4, 1.6), 0.12, 0.08, k(20, 0, ph)))
    balls = [{"center": [0, 2.85, 2.0], "radius": 0.55, "bone": "neck"},
             {"center": [0, 2.7, 2.4], "radius": 0.4, "bone": "neck"},
             {"center": [0, 1.55, 0.4], "radius": 0.8, "bone": "hips"},
             {"center": [-0.55, 0.1, 0.3], "radius": 0.3, "bone": "shin_l"},
             {"center": [0.55, 0.1, 0.3], "radius": 0.3, "bone": "shin_r"}]
    return {"balls": balls, "tubes": [], "bones": bones}


RIGGED = {"spider": spider, "dinosaur": dinosaur}
