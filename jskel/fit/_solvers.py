"""The solver adapter: one small interface over jaxopt and optax (issue 10).

jaxopt is no longer maintained upstream; it is used here for Levenberg-Marquardt and
Gauss-Newton on residuals behind :func:`make`, so another library can replace it by adding an
entry. L-BFGS is the project's own (``_lbfgs``: jaxopt's, with its zoom line search, wrote the
loss into its program about eight times). Every solver is driven the same way:

    step = make(name, residuals, loss, maxiter, tol)   # a Stepper; residuals(x, *args), loss(x, *args)
    state = step.init(x0, *args)
    x, state = step.update(x, state, *args)            # one iteration (the caller jits it)
    step.error(state)                                  # the solver's own stopping measure
    step.value(state)                                  # the loss at the state's point (None: not held)

which lets the caller record the loss after every iteration (the fit's loss curve) and stop on
the solver's criterion or its own; ``jskel.fit._fit.run_to_end`` wraps the same update in one
``while_loop`` (``vmap`` of it fits many problems at once).

``residuals(x, *args) -> (M,)`` are already robust (see :func:`robust_residuals`);
``loss(x, *args)`` is half their sum of squares, the quantity every solver decreases; ``args``
(the points) are traced, so new points of the same shape reuse the compiled solver.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _lbfgs


def robust_residuals(r, kind: str, scale):
    """Residuals whose half sum of squares is the robust loss: ``l2``: r; ``huber``: the
    residual of Huber's loss (quadratic within ``scale``, linear beyond); ``cauchy``:
    ``scale^2 log(1 + (r/scale)^2)``; ``geman_mcclure``: ``scale^2 x / (1 + x)``, ``x = (r/scale)^2``
    (bounded: redescending, needs a start within a few ``scale`` of the surface). Written as r times a weight that is 1 near zero, so the
    map is smooth at r = 0 (a sign(r) sqrt(loss) form has an infinite slope there)."""
    if kind == "l2":
        return r
    x2 = (r / scale) ** 2
    if kind == "huber":
        # 0.5 rho^2 = huber(r) = 0.5 r^2 (|r| <= s), s |r| - 0.5 s^2 beyond: rho = r sqrt(2 s/|r| - s^2/r^2)
        big = x2 > 1.0
        w2 = jnp.where(big, 2.0 / jnp.sqrt(jnp.where(big, x2, 1.0)) - 1.0 / jnp.where(big, x2, 1.0), 1.0)
        return r * jnp.sqrt(w2)
    if kind == "cauchy":
        small = x2 < 1e-6
        w2 = jnp.where(small, 1.0 - 0.5 * x2, jnp.log1p(x2) / jnp.where(small, 1.0, x2))
        return r * jnp.sqrt(w2)
    if kind == "geman_mcclure":
        # 0.5 rho^2 = 0.5 s^2 x2 / (1 + x2): bounded by s^2 / 2, so a point far away costs the
        # same wherever the surface is (Cauchy's log keeps rewarding a surface that reaches
        # towards outliers: on a 50-segment chain with 5 % outliers L-BFGS grew a 6-unit spike)
        return r * jax.lax.rsqrt(1.0 + x2)
    raise ValueError(f"solver.loss: unknown robust loss {kind!r} (l2, huber, cauchy, geman_mcclure)")


class Stepper(NamedTuple):
    init: Callable  # (x0, *args) -> state
    update: Callable  # (x, state, *args) -> (x, state)
    error: Callable  # state -> the solver's stopping measure
    value: Callable | None = None  # state -> the loss at the state's point, where the state holds it
    blank: Callable | None = None  # x0 -> a state one update turns into the initial state at x0 (no iteration counted)


SOLVERS = ("lm", "gauss_newton", "lbfgs", "adam")


class AdamState(NamedTuple):
    """State of the ``adam`` stepper (module level: a state returned by one stepper is the input
    type of another's compiled update, so its class must be the same)."""

    opt: object
    error: jnp.ndarray
    iter_num: jnp.ndarray


DAMPING_MAX = 2.0**32  # as jaxopt's cap on mu (and on nu)


class NormalState(NamedTuple):
    """State of :func:`normal_solver`: the loss, J^T r, J^T J at the current point, the damping
    (mu, and nu, its growth after a rejected step), the stopping measure ||J^T r||."""

    value: jnp.ndarray
    gradient: jnp.ndarray
    jtj: jnp.ndarray
    damping: jnp.ndarray
    increase: jnp.ndarray
    error: jnp.ndarray
    iter_num: jnp.ndarray


def normal_solver(system: Callable, damped: bool = True, tau: float = 1e-6, clip: Callable | None = None) -> Stepper:
    """Levenberg-Marquardt (``damped``) or Gauss-Newton on supplied normal equations:
    ``system(x, *args) -> (r, J^T J, J^T r)`` (assembled from the problem's sparsity, ``_normal``,
    or from a dense Jacobian, ``_problem.dense_equations``); the loss is ``|r|^2 / 2``.

    The same algorithm as jaxopt's ``LevenbergMarquardt`` (Madsen, Nielsen and Tingleff 2004,
    Sec. 3.2 and Algorithm 3.16, as jaxopt implements it): step ``(J^T J + mu I) h = -J^T r`` by
    Cholesky; gain ratio ``rho = (F(x) - F(x + h)) / (h^T (mu h - J^T r) / 2)``; accepted when
    ``rho > 0``, then ``mu *= max(1/3, 1 - (2 rho - 1)^3)``, ``nu = 2``; else ``mu *= nu``,
    ``nu *= 2``; ``mu`` starts at ``tau max diag(J^T J)``. Gauss-Newton takes every step with
    ``mu`` fixed at ``1e-9 max diag(J^T J)`` (a ridge that keeps the factorisation defined where
    J^T J is singular, as jaxopt's conjugate gradients are).

    The program holds the system once: an update evaluates it at the trial point (its ``r`` is
    the trial's loss) and keeps it or the old one by the gain ratio (a rejected step costs a
    system instead of a loss; an accepted one a system instead of a loss and a system). The
    initial state is one update from :func:`blank <Stepper>`'s state (``iter_num`` -1: a zero
    step, always taken, ``mu`` set from the new J^T J), so the host loop compiles one program
    where an ``init`` of its own was a second program holding the system again.

    ``clip(x, h) -> h``: the step shortened unknown by unknown before it is tried (the fit's
    ``solver.step_limit``, ``_fit.step_clip``); the gain ratio then divides by the model's own
    predicted decrease, ``-(h . J^T r + h . J^T J h / 2)``, which equals the form above for an
    unclipped step."""

    def blank(x0):
        p, dt = x0.shape[-1], x0.dtype
        z = np.zeros((p,), dt)
        return NormalState(np.asarray(np.inf, dt), z, np.zeros((p, p), dt), np.asarray(1.0, dt), np.asarray(2.0, dt),
                           np.asarray(np.inf, dt), np.int32(-1))

    def update(x, st, *args):
        fresh = st.iter_num < 0  # from blank: h = 0, taken, mu from the system at x
        a = st.jtj + st.damping * jnp.eye(x.shape[-1], dtype=x.dtype)
        h = -jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), st.gradient)
        if clip is None:
            predicted = 0.5 * jnp.dot(h, st.damping * h - st.gradient)
        else:
            h = clip(x, h)
            predicted = -(jnp.dot(h, st.gradient) + 0.5 * jnp.dot(h, st.jtj @ h))
        xn = x + h
        r, jtj, g = system(xn, *args)
        ln = 0.5 * jnp.sum(r * r)
        rho = (st.value - ln) / predicted
        # (a clipped step need not descend: one the model itself says raises the loss is refused)
        ok = fresh | (jnp.isfinite(ln) & (rho > 0) & (predicted > 0)) if damped else jnp.asarray(True)
        start = (tau if damped else 1e-9) * jnp.max(jnp.diagonal(jtj))
        grown = st.damping * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3) if damped else st.damping
        two = jnp.asarray(2.0, x.dtype)
        new = NormalState(ln, g, jtj, jnp.where(fresh, start, grown), two, jnp.sqrt(jnp.sum(g * g)), st.iter_num + 1)
        old = st._replace(damping=jnp.minimum(st.damping * st.increase, DAMPING_MAX),
                          increase=jnp.minimum(2.0 * st.increase, DAMPING_MAX), iter_num=st.iter_num + 1)
        keep = lambda n, o: jnp.where(ok, n, o)  # noqa: E731
        return keep(xn, x), jax.tree_util.tree_map(keep, new, old)

    def init(x0, *args):
        return update(x0, blank(x0), *args)[1]

    return Stepper(init, update, lambda st: st.error, lambda st: st.value, blank)


