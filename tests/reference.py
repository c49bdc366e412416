"""An independent float64 NumPy implementation of Bhagvat et al. 2009, Sec. 2, for tests only.

Written from the paper, not from jskel: cutting planes from Eq. 3-5 with A and B found as 3D
line-line intersections (jskel solves in 2D), the cone in the apex form of Eq. 1-2 and the
quadratic of Eq. 10 solved by the textbook formula (jskel uses the apex-free form, a recentred
origin and the cancellation-free roots); a separate closed form for cylinders.
Branching rule (documented in jskel.frusta._skeleton): the child best aligned with the
incoming segment shares the medial cutting plane; others get a perpendicular capped base.
"""

from __future__ import annotations

import numpy as np


def _unit(v):
    return v / np.linalg.norm(v)


def _line_meet(p1, d1, p2, d2):
    """Closest point of line 2 to line 1 (they are coplanar here, so it is the intersection)."""
    w = p1 - p2
    a, b, c = d1 @ d1, d1 @ d2, d2 @ d2
    d, e = d1 @ w, d2 @ w
    den = a * c - b * b
    if abs(den) < 1e-14 * a * c:
        return None
    s = (a * e - b * d) / den
    return p2 + s * d2


def segments(joints, radii, parents):
    """List of dicts, one per segment (ordered by end joint), with both clipping planes."""
    joints = np.asarray(joints, float)
    radii = np.asarray(radii, float)
    parents = np.asarray(parents)
    segs = []
    index = {}
    for j in range(len(joints)):
        p = parents[j]
        if p < 0:
            continue
        c1, c2 = joints[p], joints[j]
        m = _unit(c2 - c1)
        index[j] = len(segs)
        segs.append(dict(c1=c1, c2=c2, m=m, h=np.linalg.norm(c2 - c1), r1=radii[p], r2=radii[j],
                         bottom=(m, c1, True), top=(m, c2, True), start=p, end=j))
    for jt in range(len(joints)):
        if jt not in index:
            continue
        a = segs[index[jt]]
        kids = [segs[index[c]] for c in range(len(joints)) if parents[c] == jt]
        if not kids:
            continue
        b = max(kids, key=lambda s: s["m"] @ a["m"])
        n, p = cut_plane(a, b)
        a["top"] = (n, p, False)
        b["bottom"] = (n, p, False)
    return segs


def cut_plane(a, b):
    """Eq. 3-5: plane through A and B, perpendicular to the medial plane."""
    cr = np.cross(a["m"], b["m"])
    if np.linalg.norm(cr) < 1e-7:
        return a["m"], a["c2"]
    nm = _unit(cr)
    pts = []
    for sign in (1.0, -1.0):
        sa = np.cross(a["m"], nm)
        sb = np.cross(b["m"], nm)
        l1 = a["c1"] - sign * a["r1"] * sa
        l2 = a["c2"] - sign * a["r2"] * sa
        l3 = b["c1"] - sign * b["r1"] * sb
        l4 = b["c2"] - sign * b["r2"] * sb
        x = _line_meet(l1, l2 - l1, l3, l4 - l3)
        if x is None:
            return _unit(a["m"] + b["m"]), a["c2"]
        pts.append(x)
    n = _unit(np.cross(pts[0] - pts[1], nm))
    if n @ (a["m"] + b["m"]) < 0:
        n = -n
    # jskel's documented guard: a plane that does not cut both cones in ellipses (|n . m| within
    # 0.05 of the sine of the cone's half-angle) is replaced by the bisector plane at the joint
    for s in (a, b):
        k = (s["r2"] - s["r1"]) / np.linalg.norm(s["c2"] - s["c1"])
        if abs(n @ s["m"]) <= abs(k) / np.sqrt(1 + k * k) + 0.05:
            return _unit(a["m"] + b["m"]), a["c2"]
    return n, pts[0]


def _frame(m):
    ref = np.eye(3)[np.argmin(np.abs(m))]
    x = _unit(ref - (ref @ m) * m)
    z = np.cross(x, m)
    return x, z


def _between(seg, P, tol):
    nb, pb, _ = seg["bottom"]
    nt, pt, _ = seg["top"]
    return ((P - pb) @ nb >= -tol) & ((P - pt) @ nt <= tol)


