"""Wavefront compaction: run a function only on the rays that need it.

Under ``vmap`` a per-ray ``lax.cond`` becomes a ``select`` that evaluates both branches, so
masking an effect costs as much as tracing every ray. :func:`compact_map` gathers the rays that
need the work into dense sub-batches, runs only as many as there are such rays, and scatters
the results back.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp

from .rays import Rays


def compact_map(fn: Callable, need: jnp.ndarray, rays: Rays, base, lanes: int):
    """``base`` with the entries where ``need`` (N,) holds replaced by ``fn(rays_sub)``, where
    ``fn`` maps a Rays batch of ``lanes`` rays to a pytree like ``base``'s rows. ``rays`` may
    be any pytree of arrays with leading axis N (``fn`` then gets the same pytree of ``lanes``
    rows).

    Compaction, not masking (wavefront style): the needed rays are gathered into dense
    sub-batches of ``lanes`` and a ``while_loop`` runs only as many sub-batches as there are
    needed rays (none when none is needed), then the results are scattered back. Under vmap a
    per-ray ``cond`` would run ``fn`` on every ray. The needed rows are found with popcounts
    (``accel._bins.first_set``), not ``jnp.nonzero``'s prefix sum over N.

    Derivatives in both modes, ``jax.grad`` included: a ``while_loop`` whose trip count is data
    cannot be reversed, so under differentiation (a ``custom_jvp``) the same sub-batches run in
    a loop of static length ceil(N / lanes) whose sub-batches past the count are a ``lax.cond``
    that skips them (a ``scan``, which JAX transposes); without a derivative the program is the
    ``while_loop`` alone. ``fn`` may close over traced values (``jax.closure_convert`` hoists
    them into arguments, so their derivatives flow too)."""
    from .accel import first_set, pack_bits

    n = need.shape[0]
    lanes = min(lanes, n)
    order, count = first_set(pack_bits(need), n)
    order = jnp.concatenate([jnp.minimum(order, n - 1), jnp.zeros((lanes,), jnp.int32)])
    fn_c, consts = jax.closure_convert(fn, jax.tree_util.tree_map(lambda a: a[:lanes], rays))
    return _compact(fn_c, lanes, order, count, consts, rays, base)


def _loop(fn: Callable, lanes: int, order, count, consts, rays, base, static_length: bool):
    """The sub-batches of :func:`compact_map`: a ``while_loop`` over the needed ones, or (for
    derivatives) a loop of static length that skips the rest by a ``lax.cond``."""
    n = order.shape[0] - lanes

    def step(j, acc):
        lane = j * lanes + jnp.arange(lanes, dtype=jnp.int32)
        idx = jax.lax.dynamic_slice(order, (j * lanes,), (lanes,))
        out = fn(jax.tree_util.tree_map(lambda a: a[idx], rays), *consts)
        dst = jnp.where(lane < count, idx, n)  # n: dropped by the scatter
        return jax.tree_util.tree_map(lambda a, o: a.at[dst].set(o.astype(a.dtype), mode="drop"), acc, out)

    if static_length:
        def body(j, acc):
            return jax.lax.cond(j * lanes < count, step, lambda _, a: a, j, acc)

        return jax.lax.fori_loop(0, -(-n // lanes), body, base)
    return jax.lax.while_loop(lambda st: st[0] * lanes < count, lambda st: (st[0] + 1, step(*st)), (jnp.int32(0), base))[1]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _compact(fn: Callable, lanes: int, order, count, consts, rays, base):
    return _loop(fn, lanes, order, count, consts, rays, base, False)


@_compact.defjvp
def _compact_jvp(fn: Callable, lanes: int, primals, tangents):
    order, count = primals[:2]
    return jax.jvp(lambda c, r, b: _loop(fn, lanes, order, count, c, r, b, True), primals[2:], tangents[2:])
