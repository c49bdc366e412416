"""``wavefront.refill_loop``: persistent lanes refilled as their items finish."""

import numpy as np


def test_refill_loop_emits_every_item_once_after_its_own_iterations(rng):
    """Items that take 0 to 40 iterations each (a countdown), fewer lanes than items and rounds
    of 3 iterations: every item of ``order[:count]`` is emitted exactly once, after exactly its
    own number of iterations, and no item past ``count`` is."""
    import jax
    import jax.numpy as jnp

    from jskel.wavefront import refill_loop

    n_items, count, lanes = 40, 37, 8
    need = rng.integers(0, 41, n_items)
    order = rng.permutation(n_items).astype(np.int32)
    need_j = jnp.asarray(need, jnp.int32)

    def start(items):
        return items, (need_j[items], jnp.zeros_like(items))  # (remaining, taken)

    def advance(ctx, st):
        left, taken = st
        go = left > 0
        return jnp.where(go, left - 1, left), jnp.where(go, taken + 1, taken)

    def emit(acc, items, ctx, st, fin):
        seen, iters = acc
        dst = jnp.where(fin, items, n_items)
        return seen.at[dst].add(1, mode="drop"), iters.at[dst].set(st[1], mode="drop")

    acc0 = (jnp.zeros(n_items, jnp.int32), jnp.full(n_items, -1, jnp.int32))
    padded = jnp.concatenate([jnp.asarray(order), jnp.zeros(lanes, jnp.int32)])
    run = jax.jit(lambda o: refill_loop(start, advance, lambda st: st[0] == 0, emit, o, count, lanes, 3, acc0))
    seen, iters = map(np.asarray, run(padded))
    done = np.zeros(n_items, bool)
    done[order[:count]] = True
    np.testing.assert_array_equal(seen, done.astype(int))
    np.testing.assert_array_equal(iters[done], need[done])
    assert np.all(iters[~done] == -1)
