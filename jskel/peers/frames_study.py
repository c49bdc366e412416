"""Seconds per animated frame, rebuild included, for jskel, Embree and Mitsuba (issue 6).

jskel: skeleton, cutting planes, BVH built in JAX, render with shading (``jskel_frame``); again
with the cast alone (``jskel_cast_frame``); with the frusta rebuilt on the device from the
frame's joints (``jskel_device_frame``); that rebuild again with the cast on
rays kept on the device and its result left there (``jskel_resident_frame``), as Mitsuba's cast is
timed. The compiles are shared by all frames and not counted. Embree: skeleton, cutting planes,
tessellation, BVH build, cast. Mitsuba: skeleton, control-point update with its rebuild, cast.

Each frame is done ``runs`` times by every system in turn (jskel, Embree, Mitsuba, then again),
and a frame's figure is the median of its runs; the row holds the median over frames. A shared
machine has slow spells (in one run of the cacti, jskel's per-frame cast read well above the
same run's static cast; docs/choices.md#frames-interleaved); one run per frame put some
systems' frames in a spell and not others'.
"""

from __future__ import annotations

import statistics
import time

import jax

from ..frusta import host_frusta, rebuilder, skeleton_arrays
from ..probe.cast import cast_once, cast_resident, resident_rays
from ..probe.study import shape_of
from ..probe.timing import median_of
from ..render import dtype_of, render
from .skeleton import EmbreeMesh, frusta_mesh

#: the parts of a frame, in the row's order (``<part>_s_median``)
PARTS = ("jskel_build", "jskel_cast", "jskel_cast_only", "jskel_device_build", "jskel_device_cast", "jskel_resident_cast",
         "embree_skeleton", "embree_tess", "embree_build", "embree_cast", "mitsuba_skeleton", "mitsuba_update", "mitsuba_cast")
#: the whole frame of each system
TOTALS = ("jskel", "jskel_cast", "jskel_device", "jskel_resident", "embree", "mitsuba")


def _device_rebuild(exp):
    """(rebuild, resident rays or None): the frusta rebuilt on the device from a frame's joints
    (``frusta.rebuilder``), its cast compiled here; the fixed camera's rays
    placed on the device once for every frame (the rebuild keeps one anchor), as Mitsuba's are.
    (None, None) where the object cannot be rebuilt on the device."""
    obj = shape_of(exp, "peer: skeleton")
    try:
        rb = rebuilder(obj, dtype_of(exp))
        j0, r0, _, _ = skeleton_arrays(obj.skeleton, obj.frame)
        b0 = rb(j0, r0)
        cast_once(exp, b0)  # compiles the rebuild and its cast
        return rb, resident_rays(exp, b0)
    except ValueError:
        return None, None


def _jskel_run(exp, rb, resident, part: dict, tot: dict):
    o = exp.objects[0].shape
    res = render(exp, progress=False)
    part["jskel_build"].append(res.run["build_s"])
    part["jskel_cast"].append(res.run["render_s"])
    tot["jskel"].append(res.run["build_s"] + res.run["render_s"])
    # the same frame again, built anew and cast alone (t and primitive, as the peers' casts)
    b_s, c_s, _ = cast_once(exp)
    part["jskel_cast_only"].append(c_s)
    tot["jskel_cast"].append(b_s + c_s)
    if rb is None:
        return
    t0 = time.perf_counter()  # skeleton on the host, frusta and BVH on the device, cast alone
    j, r, _, _ = skeleton_arrays(o.skeleton, o.frame)
    built = rb(j, r)
    jax.block_until_ready(built.params)
    d_build = time.perf_counter() - t0
    _, c_s, _ = cast_once(exp, built)
    part["jskel_device_build"].append(d_build)
    part["jskel_device_cast"].append(c_s)
    tot["jskel_device"].append(d_build + c_s)
    if resident is not None:  # the same build, cast on resident rays, results left there
        r_s = cast_resident(exp, built, resident)[0]
        part["jskel_resident_cast"].append(r_s)
        tot["jskel_resident"].append(d_build + r_s)