def intersect(segs, O, D, t_min=0.0, t_max=np.inf, slab_tol=0.0):
    """Nearest t and segment id for rays O, D (N,3); inf / -1 on a miss.

    slab_tol grows every segment past its cutting planes by that distance (to find rays that
    hit within it of a seam, where the two elliptical cuts may not match; Sec. 2.2).
    """
    O = np.asarray(O, float)
    D = np.asarray(D, float)
    n = O.shape[0]
    best_t = np.full(n, np.inf)
    best_id = np.full(n, -1)
    for sid, s in enumerate(segs):
        x, z = _frame(s["m"])
        E = O - s["c1"]
        ex, ey, ez = E @ x, E @ s["m"], E @ z
        dx, dy, dz = D @ x, D @ s["m"], D @ z
        r1, r2, h = s["r1"], s["r2"], s["h"]
        scale = h + r1 + r2
        tol = 1e-9 * scale + slab_tol
        if r1 == r2:  # cylinder closed form
            a = dx**2 + dz**2
            b = 2 * (ex * dx + ez * dz)
            c = ex**2 + ez**2 - r1**2
        else:  # Eq. 1-2 and Eq. 10 with the apex height h'
            hp = r1 * h / (r1 - r2)
            q = (r1 / hp) ** 2
            a = dx**2 + dz**2 - dy**2 * q
            b = 2 * ex * dx + 2 * ez * dz - 2 * dy * (ey - hp) * q
            c = ex**2 + ez**2 - (ey - hp) ** 2 * q
        disc = b * b - 4 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
            roots = [(-b - sq) / (2 * a), (-b + sq) / (2 * a)]
            lin = np.where(b != 0, -c / b, np.nan)
        roots = [np.where(np.abs(a) > 1e-300, r, lin) for r in roots]
        cands = []
        for t in roots:
            P = O + t[:, None] * D
            y = (P - s["c1"]) @ s["m"]
            ok = np.isfinite(t) & _between(s, P, tol) & (r1 + (r2 - r1) * y / h >= 0)
            cands.append(np.where(ok, t, np.inf))
        for (nrm, pnt, capped) in (s["bottom"], s["top"]):
            if not capped:
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((pnt - O) @ nrm) / (D @ nrm)
            P = O + t[:, None] * D
            L = P - s["c1"]
            y = L @ s["m"]
            rho2 = (L @ x) ** 2 + (L @ z) ** 2
            ry = r1 + (r2 - r1) * y / h
            ok = np.isfinite(t) & (rho2 <= ry * ry) & (ry >= 0) & _between(s, P, tol)
            cands.append(np.where(ok, t, np.inf))
        for t in cands:
            t = np.where((t > t_min) & (t <= t_max), t, np.inf)
            better = t < best_t
            best_t = np.where(better, t, best_t)
            best_id = np.where(better, sid, best_id)
    return best_t, best_id


def inside(segs, P):
    P = np.asarray(P, float)
    out = np.zeros(P.shape[0], bool)
    for s in segs:
        x, z = _frame(s["m"])
        L = P - s["c1"]
        y = L @ s["m"]
        ry = s["r1"] + (s["r2"] - s["r1"]) * y / s["h"]
        ok = ((L @ x) ** 2 + (L @ z) ** 2 <= ry * ry) & (ry >= 0) & _between(s, P, 0.0)
        out |= ok
    return out


def random_rays(rng, lo, hi, n, spread=1.5):
    """Origins on a sphere around the box, aimed at random points of the box grown by ``spread``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = 0.5 * (lo + hi)
    size = np.linalg.norm(hi - lo)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    O = c + 1.5 * size * u
    T = c + (rng.random((n, 3)) - 0.5) * (hi - lo) * spread
    D = T - O
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return O, D


def far_from_silhouette(segs, O, D, delta, jump):
    """Rays whose hit/miss and t are stable when the origin moves by ``delta`` sideways, and
    whose t does not change when the segments are extended by ``delta`` past their cutting
    planes (a ray within ``delta`` of a seam or a cap rim is on an edge of the surface)."""
    t0, _ = intersect(segs, O, D)
    tx, _ = intersect(segs, O, D, slab_tol=delta)
    scale = max(s["h"] + s["r1"] + s["r2"] for s in segs)
    stable = (np.isfinite(t0) == np.isfinite(tx)) & (
        ~np.isfinite(t0) | (np.abs(np.where(np.isfinite(tx), tx, 0) - np.where(np.isfinite(t0), t0, 0)) <= 1e-6 * scale)
    )
    a = np.cross(D, np.array([0.3, 0.5, 0.8]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(D, a)
    ok = stable.copy()
    for off in (a, -a, b, -b):
        t, _ = intersect(segs, O + delta * off, D)
        same = np.isfinite(t) == np.isfinite(t0)
        close = ~np.isfinite(t0) | (np.abs(np.where(np.isfinite(t), t, 0) - np.where(np.isfinite(t0), t0, 0)) < jump)
        ok &= same & close
    return ok


def rotation(q):
    """Rotation matrix of the quaternion q = (w, x, y, z) (normalised here), float64."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

