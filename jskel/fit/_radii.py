"""The radii again, with the joints fixed (``solver.radii_refit``, issue 53): a robust linear
least-squares problem solved exactly after the solver stops.

Between two joints the frusta surface is the cone through the joints' circles (Bhagvat et al.
2009, Sec. 2.1): at axial parameter ``u`` (0 at the parent joint a, 1 at the child c) its
radius is ``(1 - u) r_a + u r_c``. A point at distance ``rho`` from the axis lies
``rho - (1 - u) r_a - u r_c`` from it along the radius, which is linear in the radii. With each
point on its nearest segment (``_topology.nearest_segments``: the cone's distance, the ends'
discs beyond the ends) and the joints held where the solver left them, the radii that minimise
the fit's robust loss of those offsets solve a sparse system (each point couples the two
radii of its segment) by iteratively reweighted least squares: each pass weights a point by
its loss's ``psi(e) / e`` at its current offset (``l2``: 1; ``huber``: ``min(1, s / |e|)``;
``cauchy``: ``1 / (1 + (e / s)^2)``; ``geman_mcclure``: ``1 / (1 + (e / s)^2)^2``) and by
``solver.outside`` where the point lies outside, the fit's own weights. Points beyond a
segment's ends (``u`` outside [0, 1]: a tip's cap, the far side of a joint's plane) are left
out; a joint that few points reach keeps about its radius (a pull towards it worth ``HOLD``
points at the joint). The nearest segments are chosen again from the new radii
``ROUNDS`` times.

Why: on the 1,000-segment chain of ``experiments/bench_fit.yaml`` (100,000 points, noise sd
0.05 on radii 0.25-0.5, 5 % outliers, every radius 10 % off at the start) LM with the cover term
stops with the radii near their start (median error 6.9 %, 19 % of them within 5 %; their
errors correlate 0.87 with the start's), since its one damping for all unknowns grows until no
radius moves (docs/fitting.md). The joints are right by then (within 0.04 % of the length), and
the radii given the joints are a linear problem that needs no damping."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ._topology import nearest_segments

ROUNDS = 2  # the nearest segments chosen again from the new radii this many times
PASSES = 6  # reweighted solves per round
#: a joint's pull towards its current radius, in points of mean weight at the joint: without it a
#: joint that only a few points near its segment's far end reach (a tip whose segment has no
#: points of its own, beside which the parent's points spill past the joint) got a radius
#: extrapolated from them, 10 times the truth in the test; the pull is towards the previous pass's
#: radius, so for a joint that many points determine it slows the passes and leaves no bias
HOLD = 1.0


def irls_weights(e: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """``psi(e) / e`` of the fit's robust loss ``loss`` at scale ``scale`` (module docstring)."""
    if loss == "l2":
        return np.ones_like(e)
    x2 = (e / scale) ** 2
    if loss == "huber":
        return np.minimum(1.0, scale / np.maximum(np.abs(e), 1e-300))
    if loss == "cauchy":
        return 1.0 / (1.0 + x2)
    if loss == "geman_mcclure":
        return 1.0 / (1.0 + x2) ** 2
    raise ValueError(f"solver.loss: unknown robust loss {loss!r} (l2, huber, cauchy, geman_mcclure)")


def refit_radii(points, joints, radii, parents, loss: str, scale: float, outside: float = 1.0, min_radius: float = 0.0) -> np.ndarray:
    """(J,) radii that minimise the robust loss of the points' radial offsets from the cones of
    ``joints`` (fixed), starting from ``radii``; float64 on the host. ``scale`` and
    ``min_radius`` in world units."""
    pts = np.asarray(points, np.float64)
    joints, par = np.asarray(joints, np.float64), np.asarray(parents)
    r = np.asarray(radii, np.float64).copy()
    n_j = len(joints)
    for _ in range(ROUNDS):
        c, _ = nearest_segments(pts, joints, r, par)
        a = par[c]
        ab = joints[c] - joints[a]
        x = pts - joints[a]
        u = np.einsum("ij,ij->i", x, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        rho = np.linalg.norm(x - u[:, None] * ab, axis=1)
        keep = (u >= 0.0) & (u <= 1.0)
        u, rho, a, c = u[keep], rho[keep], a[keep], c[keep]
        if not len(u):
            return r
        rows = np.concatenate([a, c, a, c])
        cols = np.concatenate([a, c, c, a])
        for _ in range(PASSES):
            e = rho - ((1.0 - u) * r[a] + u * r[c])
            w = irls_weights(e, loss, scale) * np.where(e > 0, outside, 1.0)
            m = sp.coo_matrix((np.concatenate([w * (1 - u) ** 2, w * u * u, w * u * (1 - u), w * u * (1 - u)]), (rows, cols)),
                              shape=(n_j, n_j)).tocsc()
            g = np.bincount(a, w * (1 - u) * rho, n_j) + np.bincount(c, w * u * rho, n_j)
            hold = HOLD * max(float(np.mean(w)), 1e-300)
            r = spla.spsolve(m + hold * sp.identity(n_j, format="csc"), g + hold * r)
            r = np.maximum(r, min_radius)
    return r
