"""Benchmarks: compile time apart, warm-up, median of warm runs; sweeps of quality knobs.

``python -m jskel bench FILE`` reads a bench file. Without ``sweep`` it times each scene and
prints one JSON line per scene. With ``sweep`` (a mapping of config keys to value lists) it
renders the first scene at every combination, measures each against a ``reference`` render
(the same scene with the reference overrides, e.g. 4096 steps in float64), prints one JSON line
per setting and plots error against time (log axes, Pareto front marked).
"""

from __future__ import annotations

import itertools
import statistics
import time
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import Field

from .config import StrictModel, chunk_of, chunks_per_call_of


class BenchFile(StrictModel):
    """A benchmark file: experiments rendered at one size, timed over warm runs."""

    scenes: list[str]
    width: Annotated[int, Field(ge=1, le=16384)] = 1024
    height: Annotated[int, Field(ge=1, le=16384)] = 768
    runs: Annotated[int, Field(ge=1, le=1000)] = 5
    warmup: Annotated[int, Field(ge=0, le=100)] = 1
    set: list[str] = []
    sweep: dict[str, list[Any]] | list[dict[str, Any]] | None = None  # a grid, or explicit settings
    reference: list[str] = []
    metric: str = "depth_rmse"
    peer: Literal["embree_mesh", "embree_same_mesh", "marching_cubes", "skeleton"] | None = None
    peer_levels: list[Annotated[int, Field(ge=0, le=4096)]] = [0, 1, 2, 3, 4, 5]
    peer_match: dict[str, Any] | None = None
    # animated scenes (``peer: skeleton``): frames timed per frame with rebuild, for jskel and peers
    frames: list[float] = []
    mitsuba_variant: str = "llvm_ad_rgb"
    stats: bool = False  # frusta BVH: nodes and leaves visited per ray (one extra untimed pass)
    # also time the cast alone (nearest t and primitive of every ray, on the device, no shading
    # and no other output; what the peers' cast times hold): ``cast_s_median`` in each row
    cast: bool = False
    labels: list[str] | None = None  # a name per sweep setting (rows and the bar chart of a timing-only sweep)


class _Depth(NamedTuple):
    t: Any
    normal: Any = None


def _score_peer(row: dict, t, ref_hits, target: dict | None) -> dict:
    """Add the error metrics of a peer's depths ``t`` and whether it matches jskel's target."""
    from .metrics import compare

    row.update({k: (round(v, 8) if isinstance(v, float) else v) for k, v in compare(_Depth(t), ref_hits).items()})
    if target is not None:
        row["matches_jskel_setting"] = bool(row["depth_rmse"] is not None and row["depth_rmse"] <= target["depth_rmse"]
                                            and row["hit_miss_pct"] <= target["hit_miss_pct"])
        row["jskel_setting"] = target["setting"]
    return row


def _match_target(bench, rows):
    if bench.peer_match is None:
        return None
    target = None
    for r in rows:
        if all(r.get("setting", {}).get(k) == v for k, v in bench.peer_match.items()):
            target = r
    return target


def peer_marching_cubes(bench: "BenchFile", exp, obj, ref_hits, runs: int, rows: list[dict]):
    """Implicit models polygonised by marching cubes at ``peer_levels`` (grid cells along the
    longest side) and cast by Embree, against the same reference."""
    import time

    from .implicit import expand, primitives
    from .peers.implicit_mesh import marching_cubes_mesh
    from .peers.relief_mesh import embree_cast
    from .render import camera_of

    cfg = expand(obj)
    a, b, ra, rb, _, _ = primitives(cfg)
    O, D = camera_of(exp).ray_arrays()
    target = _match_target(bench, rows)
    out = []
    for n in bench.peer_levels:
        t0 = time.perf_counter()
        try:
            V, F = marching_cubes_mesh(a, b, ra, rb, cfg.threshold, n)
        except ValueError as e:  # e.g. a grid too coarse to contain the level set
            out.append({"peer": "marching_cubes+embree", "scene": exp.name, "grid": n, "error": str(e)})
            continue
        mesh_s = time.perf_counter() - t0
        t, build_s, med = embree_cast(V, F, O, D, runs)
        row = {"peer": "marching_cubes+embree", "scene": exp.name, "grid": n, "vertices": int(V.shape[0]),
               "triangles": int(F.shape[0]), "mesh_bytes": int(V.shape[0] * 12 + F.shape[0] * 12),
               "polygonise_s": round(mesh_s, 4), "build_s": round(build_s, 4), "render_s_median": round(med, 4),
               "runs": runs, "rays": int(O.shape[0])}
        out.append(_score_peer(row, t, ref_hits, target))
    return out


