"""The fit's normal equations and the solver that uses them (issue 10): J^T J and J^T r
assembled from each point's one segment and each segment's four joints, and those of the dense
solver's one linearization, equal those of the dense Jacobian; the colouring keeps every
dependency set apart; the Levenberg-Marquardt and Gauss-Newton steps on supplied normal
equations solve closed-form problems, from an initial state that is one update of a blank one.
(That they take jaxopt's Levenberg-Marquardt's steps on a real fit is asserted in
``test_fit``'s recovery test.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jskel.fit import perturbed, segments_of
from jskel.fit._bench import bent_chain
from jskel.fit._config import SolverConfig
from jskel.fit._cover import SAMPLES
from jskel.fit._fit import data_of, on_device
from jskel.fit._problem import dense_equations, normal_equations, normaliser_of, problem_of, residuals
from jskel.fit._normal import structure
from jskel.fit._solvers import normal_solver

from conftest import random_tree


def _problem(j, r, p, n, candidates, seed, smoothness=0.1, validity=1.0, cover=0.0):
    from jskel.fit import sample_surface

    rng = np.random.default_rng(seed)
    pts = sample_surface(j, r, p, n, rng)
    pts = pts + rng.normal(0, 0.05, pts.shape)
    k = n // 20
    pts[:k] = rng.uniform(pts.min(0) - 1, pts.max(0) + 1, (k, 3))  # outliers
    seg = segments_of(j, r, p)
    pr = problem_of(seg, SolverConfig(loss="cauchy", smoothness=smoothness, validity=validity, candidates=candidates, cover=cover))
    nz = normaliser_of(pts)
    j0, r0 = perturbed(j, r, np.asarray(p), 0.1, rng)
    return pr, jnp.asarray(nz.start(j0, r0, pr), jnp.float32), on_device(data_of(nz.points(pts), pr, np.float32, seg))


def _branching_chain():
    """The bent 12-segment chain with a side branch of two segments at joints 3, 6 and 9 (each
    leaving at a right angle to the chain, radii 0.2 then 0.12): branch points, continuations
    and side branches that start capped, in one skeleton."""
    j, r, p = bent_chain(12, 0)
    joints, radii, parents = list(j), list(r), list(p)
    for k in (3, 6, 9):
        axis = j[k + 1] - j[k]
        side = np.cross(axis, [0.3, 0.2, 1.0])
        side /= np.linalg.norm(side)
        for step, radius in ((1, 0.2), (2, 0.12)):
            joints.append(j[k] + 0.7 * step * side)
            radii.append(radius)
            parents.append(k if step == 1 else len(joints) - 2)
    return np.array(joints), np.array(radii), np.array(parents)


def test_sparse_normal_equations_equal_the_dense_jacobians():
    """A bent 12-segment chain with three side branches (side branches start capped), each point
    against its 4 nearest segments: r, J^T J and J^T r from the sparse assembly against the
    dense forward-mode Jacobian of the same residuals, with the smoothness and plane-validity
    rows in (the assembly takes each point's gradient on its winning segment alone, so a
    gradient it missed would show here), and the rows of the term from the surface back to the
    points (``solver.cover``; each on one segment's 17 numbers). (One skeleton holds the chain
    and the branches: each case compiled two programs of about 16 s on the 2-core CPU.) The
    same system with the topology padded (:func:`_padding_leaves_the_normal_equations_unchanged`)."""
    j, r, p = _branching_chain()
    pr, x, pts = _problem(j, r, p, 1200, 4, 1, cover=0.5)
    assert pr.sizes.conts >= 3 and pr.sizes.conts < pr.sizes.segments - 1
    (rr, jtj, g) = jax.jit(lambda x: normal_equations(x, pts, pr))(x)
    # the reference, dense forward mode, as one compiled program (run op by op it took twice the
    # compile time of the program, on 2 cores)
    rd, jac, dense = jax.jit(lambda x: (residuals(x, pts, pr), jax.jacfwd(lambda x: residuals(x, pts, pr))(x),
                                        dense_equations(x, pts, pr)))(x)
    jac = np.asarray(jac, np.float64)
    assert np.count_nonzero(np.abs(jac[-5 * pr.sizes.conts:]).sum(1)) > 0  # penalty rows are live
    cover_rows = jac[1200 : 1200 + SAMPLES * pr.sizes.segments]
    # cover rows are live: those beyond the dead zone (5 of 288 at this start; 16 while each
    # sample measured four blocks, which missed nearer points for some)
    assert np.count_nonzero(np.abs(cover_rows).sum(1)) >= 4
    want = jac.T @ jac
    want_g = jac.T @ np.asarray(rd, np.float64)
    # each entry against its own scale, sqrt(|want_ii want_jj|) (Cauchy-Schwarz bounds the entry
    # by it): one tolerance from the largest entry (4e7 here, a plane-validity row's) hid an
    # error of 0.6 in entries of order 10 (the fenced rows in _normal.normal_equations)
    d = np.sqrt(np.abs(np.diag(want)))
    tol = 2e-4 * np.outer(d, d) + 1e-5
    for got in ((rr, jtj, g), dense):  # the sparse assembly, and the dense solver's one linearization
        np.testing.assert_allclose(np.asarray(got[0]), np.asarray(rd), atol=1e-6)
        err = np.abs(np.asarray(got[1], np.float64) - want)
        assert np.all(err <= tol), (np.unravel_index(np.argmax(err / tol), err.shape), err.max())
        np.testing.assert_allclose(np.asarray(got[2]), want_g, atol=2e-5 * np.abs(want_g).max())
    _padding_leaves_the_normal_equations_unchanged(j, r, p, pr, x, pts, (rr, jtj, g))


def _padding_leaves_the_normal_equations_unchanged(j, r, p, pr, x, pts, exact):
    """The topology as data, padded (``_problem.Sizes`` larger than the skeleton's: 3 joints, 3
    segments, 2 continuations and 3 colours more): the residuals, J^T J and J^T r are the
    unpadded ones at the real rows and unknowns and zero elsewhere (the padding segments lie far
    away and own no point, though each point's 4 candidates could have reached them; the cover
    weight counts the real segments only; a weight from the padded count fails this)."""
    from jskel.fit._problem import Sizes, layout_of, problem_of as problem

    seg = segments_of(j, r, p)
    sz = pr.sizes
    big = problem(seg, SolverConfig(loss="cauchy", smoothness=0.1, validity=1.0, candidates=4, cover=0.5), sz.joints,
                  Sizes(*(a + b for a, b in zip(sz, (3, 3, 2, 3)))))
    nj, nb, n = sz.joints, big.sizes.joints, len(pts.points)
    xb = jnp.concatenate([x[: 3 * nj], jnp.zeros(9, x.dtype), x[3 * nj :], jnp.zeros(3, x.dtype)])
    data = on_device(jax.tree_util.tree_map(np.asarray, pts._replace(layout=layout_of(seg, big))))
    r_b, a_b, g_b = (np.asarray(a, np.float64) for a in jax.jit(lambda x, d: normal_equations(x, d, big))(xb, data))
    r_e, a_e, g_e = (np.asarray(a, np.float64) for a in exact)
    real = np.concatenate([np.arange(3 * nj), 3 * nb + np.arange(nj)])  # the real joints' unknowns in the padded layout
    rows = np.concatenate([np.arange(n), n + np.arange(SAMPLES * sz.segments),  # points, the real segments' cover rows,
                           n + SAMPLES * big.sizes.segments + np.arange(5 * sz.conts)])  # the real continuations' penalty rows
    assert len(r_b) == n + SAMPLES * big.sizes.segments + 5 * big.sizes.conts
    np.testing.assert_allclose(r_b[rows], r_e, rtol=1e-5, atol=1e-7)
    assert np.all(np.delete(r_b, rows) == 0)
    d = np.sqrt(np.abs(np.diag(a_e)))
    np.testing.assert_array_less(np.abs(a_b[np.ix_(real, real)] - a_e), 1e-5 * np.outer(d, d) + 1e-7)
    np.testing.assert_allclose(g_b[real], g_e, rtol=1e-5, atol=1e-5 * np.abs(g_e).max())
    rest = np.setdiff1d(np.arange(4 * nb), real)
    assert np.all(a_b[rest] == 0) and np.all(a_b[:, rest] == 0) and np.all(g_b[rest] == 0)
    with pytest.raises(ValueError, match="do not fit"):
        layout_of(seg, problem(seg, SolverConfig(), nj, Sizes(nj, sz.segments - 1, sz.conts, sz.colors)))


def test_the_colouring_keeps_every_dependency_set_apart():
    """Each segment's geometry depends on its joints and its continuations' far joints; each
    penalty row on both segments of its continuation: within every set the colours differ,
    and a chain of any length needs 5 colours (20 forward tangents)."""
    for n in (3, 50, 500):
        j, r, p = bent_chain(n, 0)
        st = structure(segments_of(j, r, p), n + 1)
        assert st.n_colors == min(5, n + 1)
        for idx, mask in ((st.seg_joints, st.seg_mask), (st.pen_joints, st.pen_mask)):
            for row, m in zip(idx, mask):
                c = st.colors[row[m]]
                assert len(set(c.tolist())) == len(c)
        # a middle segment depends on 4 joints: the one before it, its own two, the one after
        assert sorted(st.seg_joints[n // 2][st.seg_mask[n // 2]].tolist()) == [n // 2 - 1, n // 2, n // 2 + 1, n // 2 + 2]
    jt, rt, pt = random_tree(np.random.default_rng(3), 30)
    st = structure(segments_of(jt, rt, pt), len(jt))
    for row, m in zip(st.pen_joints, st.pen_mask):
        assert len(set(st.colors[row[m]].tolist())) == int(m.sum())


def _linear_system(a, b):
    def system(x):
        r = a @ x - b
        return r, a.T @ a, a.T @ r

    return system


@pytest.mark.parametrize("damped", [True, False], ids=["lm", "gauss_newton"])
def test_normal_solver_reaches_closed_form_minima(damped):
    """A linear least-squares problem (truth: NumPy's float64 lstsq) and Rosenbrock's function
    as residuals (10 (y - x^2), 1 - x; minimum at (1, 1))."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 4))
    b = rng.normal(size=30)
    want = np.linalg.lstsq(a, b, rcond=None)[0]
    system = _linear_system(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32))
    step = normal_solver(lambda x: system(x), damped=damped)
    x = jnp.zeros(4, jnp.float32)
    st = step.init(x)  # one update from the blank state: a zero step to x, the system there
    res0 = -b  # a @ 0 - b, in float64
    np.testing.assert_allclose(float(st.value), 0.5 * res0 @ res0, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(st.gradient), a.T @ res0, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(float(st.damping), (1e-6 if damped else 1e-9) * np.max(np.diag(a.T @ a)), rtol=1e-5)
    assert int(st.iter_num) == 0 and np.array_equal(np.asarray(step.update(x, step.blank(x))[0]), np.zeros(4))
    upd = jax.jit(step.update)
    for _ in range(8):
        x, st = upd(x, st)
    np.testing.assert_allclose(np.asarray(x), want, atol=2e-5)
    assert float(step.error(st)) < 1e-3

    def ros(x):
        r = jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])
        jac = jnp.stack([jnp.stack([-20.0 * x[0], 10.0]), jnp.stack([-1.0, 0.0])])
        return r, jac.T @ jac, jac.T @ r

    step = normal_solver(ros, damped=damped)
    x = jnp.asarray([-1.2, 1.0], jnp.float32)
    st = step.init(x)
    upd = jax.jit(step.update)
    for _ in range(60):
        x, st = upd(x, st)
    np.testing.assert_allclose(np.asarray(x), [1.0, 1.0], atol=1e-4)


