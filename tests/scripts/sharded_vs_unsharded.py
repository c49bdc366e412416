"""Run under XLA_FLAGS=--xla_force_host_platform_device_count=4: render small experiments of
each representation with render.devices=one and =all and report whether every output is equal
bit for bit (one JSON line).

Both sides run the same chunks per call: a chunk run alone and a chunk run inside a call's
loop are two XLA programs, whose shading may round the last bit of a colour apart (seen on
the implicit blobs: 53 of 3,600 channels, 6e-8). Here 40 x 30 rays in chunks of 150 are 8
chunks on one device and 2 per device on four, so ``auto`` would group one side only."""

import json
import sys

import jax
import numpy as np

from jskel import config
from jskel.render import render

# one case per representation's kind of build (the executor that shards knows nothing of
# representations): the frusta BVH with chunks grouped per call, implicit blocks, cells
cases = {
    # 2 chunks per call on both sides (16 chunks of 75 on one device, 4 per device on four): with
    # 4 devices each call's chunks are dealt out in turn (call_layout.call_rays)
    "frusta_bvh_grouped": ("experiments/saguaro.yaml", ["render.chunk=75", "render.chunks_per_call=2", "object.accel=bvh"]),
    "implicit_blocks": ("experiments/blobs_5000.yaml", []),
    "cells_reflection": ("experiments/torus_cells_reflection.yaml", [f"object.cache={sys.argv[1]}", "object.tiles=6",
                                                                     "object.tile_map.resolution=16", "object.search=linear"]),
    # the voxel walk: the sharded program rounds its t apart in the last bits on some rays
    # (``close``: the same hits, cells and image, t within float32 rounding)
    "cells_walk": ("experiments/torus_cells_reflection.yaml", [f"object.cache={sys.argv[1]}", "object.tiles=6",
                                                               "object.tile_map.resolution=16", "object.search=voxels"]),
}
out = {"devices": jax.local_device_count()}
for name, (path, extra) in cases.items():
    res = {}
    for dev in ("one", "all"):
        exp = config.load(path, ["camera.width=40", "camera.height=30", "render.chunk=150", "render.chunks_per_call=1", f"render.devices={dev}", *extra])
        r = render(exp, progress=False)
        res[dev] = (r.hits, r.rgb, r.run["devices_used"])
    a, b = res["one"], res["all"]
    same = all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in zip(jax.tree_util.tree_leaves(a[0]), jax.tree_util.tree_leaves(b[0])))
    same = same and np.array_equal(a[1], b[1])
    ha, hb = a[0], b[0]
    hit = np.isfinite(np.asarray(ha.t))
    close = (np.array_equal(hit, np.isfinite(np.asarray(hb.t))) and np.array_equal(np.asarray(ha.prim), np.asarray(hb.prim))
             and np.array_equal(a[1], b[1]) and bool(np.allclose(np.asarray(ha.t)[hit], np.asarray(hb.t)[hit], rtol=1e-6, atol=0)))
    out[name] = {"equal": bool(same), "close": bool(close), "t_differ": int(np.sum(np.asarray(ha.t)[hit] != np.asarray(hb.t)[hit])),
                 "devices_used": [a[2], b[2]], "hit_fraction": float(hit.mean())}

# the bench's resident cast (rays placed on the devices before the clock, results left there) on
# four devices: each call takes a chunk per device, and the hits are the one-device render's
from jskel import registry  # noqa: E402
from jskel.probe.cast import cast_resident, resident_rays  # noqa: E402
from jskel.camera import tile_inverse  # noqa: E402

exp = config.load("experiments/saguaro.yaml", ["camera.width=40", "camera.height=30", "render.chunk=150", "render.devices=all"])
obj = exp.objects[0].shape
want = render(config.load("experiments/saguaro.yaml", ["camera.width=40", "camera.height=30", "render.chunk=150", "render.devices=one"]),
             progress=False).hits
built = registry.get(obj.type).build(obj, np.float32)
res = resident_rays(exp, built)
_, outs = cast_resident(exp, built, res)
inv = tile_inverse(40, 30, exp.render.tile)
t, prim = (x[inv] for x in res.host_outputs(outs))
hit = np.isfinite(np.asarray(want.t))
same = (np.array_equal(np.isfinite(t), hit) and np.array_equal(prim[hit], np.asarray(want.prim)[hit])
        and bool(np.allclose(t[hit], np.asarray(want.t)[hit], rtol=2e-6, atol=0)))
out["frusta_resident_cast"] = {"equal": bool(same), "devices_used": [1, len(res.calls[0].origins.sharding.device_set)],
                               "hit_fraction": float(hit.mean()), "calls": len(res.calls)}
print(json.dumps(out))
