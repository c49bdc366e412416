"""A batch of rays in groups: ``lax.map`` over groups, the caller's vmapped function within one.

A vmapped while loop (a BVH walk) runs until its slowest lane ends, so small groups of coherent
rays waste the fewest lanes (``_lbvh``'s docstring has the measurements)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def pad_groups(arrays, g: int):
    """Arrays (N, ...) padded by repeating the last row to a multiple of g, as (N/g, g, ...)."""
    n = arrays[0].shape[0]
    pad = (-n) % g

    def padded(x):
        return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x

    return [padded(a).reshape((-1, g) + a.shape[1:]) for a in arrays]


def map_groups(fn: Callable, group: int, *arrays):
    """``fn(*arrays)`` computed in groups of ``group`` rows (the last padded by repeating its last
    row): ``fn`` takes and returns arrays with a leading group axis (a vmapped function); the
    outputs, a pytree, are cut back to the N rows given."""
    n = arrays[0].shape[0]
    out = jax.lax.map(lambda xs: fn(*xs), tuple(pad_groups(list(arrays), min(group, n))))
    return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:])[:n], out)