def test_a_clipped_step_still_reaches_the_least_squares_minimum():
    """LM with every component of its step clipped to 0.05 (``normal_solver``'s ``clip``, the
    gain ratio on the model's own predicted decrease) reaches the float64 lstsq minimum of the
    linear problem above, whose unclipped first step is several times longer, and never moves a
    component by more than the clip."""
    from jskel.fit._solvers import normal_solver

    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 4))
    b = rng.normal(size=30) + 3.0
    want = np.linalg.lstsq(a, b, rcond=None)[0]
    assert np.max(np.abs(want)) > 0.2  # the minimum lies several clipped steps away
    step = normal_solver(_linear_system(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)),
                         clip=lambda x, h: jnp.clip(h, -0.05, 0.05))
    x = jnp.zeros(4, jnp.float32)
    st = step.init(x)
    upd = jax.jit(step.update)
    for _ in range(60):
        x_new, st = upd(x, st)
        assert np.max(np.abs(np.asarray(x_new - x))) <= 0.05 + 1e-6
        x = x_new
    np.testing.assert_allclose(np.asarray(x), want, atol=2e-5)
    # a "clip" that turns the step uphill: the model predicts a rise, and LM refuses every step
    # (a gain ratio of a rise over a predicted rise is positive; it once accepted them)
    up = normal_solver(_linear_system(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)), clip=lambda x, h: -h)
    x0 = jnp.zeros(4, jnp.float32)
    st = up.init(x0)
    for _ in range(3):
        x1, st = jax.jit(up.update)(x0, st)
        np.testing.assert_array_equal(np.asarray(x1), np.zeros(4))


