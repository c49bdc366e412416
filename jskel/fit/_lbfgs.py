"""L-BFGS whose line search evaluates the loss and its gradient at one place in the program.

jaxopt's ``LBFGS`` (zoom line search) writes the loss and its gradient into its program at
about eight places: the search's first iteration is unrolled before its loop, and both copies
hold separate evaluations for the bracketing phase, the zoom phase and a safeguarded step
(``jaxopt/_src/zoom_linesearch.py``). For the fit, whose loss carries the cutting-plane
geometry of every joint, that made one program of two L-BFGS starts about 41,500 jaxpr
equations, whose XLA compile took over twice as long as this module's program for the same solve
(docs/choices.md#lbfgs-one-evaluation). Here the search is the same algorithm, strong
Wolfe conditions by bracketing and zoom (Nocedal and Wright 2006, *Numerical Optimization*,
2nd ed., Alg. 3.5 and 3.6, cubic interpolation Eq. 3.59, safeguarded by bisection), written as
a state machine: every pass of one ``while_loop`` evaluates the loss and gradient once at the
trial step and only scalar logic decides the next trial. The direction is the two-loop
recursion (Alg. 7.4) over the last ``history`` pairs, scaled by ``s.y / y.y`` (Eq. 7.20); a
pair whose curvature ``s.y`` is not positive is not stored. The search returns the lowest
point it found that meets the sufficient-decrease condition; if none (``maxls`` trials, or
the bracket narrowed until its next trial is that point in floating point), the iterate stays
and the history is cleared, so the next iteration tries steepest descent. Where steepest
descent found no decrease either, the point is a minimum to the loss's precision and later
iterations evaluate nothing (``stuck``): on the fit's recovery test the searches that failed
there had cost 20 evaluations each, 200 of 260 on that fit, while the fit's ``patience``
counted its stalled iterations.

Why not a maintained library's: optax 0.2.8's ``lbfgs`` (``scale_by_zoom_linesearch``) evaluates
the loss and gradient at two places in its search loop (``_search_interval`` and
``_zoom_into_interval``, chosen by ``lax.cond``, which runs both branches once the fit vmaps
over starts) and once more in ``value_and_grad_from_state``; jaxopt's ``backtracking`` search
unrolls its first iteration as the zoom does and only shrinks the step, so it cannot restore
the curvature condition. Both were judged from their source, not measured; the program sizes
that chose this one are ``tests/scripts/fit_programs.py``'s.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

C1, C2 = 1e-4, 0.9  # sufficient decrease and curvature constants (Nocedal and Wright, Sec. 3.1)


class LbfgsState(NamedTuple):
    """The loss and gradient at the iterate, the last pairs (s, y, 1 / s.y; newest last, 1 / s.y
    zero in unused rows), the stopping measure ||grad||, iterations, the search's trials, and
    whether steepest descent from the iterate found no decrease."""

    value: jnp.ndarray
    grad: jnp.ndarray
    s: jnp.ndarray
    y: jnp.ndarray
    rho: jnp.ndarray
    error: jnp.ndarray
    iter_num: jnp.ndarray
    evals: jnp.ndarray
    stuck: jnp.ndarray


class _Search(NamedTuple):
    """The line search's state: ``lo`` the lowest sufficient-decrease point so far (step, value,
    slope, point, gradient), ``hi`` the other end of the bracket once ``zoom`` (step, value,
    slope), the next trial step, trials made, and whether the Wolfe conditions held."""

    a_lo: jnp.ndarray
    f_lo: jnp.ndarray
    d_lo: jnp.ndarray
    x_lo: jnp.ndarray
    g_lo: jnp.ndarray
    a_hi: jnp.ndarray
    f_hi: jnp.ndarray
    d_hi: jnp.ndarray
    zoom: jnp.ndarray
    a: jnp.ndarray
    i: jnp.ndarray
    done: jnp.ndarray


def direction(g, s, y, rho):
    """``-H g`` by the two-loop recursion (Nocedal and Wright, Alg. 7.4); rows with ``rho`` 0
    contribute nothing."""
    def back(q, syr):
        si, yi, ri = syr
        al = ri * jnp.dot(si, q)
        return q - al * yi, al

    q, al = jax.lax.scan(back, g, (s, y, rho), reverse=True)
    yy = jnp.dot(y[-1], y[-1])
    gamma = jnp.where((rho[-1] > 0) & (yy > 0), jnp.dot(s[-1], y[-1]) / jnp.where(yy > 0, yy, 1.0), 1.0)

    def fwd(r, syra):
        si, yi, ri, ai = syra
        return r + si * (ai - ri * jnp.dot(yi, r)), None

    r, _ = jax.lax.scan(fwd, gamma * q, (s, y, rho, al))
    return -r


def _trial(lo_a, lo_f, lo_d, hi_a, hi_f, hi_d):
    """The cubic's minimiser between the bracket's ends (Nocedal and Wright, Eq. 3.59), or the
    midpoint where it is not finite or within a tenth of the bracket of either end."""
    d1 = lo_d + hi_d - 3.0 * (lo_f - hi_f) / (lo_a - hi_a)
    disc = d1 * d1 - lo_d * hi_d
    d2 = jnp.sign(hi_a - lo_a) * jnp.sqrt(jnp.maximum(disc, 0.0))
    a = hi_a - (hi_a - lo_a) * (hi_d + d2 - d1) / (hi_d - lo_d + 2.0 * d2)
    w = jnp.abs(hi_a - lo_a)
    ok = jnp.isfinite(a) & (disc >= 0) & (jnp.abs(a - lo_a) > 0.1 * w) & (jnp.abs(a - hi_a) > 0.1 * w)
    return jnp.where(ok, a, 0.5 * (lo_a + hi_a))


def _search_step(vg, x, p, f0, d0, st: _Search, *args) -> _Search:
    """One trial of the line search: the loss and gradient at ``x + a p`` (the one evaluation),
    then Alg. 3.5's bracketing or Alg. 3.6's zoom on scalars."""
    f, g = vg(x + st.a * p, *args)
    d = jnp.dot(g, p)
    worse = (f > f0 + C1 * st.a * d0) | ~jnp.isfinite(f) | ((f >= st.f_lo) & (st.zoom | (st.i > 0)))
    done = ~worse & (jnp.abs(d) <= -C2 * d0)
    flip = ~worse & ~done & jnp.where(st.zoom, d * (st.a_hi - st.a_lo) >= 0, d >= 0)
    to_lo = ~worse  # the trial is the new lowest sufficient-decrease point
    hi = (jnp.where(worse, st.a, jnp.where(flip, st.a_lo, st.a_hi)), jnp.where(worse, f, jnp.where(flip, st.f_lo, st.f_hi)),
          jnp.where(worse, d, jnp.where(flip, st.d_lo, st.d_hi)))
    lo = (jnp.where(to_lo, st.a, st.a_lo), jnp.where(to_lo, f, st.f_lo), jnp.where(to_lo, d, st.d_lo))
    zoom = st.zoom | worse | flip
    a_next = jnp.where(zoom, _trial(*lo, *hi), 2.0 * st.a)
    return _Search(lo[0], lo[1], lo[2], jnp.where(to_lo, x + st.a * p, st.x_lo), jnp.where(to_lo, g, st.g_lo),
                   hi[0], hi[1], hi[2], zoom, a_next, st.i + 1, done)


def lbfgs(loss: Callable, history: int = 10, maxls: int = 20) -> "tuple[Callable, Callable]":
    """(init, update) of L-BFGS on ``loss(x, *args)`` (x a flat vector), as the solver adapter
    drives them (``_solvers.Stepper``)."""
    vg = jax.value_and_grad(loss)

    def init(x0, *args):
        f, g = vg(x0, *args)
        z = jnp.zeros((history, x0.shape[-1]), x0.dtype)
        return LbfgsState(f, g, z, z, jnp.zeros((history,), x0.dtype), jnp.sqrt(jnp.dot(g, g)), jnp.int32(0), jnp.int32(1),
                          jnp.asarray(False))

    def update(x, st: LbfgsState, *args):
        p = direction(st.grad, st.s, st.y, st.rho)
        d0 = jnp.dot(st.grad, p)
        fresh = ~(d0 < 0)  # not a descent direction (a stale history): steepest descent
        p = jnp.where(fresh, -st.grad, p)
        d0 = jnp.where(fresh, -jnp.dot(st.grad, st.grad), d0)
        empty = fresh | ~jnp.any(st.rho > 0)
        a0 = jnp.where(empty, jnp.minimum(1.0, 1.0 / jnp.sqrt(-d0)), 1.0).astype(x.dtype)
        zero = jnp.zeros((), x.dtype)
        s0 = _Search(zero, st.value, d0, x, st.grad, zero, st.value, d0, jnp.asarray(False), a0, jnp.int32(0), jnp.asarray(False))
        limit = jnp.where(st.stuck, 0, maxls)

        def more(c):  # not done, trials left, and the next trial is not the lowest point again
            return ~c.done & (c.i < limit) & ~jnp.all(x + c.a * p == c.x_lo)

        ls = jax.lax.while_loop(more, lambda c: _search_step(vg, x, p, st.value, d0, c, *args), s0)
        moved = ls.a_lo > 0
        sk, yk = ls.x_lo - x, ls.g_lo - st.grad
        sy = jnp.dot(sk, yk)
        keep = moved & (sy > 1e-10 * jnp.sqrt(jnp.dot(sk, sk) * jnp.dot(yk, yk)))

        def push(h, v):
            return jnp.where(keep, jnp.concatenate([h[1:], v[None]]), jnp.where(moved, h, jnp.zeros_like(h)))

        rho = push(st.rho, jnp.where(keep, 1.0 / jnp.where(keep, sy, 1.0), 0.0))
        g = ls.g_lo
        return ls.x_lo, LbfgsState(ls.f_lo, g, push(st.s, sk), push(st.y, yk), rho, jnp.sqrt(jnp.dot(g, g)), st.iter_num + 1, st.evals + ls.i,
                                   ~moved & empty)

    return init, update
