"""Run by hand (not by the suite): what the host's part of a cast costs, in one process.

For each scene at 1024 x 768 (bench_scale's frame), the compiled cast (``interface.cast_t_prim``
through ``executor.map_chunks``' layout: 4,096-ray chunks, 64 a call, every host device) is
timed, alternating, as:

- ``cast_once``: ``probe.cast.cast_once``, the bench's ``cast_s``: each call's rays laid out on
  the host, passed, results copied back into ray order;
- ``host_in_numpy16``: the calls alone on rays laid out beforehand in NumPy arrays offset to
  start 16 bytes past a 64-byte boundary (NumPy's own allocations start on 16): JAX copies each
  into a device buffer;
- ``host_in_aligned``: the same rays in 64-byte-aligned arrays (``call_layout.aligned_zeros``,
  what ``call_rays`` makes): JAX aliases them;
- ``resident``: ``probe.cast.cast_resident``, rays placed on the devices beforehand, results
  left there (how the Mitsuba peer is timed);
- ``layout``: laying out every call's rays on the host, no cast.

    python tests/scripts/host_path.py oasis pine dancing_cacti

One JSON line per scene: medians of ``--runs`` warm runs, seconds."""

import argparse
import json
import statistics
import time

import jskel

jskel.use_host_devices()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jskel import registry  # noqa: E402
from jskel.compile.call_layout import aligned_zeros  # noqa: E402
from jskel.config import load  # noqa: E402
from jskel.executor import compile_batch_fn  # noqa: E402
from jskel.measure.files import provenance  # noqa: E402
from jskel.probe.cast import cast_once, cast_resident, resident_rays  # noqa: E402
from jskel.probe.study import shape_of  # noqa: E402
from jskel.interface import Object  # noqa: E402
from jskel.render import dtype_of  # noqa: E402


def _offset(x, off: int):
    """A copy of the host array ``x`` starting ``off`` bytes past a 64-byte boundary."""
    raw = np.empty(x.nbytes + 128, np.uint8)
    start = (-raw.ctypes.data) % 64 + off
    y = raw[start : start + x.nbytes].view(x.dtype).reshape(x.shape)
    y[...] = x
    return y


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--runs", type=int, default=9)
    args = ap.parse_args()
    for scene in args.scenes:
        exp = load(f"experiments/{scene}.yaml", ["camera.width=1024", "camera.height=768"])
        obj = shape_of(exp, "host_path")
        built = registry.get(obj.type).build(obj, dtype_of(exp))
        res = resident_rays(exp, built)
        params = Object(built.params, built.static, obj.type)
        if res.mesh is not None:
            params = jax.device_put(params, jax.sharding.NamedSharding(res.mesh, jax.sharding.PartitionSpec()))
        compiled, _ = compile_batch_fn(res.batch_fn, (params, res.calls[0]), res.mesh)
        host = [jax.tree_util.tree_map(np.asarray, c) for c in res.calls]
        numpy16 = [jax.tree_util.tree_map(lambda x: _offset(x, 16), c) for c in host]
        aligned = [jax.tree_util.tree_map(lambda x: _offset(x, 0), c) for c in host]
        assert all(x.ctypes.data % 64 == 16 for c in numpy16 for x in jax.tree_util.tree_leaves(c))
        assert all(aligned_zeros((1,), np.float32).ctypes.data % 64 == 0 for _ in range(3))

        def calls(inputs):
            def run():
                t0 = time.perf_counter()
                jax.block_until_ready([compiled(params, c) for c in inputs])
                return time.perf_counter() - t0
            return run

        from jskel.compile.call_layout import call_rays

        def layout():
            t0 = time.perf_counter()
            for i in range(res.layout.calls):
                [call_rays(np.asarray(a), res.layout, i) for a in camera_rays]
            return time.perf_counter() - t0

        from jskel.render import camera_of, framed
        camera_rays = camera_of(framed(exp, built.bounds)).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))
        fns = {"cast_once": lambda: cast_once(exp, built)[1], "host_in_numpy16": calls(numpy16), "host_in_aligned": calls(aligned),
               "resident": lambda: cast_resident(exp, built, res)[0], "layout": layout}
        for f in fns.values():
            f()
        times = {k: [] for k in fns}
        for _ in range(args.runs):
            for k, f in fns.items():
                times[k].append(f())
        med = {k: round(statistics.median(v), 4) for k, v in times.items()}
        print(json.dumps(dict(scene=scene, rays=res.layout.n, calls=res.layout.calls, devices=1 if res.mesh is None else res.mesh.size,
                              seconds_median=med, run=provenance())), flush=True)


if __name__ == "__main__":
    main()