def _peer_runs(o, rays, level: int, mc, part: dict, tot: dict):
    t0 = time.perf_counter()
    arrays = host_frusta(o)[0]
    t1 = time.perf_counter()
    V, F = frusta_mesh(arrays, level)
    t2 = time.perf_counter()
    em = EmbreeMesh(V, F)
    _, cast_s = em.cast(*rays)
    part["embree_skeleton"].append(t1 - t0)
    part["embree_tess"].append(t2 - t1)
    part["embree_build"].append(em.build_s)
    part["embree_cast"].append(cast_s)
    tot["embree"].append(t2 - t0 + em.build_s + cast_s)
    if mc is None:
        return
    t0 = time.perf_counter()
    j, r, p, _ = skeleton_arrays(o.skeleton, o.frame)
    sk = time.perf_counter() - t0
    up = mc.update(j, r, p)
    _, cast_s = mc.cast(*rays)
    part["mitsuba_skeleton"].append(sk)
    part["mitsuba_update"].append(up)
    part["mitsuba_cast"].append(cast_s)
    tot["mitsuba"].append(sk + up + cast_s)


def _frame_medians(frames, exp, rays, level: int, mc, runs: int):
    """({part: [median per frame]}, {system: [median per frame]}, jskel's compile seconds)."""
    obj = shape_of(exp, "peer: skeleton")
    rb, resident = _device_rebuild(exp)
    parts, totals = {k: [] for k in PARTS}, {k: [] for k in TOTALS}
    compile_s = None
    for f in frames:  # host loop over frames
        o = obj.model_copy(update={"frame": f})
        e = exp.with_shapes(o)
        if compile_s is None:
            compile_s = render(e, progress=False).run["compile_s"]  # the first call compiles
            cast_once(e)  # and the cast alone
        part, tot = {k: [] for k in PARTS}, {k: [] for k in TOTALS}
        for _ in range(max(runs, 1)):
            _jskel_run(e, rb, resident, part, tot)
            _peer_runs(o, rays, level, mc, part, tot)
        for mine, all_frames in ((part, parts), (tot, totals)):
            for k, v in mine.items():
                if v:
                    all_frames[k].append(statistics.median(v))
    return parts, totals, compile_s


def _over(row: dict, name: str, a: str, b: str):
    row[name] = round(row[a] / row[b], 2)


def frames_row(frames, exp, rays, level: int, mc, base: dict, runs: int = 1) -> dict:
    """The animated frames' row: per-part and whole-frame medians and jskel's ratios to Embree
    and (where ``mc``, Mitsuba's curves, ran) to Mitsuba."""
    parts, totals, compile_s = _frame_medians(frames, exp, rays, level, mc, runs)
    row = dict(base, peer="animated_frames", frames=len(frames), runs_per_frame=max(runs, 1), gs_level=level,
               jskel_compile_s=round(compile_s, 3), jskel_frame_s_median=median_of(totals["jskel"]),
               embree_frame_s_median=median_of(totals["embree"]),
               **{f"{k}_s_median": median_of(v) for k, v in parts.items() if v})
    _over(row, "jskel_over_embree", "jskel_frame_s_median", "embree_frame_s_median")
    # a frame with the cast alone (build, then t and primitive per ray: what the peers' frames hold)
    row["jskel_cast_frame_s_median"] = median_of(totals["jskel_cast"])
    _over(row, "jskel_cast_frame_over_embree", "jskel_cast_frame_s_median", "embree_frame_s_median")
    for k in ("jskel_device", "jskel_resident"):  # rebuilt on the device; and cast on resident rays
        if totals[k]:
            row[f"{k}_frame_s_median"] = median_of(totals[k])
            _over(row, f"{k}_frame_over_embree", f"{k}_frame_s_median", "embree_frame_s_median")
    if totals["mitsuba"]:
        row["mitsuba_variant"] = mc.variant
        row["mitsuba_frame_s_median"] = median_of(totals["mitsuba"])
        for k in ("jskel", "jskel_cast", "jskel_device", "jskel_resident"):
            if k == "jskel" or totals[k]:
                name = "jskel_over_mitsuba" if k == "jskel" else f"{k}_frame_over_mitsuba"
                _over(row, name, f"{k}_frame_s_median", "mitsuba_frame_s_median")
    return row
