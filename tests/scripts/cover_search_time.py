"""Run by hand (not by the suite): what the cover term's two searches cost an evaluation, on a
chain of 1,000 segments (radius 0.02, steps of 0.1) with 100,000 points on its surface (noise
0.002), the size of bench_fit.yaml's scale case. One process, warm medians of 5, compile apart;
one JSON line per setting:

- ``nearest_grouped``: ``_cover.nearest_points`` as the fit calls it, each segment's 16 samples
  sharing a list of blocks;
- ``nearest_each``: the same function with every sample a group of its own, so each sample
  scores every block (the cost of the search before the per-segment lists);
- ``kept_blocked`` / ``kept_all``: the samples' signed distances to the skeleton (which samples
  count) through the fit's candidate blocks (``_problem.blocks_of``), and against every segment.

Both pairs must agree (the script says whether they do). Then what the number of blocks a
sample measures (``_cover.NEAREST_BLOCKS``, set before compiling) changes: on the chain, the
share of samples whose point with 4 blocks lies further than with 6; on the ring of cones
around a noisy torus of ``tests/test_fit_cover.py``, the samples whose point is not the
nearest (float64 brute force) and by how much.

    python tests/scripts/cover_search_time.py
"""
import json
import statistics
import time

import jax
import numpy as np

from jskel.fit import segments_of
from jskel.fit import _cover
from jskel.fit._config import SolverConfig
from jskel.fit._distance import distances_of, geometry
from jskel.fit._fit import data_of, on_device
from jskel.fit._problem import _data, blocks_of, problem_of, radii_of, unpack


def chain(rng, s=1000, n=100_000):
    steps = rng.normal(size=(s, 3))
    steps[:, 1] += 2.0
    steps /= np.linalg.norm(steps, axis=1, keepdims=True)
    j = np.concatenate([[np.zeros(3)], np.cumsum(steps, 0)]) * 0.1
    seg = rng.integers(0, s, n)
    u, a = rng.uniform(0, 1, n), rng.uniform(0, 2 * np.pi, n)
    m = j[seg + 1] - j[seg]
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    e1 = np.cross(m, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(m, e1)
    c = j[seg] + u[:, None] * (j[seg + 1] - j[seg])
    pts = c + 0.02 * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2) + rng.normal(scale=0.002, size=(n, 3))
    return j, np.arange(-1, s), pts


def torus_misses():
    """(missed, worst excess) of the cover search on test_fit_cover's torus ring, at the
    current ``_cover.NEAREST_BLOCKS`` (a new function each call: jit retraces, reading it again)."""
    from jskel.fit._cover import point_index

    rng = np.random.default_rng(4)
    u, v = rng.uniform(0, 2 * np.pi, (2, 2000))
    pts = np.stack([(1 + 0.3 * np.cos(v)) * np.cos(u), (1 + 0.3 * np.cos(v)) * np.sin(u), 0.3 * np.sin(v)], 1)
    pts += rng.normal(0, 0.005, pts.shape)
    a = np.linspace(0, 2 * np.pi, 25)[:24]
    j = np.stack([np.cos(a), np.sin(a), np.zeros(24)], 1)
    g = geometry(jax.numpy.asarray(j, jax.numpy.float32), jax.numpy.full(24, 0.3, jax.numpy.float32), segments_of(j, np.full(24, 0.3), np.arange(-1, 23)))
    ring = np.asarray(_cover.samples(g), np.float64)
    idx = jax.tree_util.tree_map(jax.numpy.asarray, point_index(pts.astype(np.float32)))
    got = np.asarray(jax.jit(lambda i, r: _cover.nearest_points(i, r))(idx, jax.numpy.asarray(ring, jax.numpy.float32)), np.float64).reshape(-1, 3)
    q = ring.reshape(-1, 3)
    excess = np.linalg.norm(got - q, axis=1) - np.linalg.norm(q[:, None] - pts[None], axis=-1).min(1)
    return int(np.sum(excess > 1e-6)), float(excess.max())


def timed(fn, *args, runs=5):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return out, first, statistics.median(ts)


def main():
    j, parents, pts = chain(np.random.default_rng(0))
    seg = segments_of(j, np.full(len(j), 0.02), parents)
    pr = problem_of(seg, SolverConfig(cover=1.0, block=64))
    data = on_device(data_of(pts, pr, np.float32, seg))
    x = jax.numpy.asarray(np.concatenate([j.reshape(-1), np.full(len(j), 0.02 - pr.min_radius)]), jax.numpy.float32)

    def samples_of(x):
        jo, u = unpack(x)
        g = geometry(jo, radii_of(u, pr), seg)
        return g, _cover.samples(g)

    def nearest(grouped):
        def f(x, d):
            xs = samples_of(x)[1]
            return _cover.nearest_points(_data(d, pr)[1], xs if grouped else xs.reshape(-1, 1, 3)).reshape(-1, 3)
        return jax.jit(f)

    def kept(blocked):
        def f(x, d):
            g, xs = samples_of(x)
            flat = xs.reshape(-1, 3)
            return distances_of(g, seg, flat, pr.candidates, *(blocks_of(pr, flat.shape[0]) if blocked else (0, 0)))[0]
        return jax.jit(f)

    outs = {}
    for name, fn in (("nearest_grouped", nearest(True)), ("nearest_each", nearest(False)), ("kept_blocked", kept(True)), ("kept_all", kept(False))):
        out, first, warm = timed(fn, x, data)
        outs[name] = np.asarray(out)
        print(json.dumps({"setting": name, "samples": int(outs[name].shape[0]), "first_s": round(first, 3), "warm_s_median": round(warm, 5)}), flush=True)
    with_blocks = {}
    for k in (4, 6):
        _cover.NEAREST_BLOCKS = k
        near = np.asarray(nearest(True)(x, data), np.float64)
        sam = np.asarray(jax.jit(lambda x: samples_of(x)[1])(x), np.float64).reshape(-1, 3)
        with_blocks[k] = np.linalg.norm(near - sam, axis=1)
        missed, worst = torus_misses()
        print(json.dumps({"nearest_blocks": k, "torus_ring_samples": 368, "torus_ring_missed": missed, "torus_ring_worst_excess": round(worst, 4)}), flush=True)
    print(json.dumps({"chain_samples_nearer_with_6_than_4": round(float(np.mean(with_blocks[6] < with_blocks[4] - 1e-7)), 4)}), flush=True)
    print(json.dumps({"nearest_same": bool(np.array_equal(outs["nearest_grouped"], outs["nearest_each"])),
                      "kept_same": bool(np.array_equal(np.abs(outs["kept_blocked"]) <= pr.scale, np.abs(outs["kept_all"]) <= pr.scale)),
                      "devices": [str(d) for d in jax.devices()], "jax": jax.__version__}))


if __name__ == "__main__":
    main()
