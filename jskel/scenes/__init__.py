"""Procedural skeletons of the kinds modelled in Bhagvat et al. 2009, Sec. 4 / Table 1.

Each generator returns ``(joints (J,3), radii (J,), parents (J,), colors (J,3))`` in float64,
y up; a segment takes the colour of its end joint. They run on the host at build time.

* ``saguaro``: a trunk and three arms, 30 segments (the paper's saguaro has 30);
* ``aloe``: a short stem and 25 tapering leaves with closed tips, 229 segments (paper: 229);
* ``well``: body, water, two posts, crossbar, roof cone, bucket, rope: 8 segments (paper: 8);
* ``lsystem_tree``: a bracketed 3D L-system (Prusinkiewicz and Lindenmayer, ABOP Ch. 1-2)
  ``A -> !F[&FA]/////[&FA]///////[&FA]`` from ``FFA``; 7 iterations give 4,374 segments.

Table 1's large scenes (issue 6), built from the same parts:

* ``palm``: a curved trunk of 33 segments, 26 fronds (a 20-segment rachis arching out and down
  with a 3-segment leaflet on each side of every rachis joint) and 20 two-segment coconuts:
  33 + 26 x 140 + 40 = 3,713 segments (Table 1's coconut palm: 3,713);
* ``pine``: a 62-segment trunk with 31 whorls of 5 branches, each a 12-segment axis with a
  4-segment twig on each side of every joint: 62 + 155 x 108 = 16,802 segments (Table 1's pine:
  16,997);
* ``oasis``: five palms around a pond, four with 20 coconuts and one with 16: 18,557 segments
  (Table 1: 18,557);
* ``dancing_cacti``: 72 small saguaros of 30 segments less one arm tip on two (2,158 segments,
  Table 1: 2,158) swaying with ``options.frame`` (48 frames a cycle; the experiment's
  ``object.frame``, so ``--frames`` animates it).
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
    """``iterations`` parallel rewrites of ``axiom`` by ``rules`` (ABOP Ch. 1)."""
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


def _palm_into(b: "_Builder", rng, base, height: float, fronds: int, coconuts: int, lean: float):
    """One palm added to ``b`` (see the module docstring for its parts)."""
    bark, frond_c, leaf_c, nut_c = (0.42, 0.32, 0.2), (0.3, 0.45, 0.15), (0.25, 0.55, 0.18), (0.35, 0.25, 0.1)
    n_trunk = 33
    az = rng.uniform(0, 2 * math.pi)
    lean_dir = np.array([math.cos(az), 0.0, math.sin(az)])
    prev = b.add(base, 0.32, -1, bark)
    for i in range(1, n_trunk + 1):
        f = i / n_trunk
        pos = np.asarray(base) + np.array([0.0, height * f, 0.0]) + lean_dir * lean * height * f * f
        prev = b.add(pos, 0.32 - 0.12 * f, prev, bark)
    top = prev
    crown = b.j[top]
    for k in range(fronds):
        phi = 2 * math.pi * k / fronds + rng.normal(0, 0.05)
        out = np.array([math.cos(phi), 0.0, math.sin(phi)])
        side = np.array([-math.sin(phi), 0.0, math.cos(phi)])
        rise = 0.9 - 1.6 * (k % 3) / 3 + rng.normal(0, 0.05)
        prev, pos = top, crown.copy()
        for i in range(1, 21):
            f = i / 20
            pos = pos + 0.22 * (out * math.cos(0.5 * rise - 1.6 * f) + np.array([0, 1.0, 0]) * math.sin(0.5 * rise - 1.6 * f))
            prev = b.add(pos, 0.06 * (1 - f) + 0.008, prev, frond_c)
            tangent = b.j[prev] - b.j[b.p[prev]]
            tangent /= np.linalg.norm(tangent)
            for sgn in (-1, 1):
                lp, lj = pos.copy(), prev
                ldir = sgn * side * 0.9 + tangent * 0.45 - np.array([0, 0.25, 0])
                ldir /= np.linalg.norm(ldir)
                for m in range(1, 4):
                    lp = lp + ldir * 0.16 * (1 - 0.2 * f) - np.array([0, 0.03 * m, 0])
                    lj = b.add(lp, 0.014 * (1 - m / 3) + 0.002, lj, leaf_c)
    for k in range(coconuts):
        phi = 2 * math.pi * k / max(coconuts, 1) + rng.normal(0, 0.2)
        d = np.array([math.cos(phi), -0.6, math.sin(phi)])
        d /= np.linalg.norm(d)
        j1 = b.add(crown + d * 0.2, 0.12, top, nut_c)
        b.add(crown + d * 0.38, 0.1, j1, nut_c)


def palm(seed: int, options: dict):
    """One coconut palm of 3,713 segments (Table 1)."""
    o = _check_options("palm", options, {"height": 8.0, "coconuts": 20.0})
    b = _Builder()
    _palm_into(b, np.random.default_rng(seed), (0.0, 0.0, 0.0), float(o["height"]), 26, int(o["coconuts"]), 0.08)
    return b.arrays()


def oasis(seed: int, options: dict):
    """Five palms around a pond, 18,557 segments (Table 1's oasis)."""
    _check_options("oasis", options, {})
    rng = np.random.default_rng(seed)
    b = _Builder()
    for k in range(5):
        phi = 2 * math.pi * k / 5 + rng.normal(0, 0.15)
        rad = 5.0 + rng.uniform(-0.8, 0.8)
        base = (rad * math.cos(phi), 0.0, rad * math.sin(phi))
        _palm_into(b, rng, base, 7.0 + rng.uniform(-1.0, 1.5), 26, 16 if k == 4 else 20, 0.12)
    return b.arrays()


def pine(seed: int, options: dict):
    """A conifer of 16,802 segments: trunk, whorls of branches, twigs (Table 1's pine: 16,997)."""
    o = _check_options("pine", options, {"height": 14.0})
    rng = np.random.default_rng(seed)
    bark, needle = (0.35, 0.25, 0.15), (0.12, 0.3, 0.14)
    H = float(o["height"])
    b = _Builder()
    n_trunk, whorls = 62, 31
    trunk = [b.add((0, 0, 0), 0.35, -1, bark)]
    for i in range(1, n_trunk + 1):
        f = i / n_trunk
        trunk.append(b.add((rng.normal(0, 0.01), H * f, rng.normal(0, 0.01)), 0.35 * (1 - f) + 0.02, trunk[-1], bark))
    for w in range(whorls):
        at = 8 + int((n_trunk - 9) * w / whorls)
        f = at / n_trunk
        length = 4.2 * (1 - f) + 0.4
        for k in range(5):
            phi = 2 * math.pi * (k / 5 + 0.37 * w) + rng.normal(0, 0.08)
            out = np.array([math.cos(phi), -0.25, math.sin(phi)])
            out /= np.linalg.norm(out)
            side = np.array([-math.sin(phi), 0.0, math.cos(phi)])
            prev, pos = trunk[at], b.j[trunk[at]].copy()
            for i in range(1, 13):
                g = i / 12
                pos = pos + out * length / 12 + np.array([0, 0.02 * i, 0])
                prev = b.add(pos, 0.07 * (1 - g) + 0.01, prev, bark if g < 0.5 else needle)
                for sgn in (-1, 1):
                    tp, tj = pos.copy(), prev
                    tdir = out * 0.5 + sgn * side
                    tdir /= np.linalg.norm(tdir)
                    for m in range(1, 5):
                        tp = tp + tdir * 0.11 * (1.2 - g) - np.array([0, 0.02, 0])
                        tj = b.add(tp, 0.015 * (1 - m / 4) + 0.003, tj, needle)
    return b.arrays()


def dancing_cacti(seed: int, options: dict):
    """72 small saguaros (2,158 segments) swaying with ``frame`` (48 frames a cycle)."""
    o = _check_options("dancing_cacti", options, {"frame": 0.0})
    rng = np.random.default_rng(seed)
    b = _Builder()
    t = 2 * math.pi * float(o["frame"]) / 48.0
    for c in range(72):
        j, r, p, col = saguaro(seed + 1 + c, {"height": 2.0})
        if c < 2:  # drop one arm tip: 29 segments, 72 x 30 - 2 = 2,158 in all
            keep = np.ones(len(j), bool)
            keep[-1] = False
            j, r, p, col = j[keep], r[keep], p[keep], col[keep]
        gx, gz = c % 9, c // 9
        base = np.array([1.6 * gx - 6.4 + rng.normal(0, 0.2), 0.0, 1.6 * gz - 5.6 + rng.normal(0, 0.2)])
        amp = 0.25 * (1 + 0.3 * math.sin(c))
        ang = amp * math.sin(t + 0.5 * gx + 0.3 * gz)
        # a sway about z, stronger with height (bend), as the cacti "dance"
        y = j[:, 1:2] / 2.0
        bend = ang * y
        x = j[:, 0:1] * np.cos(bend) - j[:, 1:2] * np.sin(bend)
        yy = j[:, 0:1] * np.sin(bend) + j[:, 1:2] * np.cos(bend)
        moved = np.concatenate([x, yy, j[:, 2:3]], 1) + base
        off = len(b.j)
        for i in range(len(j)):
            b.add(moved[i], r[i], -1 if p[i] < 0 else p[i] + off, col[i])
    return b.arrays()


GENERATORS = {"saguaro": saguaro, "aloe": aloe, "well": well, "lsystem_tree": lsystem_tree,
              "palm": palm, "pine": pine, "oasis": oasis, "dancing_cacti": dancing_cacti}


def generate(name: str, seed: int, options: dict):
    """The procedural skeleton ``name``: (joints, radii, parents, colors) in float64."""
    if name not in GENERATORS:
        raise ValueError(f"object.skeleton.procedural: unknown generator {name!r} (known: {', '.join(GENERATORS)})")
    return GENERATORS[name](seed, options)
