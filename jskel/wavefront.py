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


def refill_loop(start: Callable, advance: Callable, done: Callable, emit: Callable, order, count, lanes: int, steps: int, acc):
    """Persistent lanes: the items ``order[:count]`` (int32, padded with at least ``lanes``
    entries) traced by iterations of uneven number, ``lanes`` at a time, each lane refilled with
    the next item as soon as its own finishes. Returns ``acc`` after every item's ``emit``.

    ``start(items) -> (ctx, state)`` sets up a (lanes,) batch of items; ``advance(ctx, state)
    -> state`` is one iteration of every lane (a finished lane's state unchanged);
    ``done(state)`` (lanes,) bool; ``emit(acc, items, ctx, state, finished) -> acc`` folds the
    finished lanes in. Each round runs ``steps`` iterations, then emits and refills (``start``
    on the whole batch, under a ``lax.cond`` that skips it when no lane is free).

    :func:`compact_map` runs each sub-batch until its slowest item is done, so a batch of items
    whose iteration counts differ (the exact relief traversal: 20 on average, over 100 for a
    few) idles most lanes most of the time; here a lane idles only at the very end. Not
    differentiable (a ``while_loop`` of data-dependent length): callers take derivatives
    elsewhere (``accel.nearest_tangent``)."""
    lane = jnp.arange(lanes, dtype=jnp.int32)
    items = order[lane]
    ctx, st = start(items)

    def pick(m, new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(m.reshape(m.shape + (1,) * (a.ndim - 1)), a, b), new, old)

    def body(c):
        head, items, live, ctx, st, acc = c
        st = jax.lax.fori_loop(0, steps, lambda _, s: advance(ctx, s), st)
        fin = live & done(st)
        acc = emit(acc, items, ctx, st, fin)
        slot = head + jnp.cumsum(fin.astype(jnp.int32)) - 1
        take = fin & (slot < count)

        def refill(args):
            items, ctx, st = args
            new = order[jnp.clip(slot, 0, order.shape[0] - 1)]
            ctx_n, st_n = start(new)
            return jnp.where(take, new, items), pick(take, ctx_n, ctx), pick(take, st_n, st)

        items, ctx, st = jax.lax.cond(jnp.any(take), refill, lambda a: a, (items, ctx, st))
        return head + jnp.sum(take, dtype=jnp.int32), items, (live & ~fin) | take, ctx, st, acc

    init = (jnp.minimum(count, lanes).astype(jnp.int32), items, lane < count, ctx, st, acc)
    return jax.lax.while_loop(lambda c: jnp.any(c[2]), body, init)[-1]


PACKET = 64  # rays per packet: 8 x 8 pixels in ``camera.tile_order``'s default tile
LISTED = 64  # leaves a packet's list holds (more: its rays are walked)


def leaves_of(bvh, rays, capacity: int, lanes: int, packets: bool):
    """(leaves (N, capacity) int32, -1 in unused slots; overflow (N,): the ray met more leaves
    than ``capacity``): the leaves of ``bvh`` (``accel.BVH``) that each ray of the batch meets.
    Walked per ray (``accel.collect``), or with ``packets`` through each packet's list
    (``accel.collect_packets``: the same leaves, found by dense box tests instead of a vmapped
    loop), walking only the rays of packets whose list overflowed (:func:`compact_map`). Shared
    by the representations that take every leaf a ray meets: the implicit primitives' culling
    and the frusta's relief shells."""
    from . import accel

    def walk(sub):
        return jax.vmap(lambda o, d, a, b: accel.collect(bvh, o, d, a, b, capacity))(*sub)[::2]

    if not packets:
        return walk(rays)
    leaves, _, over, spill = accel.collect_packets(bvh, *rays, capacity, PACKET, LISTED)
    return compact_map(walk, spill, rays, (leaves, over), lanes)


def leaves_after(bvh, rays, need, capacity: int, skip, lanes: int):
    """(leaves, overflow) as :func:`leaves_of` gives them, for the rays ``need`` (N,) marks
    (the rest: no leaf), each walked past its first ``skip`` leaves (``accel.collect``'s
    ``skip``, may be traced): the continuation of a list that overflowed."""
    from . import accel

    def walk(sub):
        return jax.vmap(lambda o, d, a, b: accel.collect(bvh, o, d, a, b, capacity, skip))(*sub)[::2]

    n = need.shape[0]
    return compact_map(walk, need, rays, (jnp.full((n, capacity), -1, jnp.int32), jnp.zeros((n,), bool)), lanes)