def peer_embree_mesh(bench: "BenchFile", exp, obj, ref_hits, runs: int, rows: list[dict]):
    """Displaced meshes of the relief segments at increasing subdivision, cast by Embree."""
    import numpy as np

    from .frusta import host_frusta, load_height_map
    from .peers.relief_mesh import displaced_mesh, embree_cast
    from .render import camera_of

    arrays, topo, _, _, _, _ = host_frusta(obj)
    rel = obj.relief
    s = arrays.h.shape[0]
    ids = np.arange(s) if rel.segments is None else np.unique(rel.segments)
    height = load_height_map(rel.map)
    cam = camera_of(exp)
    O, D = cam.ray_arrays()
    target = _match_target(bench, rows)
    out = []
    for level in bench.peer_levels:
        nu, nv = 16 * 2**level, 4 * 2**level
        V, F = displaced_mesh(arrays, ids, height, rel.scale, rel.thickness, rel.v_mode, nu, nv)
        t, build_s, med = embree_cast(V, F, O, D, runs)
        row = {"peer": "embree_mesh", "scene": exp.name, "level": level, "grid": [nu, nv], "vertices": int(V.shape[0]),
               "triangles": int(F.shape[0]), "mesh_bytes": int(V.shape[0] * 12 + F.shape[0] * 12),
               "build_s": round(build_s, 4), "render_s_median": round(med, 4), "runs": runs, "rays": int(O.shape[0])}
        out.append(_score_peer(row, t, ref_hits, target))
    return out


def peer_embree_same_mesh(bench: "BenchFile", exp, obj, ref_hits, runs: int, rows: list[dict]):
    """Embree on the very triangles a mesh object casts (read, scaled and moved as its build
    does) and the same world rays; ratios are jskel's warm cast (and render) median over
    Embree's (above 1: jskel is slower)."""
    import numpy as np

    from .mesh import read_mesh
    from .peers.skeleton import EmbreeMesh
    from .render import camera_of

    v, f, _ = read_mesh(obj.path)
    v = v * obj.scale + np.asarray(obj.offset, np.float64)
    O, D = camera_of(exp).ray_arrays()
    em = EmbreeMesh(v, f)
    casts = [em.cast(O, D) for _ in range(runs + 1)][1:]
    med = _median([c[1] for c in casts])
    t, ref_t = casts[0][0], np.asarray(ref_hits.t, np.float64)
    a, b = np.isfinite(t), np.isfinite(ref_t)
    row = {"peer": "embree", "scene": exp.name, "rays": int(O.shape[0]), "triangles": int(f.shape[0]), "build_s": round(em.build_s, 4),
           "cast_s_median": med, "runs": runs, "mrays_per_s": round(O.shape[0] / med / 1e6, 3),
           "hit_miss_vs_jskel_pct": round(float(100 * np.mean(a != b)), 4)}
    if (a & b).any():
        row["depth_max_rel_vs_jskel"] = float(np.max(np.abs(t[a & b] - ref_t[a & b]) / ref_t[a & b]))
    jsk = rows[0] if rows else {}  # the first setting's row
    if jsk.get("cast_s_median"):
        row["jskel_cast_over_peer"] = round(jsk["cast_s_median"] / med, 2)
    if jsk.get("render_s_median"):
        row["jskel_over_peer"] = round(jsk["render_s_median"] / med, 2)
    return [row]


def _median(xs):
    return round(float(statistics.median(xs)), 5)


