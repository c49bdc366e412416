"""Render an experiment: build -> camera rays -> chunked (intersect + shade) -> AOVs.

One entry, :func:`render`, takes the one experiment value (a scene; of one object where the
file wrote ``object:``), and one writer, :func:`run_record`, makes its run.json. The batch
functions are module-level and talk to the representation's interface only
(``intersect_batch``, ``albedo``); the static options travel in the pytree (``_scene.Scene``),
so a second render of the same shapes reuses the compiled executable.
"""

from __future__ import annotations

import platform
import time
from typing import NamedTuple

import jax
import numpy as np

from .. import registry
from ..config import Experiment, chunk_of, chunks_per_call_of, resolved
from ..rays import Hit, Rays, flag_counts, make_rays
from ..compile.cache import count_programs, program_counts
from ..camera import Camera, framing, tile_inverse, tile_order
from ..executor import map_chunks
from ._aov import write_aovs as write_aovs
from ._sheet import aov_sheet as aov_sheet
from ._sheet import panels_of as panels_of
from ..shading import Lights as Lights
from ..shading import Shading as Shading
from ..shading import encode_png as encode_png
from ..shading import output_transform as output_transform
from ..shading import lights_from_config as lights_from_config
from ..shading import shade_one as shade_one
from ..shading import shading_from_config as shading_from_config


class RenderResult(NamedTuple):
    """What a render returns: hits (NumPy, leading axis H*W), linear RGB, the 8-bit image, run.json's dict, and the extra AOVs."""

    hits: object  # NumPy Hit, leading axis H*W
    rgb: np.ndarray  # (H*W, 3) linear
    image: np.ndarray  # (H, W, 3) uint8
    run: dict  # what run.json holds
    aovs: dict | None = None  # more per-pixel outputs (obj, visibility, ...: ``aovs_of``), leading axis H*W


def camera_of(exp: Experiment) -> Camera:
    """The host ``Camera`` of an experiment's ``camera`` section (``frame: auto`` resolved
    first by :func:`framed`, which needs the built object's bounds)."""
    c = exp.camera
    if c.frame == "auto":
        raise ValueError("camera.frame: auto is placed from the object's bounds: resolve it with jskel.render.framed(exp, built.bounds) first")
    return Camera(np.asarray(c.eye), np.asarray(c.target), np.asarray(c.up), c.fov_deg, c.width, c.height)


def framed(exp: Experiment, bounds) -> Experiment:
    """``exp`` with ``camera.frame: auto`` resolved against the world box ``bounds`` (lo, hi):
    eye and target placed by ``camera.framing`` (then ``frame: manual``, as run.json records
    it); ``exp`` itself for a camera placed by hand."""
    c = exp.camera
    if c.frame != "auto":
        return exp
    eye, target = framing(bounds[0], bounds[1], c.view, c.fov_deg, c.width, c.height)
    cam = c.model_copy(update={"eye": tuple(map(float, eye)), "target": tuple(map(float, target)), "frame": "manual"})
    return exp.model_copy(update={"camera": cam})


def devices_of(exp: Experiment):
    """``render.devices`` as ``map_chunks`` takes it: None (one device) or a device list."""
    d = exp.render.devices
    if d == "one":
        return None
    devs = jax.local_devices()
    if d != "all" and d > len(devs):
        raise ValueError(f"render.devices: {d} devices asked, {len(devs)} present")
    devs = devs if d == "all" else devs[:d]
    return devs if len(devs) > 1 else None


def dtype_of(exp: Experiment):
    """NumPy dtype of ``render.dtype``; float64 needs x64 switched on at the entry point."""
    if exp.render.dtype == "float64":
        if not jax.config.jax_enable_x64:
            raise ValueError("render.dtype: float64 needs jax_enable_x64 (the CLI switches it on; in Python call jax.config.update('jax_enable_x64', True) first)")
        return np.float64
    return np.float32


def environment() -> dict:
    """Versions, device and host recorded in every run.json and benchmark row."""
    import jaxlib

    from .._version import __version__

    dev = jax.devices()[0]
    return {
        "jskel": __version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "python": platform.python_version(),
        "device": f"{dev.platform}:{getattr(dev, 'device_kind', '')}",
        "device_count": jax.device_count(),
        "host": platform.machine(),
    }


