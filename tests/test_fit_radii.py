"""``solver.radii_refit`` (``jskel.fit._radii``): the radii again by robust linear least squares
with the joints fixed, on the host in float64. Truths written here: points sampled on known
cones (the radii are those cones'), the expectile of a cylinder's radial distances."""

from __future__ import annotations

import numpy as np
import pytest
from fit_truths import expectile, noisy_cylinder

from jskel.fit._radii import irls_weights, refit_radii


def _cone_points(rng, a, b, ra, rb, n, lo=0.05, hi=0.95):
    """``n`` points on the cone through the circles (a, ra) and (b, rb), uniform in the axial
    parameter in [lo, hi] and in angle: (points, their axial parameter)."""
    ax = (b - a) / np.linalg.norm(b - a)
    e1 = np.cross(ax, [0.3, 0.1, 0.9])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ax, e1)
    u, phi = rng.uniform(lo, hi, n), rng.uniform(0, 2 * np.pi, n)
    rad = ra + u * (rb - ra)
    return a + u[:, None] * (b - a) + rad[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2), u


JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 3.6, 0.2], [1.2, 5.4, 0.0]])
RADII = np.array([0.5, 0.4, 0.3, 0.15])
PARENTS = np.array([-1, 0, 1, 2])


def test_exact_radii_of_points_on_the_cones_from_a_start_far_off():
    """Points exactly on a bent 3-segment chain's cones, l2: the radii come back to 0.1 % from a
    start 40 % off (each round's nearest segments from its own radii; what remains is the pull
    towards the start, one point's weight at each joint)."""
    rng = np.random.default_rng(0)
    pts = np.concatenate([_cone_points(rng, JOINTS[PARENTS[c]], JOINTS[c], RADII[PARENTS[c]], RADII[c], 400)[0] for c in (1, 2, 3)])
    got = refit_radii(pts, JOINTS, RADII * np.array([1.4, 0.6, 1.4, 0.6]), PARENTS, "l2", 1.0)
    np.testing.assert_allclose(got, RADII, rtol=1e-3)


@pytest.mark.parametrize("loss", ["huber", "cauchy", "geman_mcclure"])
def test_robust_losses_keep_the_radii_with_outliers(loss):
    """Radial noise 0.005 and 10 % outliers uniform in the chain's box: each robust loss at
    scale 0.01 gives every radius within 1.5 % of the cones' (l2, pulled by the outliers, does
    not), from a start 30 % off."""
    rng = np.random.default_rng(1)
    pts = np.concatenate([_cone_points(rng, JOINTS[PARENTS[c]], JOINTS[c], RADII[PARENTS[c]], RADII[c], 600)[0] for c in (1, 2, 3)])
    pts += rng.normal(0, 0.005, pts.shape)
    k = len(pts) // 10
    lo, hi = pts.min(0) - 0.5, pts.max(0) + 0.5
    pts[rng.choice(len(pts), k, replace=False)] = rng.uniform(lo, hi, (k, 3))
    start = RADII * 1.3
    got = refit_radii(pts, JOINTS, start, PARENTS, loss, 0.01)
    assert np.max(np.abs(got / RADII - 1)) < 0.015, got
    plain = refit_radii(pts, JOINTS, start, PARENTS, "l2", 0.01)
    assert np.max(np.abs(plain / RADII - 1)) > 0.05  # what the outliers do to least squares


def test_a_joint_without_points_keeps_its_radius():
    """The last segment has no points of its own (only a few of its parent's, spilling past the
    joint, reach it): its tip joint's radius stays within 5 % of where it was, not extrapolated
    from those few; the other radii come from their segments' points within 1 % (each pulled
    by one point's weight towards its start)."""
    rng = np.random.default_rng(2)
    pts = np.concatenate([_cone_points(rng, JOINTS[PARENTS[c]], JOINTS[c], RADII[PARENTS[c]], RADII[c], 400)[0] for c in (1, 2)])
    start = RADII * np.array([1.2, 0.8, 1.2, 1.7])
    got = refit_radii(pts, JOINTS, start, PARENTS, "l2", 1.0)
    assert abs(got[3] / start[3] - 1) < 0.05, got
    np.testing.assert_allclose(got[:3], RADII[:3], rtol=1e-2)