def peer_skeleton(bench: "BenchFile", exp, obj, ref_hits, runs: int, rows: list[dict]):
    """Issue 6's peers on the same rays as jskel's rows: Embree on the Table 1 "GS" tessellation
    (level m and m + 1) and Mitsuba 3's round linear curves; for animated scenes (``frames``),
    seconds per frame with everything a new frame needs (skeleton, rebuild, cast) for all three.
    Ratios are jskel's warm median over the peer's (above 1: jskel is slower)."""
    import numpy as np

    from .frusta import host_frusta
    from .frusta import skeleton_arrays
    from .peers.skeleton import TABLE1_GS_LEVEL, EmbreeMesh, MitsubaCurves, frusta_mesh
    from .render import camera_of

    O, D = camera_of(exp).ray_arrays()
    ref_t = np.asarray(ref_hits.t, np.float64)
    jsk = [r for r in rows if r.get("setting", {}).get("object.accel") in ("bvh", "auto")]
    jskel_s = jsk[0]["render_s_median"] if jsk else None
    jskel_cast_s = jsk[0].get("cast_s_median") if jsk else None
    jskel_res_s = jsk[0].get("cast_resident_s_median") if jsk else None  # accelerators only
    base = {"scene": exp.name, "rays": int(O.shape[0])}

    def agree(t):
        a, b = np.isfinite(t), np.isfinite(ref_t)
        both = a & b
        out = {"hit_miss_vs_jskel_pct": round(float(100 * np.mean(a != b)), 4), "hit_fraction": round(float(a.mean()), 4)}
        if both.any():
            dt = t[both] - ref_t[both]
            out["depth_rmse_vs_jskel"] = round(float(np.sqrt(np.mean(dt * dt))), 6)
            out["depth_median_abs_vs_jskel"] = round(float(np.median(np.abs(dt))), 6)
        return out

    arrays, _, _, joints, radii, _ = host_frusta(obj)
    parents = skeleton_arrays(obj.skeleton, obj.frame)[2]
    out = []
    level = TABLE1_GS_LEVEL.get(obj.skeleton.procedural, 1)
    for m in (level, level + 1):
        t0 = time.perf_counter()
        V, F = frusta_mesh(arrays, m)
        tess_s = time.perf_counter() - t0
        em = EmbreeMesh(V, F)
        casts = [em.cast(O, D) for _ in range(runs + 1)][1:]
        med = _median([c[1] for c in casts])
        row = dict(base, peer="embree", gs_level=m, table1_level=m == level, triangles=int(F.shape[0]),
                   triangles_per_segment=16 * 4**m, mesh_bytes=int(V.shape[0] * 12 + F.shape[0] * 12),
                   tessellate_s=round(tess_s, 4), build_s=round(em.build_s, 4), cast_s_median=med, runs=runs,
                   mrays_per_s=round(O.shape[0] / med / 1e6, 3), **agree(casts[0][0]))
        if jskel_s:
            row["jskel_over_peer"] = round(jskel_s / med, 2)
        if jskel_cast_s:
            row["jskel_cast_over_peer"] = round(jskel_cast_s / med, 2)
        out.append(row)
    mc = None
    for variant in dict.fromkeys([bench.mitsuba_variant, "scalar_rgb"]):
        try:
            mc = MitsubaCurves(joints, radii, parents, variant)
            casts = [mc.cast(O, D) for _ in range(runs + 1)][1:]
        except Exception as e:  # noqa: BLE001 - a peer that cannot run is recorded, not fatal
            out.append(dict(base, peer="mitsuba", variant=variant, error=f"{type(e).__name__}: {e}"))
            mc = None
            continue
        med = _median([c[1] for c in casts])
        row = dict(base, peer="mitsuba", variant=variant, curves=mc.n_curves, build_s=round(mc.build_s, 4),
                   cast_s_median=med, runs=runs, mrays_per_s=round(O.shape[0] / med / 1e6, 3), **agree(casts[0][0]))
        if jskel_s:
            row["jskel_over_peer"] = round(jskel_s / med, 2)
        if jskel_cast_s:
            row["jskel_cast_over_peer"] = round(jskel_cast_s / med, 2)
        if jskel_res_s:  # both casts on rays already on the device, results left there
            row["jskel_resident_cast_over_peer"] = round(jskel_res_s / med, 2)
        out.append(row)
        break
    from .frusta import ANIMATED

    if bench.frames and obj.skeleton.procedural in ANIMATED:
        out += _frames_rows(bench, exp, obj, O, D, level, mc, base, runs)
    return out


