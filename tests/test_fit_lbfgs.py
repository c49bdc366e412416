"""The fit's L-BFGS (``jskel/fit/_lbfgs.py``): closed-form minima, the Wolfe conditions on its
steps, and one evaluation of the loss in its program (what keeps the fit's program small)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

from jskel.fit._lbfgs import C1, C2, lbfgs


def _run(loss, x, n):
    init, update = lbfgs(loss)
    upd = jax.jit(update)
    st = init(x)
    states = [(x, st)]
    for _ in range(n):
        x, st = upd(x, st)
        states.append((x, st))
    return states


def rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


def test_reaches_closed_form_minima_and_every_step_meets_the_wolfe_conditions():
    """A linear least-squares problem (truth: NumPy's float64 lstsq) and Rosenbrock's function in
    four variables (minimum at ones); every step that moved meets sufficient decrease and the
    strong curvature condition, checked here in float64 from the iterates; once steepest
    descent finds no decrease (float32's floor, at the minimum), iterations evaluate nothing."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(30, 4)), rng.normal(size=30)
    want = np.linalg.lstsq(a, b, rcond=None)[0]
    a32, b32 = jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)
    x, st = _run(lambda x: 0.5 * jnp.sum((a32 @ x - b32) ** 2), jnp.zeros(4, jnp.float32), 15)[-1]
    np.testing.assert_allclose(np.asarray(x), want, atol=1e-4)

    states = _run(rosenbrock, jnp.asarray([-1.2, 1.0, -1.2, 1.0], jnp.float32), 80)
    np.testing.assert_allclose(np.asarray(states[-1][0]), np.ones(4), atol=2e-3)

    def f64(x):  # Rosenbrock and its gradient in float64, written out
        x = np.asarray(x, np.float64)
        g = np.zeros_like(x)
        g[:-1] = -400.0 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2.0 * (1.0 - x[:-1])
        g[1:] += 200.0 * (x[1:] - x[:-1] ** 2)
        return np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2), g

    checked = 0
    for (x0, _), (x1, _) in zip(states[:-1], states[1:]):
        s = np.asarray(x1, np.float64) - np.asarray(x0, np.float64)
        (f0, g0), (f1, g1) = f64(x0), f64(x1)
        if np.linalg.norm(s) < 1e-5 or np.linalg.norm(g0) < 1e-2:  # float32 noise near the minimum
            continue
        assert f1 <= f0 + C1 * (g0 @ s) + 1e-5 * abs(f0)  # sufficient decrease (step a times direction is s)
        assert abs(g1 @ s) <= C2 * abs(g0 @ s) * 1.01 + 1e-5  # strong curvature
        checked += 1
    assert checked > 15
    first = next(i for i, (_, st) in enumerate(states) if bool(st.stuck))
    assert first < 70 and {int(st.evals) for _, st in states[first:]} == {int(states[first][1].evals)}
    assert all(np.array_equal(np.asarray(x), np.asarray(states[first][0])) for x, _ in states[first:])


def _count(jaxpr, name):
    n = 0
    for e in jaxpr.eqns:
        n += e.primitive.name == name
        for p in e.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, jcore.ClosedJaxpr):
                    n += _count(sub.jaxpr, name)
                elif isinstance(sub, jcore.Jaxpr):
                    n += _count(sub, name)
    return n


def test_one_iteration_evaluates_the_loss_at_one_place_in_its_program():
    """A loss whose only ``sin`` is its own: an iteration's program holds one ``sin`` (the line
    search's single evaluation, in its loop body), not one per phase of the search."""
    init, update = lbfgs(lambda x: jnp.sum(jnp.sin(x) + x * x))
    x = jnp.ones(3, jnp.float32)
    jaxpr = jax.make_jaxpr(update)(x, init(x))
    assert _count(jaxpr.jaxpr, "sin") == 1