def test_the_fit_step_limit_caps_each_joint_and_radius_by_the_joint_radius():
    """``_fit.step_clip``: a joint asked to move 10 radii moves 0.5 radius along the same
    direction, a radius asked to grow by 3 radii grows by 0.5 radius; steps within the limit are
    unchanged (radii 0.2 and 0.4, limit 0.5; the radius parameter is the radius above 0.001)."""
    from jskel.fit._fit import step_clip
    from jskel.fit._problem import problem_of

    j, r, p = np.array([[0.0, 0, 0], [0, 1.0, 0]]), np.array([0.2, 0.4]), np.array([-1, 0])
    pr = problem_of(segments_of(j, r, p), SolverConfig())
    x = jnp.asarray(np.concatenate([j.reshape(-1), r]), jnp.float32)
    h = np.array([2.0, 0.0, 0.0, 0.03, 0.04, 0.0, 1.2, -0.05], np.float32)  # joint 0 by 10 radii, joint 1 by 0.125
    got = np.asarray(jax.jit(step_clip(0.5, pr))(x, jnp.asarray(h)))
    rad = np.asarray(pr.min_radius + 1e-3 * np.log1p(np.exp(r / 1e-3)))  # radii_of, in float64
    np.testing.assert_allclose(got[:3], [0.5 * rad[0], 0.0, 0.0], rtol=1e-5)
    np.testing.assert_allclose(got[3:6], h[3:6], rtol=1e-6)
    np.testing.assert_allclose(got[6:], [0.5 * rad[0], -0.05], rtol=1e-5)
    for bad in ({"name": "lbfgs"}, {"name": "adam"}, {"name": "lm", "jacobian": "jaxopt"}):  # solvers it would not cap
        with pytest.raises(ValueError, match="step_limit: 0.5 caps the steps of lm / gauss_newton"):
            SolverConfig(step_limit=0.5, **bad)
    from jskel.fit._bench import FitBench

    with pytest.raises(ValueError, match=r"step_limit: 0.5 caps .* \(got solvers \['lbfgs'\]"):
        FitBench(step_limit=0.5, solvers=["lm", "lbfgs"])