def _frames_rows(bench, exp, obj, O, D, level, mc, base, runs: int = 1):
    """Seconds per animated frame, rebuild included: jskel (skeleton, cutting planes, BVH built in
    JAX, render with shading; again with the cast alone, ``jskel_cast_frame_s_median``; with
    the frusta rebuilt on the device from the frame's joints, ``jskel_device_frame_s_median``;
    on an accelerator that rebuild again with the cast on rays kept on the device and its result
    left there, ``jskel_resident_frame_s_median``, as Mitsuba's cast is timed; the compiles are
    shared by all frames and not counted), Embree (skeleton, cutting
    planes, tessellation, BVH build, cast) and Mitsuba (skeleton, control-point update with its
    rebuild, cast).

    Each frame is done ``runs`` times by every system in turn (jskel, Embree, Mitsuba, then
    again), and a frame's figure is the median of its runs; the row holds the median over frames.
    This shared 2-core machine has slow spells (in one run of the cacti, jskel's per-frame cast
    read 0.165 s against the same run's static 0.113 s); one run per frame put some systems'
    frames in a spell and not others'."""
    import jax

    from .frusta import host_frusta, rebuilder
    from .frusta import skeleton_arrays
    from .peers.skeleton import EmbreeMesh, frusta_mesh
    from .render import dtype_of, render

    totals = {"jskel": [], "jskel_cast": [], "jskel_device": [], "jskel_resident": [], "embree": [], "mitsuba": []}
    parts = {"jskel_build": [], "jskel_cast": [], "jskel_cast_only": [], "jskel_device_build": [], "jskel_device_cast": [],
             "jskel_resident_cast": [],
             "embree_skeleton": [], "embree_tess": [], "embree_build": [],
             "embree_cast": [], "mitsuba_skeleton": [], "mitsuba_update": [], "mitsuba_cast": []}
    compile_s = None
    try:  # the frusta rebuilt on the device from each frame's joints (frusta._device)
        rb = rebuilder(obj, dtype_of(exp))
        j0, r0, _, _ = skeleton_arrays(obj.skeleton, obj.frame)
        b0 = rb(j0, r0)
        cast_once(exp, obj, b0)  # compiles the rebuild and its cast
        # on an accelerator, the fixed camera's rays placed on the device once for every frame
        # (the rebuild keeps one anchor), as Mitsuba's are
        resident = resident_rays(exp, b0) if _on_accelerator() else None
    except ValueError:
        rb = resident = None
    for f in bench.frames:  # host loop over frames
        o = obj.model_copy(update={"frame": f})
        if compile_s is None:
            compile_s = render(exp, o, progress=False).run["compile_s"]  # the first call compiles
            cast_once(exp, o)  # and the cast alone
        tot = {k: [] for k in totals}
        part = {k: [] for k in parts}
        for _ in range(max(runs, 1)):
            res = render(exp, o, progress=False)
            part["jskel_build"].append(res.run["build_s"])
            part["jskel_cast"].append(res.run["render_s"])
            tot["jskel"].append(res.run["build_s"] + res.run["render_s"])
            # the same frame again, built anew and cast alone (t and primitive, as the peers' casts)
            b_s, c_s, _ = cast_once(exp, o)
            part["jskel_cast_only"].append(c_s)
            tot["jskel_cast"].append(b_s + c_s)
            if rb is not None:  # skeleton on the host, frusta and BVH on the device, cast alone
                t0 = time.perf_counter()
                j, r, _, _ = skeleton_arrays(o.skeleton, o.frame)
                built = rb(j, r)
                jax.block_until_ready(built.params)
                d_build = time.perf_counter() - t0
                _, c_s, _ = cast_once(exp, o, built)
                part["jskel_device_build"].append(d_build)
                part["jskel_device_cast"].append(c_s)
                tot["jskel_device"].append(d_build + c_s)
                if resident is not None:  # the same build, cast on resident rays, results left there
                    r_s = cast_resident(exp, o, built, resident)[0]
                    part["jskel_resident_cast"].append(r_s)
                    tot["jskel_resident"].append(d_build + r_s)
            t0 = time.perf_counter()
            arrays = host_frusta(o)[0]
            t1 = time.perf_counter()
            V, F = frusta_mesh(arrays, level)
            t2 = time.perf_counter()
            em = EmbreeMesh(V, F)
            _, cast_s = em.cast(O, D)
            part["embree_skeleton"].append(t1 - t0)
            part["embree_tess"].append(t2 - t1)
            part["embree_build"].append(em.build_s)
            part["embree_cast"].append(cast_s)
            tot["embree"].append(t2 - t0 + em.build_s + cast_s)
            if mc is not None:
                t0 = time.perf_counter()
                j, r, p, _ = skeleton_arrays(o.skeleton, o.frame)
                sk = time.perf_counter() - t0
                up = mc.update(j, r, p)
                _, cast_s = mc.cast(O, D)
                part["mitsuba_skeleton"].append(sk)
                part["mitsuba_update"].append(up)
                part["mitsuba_cast"].append(cast_s)
                tot["mitsuba"].append(sk + up + cast_s)
        for k, v in part.items():
            if v:
                parts[k].append(statistics.median(v))
        for k, v in tot.items():
            if v:
                totals[k].append(statistics.median(v))
    jt, jc, jd, jr, et, mt = (totals[k] for k in ("jskel", "jskel_cast", "jskel_device", "jskel_resident", "embree", "mitsuba"))
    row = dict(base, peer="animated_frames", frames=len(bench.frames), runs_per_frame=max(runs, 1), gs_level=level, jskel_compile_s=round(compile_s, 3),
               jskel_frame_s_median=_median(jt), embree_frame_s_median=_median(et),
               **{f"{k}_s_median": _median(v) for k, v in parts.items() if v})
    row["jskel_over_embree"] = round(row["jskel_frame_s_median"] / row["embree_frame_s_median"], 2)
    # a frame with the cast alone (build, then t and primitive per ray: what the peers' frames hold)
    row["jskel_cast_frame_s_median"] = _median(jc)
    row["jskel_cast_frame_over_embree"] = round(row["jskel_cast_frame_s_median"] / row["embree_frame_s_median"], 2)
    if jd:  # the same with the frusta rebuilt on the device
        row["jskel_device_frame_s_median"] = _median(jd)
        row["jskel_device_frame_over_embree"] = round(row["jskel_device_frame_s_median"] / row["embree_frame_s_median"], 2)
    if jr:  # and cast on rays resident on the accelerator, results left there
        row["jskel_resident_frame_s_median"] = _median(jr)
        row["jskel_resident_frame_over_embree"] = round(row["jskel_resident_frame_s_median"] / row["embree_frame_s_median"], 2)
    if mt:
        row["mitsuba_variant"] = mc.variant
        row["mitsuba_frame_s_median"] = _median(mt)
        row["jskel_over_mitsuba"] = round(row["jskel_frame_s_median"] / row["mitsuba_frame_s_median"], 2)
        row["jskel_cast_frame_over_mitsuba"] = round(row["jskel_cast_frame_s_median"] / row["mitsuba_frame_s_median"], 2)
        if jd:
            row["jskel_device_frame_over_mitsuba"] = round(row["jskel_device_frame_s_median"] / row["mitsuba_frame_s_median"], 2)
        if jr:
            row["jskel_resident_frame_over_mitsuba"] = round(row["jskel_resident_frame_s_median"] / row["mitsuba_frame_s_median"], 2)
    return [row]


