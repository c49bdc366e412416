"""``jskel.compile.host_eval``: JAX functions evaluated by NumPy from their jaxprs, against XLA's own
evaluation of the same functions (an independent implementation of every primitive's
semantics), and the frusta build that now hands XLA no program."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from jskel.compile.host_eval import HostFn


def _floats(x, y, i, j):
    """Elementwise float and integer primitives, with XLA's integer division and remainder
    (toward zero) on negative operands."""
    return dict(
        arith=(x + y, x - y, x * y, x / (y + 3.0), jnp.maximum(x, y), jnp.minimum(x, y), -x, jnp.abs(x)),
        trans=(jnp.sqrt(jnp.abs(x)), jnp.sin(x), jnp.cos(x), jnp.arctan2(x, y), jnp.exp(-x * x), jnp.log1p(jnp.abs(y)),
               jnp.floor(x), jnp.ceil(x), jnp.sign(x), jnp.round(x * 3.0), lax.rsqrt(jnp.abs(x) + 1.0), jnp.tanh(y),
               x ** 3, jnp.fmod(x, 0.7), jnp.clip(x, -0.5, 0.5), jnp.isfinite(x / y)),
        ints=(i // jnp.where(j == 0, 1, j), lax.div(i, jnp.where(j == 0, 1, j)), lax.rem(i, jnp.where(j == 0, 1, j)),
              i * j, i - j, jnp.left_shift(i.astype(jnp.uint32), 3), lax.shift_right_logical(i, jnp.full_like(i, 2)),
              jnp.right_shift(i, 1), i & j, i | j, i ^ j, ~i, (i > j) & (x > 0), ~(i > j)),
        conv=(x.astype(jnp.int32), (x > 0).astype(jnp.float32), i.astype(jnp.float64)),
        cmp=(x < y, x <= y, x == y, x != y, x >= y),
    )


def _shapes(x, i):
    """Shape, index and reduction primitives: gathers and scatters of ``x[idx]`` and ``.at``
    forms (in and out of bounds, each mode), sort with a second operand, loops, conditionals,
    contractions."""
    m = x.reshape(4, 6)
    idx = jnp.abs(i[:5]) % 4
    far = jnp.array([0, 3, 7, -9])
    return dict(
        gather=(m[idx], m[:, idx % 6], m[idx, idx], m.at[far].get(mode="fill", fill_value=-1.0),
                m.at[far].get(mode="clip"), jnp.take(x, far, mode="wrap")),
        scatter=(m.at[idx].set(9.0), m.at[idx].add(1.0), m.at[:, idx].min(-2.0), m.at[far].max(5.0, mode="drop"),
                 m.at[far, 1].set(3.0, mode="drop"), x.at[i % 24].multiply(2.0)),
        sort=lax.sort((i % 3, x[: i.shape[0]]), num_keys=1),
        reduce=(m.sum(0), m.max(1), m.min(), jnp.prod(m[:2], 1), jnp.argmin(m, 1), jnp.argmax(m, 0),
                jnp.all(m > -5, 0), jnp.any(m > 1, 1), jnp.cumsum(m, 1), lax.cumsum(m, 0, reverse=True)),
        layout=(m.T, m[::2, 1:5], jnp.concatenate([m, m * 2], 1), jnp.stack([x, x], 1), m[None, :, 2], jnp.flip(m, 1),
                jnp.broadcast_to(m[:, None, :], (4, 2, 6)), jnp.arange(5) * 2, lax.dynamic_slice(m, (i[0] % 7, 9), (2, 3)),
                lax.dynamic_update_slice(m, jnp.ones((2, 2)), (3, -4))),
        dot=(m @ m.T, jnp.einsum("ij,kj->ik", m, m), jnp.einsum("bij,bjk->bik", m.reshape(2, 2, 6), m.reshape(2, 6, 2))),
        control=(lax.fori_loop(0, i[1] % 5 + 2, lambda k, c: c * 0.5 + k, m[0]),
                 lax.cond(x[0] > 0, lambda v: v * 2.0, lambda v: v - 1.0, m[1]),
                 lax.switch(jnp.abs(i[2]) % 3, [lambda v: v, lambda v: v + 1, lambda v: -v], m[2]),
                 lax.while_loop(lambda c: c[0] < 5, lambda c: (c[0] + 1, c[1] * 1.5), (0, x[3]))[1]),
    )


def _check(got, want):
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape
        if np.issubdtype(a.dtype, np.inexact):
            np.testing.assert_allclose(a, b, rtol=1e-12 if a.dtype == np.float64 else 2e-6, atol=1e-300, equal_nan=True)
        else:
            np.testing.assert_array_equal(a, b)


def test_every_primitive_of_two_functions_as_xla_evaluates_it(rng):
    with jax.enable_x64(True):
        x, y = rng.normal(size=24) * 3.0, rng.normal(size=24)
        y[3] = 0.0  # x / 0 and an atan2 on an axis
        i, j = rng.integers(-20, 20, size=24), rng.integers(-6, 6, size=24)
        for fn, args in ((_floats, (x, y, i, j)), (_floats, (x.astype(np.float32), y.astype(np.float32), i.astype(np.int32), j.astype(np.int32))),
                         (_shapes, (x, i))):
            _check(HostFn(fn)(*args), jax.jit(fn)(*args))


def test_static_arguments_and_one_trace_per_shape(rng):
    calls = []

    def fn(a, n):
        calls.append(1)
        return jnp.tile(a, n) * 2.0

    f = HostFn(fn, static_argnums=(1,))
    a = rng.normal(size=3).astype(np.float32)
    np.testing.assert_array_equal(f(a, 2), np.tile(a, 2) * 2.0)
    f(a + 1.0, 2)
    assert len(calls) == 1  # new values, the same trace
    f(a, 3)
    assert len(calls) == 2


def test_a_primitive_without_a_rule_is_an_error_naming_it():
    with pytest.raises(NotImplementedError, match="'erf_inv'"):
        HostFn(lambda v: lax.erf_inv(v))(np.zeros(3, np.float32))


def test_the_frusta_build_hands_xla_no_program(rng):
    """A branched skeleton's float64 geometry and BVH: NumPy's evaluation of
    ``_geometry.frusta_fields`` equals XLA's jitted one to 1e-12 of the skeleton's size, and
    building it hands XLA nothing (``jskel.compile.cache.program_counts``)."""
    from jskel import frusta
    from jskel.compile.cache import count_programs, program_counts
    from jskel.frusta import _build
    from jskel.frusta._geometry import frusta_fields, padded_topology
    from jskel.frusta._skeleton import topology

    j = np.array([[0, 0, 0], [0, 1, 0], [0.3, 2, 0.1], [-0.8, 2.2, 0.3], [0.4, 3.1, -0.2], [1.2, 2.4, 0.5]], float)
    j = j + 0.05 * rng.normal(size=j.shape)
    r = np.array([0.3, 0.25, 0.2, 0.12, 0.15, 0.1])
    p = np.array([-1, 0, 1, 1, 2, 2])
    topo = topology(j, p, "skeleton")
    ptopo = padded_topology(topo, 32, np)
    ptopo = ptopo._replace(by_level=np.concatenate([ptopo.by_level, np.full((16 - ptopo.by_level.shape[0], ptopo.by_level.shape[1]), 32, np.int32)]))
    args = (np.concatenate([j, np.zeros((26, 3))]), np.concatenate([r, np.zeros(26)]), ptopo, np.float64(0.1), np.int32(topo.depth.max() + 1), None)
    with jax.enable_x64(True):
        got, want = HostFn(frusta_fields)(*args), jax.jit(frusta_fields)(*args)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype
        if a.dtype == np.float64:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * 3.0)
        else:
            np.testing.assert_array_equal(a, b)
    from jskel.compile import events

    def handed(jj, rr, pp):
        """Programs handed to XLA (compiled or loaded) while building (jj, rr, pp), and their names."""
        count_programs()
        before, names = program_counts(), {k: list(v) for k, v in events._by_name.items()}
        _build.build_frusta(jj * 1.01, rr, topology(jj, pp, "skeleton"))
        frusta.build(frusta.FrustaConfig.model_validate(
            {"type": "frusta", "skeleton": {"joints": (jj * 0.99).tolist(), "radii": rr.tolist(), "parents": pp.tolist()}, "accel": "bvh"}))
        after = program_counts()
        return after["compiled"] + after["loaded"] - before["compiled"] - before["loaded"], {
            k for k, v in events._by_name.items() if names.get(k) != v}

    n, names = handed(j, r, p)
    if n:  # the count is the process's: once in a full run one program landed in it from elsewhere. A build
        # that used XLA hands it a program again for a skeleton of new shapes (a 40-joint chain), so the test
        # still fails then
        chain = np.cumsum(np.full((40, 3), [0.05, 0.2, 0.0]), axis=0)
        n2, names2 = handed(chain, np.full(40, 0.1), np.arange(-1, 39))
        assert n2 == 0, (names, names2)


def _traced(calls):
    def fn(a, b):
        calls.append(1)
        return {"sum": a + b, "scaled": a * jnp.sum(b)}

    fn.__qualname__ = fn.__name__ = "traced_for_test"  # a module-level name: stored values need a stable key
    return fn


def test_a_value_is_stored_and_read_back_untraced_and_new_values_compute(store, rng):
    """With a cache directory in use, a fresh HostFn (a new process's) reads the result of the
    same arguments back without tracing, bit for bit; other argument values are computed (and
    equal NumPy's arithmetic written here)."""
    calls = []
    a, b = rng.normal(size=5), rng.normal(size=5)
    first = HostFn(_traced(calls))(a, b)
    again = HostFn(_traced(calls))(a, b)
    assert len(calls) == 1 and len(list(store.glob("*.jxv"))) == 1
    for k in ("sum", "scaled"):
        np.testing.assert_array_equal(first[k], again[k])
    other = HostFn(_traced(calls))(a, b + 1.0)
    assert len(calls) == 2
    np.testing.assert_allclose(other["scaled"], a * np.sum(b + 1.0), rtol=1e-6)


def test_a_slow_evaluation_is_compiled_when_asked_again(monkeypatch, rng):
    """An evaluation over ``COMPILE_AFTER_S`` hands XLA the program the next time (counted by
    ``jskel.compile.cache``), which gives what NumPy gave; a fast one never does."""
    from jskel.compile import host_eval
    from jskel.compile.cache import count_programs, program_counts

    count_programs()
    a, b = rng.normal(size=7).astype(np.float32), rng.normal(size=7).astype(np.float32)
    fast = HostFn(_traced([]))
    for _ in range(3):
        n0 = program_counts()["compiled"] + program_counts()["loaded"]
        fast(a, b)
        assert program_counts()["compiled"] + program_counts()["loaded"] == n0
    monkeypatch.setattr(host_eval, "COMPILE_AFTER_S", -1.0)
    slow = HostFn(_traced([]))
    by_numpy = slow(a, b)
    n0 = program_counts()["compiled"] + program_counts()["loaded"]
    by_xla = slow(a, b)
    assert program_counts()["compiled"] + program_counts()["loaded"] == n0 + 1
    for k in ("sum", "scaled"):
        np.testing.assert_allclose(by_xla[k], by_numpy[k], rtol=1e-6)


def test_evaluations_that_add_up_to_the_threshold_are_compiled(monkeypatch, rng):
    """Evaluations each under ``COMPILE_AFTER_S`` whose seconds add up past it (an animation
    building the same shapes every frame) hand XLA the program after the one that crosses it: on
    a clock that advances 0.05 s a reading, each evaluation takes 0.05 s, so with a 0.12 s
    threshold the first three are NumPy's and the fourth compiles; a program of other shapes
    starts its own count."""
    import types

    from jskel.compile import host_eval
    from jskel.compile.cache import count_programs, program_counts

    now = [0.0]

    def tick():
        now[0] += 0.05
        return now[0]

    monkeypatch.setattr(host_eval, "time", types.SimpleNamespace(perf_counter=tick))
    monkeypatch.setattr(host_eval, "COMPILE_AFTER_S", 0.12)
    count_programs()
    a, b = rng.normal(size=5).astype(np.float32), rng.normal(size=5).astype(np.float32)
    fn = HostFn(_traced([]))
    seen = []
    for i in range(4):  # new values each frame, as an animation's (a stored value is never read back)
        n0 = program_counts()["compiled"] + program_counts()["loaded"]
        out = fn(a + i, b)
        seen.append(program_counts()["compiled"] + program_counts()["loaded"] - n0)
        np.testing.assert_allclose(out["scaled"], (a + i) * np.sum(b), rtol=1e-6)
    assert seen == [0, 0, 0, 1]
    n0 = program_counts()["compiled"] + program_counts()["loaded"]
    fn(a[:3], b[:3])  # other shapes: NumPy again
    assert program_counts()["compiled"] + program_counts()["loaded"] == n0

