"""Procedural skeletons of the kinds modelled in Bhagvat et al. 2009, Sec. 4 / Table 1.

Each generator returns ``(joints (J,3), radii (J,), parents (J,), colors (J,3))`` in float64,
y up; a segment takes the colour of its end joint. They run on the host at build time.

* ``saguaro``: a trunk and three arms, 30 segments (the paper's saguaro has 30);
* ``aloe``: a short stem and 25 tapering leaves with closed tips, 229 segments (paper: 229);
* ``well``: body, water, two posts, crossbar, roof cone, bucket, rope: 8 segments (paper: 8);
* ``lsystem_tree``: a bracketed 3D L-system (Prusinkiewicz and Lindenmayer, ABOP Ch. 1-2)
  ``A -> !F[&FA]/////[&FA]///////[&FA]`` from ``FFA``; 7 iterations give 4,374 segments.
"""

from __future__ import annotations

import math

import numpy as np

_GREEN = (0.22, 0.42, 0.16)


def _check_options(name: str, options: dict, allowed: dict) -> dict:
    out = dict(allowed)
    for k, v in options.items():
        if k not in allowed:
            known = ", ".join(sorted(allowed)) or "none"
            raise ValueError(f"object.skeleton.options.{k}: unknown option for {name} (got {v!r}; known: {known})")
        out[k] = v
    return out


class _Builder:
    def __init__(self):
        self.j, self.r, self.p, self.c = [], [], [], []

    def add(self, pos, radius, parent, color):
        self.j.append(np.asarray(pos, np.float64))
        self.r.append(float(radius))
        self.p.append(int(parent))
        self.c.append(tuple(color))
        return len(self.j) - 1

    def arrays(self):
        return np.array(self.j), np.array(self.r), np.array(self.p, np.int64), np.array(self.c, np.float64)


def saguaro(seed: int, options: dict):
    """Trunk of 12 segments and 3 arms of 6 that leave sideways and turn upwards."""
    o = _check_options("saguaro", options, {"height": 6.0})
    rng = np.random.default_rng(seed)
    b = _Builder()
    H = float(o["height"])
    n_trunk = 12
    prev = b.add((0, 0, 0), 0.45, -1, _GREEN)
    trunk = [prev]
    for i in range(1, n_trunk + 1):
        f = i / n_trunk
        x = 0.05 * math.sin(2.0 * f) + rng.normal(0, 0.01)
        r = 0.45 - 0.1 * f if i < n_trunk else 0.2
        prev = b.add((x, H * f, 0.02 * f), r, prev, _GREEN)
        trunk.append(prev)
    for k, (at, phi) in enumerate([(4, 0.3), (6, 2.6), (8, 4.4)]):
        base = b.j[trunk[at]]
        out = np.array([math.cos(phi), 0.0, math.sin(phi)])
        up = np.array([0.0, 1.0, 0.0])
        steps = [(0.55, 0.12), (0.45, 0.35), (0.2, 0.5), (0.05, 0.6), (0.0, 0.55), (0.0, 0.45)]
        prev = trunk[at]
        pos = base.copy()
        for s, (o_, u_) in enumerate(steps):
            pos = pos + out * o_ + up * u_
            r = 0.28 - 0.02 * s if s < len(steps) - 1 else 0.14
            prev = b.add(pos, r, prev, _GREEN)
    return b.arrays()


def aloe(seed: int, options: dict):
    """A stem of 4 segments and 25 leaves of 9 segments each, arranged by the golden angle."""
    o = _check_options("aloe", options, {"leaves": 25.0})
    n_leaves = int(o["leaves"])
    if n_leaves < 1:
        raise ValueError(f"object.skeleton.options.leaves: need at least 1 (got {n_leaves})")
    rng = np.random.default_rng(seed)
    b = _Builder()
    stem = [b.add((0, 0, 0), 0.35, -1, (0.35, 0.3, 0.2))]
    for i in range(1, 5):
        stem.append(b.add((0, 0.12 * i, 0), 0.35 - 0.04 * i, stem[-1], (0.35, 0.3, 0.2)))
    golden = math.pi * (3 - math.sqrt(5))
    for L in range(n_leaves):
        phi = L * golden
        level = L / n_leaves
        at = stem[1 + min(int(level * 4), 3)]
        out = np.array([math.cos(phi), 0.0, math.sin(phi)])
        elev = math.radians(70 - 45 * (1 - level)) + rng.normal(0, 0.05)
        length = 1.6 * (1.1 - 0.5 * level)
        prev = at
        pos = b.j[at].copy()
        col = (0.25 + 0.1 * level, 0.5 + 0.1 * level, 0.25)
        for s in range(1, 10):
            f = s / 9
            ang = elev - 1.1 * f * f  # leaves arch outward and droop at the tip
            seg = length / 9
            pos = pos + seg * (math.cos(ang) * out + math.sin(ang) * np.array([0.0, 1.0, 0.0]))
            r = 0.11 * (1 - f) if s < 9 else 0.0
            prev = b.add(pos, r, prev, col)
    return b.arrays()