_CAST_FNS: dict = {}


def _cast_fn(rep_name: str, static):
    """``(params, rays) -> (t, prim)``: the representation's first stage (``cast``) with nothing
    else kept (XLA drops whatever payload no output needs)."""
    key = (rep_name, static)
    if key not in _CAST_FNS:
        from . import registry

        rep = registry.get(rep_name)

        def fn(params, rays):
            pre = rep.cast(params, static, rays)
            return pre.t, pre.prim

        _CAST_FNS[key] = fn
    return _CAST_FNS[key]


def cast_once(exp, obj, built=None) -> tuple[float, float, float]:
    """(build seconds, cast seconds, compile seconds) of one frame: the representation's build,
    then the cast alone (``_cast_fn``) of the camera's rays in screen-tile order, chunked as the
    render chunks them; the outputs come back to the host as ``t`` and ``prim`` only. The rays are
    made (host arrays, ``Camera.tiled_rays``) before the cast's clock starts, as the peers' rays
    are."""
    import jax

    from . import registry
    from .executor import map_chunks
    from .render import camera_of, devices_of, dtype_of

    dtype = dtype_of(exp)
    rep = registry.get(obj.type)
    t0 = time.perf_counter()
    built = rep.build(obj, dtype) if built is None else built
    jax.block_until_ready(built.params)  # (asynchronous dispatch: the build's device work ends here)
    build_s = time.perf_counter() - t0
    cam = camera_of(exp)
    rays = cam.tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype)
    res = map_chunks(_cast_fn(obj.type, built.static), built.params, rays, chunk=chunk_of(exp.render), progress=False,
                     devices=devices_of(exp), group=chunks_per_call_of(exp.render))
    return build_s, res.run_s, res.compile_s


