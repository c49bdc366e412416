"""Wavefront compaction: run a function only on the rays that need it.

Under ``vmap`` a per-ray ``lax.cond`` becomes a ``select`` that evaluates both branches, so
masking an effect costs as much as tracing every ray. :func:`compact_map` gathers the rays that
need the work into dense sub-batches, runs only as many as there are such rays, and scatters
the results back.
"""

from __future__ import annotations

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
    (``accel._bins.first_set``), not ``jnp.nonzero``'s prefix sum over N."""
    from .accel import first_set, pack_bits

    n = need.shape[0]
    lanes = min(lanes, n)
    order, count = first_set(pack_bits(need), n)
    order = jnp.concatenate([jnp.minimum(order, n - 1), jnp.zeros((lanes,), jnp.int32)])

    def body(state):
        j, acc = state
        lane = j * lanes + jnp.arange(lanes, dtype=jnp.int32)
        idx = jax.lax.dynamic_slice(order, (j * lanes,), (lanes,))
        out = fn(jax.tree_util.tree_map(lambda a: a[idx], rays))
        dst = jnp.where(lane < count, idx, n)  # n: dropped by the scatter
        acc = jax.tree_util.tree_map(lambda a, o: a.at[dst].set(o.astype(a.dtype), mode="drop"), acc, out)
        return j + 1, acc

    return jax.lax.while_loop(lambda st: st[0] * lanes < count, body, (jnp.int32(0), base))[1]