def peak_rss_mb() -> float | None:
    """The process's peak resident memory so far in MiB (Linux/macOS), None elsewhere."""
    try:
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return round(r / (2**20 if sys.platform == "darwin" else 2**10), 1)
    except Exception:  # noqa: BLE001 - not available on this platform
        return None


def _trace(exp: Experiment, fn, params, rays: Rays, progress):
    """``map_chunks`` of ``fn`` over ``rays`` on every local device of this process, and over
    several hosts (each traces its share, then every share is gathered)."""
    budget = None if exp.render.memory_mb is None else int(exp.render.memory_mb * 2**20)
    n_proc = jax.process_count()
    if n_proc > 1:
        from ..distributed import gather, share

        lo, hi = share(rays.size, chunk_of(exp.render), n_proc, jax.process_index())
        mine = Rays(*(a[lo:hi] for a in rays))
        res = map_chunks(fn, params, mine, chunk=chunk_of(exp.render), progress=progress, desc="render", devices=devices_of(exp),
                         memory_budget=budget, group=chunks_per_call_of(exp.render))
        per = share(rays.size, chunk_of(exp.render), n_proc, 0)[1]
        return res._replace(out=gather(res.out, hi - lo, per))
    return map_chunks(fn, params, rays, chunk=chunk_of(exp.render), progress=progress, desc="render", devices=devices_of(exp),
                         memory_budget=budget, group=chunks_per_call_of(exp.render))


def camera_rays(exp: Experiment, cam: Camera, origin, dtype) -> Rays:
    """``render.spp`` samples per pixel in screen-tile order, relative to ``origin`` (host):
    the first through the pixel centres (``Camera.tiled_rays``), the others jittered uniformly
    in the pixel from ``render.seed``; sample s occupies rays ``[s * H * W, (s + 1) * H * W)``."""
    rays = cam.tiled_rays(exp.render.tile, anchor=origin, dtype=dtype)
    if exp.render.spp == 1:
        return rays
    n_pix = cam.width * cam.height
    order = tile_order(cam.width, cam.height, exp.render.tile)
    rng = np.random.default_rng(exp.render.seed)
    os_, ds_ = [np.asarray(rays.origins, np.float64)], [np.asarray(rays.directions, np.float64)]
    for _ in range(1, exp.render.spp):
        o, d = cam.ray_arrays(anchor=origin, jitter=rng.uniform(-0.5, 0.5, (n_pix, 2)))
        os_.append(o[order])
        ds_.append(d[order])
    return make_rays(np.concatenate(os_), np.concatenate(ds_), 0.0, np.inf, dtype)


class _Frame(NamedTuple):
    """What the integrator gives a render: the executor's result, the rays traced, the first
    sample's outputs in image order (NumPy) and the pixels' mean colour and 8-bit image."""

    res: object
    rays: int
    first: dict
    rgb: np.ndarray
    image: np.ndarray


def _integrate(exp: Experiment, params, static, origin, dtype, progress) -> _Frame:
    """Camera rays (``render.spp`` per pixel) through the integrator, back in image order."""
    from ._scene import Scene, scene_call

    cam = camera_of(exp)
    n_pix = cam.width * cam.height
    rays = camera_rays(exp, cam, origin, dtype)
    res = _trace(exp, scene_call, Scene(params, static), rays, progress)
    inv = tile_inverse(cam.width, cam.height, exp.render.tile)
    first = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n_pix][inv], {k: v for k, v in res.out.items() if k != "rgb"})
    rgb = np.asarray(res.out["rgb"])
    if exp.render.spp > 1:
        rgb = np.asarray(rgb, np.float64).reshape(exp.render.spp, n_pix, 3).mean(axis=0).astype(rgb.dtype)
    rgb = rgb[:n_pix][inv]
    image = encode_png(rgb.reshape(cam.height, cam.width, 3), output_transform(exp.shading))
    return _Frame(res, int(rays.size), first, rgb, image)


def _flag_counts(flags) -> dict:
    """run.json's ``flags``: the number of pixels carrying each bit, by the names of
    ``rays.FLAG_NAMES`` (the bits docs/numerics.md lists)."""
    return flag_counts(flags)