def _on_accelerator() -> bool:
    """Whether JAX's default backend is an accelerator: resident casts are timed there only."""
    import jax

    return jax.default_backend() != "cpu"


def _ray_mesh_of(exp):
    """The ray mesh ``executor.map_chunks`` uses for ``render.devices`` (None: one device)."""
    from .executor import ray_mesh
    from .render import devices_of

    devices = devices_of(exp)
    return ray_mesh(devices) if devices is not None else None


def resident_rays(exp, built) -> list:
    """The camera's rays for ``built`` in screen-tile order, cut into the chunks a render uses
    (``render.chunk``, times the devices of ``render.devices``; the last padded by repeating its
    last ray, as ``executor.map_chunks`` pads), each placed on the device(s) ahead of a cast: a list
    of device ``Rays`` for :func:`cast_resident`."""
    import jax
    import numpy as np

    from .rays import Rays
    from .executor import _pad_to
    from .render import camera_of, dtype_of

    rays = camera_of(exp).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))
    mesh = _ray_mesh_of(exp)
    n = rays.size
    per = min(chunk_of(exp.render), n) * (1 if mesh is None else mesh.size)
    put = jax.devices()[0] if mesh is None else jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("rays"))
    chunks = [Rays(*(jax.device_put(np.ascontiguousarray(_pad_to(a[lo : lo + per], per)), put) for a in rays))
              for lo in range(0, n, per)]
    return jax.block_until_ready(chunks)


