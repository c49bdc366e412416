"""Run under XLA_FLAGS=--xla_force_host_platform_device_count=4: ``map_chunks`` over four
devices with grouped calls whose last call holds padding chunks (each device skips its own),
against NumPy in float64; prints one JSON line."""

import json

import jax
import numpy as np

from jskel.executor import map_chunks
from jskel.rays import make_rays


def dot(p, r):
    return {"v": p * (r.origins * r.directions).sum(-1) + r.t_max, "i": r.origins[:, 0].astype(np.int32)}


rng = np.random.default_rng(27)
out = {"devices": jax.local_device_count(), "cases": []}
# (rays, chunk per device, chunks per call): two calls of 4 chunks per device, the second's
# chunks half padding; the same with one live chunk in the second call (three devices run none);
# two calls of 8, the second with 17 of 32 live (one partial); 5 chunks (below 8: one per call)
for n, chunk, group in [(1200, 50, 4), (850, 50, 4), (977, 20, 8), (5000, 256, 16)]:
    o, d = rng.uniform(-100, 100, (n, 3)).round(), rng.normal(size=(n, 3))
    rays = make_rays(o, d / np.linalg.norm(d, axis=1, keepdims=True), 0.0, 2.0)
    got = map_chunks(dot, np.float32(0.5), rays, chunk=chunk, progress=False, group=group, devices="all").out
    want = 0.5 * np.sum(np.asarray(rays.origins, np.float64) * np.asarray(rays.directions, np.float64), -1) + 2.0
    ok = bool(np.allclose(got["v"], want, rtol=1e-5, atol=1e-4) and np.array_equal(got["i"], o[:, 0].astype(np.int32)))
    out["cases"].append({"rays": n, "chunk": chunk, "group": group, "equal": ok})
print(json.dumps(out))
