"""Skeleton -> conical frusta (host side, NumPy float64), Bhagvat et al. 2009, Sec. 2.1-2.3.

Each segment becomes a frustum in a local frame ``(U, M, W)`` at its base joint ``C1``: ``M``
the unit medial axis (the paper's y), ``U`` and ``W`` the paper's x and z. The cone of Eq. 1-2
is written without the apex height h' = r1 h / (r1 - r2):

    x^2 + z^2 = (r1 + k y)^2,   k = (r2 - r1) / h,

which is Eq. 1 multiplied by (r1 / h')^2 = k^2, so the cylinder r1 == r2 (h' infinite, k = 0)
and the closed tip r2 == 0 are the same formula, with no division by r1 - r2.

Each segment is clipped by two planes ``n . (P - C1) >= d`` (bottom) and ``n . (P - C1) <= d``
(top), with both normals pointing along ``M``. The plane shared by a segment and its
continuation is the medial-plane construction of Eq. 3-5; free ends and the bases of side
branches (see ``_skeleton``) are cut perpendicular to the axis and closed by flat caps.

The frames align u across joints as in Sec. 2.3: the u = 0 generator of the lower frustum meets
the cutting plane at a point Q; the upper frustum's ``W`` is chosen through Q, which is the
paper's "subtract u_t" built into the frame. A twist theta per segment adds v * theta to u
(Sec. 2.3), and the offsets accumulate along a chain so a twisted texture stays continuous.

Minor-axis matching (Sec. 2.2, optional): the base radius of a continuation is rescaled until
the minor axes of the two elliptical cuts agree, recomputing the cutting plane each time.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._skeleton import Topology

_COLLINEAR_SIN = 1e-7


class FrustaArrays(NamedTuple):
    """Per-segment float64 arrays (S first); see the module docstring for the frame."""

    c1: np.ndarray  # (S,3) base joint
    m: np.ndarray  # (S,3) unit axis
    u: np.ndarray  # (S,3) frame x
    w: np.ndarray  # (S,3) frame z (u = 0 direction)
    h: np.ndarray  # (S,) length
    r1: np.ndarray  # (S,) radius at C1
    r2: np.ndarray  # (S,) radius at C2
    nb: np.ndarray  # (S,3) bottom plane normal (n . M > 0)
    db: np.ndarray  # (S,) bottom plane offset: n . (P - C1) >= db inside
    nt: np.ndarray  # (S,3) top plane normal
    dt: np.ndarray  # (S,) top plane offset: n . (P - C1) <= dt inside
    cap_b: np.ndarray  # (S,) bool: bottom closed by a flat cap
    cap_t: np.ndarray  # (S,) bool
    u_off: np.ndarray  # (S,) u offset (turns) from the twist of the segments below
    twist: np.ndarray  # (S,) twist (turns per unit v)
    v_off: np.ndarray  # (S,) number of segments before this one along its chain (v spans segments)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _any_perp(m):
    """A unit vector perpendicular to each row of m (coordinate-axis substitution of Sec. 2.2)."""
    ax = np.eye(3)[np.argmin(np.abs(m), axis=-1)]
    p = ax - np.sum(ax * m, -1, keepdims=True) * m
    return _unit(p)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


ELLIPSE_MARGIN = 0.05  # |n . m| must exceed sin(half-angle) by this much


def _cuts_ellipse(n, m, r0, r1, h):
    """Whether planes of normal n cut the cones (axis m, radii r0 -> r1 over h) in ellipses."""
    k = (r1 - r0) / np.where(h > 0, h, 1.0)
    return np.abs(np.sum(n * m, -1)) > np.abs(k) / np.sqrt(1.0 + k * k) + ELLIPSE_MARGIN


def cutting_planes(j, ma, ca, ra0, ra1, ha, mb, rb0, rb1, hb):
    """Cutting planes at joints ``j`` between segments a (ending at j) and b (starting at j).

    Bhagvat et al. 2009, Eq. 3-5, vectorised over K joints (all arrays have leading K).
    Segment a runs from ``ca`` to ``j`` with radii ``ra0 -> ra1``; b runs from ``j`` along ``mb``
    for ``hb`` with radii ``rb0 -> rb1``. The construction is done in 2D inside the medial plane
    (origin j, axes e1 = ma, e2 = Nm x ma), as the paper suggests.

    Returns ``(n, p)``: unit plane normals with n . (ma + mb) > 0 and a point on each plane.
    Collinear axes (the paper's coordinate-axis fallback) give the plane through j perpendicular
    to the axis, which is the limit of the construction; side lines that are parallel (A or B
    at infinity), or a plane that would not cut both cones in ellipses (``_cuts_ellipse``),
    fall back to the bisector plane through j.
    """
    cr = np.cross(ma, mb)
    sin = np.linalg.norm(cr, axis=-1)
    collinear = sin < _COLLINEAR_SIN
    nm = np.where(collinear[:, None], _any_perp(ma), cr / np.maximum(sin, 1e-300)[:, None])
    e1 = ma
    e2 = np.cross(nm, ma)
    # 2D coordinates (origin j) of the axis directions and the joints
    da = np.stack([np.ones_like(sin), np.zeros_like(sin)], -1)
    db = np.stack([np.sum(mb * e1, -1), np.sum(mb * e2, -1)], -1)
    ca2 = np.stack([np.sum((ca - j) * e1, -1), np.sum((ca - j) * e2, -1)], -1)
    cb2 = db * hb[:, None]

    def side(d):  # M x Nm in 2D (Nm is +z of the 2D frame)
        return np.stack([d[:, 1], -d[:, 0]], -1)

    sa, sb = side(da), side(db)
    zero = np.zeros_like(ca2)

    def meet(sign):
        # Eq. 4: L = C - r (M x Nm) on the left (sign=+1) or + r on the right (sign=-1)
        l1 = ca2 - sign * ra0[:, None] * sa
        l2 = zero - sign * ra1[:, None] * sa
        l3 = zero - sign * rb0[:, None] * sb
        l4 = cb2 - sign * rb1[:, None] * sb
        d1 = l2 - l1
        d2 = l4 - l3
        den = _cross2(d1, d2)
        s = _cross2(l3 - l1, d2) / np.where(den == 0, 1.0, den)
        pt = l1 + s[:, None] * d1
        scale = np.linalg.norm(d1, axis=-1) * np.linalg.norm(d2, axis=-1)
        ok = np.abs(den) > 1e-9 * scale
        return pt, ok

    a2, oka = meet(+1.0)
    b2, okb = meet(-1.0)
    ab = a2 - b2
    ab3 = ab[:, :1] * e1 + ab[:, 1:] * e2
    n = _unit(np.cross(ab3, nm))
    p = j + a2[:, :1] * e1 + a2[:, 1:] * e2
    bis = _unit(ma + mb)
    # a plane must cut each cone in an ellipse (|n . m| above the sine of the cone's half-angle),
    # else the region between the planes is unbounded along a generator (a hyperbolic cut): a
    # strong change of taper with a small bend (a palm leaflet leaving the thick rachis) puts
    # Eq. 3-5's A and B far along the axis and the plane nearly through it. Those joints take
    # the bisector plane.
    fallback = ~(oka & okb) & ~collinear
    fallback |= ~collinear & ~(_cuts_ellipse(n, ma, ra0, ra1, ha) & _cuts_ellipse(n, mb, rb0, rb1, hb))
    n = np.where(fallback[:, None], bis, n)
    p = np.where(fallback[:, None], j, p)
    n = np.where(collinear[:, None], ma, n)
    p = np.where(collinear[:, None], j, p)
    n = n * np.where(np.sum(n * (ma + mb), -1) < 0, -1.0, 1.0)[:, None]
    return n, p


def minor_semi_axis(c1, m, r1, k, n, p, nm):
    """Minor semi-axis of the ellipse cut from the cone (c1, m, r1, slope k) by plane (n, p).

    The major axis lies in the medial plane (normal ``nm``); the minor axis is along ``nm``
    through the ellipse centre. It is found as the half chord of the cut along ``nm`` through
    the centre of the major axis (Sec. 2.2).
    """
    # major axis endpoints: intersect the plane with the two side lines in the medial plane
    s = np.cross(m, nm)
    ends = []
    for sign in (+1.0, -1.0):
        base = c1 - sign * r1[:, None] * s
        dirn = m - sign * k[:, None] * s
        t = np.sum(n * (p - base), -1) / np.sum(n * dirn, -1)
        ends.append(base + t[:, None] * dirn)
    cm = 0.5 * (ends[0] + ends[1])
    y = np.sum((cm - c1) * m, -1)
    rad = cm - c1 - y[:, None] * m
    dperp2 = np.sum(rad * rad, -1)
    return np.sqrt(np.maximum((r1 + k * y) ** 2 - dperp2, 0.0))


def build_frusta(
    joints: np.ndarray,
    radii: np.ndarray,
    topo: Topology,
    twist_turns: float = 0.0,
    match_minor_axes: bool = False,
    match_tol: float = 1e-10,
    match_iters: int = 100,
) -> tuple[FrustaArrays, dict]:
    """Build every segment's frustum; returns (arrays, info) with info on minor-axis matching."""
    s0, s1 = topo.seg_start, topo.seg_end
    ns = s0.shape[0]
    c1 = joints[s0].copy()
    c2 = joints[s1]
    h = np.linalg.norm(c2 - c1, axis=-1)
    m = (c2 - c1) / h[:, None]
    r1 = radii[s0].copy()
    r2 = radii[s1].copy()
    # defaults: perpendicular planes at both ends, capped
    nb = m.copy()
    db = np.zeros(ns)
    nt = m.copy()
    dt = h.copy()
    cap_b = np.ones(ns, bool)
    cap_t = np.ones(ns, bool)
    info = {"minor_axis_iterations": 0, "minor_axis_mismatch": 0.0}

    cont = np.nonzero(topo.parent_seg >= 0)[0]  # segments b that continue a
    order = cont[np.argsort(topo.depth[cont], kind="stable")]
    levels = np.unique(topo.depth[order]) if order.size else []

    def planes_for(bs):
        a = topo.parent_seg[bs]
        return cutting_planes(
            joints[s0[bs]], m[a], c1[a], r1[a], r2[a], h[a], m[bs], r1[bs], r2[bs], h[bs]
        )

    for lvl in levels:  # host loop over depth levels; vectorised within a level
        bs = order[topo.depth[order] == lvl]
        a = topo.parent_seg[bs]
        n, p = planes_for(bs)
        if match_minor_axes:
            cr = np.cross(m[a], m[bs])
            sin = np.linalg.norm(cr, axis=-1)
            nm = np.where((sin < _COLLINEAR_SIN)[:, None], _any_perp(m[a]), cr / np.maximum(sin, 1e-300)[:, None])
            for it in range(match_iters):
                ka = (r2[a] - r1[a]) / h[a]
                kb = (r2[bs] - r1[bs]) / h[bs]
                ba = minor_semi_axis(c1[a], m[a], r1[a], ka, n, p, nm)
                bb = minor_semi_axis(c1[bs], m[bs], r1[bs], kb, n, p, nm)
                mis = np.abs(ba - bb) / np.maximum(ba, 1e-300)
                info["minor_axis_iterations"] = max(info["minor_axis_iterations"], it)
                if np.all(mis <= match_tol):
                    break
                ratio = np.where(bb > 0, ba / np.where(bb > 0, bb, 1.0), 1.0)
                r1[bs] = r1[bs] * ratio
                n, p = planes_for(bs)
            info["minor_axis_mismatch"] = max(info["minor_axis_mismatch"], float(np.max(mis)) if mis.size else 0.0)
        nt[a] = n
        dt[a] = np.sum(n * (p - c1[a]), -1)
        cap_t[a] = False
        nb[bs] = n
        db[bs] = np.sum(n * (p - c1[bs]), -1)
        cap_b[bs] = False

    # frames, in depth order: roots get a fixed reference, side branches parallel-transport the
    # frame of the segment they grow from, continuations pass through Q (Sec. 2.3)
    w = np.zeros((ns, 3))
    u_off = np.zeros(ns)
    v_off = np.zeros(ns)
    twist = np.full(ns, float(twist_turns))
    for lvl in np.unique(topo.depth):
        ss = np.nonzero(topo.depth == lvl)[0]
        bp = topo.branch_parent[ss]
        ref = np.where((bp >= 0)[:, None], w[np.maximum(bp, 0)], np.array([0.0, 0.0, 1.0]))
        wr = ref - np.sum(ref * m[ss], -1, keepdims=True) * m[ss]
        nrm = np.linalg.norm(wr, axis=-1)
        wr = np.where((nrm > 1e-6)[:, None], wr / np.maximum(nrm, 1e-300)[:, None], _any_perp(m[ss]))
        a = topo.parent_seg[ss]
        is_c = a >= 0
        if np.any(is_c):
            sc, ac = ss[is_c], a[is_c]
            k = (r2[ac] - r1[ac]) / h[ac]
            base = c1[ac] + r1[ac][:, None] * w[ac]
            dirn = m[ac] + k[:, None] * w[ac]
            den = np.sum(nt[ac] * dirn, -1)
            y = (dt[ac] - np.sum(nt[ac] * (base - c1[ac]), -1)) / np.where(den == 0, 1.0, den)
            q = base + y[:, None] * dirn
            wq = q - c1[sc]
            wq = wq - np.sum(wq * m[sc], -1, keepdims=True) * m[sc]
            nq = np.linalg.norm(wq, axis=-1)
            good = (nq > 1e-9 * (h[sc] + r1[sc])) & (den != 0)
            wc = np.where(good[:, None], wq / np.maximum(nq, 1e-300)[:, None], wr[is_c])
            wr[is_c] = wc
            u_off[sc] = u_off[ac] + twist[ac]
            v_off[sc] = v_off[ac] + 1.0
        w[ss] = wr
    u = np.cross(m, w)
    u_off = np.mod(u_off, 1.0)
    arrays = FrustaArrays(c1, m, u, w, h, r1, r2, nb, db, nt, dt, cap_b, cap_t, u_off, twist, v_off)
    return arrays, info