def cast_resident(exp, obj, built, chunks) -> tuple[float, list]:
    """(seconds, [(t, prim) per chunk]) of one cast of rays already on the device
    (:func:`resident_rays`), t and primitive left there: how the Mitsuba peer's cast is timed
    (its rays are put on the GPU before its clock starts and its result is not copied back),
    where :func:`cast_once` also times the rays' copy to the device and the results' copy back.
    The same compiled ``_cast_fn`` as ``cast_once``'s (one chunk per call, no grouping), every
    call dispatched before one wait. On a CPU the copies cost nothing; on a GPU they are most of
    a 1024x768 cast (README, performance)."""
    import jax

    from .executor import compile_batch_fn

    mesh = _ray_mesh_of(exp)
    params = built.params
    if mesh is not None:
        params = jax.device_put(params, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    compiled, _ = compile_batch_fn(_cast_fn(obj.type, built.static), (params, chunks[0]), mesh)
    jax.block_until_ready(params)
    t0 = time.perf_counter()
    outs = [compiled(params, c) for c in chunks]
    jax.block_until_ready(outs)
    return time.perf_counter() - t0, outs


def timed_cast(exp, obj, runs: int, warmup: int) -> dict:
    """``cast_s_median`` (and min, max) over ``runs`` warm casts of one build (``cast_once``).
    On an accelerator also ``cast_resident_s_median``: the same casts with the rays already on
    the device and the results left there (:func:`cast_resident`, as the Mitsuba peer is timed)."""
    from . import registry
    from .render import dtype_of

    built = registry.get(obj.type).build(obj, dtype_of(exp))
    for _ in range(max(warmup, 1)):
        cast_once(exp, obj, built)
    times = [cast_once(exp, obj, built)[1] for _ in range(runs)]
    med = statistics.median(times)
    row = {"cast_s_median": round(med, 4), "cast_s_min": round(min(times), 4), "cast_s_max": round(max(times), 4),
           "cast_mrays_per_s": round(exp.camera.width * exp.camera.height / med / 1e6, 4)}
    if _on_accelerator():
        chunks = resident_rays(exp, built)
        for _ in range(max(warmup, 1)):
            cast_resident(exp, obj, built, chunks)
        res = [cast_resident(exp, obj, built, chunks)[0] for _ in range(runs)]
        row.update(cast_resident_s_median=round(statistics.median(res), 5), cast_resident_s_min=round(min(res), 5),
                   cast_resident_s_max=round(max(res), 5))
    return row


def timed_render(exp, obj, runs: int, warmup: int) -> tuple[dict, object]:
    """Render once (compiles; its compile seconds are kept), ``warmup - 1`` more, then ``runs``
    timed renders. Returns (row, first result)."""
    from .render import render

    first = render(exp, obj, progress=False)
    for _ in range(max(warmup - 1, 0)):
        render(exp, obj, progress=False)
    warm = [render(exp, obj, progress=False).run for _ in range(runs)]
    times = [w["render_s"] for w in warm]
    med = statistics.median(times)
    r = first.run
    row = {
        "scene": exp.name,
        "primitives": r["primitives"],
        "width": exp.camera.width,
        "height": exp.camera.height,
        "rays": r["rays"],
        "dtype": exp.render.dtype,
        "chunk": chunk_of(exp.render),
        "compile_s": round(r["compile_s"], 4),
        "render_s_median": round(med, 4),
        "render_s_min": round(min(times), 4),
        "render_s_max": round(max(times), 4),
        "runs": runs,
        "mrays_per_s": round(r["rays"] / med / 1e6, 4),
        "hit_fraction": round(r["hit_fraction"], 4),
        "device": r["device"],
        "jax": r["jax"],
        "jskel": r["jskel"],
    }
    # the build of warm runs (the first also compiles the jitted BVH build for new shapes)
    row["build_s"] = round(statistics.median(w["build_s"] for w in warm), 4)
    row["build_first_s"] = round(r["build_s"], 4)
    row["us_per_ray"] = round(med / r["rays"] * 1e6, 4)
    for k in ("memory", "memory_bytes", "precompute_s", "cache"):
        if k in r["info"]:
            row[k] = r["info"][k]
    for k in ("effects", "secondary_rays", "spp"):  # scenes
        if k in r:
            row[k] = r[k]
    return row, first


def plot_bars(rows: list[dict], path: Path, title: str):
    """Warm median seconds per row as a bar chart (min-max as error bars), labelled by each
    row's ``label``; secondary rays per frame written over the bars where rows have them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return None
    labels = [r.get("label") or str(r.get("setting")) for r in rows]
    med = [r["render_s_median"] for r in rows]
    lo = [m - r["render_s_min"] for m, r in zip(med, rows)]
    hi = [r["render_s_max"] - m for m, r in zip(med, rows)]
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(rows)), 4.2))
    bars = ax.bar(range(len(rows)), med, yerr=[lo, hi], color="#4477aa", capsize=3)
    for b, r in zip(bars, rows):
        if r.get("secondary_rays") is not None:
            ax.annotate(f"{r['secondary_rays']:,}", (b.get_x() + b.get_width() / 2, b.get_height()), ha="center", va="bottom",
                        fontsize=7, xytext=(0, 2), textcoords="offset points")
    ax.set_xticks(range(len(rows)), labels, rotation=30, ha="right")
    ax.set_ylabel("warm median seconds per frame")
    ax.set_title(title + "\n(numbers: secondary rays per frame)" if any("secondary_rays" in r for r in rows) else title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def sweep_settings(sweep) -> list[dict]:
    """Settings of a sweep: the cartesian product of a mapping, or an explicit list."""
    if isinstance(sweep, list):
        return [dict(s) for s in sweep]
    keys = list(sweep)
    return [dict(zip(keys, vals)) for vals in itertools.product(*(sweep[k] for k in keys))]


def pareto_plot(t, e, labels: list[str], path: Path, ylabel: str, title: str, marked=None, marked_label: str = ""):
    """Error ``e`` against time ``t`` on log axes with the Pareto front marked, one label per
    point; ``marked`` (bool mask) points get an extra hollow marker (e.g. a peer's meshes).
    Shared by the bench and sweep commands."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .metrics import pareto_front

    t, e = np.asarray(t, float), np.asarray(e, float)
    front = pareto_front(t, e)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.scatter(t[~front], e[~front], c="0.6", s=18, label="setting")
    order = np.argsort(t[front])
    ax.plot(t[front][order], e[front][order], "o-", c="C3", label="Pareto front")
    if marked is not None and np.any(marked):
        m = np.asarray(marked)
        ax.scatter(t[m], e[m], marker="^", facecolors="none", edgecolors="C0", s=40, label=marked_label)
    for lab, ti, ei in zip(labels, t, e):
        ax.annotate(lab, (ti, ei), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm median render time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=8)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_sweep(rows: list[dict], keys: list[str], metric: str, path: Path, title: str):
    """A bench sweep's ``metric`` against warm median time (``pareto_plot``); None if no row
    has the metric."""
    ok = [r for r in rows if r.get(metric) is not None and r[metric] > 0]
    if not ok:
        return None
    labels = [",".join(str(r["setting"].get(k, "-")) for k in keys) for r in ok]
    title = title + "\nlabels: " + ", ".join(k.split(".")[-1] for k in keys) + " (- where a setting omits one)"
    return pareto_plot([r["render_s_median"] for r in ok], [r[metric] for r in ok], labels, path, metric, title)


def plot_scaling(rows: list[dict], path: Path, title: str):
    """Cost per ray and traversal work per ray against the number of primitives (log2 x axis,
    so growth in proportion to log(segments) is a straight line), from rows with ``stats``.
    The first swept key is the size axis; rows that differ in the other swept keys are drawn
    as separate lines (e.g. per-ray walks against packets)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ok = [r for r in rows if r.get("nodes_per_ray_mean") is not None]
    if len(ok) < 2:
        return None
    groups: dict[str, list[dict]] = {}
    for r in ok:
        st = r.get("setting", {})
        label = ", ".join(f"{k.split('.')[-1]}={v}" for k, v in list(st.items())[1:]) or "all"
        groups.setdefault(label, []).append(r)
    third = any("packet_steps_mean" in r or "bin_tests_per_ray_mean" in r for r in ok)  # packets or bins swept
    fig, ax = plt.subplots(1, 3 if third else 2, figsize=(14, 4) if third else (9.5, 4))
    for i, (label, rs) in enumerate(groups.items()):
        rs = sorted(rs, key=lambda r: r["primitives"])
        n = np.array([r["primitives"] for r in rs], float)
        ax[0].plot(n, [r["us_per_ray"] for r in rs], "o-", c=f"C{i}", label=label)
        ax[1].plot(n, [r["nodes_per_ray_mean"] for r in rs], "o-", c=f"C{i}", label=f"nodes ({label})")
        ax[1].plot(n, [r["leaves_per_ray_mean"] for r in rs], "s--", c=f"C{i}", label=f"leaves ({label})")
        if any("packet_steps_mean" in r for r in rs):
            ax[2].plot(n, [r.get("packet_steps_mean", np.nan) for r in rs], "o-", c=f"C{i}", label=f"packet steps ({label})")
        if any("bin_tests_per_ray_mean" in r for r in rs):
            ax[2].plot(n, [r.get("bin_tests_per_ray_mean", np.nan) for r in rs], "s--", c=f"C{i}", label=f"bin tests per ray ({label})")
    ax[0].set_ylabel("warm median microseconds per ray")
    ax[1].set_ylabel("per ray, its own walk (mean)")
    if third:
        ax[2].set_ylabel("packets: loop steps; bins: segment tests per ray")
    for a in ax:
        a.set_xscale("log", base=2)
        a.set_xlabel("segments")
        a.set_ylim(bottom=0)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
