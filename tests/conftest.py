"""Shared test helpers. Tests stay in float32 (the default); x64 is never switched on here.

Compile time dominates on 2 cores, so every frusta test casts rays through the same two
module-level functions (``interface.intersect``, ``interface.intersect_each``): skeletons are padded to one block of 64 segments and rays are evaluated
in chunks of 8192, so the shapes never change between tests.
"""

from __future__ import annotations

import os

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".jax_cache"))
# every program is written to it, as the CLI writes them (``cache.MIN_COMPILE_S``), not only those
# over JAX's default second: the two workers and the CLI, sweep and notebook subprocesses compile
# many of the same small programs (the builds' pieces, the executor's)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# jskel's own cache directory (precomputed cell objects, ``cache: auto``) in the checkout, not the
# user's home; compiled programs stay in JAX's folder above
os.environ.setdefault("JSKEL_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".jskel_cache"))
# one CPU device, as the tests' shapes assume (jskel would otherwise make one per core; the
# sharding tests force their own count); subprocesses inherit it
os.environ.setdefault("JSKEL_HOST_DEVICES", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jskel import frusta  # noqa: E402
from jskel.interface import Object, intersect, intersect_each  # noqa: E402
from jskel.rays import make_rays  # noqa: E402
from jskel.executor import map_chunks  # noqa: E402

CHUNK = 8192


def batch_fn(culled):
    """The module-level batch query ``(Object, rays) -> Hit``: the representation's batch
    (``culled``) or ``vmap`` of one ray; the static options ride in the ``Object`` pytree, so
    each static setting compiles once without a cache of closures here."""
    return intersect if culled else intersect_each


def frusta_object(built):
    """A frusta build as the ``Object`` pytree the batch queries take."""
    return Object(built.params, built.static, "frusta")


def build_skeleton(joints, radii, parents, offset=(0.0, 0.0, 0.0), **kw):
    cfg = frusta.FrustaConfig.model_validate(
        {"type": "frusta", "skeleton": {"joints": np.asarray(joints, float).tolist(), "radii": list(map(float, radii)),
                                         "parents": list(map(int, parents)), "offset": list(offset)}, **kw}
    )
    return frusta.build(cfg)


def whole_chunks(fn, obj, rays, chunk=CHUNK):
    """``map_chunks(fn, obj, rays, chunk)``'s output, with a batch of fewer than ``chunk`` rays
    padded to one whole chunk (its last ray repeated, as the executor pads a last chunk) and the
    padding cut off again. The executor itself pads a small batch only to its size bucket, so
    tests casting 39 and 8,000 rays through the same object would compile two programs; this
    way every cast of one static configuration and table shape shares one. A ray's result
    never depends on the other rays of its batch (the packet and bins tests check that against
    brute force), so the padding changes nothing."""
    n = rays.size
    if n < chunk:
        idx = np.minimum(np.arange(chunk), n - 1)
        rays = jax.tree_util.tree_map(lambda a: np.asarray(a)[idx], rays)
    out = map_chunks(fn, obj, rays, chunk=chunk, progress=False).out
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], out)


def cast(built, O, D, t_min=0.0, t_max=np.inf, culled=False):
    """Cast float64 world rays (O, D) against ``built``; returns a NumPy Hit in world units."""
    O = np.asarray(O, np.float64) - built.anchor
    out = whole_chunks(batch_fn(culled), frusta_object(built), make_rays(O, D, t_min, t_max))
    return out._replace(position=np.asarray(out.position, np.float64) + built.anchor)


def random_tree(rng, n, lift=0.3, length=0.8, r_max=0.3):
    """A random branching skeleton of n joints (each joint's parent drawn among the earlier
    ones, steps of ``length`` leaning up by ``lift``): (joints (n,3), radii (n,), parents)."""
    joints, parents = [np.zeros(3)], [-1]
    for i in range(1, n):
        par = int(rng.integers(0, i))
        step = rng.normal(size=3)
        step[1] = abs(step[1]) + lift
        joints.append(joints[par] + length * step / np.linalg.norm(step))
        parents.append(par)
    return np.array(joints), rng.uniform(0.05, r_max, n), np.array(parents)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def assert_hits_agree(a, b, rtol: float = 0.0):
    """Two casts of the same rays (NumPy Hits): the same hits and misses, t equal (``rtol`` 0)
    or within ``rtol`` (programs that XLA fuses apart may round differently), and the same
    primitive wherever t does not tie within that tolerance."""
    h = np.isfinite(a.t)
    np.testing.assert_array_equal(h, np.isfinite(b.t))
    if rtol == 0.0:
        np.testing.assert_array_equal(a.t, b.t)
    else:
        np.testing.assert_allclose(b.t[h], a.t[h], rtol=rtol, atol=0)
    same = a.prim == b.prim
    assert np.all(same[~h])
    assert np.all(same[h] | (np.abs(a.t[h] - b.t[h]) <= rtol * a.t[h]))  # another id only on a tie


@pytest.fixture
def store(tmp_path):
    """A fresh private directory of stored executables and values in use for the test
    (``jskel.compile.executables``), the previous one restored after."""
    from jskel.compile import executables

    before = executables._state["dir"]
    d = executables.use_dir(tmp_path / "x")
    yield d
    executables._state["dir"] = before