def well(seed: int, options: dict):
    """The well of Figure 10 from eight segments."""
    _check_options("well", options, {})
    stone, wood, water, roof, rope = (0.55, 0.5, 0.45), (0.45, 0.3, 0.15), (0.1, 0.2, 0.35), (0.5, 0.2, 0.12), (0.7, 0.6, 0.4)
    b = _Builder()
    a = b.add((0, 0, 0), 1.2, -1, stone)
    b.add((0, 0.9, 0), 1.2, a, stone)  # body
    a = b.add((0, 0.8, 0), 1.0, -1, water)
    b.add((0, 0.93, 0), 1.0, a, water)  # water surface inside the rim
    for x in (-1.0, 1.0):  # posts
        a = b.add((x, 0.9, 0), 0.08, -1, wood)
        b.add((x, 2.7, 0), 0.08, a, wood)
    a = b.add((-1.15, 2.5, 0), 0.06, -1, wood)
    b.add((1.15, 2.5, 0), 0.06, a, wood)  # crossbar
    a = b.add((0, 2.65, 0), 1.6, -1, roof)
    b.add((0, 3.5, 0), 0.0, a, roof)  # roof cone, closed tip
    a = b.add((0, 1.3, 0), 0.22, -1, wood)
    b.add((0, 1.7, 0), 0.27, a, wood)  # bucket
    a = b.add((0, 1.7, 0), 0.015, -1, rope)
    b.add((0, 2.5, 0), 0.015, a, rope)  # rope
    return b.arrays()


def _rot(axis, ang):
    axis = axis / np.linalg.norm(axis)
    c, s = math.cos(ang), math.sin(ang)
    x, y, z = axis
    return np.array(
        [
            [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
            [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
            [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
        ]
    )


def lsystem_string(axiom: str, rules: dict, iterations: int) -> str:
    s = axiom
    for _ in range(iterations):
        s = "".join(rules.get(ch, ch) for ch in s)
    return s


def lsystem_tree(seed: int, options: dict):
    """Turtle interpretation (F, + -, & ^, / \\, [ ], !) of a bracketed 3D L-system."""
    o = _check_options(
        "lsystem_tree",
        options,
        {"iterations": 7.0, "pitch_deg": 28.0, "roll_deg": 137.5, "length": 1.2, "radius": 0.18, "jitter": 0.1},
    )
    it = int(o["iterations"])
    if not 0 <= it <= 9:
        raise ValueError(f"object.skeleton.options.iterations: must be in [0, 9] (got {it})")
    rng = np.random.default_rng(seed)
    s = lsystem_string("FFA", {"A": "!F[&FA]/////[&FA]///////[&FA]"}, it)
    pitch = math.radians(o["pitch_deg"])
    roll = math.radians(o["roll_deg"]) / 5.0  # five '/' between siblings
    b = _Builder()
    bark, leafy = (0.4, 0.28, 0.18), (0.3, 0.5, 0.2)
    state = dict(pos=np.zeros(3), H=np.array([0.0, 1.0, 0.0]), L=np.array([-1.0, 0.0, 0.0]), U=np.array([0.0, 0.0, 1.0]), len=float(o["length"]), rad=float(o["radius"]), joint=-1, depth=0)
    state["joint"] = b.add(state["pos"], state["rad"], -1, bark)
    stack = []
    jit = float(o["jitter"])
    for ch in s:  # host loop over L-system symbols at build time
        if ch == "F":
            d = state["H"] * state["len"]
            state["pos"] = state["pos"] + d
            col = leafy if state["depth"] >= it else bark
            state["joint"] = b.add(state["pos"], state["rad"], state["joint"], col)
        elif ch in "&^":
            a = pitch * (1 + jit * rng.normal()) * (1 if ch == "&" else -1)
            R = _rot(state["L"], a)
            state["H"], state["U"] = R @ state["H"], R @ state["U"]
        elif ch in "/\\":
            a = roll * (1 + jit * rng.normal()) * (1 if ch == "/" else -1)
            R = _rot(state["H"], a)
            state["L"], state["U"] = R @ state["L"], R @ state["U"]
        elif ch in "+-":
            a = pitch * (1 if ch == "+" else -1)
            R = _rot(state["U"], a)
            state["H"], state["L"] = R @ state["H"], R @ state["L"]
        elif ch == "!":
            state["rad"] *= 0.7
            state["len"] *= 0.78
            state["depth"] += 1
        elif ch == "[":
            stack.append({k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in state.items()})
        elif ch == "]":
            state = stack.pop()
    return b.arrays()


GENERATORS = {"saguaro": saguaro, "aloe": aloe, "well": well, "lsystem_tree": lsystem_tree}


def generate(name: str, seed: int, options: dict):
    if name not in GENERATORS:
        raise ValueError(f"object.skeleton.procedural: unknown generator {name!r} (known: {', '.join(GENERATORS)})")
    return GENERATORS[name](seed, options)
