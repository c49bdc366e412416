"""Derivatives of a traversal's nearest hit from its winning primitive (reverse mode included).

A BVH walk is a ``lax.while_loop`` whose trip count depends on the data; JAX differentiates it
in forward mode only (``jax.grad`` raises). Yet the nearest hit's distance depends on the
parameters only through the primitive that won: the walk chooses *which* primitive (a
piecewise-constant choice), the primitive's closed form gives *where*. :func:`nearest_tangent`
therefore keeps the walk for the value and takes the derivative of that closed form at the
winner (as ``numerics.differentiable_root`` keeps a bisection for the value and takes the
implicit-function derivative). The tangent rule is linear in the tangents, so JAX transposes it
and ``jax.grad`` / ``jax.vjp`` work; without a derivative the program is the walk alone.

Rays that missed get a zero derivative without NaN: the closed form is evaluated on inputs
whose tangents are cut there (:func:`hold`, the inner half of the double ``where``), and the
tangent is zeroed there (the outer half).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np


def hold(keep, tree):
    """``tree`` with the derivative of its floating leaves kept only where ``keep`` (broadcast
    over trailing axes); elsewhere the value is unchanged and its tangent is 0. Applied to a
    closed form's *inputs*, it keeps a miss's inf or NaN coefficients out of both modes."""

    def one(a):
        if not jnp.issubdtype(a.dtype, jnp.floating):
            return a
        k = jnp.reshape(keep, jnp.shape(keep) + (1,) * (a.ndim - jnp.ndim(keep)))
        return jnp.where(k, a, jax.lax.stop_gradient(a))

    return jax.tree_util.tree_map(one, tree)


def _zero_tangent(x):
    if jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def nearest_tangent(search: Callable, winner: Callable):
    """``f(params, rays) = search(params, rays)`` with derivatives from ``winner``.

    search(params, rays) -> tuple whose first entry is t (N,) (+inf on a miss), the rest any
      arrays of leading axis N (the winning primitive's index among them): any program, loops
      with data-dependent trip counts included; it is never differentiated.
    winner(params, rays, out) -> tuple of the same length: for each float entry of ``out`` that
      moves with the parameters, its value from the closed form of the winning primitive named
      in ``out`` (differentiable; its value is not used), else None (tangent 0). It should
      :func:`hold` its inputs where ``out`` says the ray missed.

    The derivative of entry k is the ``jax.jvp`` of ``winner``'s entry k, zeroed where t is not
    finite. Both ``params`` and ``rays`` may hold integer leaves (their tangents are float0)."""

    @jax.custom_jvp
    def f(params, rays):
        return search(params, rays)

    @f.defjvp
    def f_jvp(primals, tangents):
        out = search(*primals)
        hit = jnp.isfinite(out[0])
        closed = jax.jvp(lambda p, r: winner(p, r, out), primals, tangents)[1]
        dout = []
        for x, dx in zip(out, closed):
            if dx is None:
                dout.append(_zero_tangent(x))
            else:
                k = jnp.reshape(hit, hit.shape + (1,) * (dx.ndim - hit.ndim))
                dout.append(jnp.where(k, dx, jnp.zeros_like(dx)).astype(x.dtype))
        return out, tuple(dout)

    return f