def render(exp: Experiment, progress: bool | None = None) -> RenderResult:
    """Render one frame of an experiment (host function; the heavy work is jitted in chunks):
    the one entry of the CLI, the benchmarks, the sweeps, the latency benchmark, the peers'
    studies and the viewer (the fit writes an experiment file, ``fitted.yaml``, and renders none).

    ``exp`` is the one experiment value (``config.load``): a scene, of one object where its
    file wrote ``object:``; see ``jskel.render._scene`` for the integrator. ``render.spp``
    samples per pixel: the first through the pixel centre (the AOVs come from it), the others
    jittered uniformly in the pixel from ``render.seed``; the colour is their mean. Effects
    exist only where the experiment calls for them, and so do their outputs (:func:`aovs_of`)."""
    from ._build import assemble, place_objects, world_bounds

    count_programs()
    prog = exp.render.progress if progress is None else progress
    _check_steps(exp)
    dtype = dtype_of(exp)
    t0 = time.perf_counter()
    placed = place_objects(exp, dtype)
    exp = framed(exp, world_bounds(placed))
    params, static, origin, objects_info = assemble(exp, placed, dtype)
    jax.block_until_ready(params)  # dispatch is asynchronous: the build ends here, not in the render
    build_s = time.perf_counter() - t0
    fr = _integrate(exp, params, static, origin, dtype, prog)
    h = fr.first["hit"]
    # hit positions back to world coordinates (host, float64)
    hits = Hit(h.t, np.asarray(h.position, np.float64) + origin, h.normal, h.uv, h.prim, h.flags)
    aovs = aovs_of(exp, placed, static, fr.first, hits, origin)
    run = run_record(exp, placed, static, fr, build_s, origin, objects_info, params, hits)
    return RenderResult(hits, fr.rgb, fr.image, run, aovs or None)


def aovs_of(exp: Experiment, placed, static, first: dict, hits: Hit, origin) -> dict:
    """A render's outputs beyond depth, normal, uv, prim and flags, each only where the
    experiment calls for what it shows: ``obj`` (the object hit, -1 on a miss) with two objects
    or more; ``visibility`` (per light, 1 lit / 0 shadowed) where a light casts shadows, and
    ``secondary`` (secondary rays per pixel) where a material reflects or refracts, both always
    with two objects or more (a scene's files have always held them, read beside ``obj``);
    ``reflect_obj`` / ``refract_obj`` (where the path that starts with the pixel's first
    reflection / refraction ray ends: the object its last ray hit, -1 if it escaped or there is
    none; through a glass rod that is the object seen behind it; where a path branches, one of
    the branches) with two objects or more; ``steps`` where ``render.steps`` asks; and each
    representation's own (``Representation.extra_aovs``, e.g. a cell object's ``cell``) on the
    pixels whose object it is."""
    eff = static.effects
    several = len(placed) > 1
    obj = first["obj"] if several else np.where(np.isfinite(hits.t), 0, -1)
    out = {}
    if several:
        out["obj"] = obj
    if eff.shadows or several:
        out["visibility"] = first["visibility"]
    if eff.bounces or several:
        out["secondary"] = first["secondary"]
    if len(placed) > 1 and eff.reflection:
        out["reflect_obj"] = first["first_obj"][:, 0]
    if len(placed) > 1 and eff.refraction:
        out["refract_obj"] = first["first_obj"][:, 1]
    for k, p in enumerate(placed):
        mine = obj == k
        theirs = hits if len(placed) == 1 else Hit(np.where(mine, hits.t, np.inf), hits.position, hits.normal, hits.uv,
                                                   np.where(mine, hits.prim, -1), hits.flags)
        for name, a in p.rep.extra_aovs(p.built, theirs).items():
            a = np.asarray(a)
            out[name] = a if name not in out else np.where(mine.reshape((-1,) + (1,) * (a.ndim - 1)), a, out[name])
    if exp.render.steps:
        out["steps"] = steps_image(exp, placed[0], static.identity[0], origin)
    return out


