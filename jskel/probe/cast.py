"""The cast alone, timed as the peers' casts are: nearest ``t`` and primitive of every ray.

:func:`cast_once` builds (or takes a build), makes the camera's rays on the host in screen-tile
order before its clock starts, and casts them chunked as the render chunks them, copying ``t``
and the primitive back. :func:`cast_resident` casts rays already on the device and leaves the
results there, how the Mitsuba peer's cast is timed. The compiled cast is the representation's
first stage with nothing else kept (``interface.cast_t_prim``, one module-level function: the
static options ride in the ``interface.Object`` pytree).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from .. import registry
from ..config import chunk_of, chunks_per_call_of
from ..executor import _pad_to, batch_bucket, compile_batch_fn, map_chunks, ray_mesh
from ..interface import Object, cast_t_prim
from ..rays import Rays
from ..render import camera_of, devices_of, dtype_of, framed
from .study import shape_of
from .timing import Spread, spread, warm_runs

def on_accelerator() -> bool:
    """Whether JAX's default backend is an accelerator: resident casts are timed there only."""
    return jax.default_backend() != "cpu"


def cast_once(exp, built=None) -> tuple[float, float, float]:
    """(build seconds, cast seconds, compile seconds) of one frame: the representation's build
    (skipped when ``built`` is given), then the cast alone of the camera's rays in screen-tile
    order, chunked as the render chunks them; ``t`` and ``prim`` come back to the host. The rays
    are made (host arrays, ``Camera.tiled_rays``) before the cast's clock starts, as the peers'
    rays are. ``exp`` is an experiment of one object (``study.shape_of``)."""
    dtype = dtype_of(exp)
    obj = shape_of(exp, "cast")
    t0 = time.perf_counter()
    built = registry.get(obj.type).build(obj, dtype) if built is None else built
    jax.block_until_ready(built.params)  # (asynchronous dispatch: the build's device work ends here)
    build_s = time.perf_counter() - t0
    rays = camera_of(framed(exp, built.bounds)).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype)
    res = map_chunks(cast_t_prim, Object(built.params, built.static, obj.type), rays, chunk=chunk_of(exp.render), progress=False,
                     devices=devices_of(exp), group=chunks_per_call_of(exp.render))
    return build_s, res.run_s, res.compile_s


def _ray_mesh_of(exp):
    """The ray mesh ``executor.map_chunks`` uses for ``render.devices`` (None: one device)."""
    devices = devices_of(exp)
    return ray_mesh(devices) if devices is not None else None


def resident_rays(exp, built) -> list:
    """The camera's rays for ``built`` in screen-tile order, cut into the chunks a render uses
    (``render.chunk``, times the devices of ``render.devices``; the last padded by repeating its
    last ray, as ``executor.map_chunks`` pads), each placed on the device(s) ahead of a cast: a
    list of device ``Rays`` for :func:`cast_resident`."""
    rays = camera_of(framed(exp, built.bounds)).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))
    mesh = _ray_mesh_of(exp)
    n = rays.size
    per = min(chunk_of(exp.render), batch_bucket(n)) * (1 if mesh is None else mesh.size)
    put = jax.devices()[0] if mesh is None else jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("rays"))
    chunks = [Rays(*(jax.device_put(np.ascontiguousarray(_pad_to(a[lo : lo + per], per)), put) for a in rays))
              for lo in range(0, n, per)]
    return jax.block_until_ready(chunks)


def cast_resident(exp, built, chunks) -> tuple[float, list]:
    """(seconds, [(t, prim) per chunk]) of one cast of rays already on the device
    (:func:`resident_rays`), t and primitive left there: how the Mitsuba peer's cast is timed
    (its rays are put on the GPU before its clock starts and its result is not copied back),
    where :func:`cast_once` also times the rays' copy to the device and the results' copy back.
    The same compiled cast as ``cast_once``'s (one chunk per call, no grouping), every call
    dispatched before one wait. On a CPU the copies cost nothing; on a GPU they are most of a
    1024x768 cast (docs/performance.md)."""
    mesh = _ray_mesh_of(exp)
    params = Object(built.params, built.static, shape_of(exp, "cast").type)
    if mesh is not None:
        params = jax.device_put(params, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    compiled, _ = compile_batch_fn(cast_t_prim, (params, chunks[0]), mesh)
    jax.block_until_ready(params)
    t0 = time.perf_counter()
    outs = [compiled(params, c) for c in chunks]
    jax.block_until_ready(outs)
    return time.perf_counter() - t0, outs


def _columns(prefix: str, s: Spread, digits: int) -> dict:
    return {f"{prefix}_median": round(s.median, digits), f"{prefix}_min": round(s.min, digits),
            f"{prefix}_max": round(s.max, digits)}


def timed_cast(exp, runs: int, warmup: int) -> dict:
    """``cast_s_median`` (and min, max) over ``runs`` warm casts of one build (:func:`cast_once`,
    timed by ``timing.warm_runs``). On an accelerator also ``cast_resident_s_median``: the same
    casts with the rays already on the device and the results left there (:func:`cast_resident`,
    as the Mitsuba peer is timed)."""
    obj = shape_of(exp, "cast")
    built = registry.get(obj.type).build(obj, dtype_of(exp))
    s = spread(warm_runs(lambda: cast_once(exp, built)[1], runs, warmup).warm)
    row = _columns("cast_s", s, 4)
    row["cast_mrays_per_s"] = round(exp.camera.width * exp.camera.height / s.median / 1e6, 4)
    if on_accelerator():
        chunks = resident_rays(exp, built)
        res = spread(warm_runs(lambda: cast_resident(exp, built, chunks)[0], runs, warmup).warm)
        row.update(_columns("cast_resident_s", res, 5))
    return row