def make(name: str, residuals: Callable, loss: Callable, maxiter: int, tol: float, learning_rate: float = 0.01,
         dense: bool = True, normal: Callable | None = None, clip: Callable | None = None) -> Stepper:
    """A :class:`Stepper` for solver ``name`` (``lm``, ``gauss_newton``, ``lbfgs``, ``adam``).

    ``normal``: for ``lm`` and ``gauss_newton``, ``normal(x, *args) -> (r, J^T J, J^T r)``
    supplied by the caller (:func:`normal_solver`; the fit's are ``_problem.dense_equations``
    and the sparse ``_normal``); without it jaxopt's solvers run on ``residuals`` (the fit's
    ``solver.jacobian: jaxopt``, kept as the reference the project's solver is checked
    against). ``dense``: jaxopt's Levenberg-Marquardt forms the Jacobian (forward mode) and
    solves its normal equations by Cholesky; otherwise it runs matrix-free conjugate gradients
    on J^T J products. On the 24-unknown chain the matrix-free form took several times as long
    to compile as the dense one (docs/choices.md#lm-dense). ``clip``: :func:`normal_solver`'s."""
    if normal is not None and name in ("lm", "gauss_newton"):
        return normal_solver(normal, damped=name == "lm", clip=clip)
    if name == "lbfgs":
        init, update = _lbfgs.lbfgs(loss)
        return Stepper(init, update, lambda st: st.error, lambda st: st.value)
    if name in ("lm", "gauss_newton"):
        import warnings

        with warnings.catch_warnings():  # "JAXopt is no longer maintained": known, hence this adapter
            warnings.simplefilter("ignore", DeprecationWarning)
            import jaxopt

        if name == "lm":
            kw = {"materialize_jac": True, "solver": "cholesky"} if dense else {}
            s = jaxopt.LevenbergMarquardt(residual_fun=residuals, maxiter=maxiter, tol=tol, xtol=tol, gtol=tol, jit=True, **kw)
        else:
            s = jaxopt.GaussNewton(residual_fun=residuals, maxiter=maxiter, tol=tol, jit=True)
        return Stepper(s.init_state, s.update, lambda st: st.error, lambda st: st.value)
    if name == "adam":
        import optax

        opt = optax.adam(learning_rate)
        grad = jax.grad(loss)

        def init(x0, *args):
            return AdamState(opt.init(x0), jnp.asarray(jnp.inf, x0.dtype), jnp.int32(0))

        def update(x, st, *args):
            g = grad(x, *args)
            upd, o = opt.update(g, st.opt, x)
            err = jnp.sqrt(jnp.sum(g * g))
            return optax.apply_updates(x, upd), AdamState(o, err, st.iter_num + 1)

        return Stepper(init, update, lambda st: st.error)
    raise ValueError(f"solver.name: unknown solver {name!r} ({', '.join(SOLVERS)})")