def run_record(exp: Experiment, placed, static, fr, build_s: float, origin, objects_info: list, params, hits: Hit) -> dict:
    """The one writer of ``run.json``: the resolved config (the experiment as a scene), versions,
    seconds, rays, effects (where any), flag counts, each object's build info (``objects``) and
    ``info``: the scene's counts, with a scene of one's build info beside them."""
    res = fr.res
    primitives = int(sum(i["primitives"] for i in objects_info))
    info = {"objects": len(placed), "primitives": primitives}
    if len(placed) == 1:
        info = {**info, **placed[0].built.info}
    run = {
        "config": resolved(exp),
        **environment(),
        "build_s": build_s,
        "compile_s": res.compile_s,
        "compile_cached": res.compile_s == 0.0,
        "render_s": res.run_s,
        "rays": fr.rays,
        "primitives": primitives,
        "chunk": chunk_of(exp.render),
        "devices_used": len(devices_of(exp) or [None]),
        "processes": jax.process_count(),
        "mrays_per_s": fr.rays / res.run_s / 1e6 if res.run_s > 0 else None,
        "programs": program_counts(),  # this process's so far: compiled by XLA, loaded from the persistent cache
        "spp": exp.render.spp,
        "secondary_rays": int(np.sum(res.out["secondary"])) if "secondary" in res.out else 0,
        "hit_fraction": float(np.mean(np.isfinite(hits.t))),
        "origin": [float(x) for x in origin],
        "objects": objects_info,
        "info": info,
        "params_bytes": int(sum(getattr(x, "nbytes", 0) for x in jax.tree_util.tree_leaves(params))),
        "peak_host_mb": peak_rss_mb(),
        "flags": _flag_counts(res.out["hit"].flags),
    }
    eff = static.effects
    if eff.shadows or eff.reflection or eff.refraction:
        run["effects"] = eff._asdict()
    if res.memory is not None:
        run["memory_budget"] = res.memory
    return run


def _check_steps(exp: Experiment) -> None:
    """``render.steps`` is refused (``ValueError``, before anything is built) for a scene of
    several objects and for a representation that counts no steps
    (``Representation.steps_per_ray`` left as is)."""
    if not exp.render.steps:
        return
    from ..interface import Representation

    if len(exp.objects) > 1:
        raise ValueError(f"render.steps: true: a scene's steps are counted for one object (got {len(exp.objects)} objects)")
    rep = registry.get(exp.objects[0].shape.type)
    if type(rep).steps_per_ray is Representation.steps_per_ray:
        raise ValueError(f"render.steps: true: {exp.objects[0].at(0)}.type {rep.name!r} counts no search steps (cells do)")


def steps_image(exp: Experiment, p, identity: bool, origin) -> np.ndarray:
    """(H*W,) int32 in image order: each pixel-centre camera ray's search steps
    (``Representation.steps_per_ray``) of the one object ``p`` (a ``_build.Placed``), one more
    pass over the rays of the render's first sample, in the object's frame: relative to the
    render's ``origin`` where its placement there is the identity (``SceneStatic.identity``)."""
    cam = camera_of(exp)  # ``exp`` as the render framed it
    if identity:
        rays = cam.tiled_rays(exp.render.tile, anchor=origin, dtype=dtype_of(exp))
    else:  # the camera rays placed in the object's frame on the host (float64), then cast
        o, d = cam.ray_arrays(anchor=np.zeros(3))
        order = tile_order(cam.width, cam.height, exp.render.tile)
        rt = p.rotation.T
        o_obj = (o[order] - p.translate) @ rt.T / p.scale - np.asarray(p.built.anchor, np.float64)
        rays = make_rays(o_obj, d[order] @ rt.T, 0.0, np.inf, dtype_of(exp))
    steps = np.asarray(p.rep.steps_per_ray(p.built, rays, chunk_of(exp.render)), np.int32)
    return steps[tile_inverse(cam.width, cam.height, exp.render.tile)]


__all__ = ["aov_sheet", "aovs_of", "Lights", "RenderResult", "Shading", "camera_of", "devices_of", "dtype_of", "encode_png", "environment", "framed", "lights_from_config", "output_transform", "panels_of", "peak_rss_mb", "camera_rays", "render", "run_record", "shade_one", "shading_from_config", "write_aovs"]
