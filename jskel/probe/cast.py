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

from .. import registry
from ..config import chunk_of, chunks_per_call_of
from ..executor import Resident, compile_batch_fn, map_chunks, replicated, resident_calls
from ..interface import Object, cast_t_prim
from ..render import camera_of, devices_of, dtype_of, framed
from .study import shape_of
from .timing import Spread, spread, warm_runs

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


def resident_rays(exp, built) -> Resident:
    """The camera's rays for ``built`` in screen-tile order, cut into the calls a render makes
    (``render.chunk``, ``render.chunks_per_call``, ``render.devices``: the layout of
    ``executor.map_chunks``, the same compiled program) and placed on the device(s) ahead of a
    cast (``executor.resident_calls``), for :func:`cast_resident`."""
    rays = camera_of(framed(exp, built.bounds)).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))
    params = Object(built.params, built.static, shape_of(exp, "cast").type)
    return resident_calls(cast_t_prim, params, rays, chunk=chunk_of(exp.render), devices=devices_of(exp), group=chunks_per_call_of(exp.render))


def cast_resident(exp, built, resident: Resident) -> tuple[float, list]:
    """(seconds, [(t, prim) per call]) of one cast of rays already on the device
    (:func:`resident_rays`), t and primitive left there: how the Mitsuba peer's cast is timed
    (its rays are made into Dr.Jit arrays before its clock starts and its result is not
    copied back), where :func:`cast_once` also times laying the rays out for each call and
    copying the results back. The same compiled cast as ``cast_once``'s, every call
    dispatched before one wait. On a GPU the copies are most of a 1024x768 cast; on the CPU a
    smaller part of it (docs/performance.md, ``tests/scripts/host_path.py``)."""
    params = Object(built.params, built.static, shape_of(exp, "cast").type)
    if resident.mesh is not None:
        params = replicated(params, resident.mesh)
    compiled, _ = compile_batch_fn(resident.batch_fn, (params, resident.calls[0]), resident.mesh)
    jax.block_until_ready(params)
    t0 = time.perf_counter()
    outs = [compiled(params, c) for c in resident.calls]
    jax.block_until_ready(outs)
    return time.perf_counter() - t0, outs


def _columns(prefix: str, s: Spread, digits: int) -> dict:
    return {f"{prefix}_median": round(s.median, digits), f"{prefix}_min": round(s.min, digits),
            f"{prefix}_max": round(s.max, digits)}


def timed_cast(exp, runs: int, warmup: int) -> dict:
    """``cast_s_median`` (and min, max) over ``runs`` warm casts of one build (:func:`cast_once`,
    timed by ``timing.warm_runs``), and ``cast_resident_s_median``: the same casts with the rays
    already on the device and the results left there (:func:`cast_resident`, as the Mitsuba
    peer is timed)."""
    obj = shape_of(exp, "cast")
    built = registry.get(obj.type).build(obj, dtype_of(exp))
    s = spread(warm_runs(lambda: cast_once(exp, built)[1], runs, warmup).warm)
    row = _columns("cast_s", s, 4)
    row["cast_mrays_per_s"] = round(exp.camera.width * exp.camera.height / s.median / 1e6, 4)
    resident = resident_rays(exp, built)
    res = spread(warm_runs(lambda: cast_resident(exp, built, resident)[0], runs, warmup).warm)
    row.update(_columns("cast_resident_s", res, 5))
    return row
