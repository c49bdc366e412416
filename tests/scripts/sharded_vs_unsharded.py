"""Run under XLA_FLAGS=--xla_force_host_platform_device_count=4: render small experiments of
each representation with render.devices=one and =all and report whether every output is equal
bit for bit (one JSON line)."""

import json
import sys

import jax
import numpy as np

from jskel import config
from jskel.render import render

cases = {
    "frusta_bvh": ("experiments/aloe.yaml", []),
    "frusta_blocks": ("experiments/well.yaml", []),
    "implicit_blocks": ("experiments/blobs_5000.yaml", []),
    "cells_reflection": ("experiments/torus_cells_reflection.yaml", [f"object.cache={sys.argv[1]}", "object.tiles=6",
                                                                     "object.tile_map.resolution=16"]),
}
out = {"devices": jax.local_device_count()}
for name, (path, extra) in cases.items():
    res = {}
    for dev in ("one", "all"):
        exp, obj = config.load(path, ["camera.width=40", "camera.height=30", "render.chunk=150", f"render.devices={dev}", *extra])
        r = render(exp, obj, progress=False)
        res[dev] = (r.hits, r.rgb, r.run["devices_used"])
    a, b = res["one"], res["all"]
    same = all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in zip(jax.tree_util.tree_leaves(a[0]), jax.tree_util.tree_leaves(b[0])))
    same = same and np.array_equal(a[1], b[1])
    out[name] = {"equal": bool(same), "devices_used": [a[2], b[2]], "hit_fraction": float(np.isfinite(a[0].t).mean())}
print(json.dumps(out))