def test_an_outside_weight_gives_the_expectile_of_a_cylinder():
    """A cylinder of radius 0.3 with radial noise 0.02: with ``outside`` w the radii are the
    w / (1 + w) expectile of the points' radial distances (w sum (rho - r)+ = sum (r - rho)+,
    found here by bisection), as the fit's own weights give (``test_fit``)."""
    pts, rho = noisy_cylinder()
    for w in (1.0, 16.0):
        want = expectile(rho, w)
        got = refit_radii(pts, np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), np.array([0.5, 0.1]), np.array([-1, 0]), "l2", 1.0, outside=w)
        np.testing.assert_allclose(got, want, rtol=1e-2)
        np.testing.assert_allclose(got.mean(), want, rtol=2e-3)


def test_irls_weights_are_psi_over_e():
    """Each loss's weight against psi(e) / e from the derivative of its loss written here
    (central differences of rho(e) in float64)."""
    s = 0.3
    e = np.array([-2.0, -0.5, -0.1, 0.05, 0.2, 0.7, 3.0])
    losses = {"l2": lambda x: 0.5 * x * x,
              "huber": lambda x: np.where(np.abs(x) <= s, 0.5 * x * x, s * np.abs(x) - 0.5 * s * s),
              "cauchy": lambda x: 0.5 * s * s * np.log1p((x / s) ** 2),
              "geman_mcclure": lambda x: 0.5 * s * s * (x / s) ** 2 / (1 + (x / s) ** 2)}
    h = 1e-6
    for name, rho in losses.items():
        psi = (rho(e + h) - rho(e - h)) / (2 * h)
        np.testing.assert_allclose(irls_weights(e, name, s), psi / e, rtol=1e-6, err_msg=name)
    with pytest.raises(ValueError, match="solver.loss"):
        irls_weights(e, "tukey", s)


def test_nearest_segments_through_the_kd_tree_are_the_exhaustive_search():
    """``_topology.nearest_segments`` from ``NEAR_FROM`` segments on scores each point's
    ``NEAR`` nearest segment centres and falls back to every segment where it cannot certify:
    on a random 300-segment tree with one long thick segment (whose bounding sphere leaves many
    points uncertified) and surface, noisy and far points, the segment and distance are the
    exhaustive argmin over every segment (written here over ``_cone_distances``, the distance
    both use), with and without an ``alive`` mask."""
    from jskel.fit import _topology as T

    rng = np.random.default_rng(5)
    n_j = 301
    parents = np.concatenate([[-1], [rng.integers(0, i) for i in range(1, n_j)]])
    joints = np.zeros((n_j, 3))
    for i in range(1, n_j):
        joints[i] = joints[parents[i]] + rng.normal(0, 1.0, 3)
    radii = rng.uniform(0.05, 0.4, n_j)
    pts = np.concatenate([joints[1:] + rng.normal(0, 0.5, (n_j - 1, 3)), rng.uniform(joints.min(0) - 5, joints.max(0) + 5, (2000, 3))])
    long_j, long_r = joints.copy(), radii.copy()
    long_j[7] = long_j[parents[7]] + np.array([30.0, 0.0, 0.0])  # the long one
    long_r[7] = 3.0
    long_pts = np.concatenate([pts, long_j[parents[7]] + rng.uniform(0, 1, (300, 1)) * (long_j[7] - long_j[parents[7]]) + rng.normal(0, 3.0, (300, 3))])
    assert T.NEAR_FROM <= 300
    for joints, radii, pts, alive in ((joints, radii, pts, None), (long_j, long_r, long_pts, None),
                                      (long_j, long_r, long_pts, rng.uniform(size=n_j) > 0.2)):
        seg, dist = T.nearest_segments(pts, joints, radii, parents, alive=alive)
        child = np.nonzero((parents >= 0) & (True if alive is None else alive))[0]
        a, ab = joints[parents[child]], joints[child] - joints[parents[child]]
        ll = np.sum(ab * ab, 1)
        d = T._cone_distances(pts[:, None, :], a[None], ab[None], ll[None], np.sqrt(ll)[None], radii[parents[child]][None], radii[child][None])
        np.testing.assert_array_equal(dist, d.min(1))
        np.testing.assert_array_equal(seg, child[np.argmin(d, 1)])
