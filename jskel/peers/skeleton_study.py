"""Issue 6's peers on the rays jskel casts (``peer: skeleton``): Embree on the Table 1 "GS"
tessellation (Bhagvat et al. 2009, Sec. 4: level m and m + 1) and Mitsuba 3's round linear
curves; for animated scenes (``frames``) also seconds per frame (``peers.frames_study``).
Ratios are jskel's warm median over the peer's (above 1: jskel is slower)."""

from __future__ import annotations

import time

import numpy as np

from ..frusta import ANIMATED, host_frusta, skeleton_arrays
from ..probe.timing import median_of, warm_runs
from ..render import camera_of
from .frames_study import frames_row
from .skeleton import TABLE1_GS_LEVEL, EmbreeMesh, MitsubaCurves, frusta_mesh
from ..probe.study import StudyOptions, shape_of


def agreement(t, ref_t) -> dict:
    """A peer's depths ``t`` against jskel's ``ref_t``: hit/miss disagreement (% of rays), the
    peer's hit fraction, and over rays both hit the depth RMSE and median absolute difference."""
    a, b = np.isfinite(t), np.isfinite(ref_t)
    both = a & b
    out = {"hit_miss_vs_jskel_pct": round(float(100 * np.mean(a != b)), 4), "hit_fraction": round(float(a.mean()), 4)}
    if both.any():
        dt = t[both] - ref_t[both]
        out["depth_rmse_vs_jskel"] = round(float(np.sqrt(np.mean(dt * dt))), 6)
        out["depth_median_abs_vs_jskel"] = round(float(np.median(np.abs(dt))), 6)
    return out


def _ratios(row: dict, jsk: dict, med: float, resident: bool = False) -> dict:
    """jskel's render and cast medians (``jsk``: its first BVH row) over a peer's ``med``."""
    if jsk.get("render_s_median"):
        row["jskel_over_peer"] = round(jsk["render_s_median"] / med, 2)
    if jsk.get("cast_s_median"):
        row["jskel_cast_over_peer"] = round(jsk["cast_s_median"] / med, 2)
    if resident and jsk.get("cast_resident_s_median"):  # both casts on rays already on the device
        row["jskel_resident_cast_over_peer"] = round(jsk["cast_resident_s_median"] / med, 2)
    return row


def _embree_rows(arrays, level: int, O, D, ref_t, runs: int, base: dict, jsk: dict) -> list[dict]:
    out = []
    for m in (level, level + 1):
        t0 = time.perf_counter()
        V, F = frusta_mesh(arrays, m)
        tess_s = time.perf_counter() - t0
        em = EmbreeMesh(V, F)
        casts = warm_runs(lambda: em.cast(O, D), runs, 1).warm
        med = median_of([c[1] for c in casts])
        row = dict(base, peer="embree", gs_level=m, table1_level=m == level, triangles=int(F.shape[0]),
                   triangles_per_segment=16 * 4**m, mesh_bytes=int(V.shape[0] * 12 + F.shape[0] * 12),
                   tessellate_s=round(tess_s, 4), build_s=round(em.build_s, 4), cast_s_median=med, runs=runs,
                   mrays_per_s=round(O.shape[0] / med / 1e6, 3), **agreement(casts[0][0], ref_t))
        out.append(_ratios(row, jsk, med))
    return out


#: seconds of pause after each cast timed in turn with another system's (``_mitsuba_rows``)
PAUSE = 0.05


def _paused(fn):
    """``fn()``, then :data:`PAUSE` seconds of sleep."""
    out = fn()
    time.sleep(PAUSE)
    return out


def _jskel_casts(exp) -> tuple:
    """(cast, resident cast) of ``exp``'s one object, each a function returning its seconds:
    ``probe.cast.cast_once`` (rays laid out on the host, results copied back) and
    ``probe.cast.cast_resident`` (rays already on the device, results left there) of one build,
    for timing in turn with a peer."""
    from .. import registry
    from ..probe.cast import cast_once, cast_resident, resident_rays
    from ..render import dtype_of

    obj = shape_of(exp, "peer: skeleton")
    built = registry.get(obj.type).build(obj, dtype_of(exp))
    res = resident_rays(exp, built)
    return (lambda: cast_once(exp, built)[1]), (lambda: cast_resident(exp, built, res)[0])


def _mitsuba_rows(exp, skeleton, variant: str, O, D, ref_t, runs: int, base: dict, jsk: dict):
    """(rows, the curves or None): the first Mitsuba variant of ``variant`` and ``scalar_rgb``
    that runs; a variant that cannot run is a row with its error, not a failure.

    Mitsuba's casts are timed in turn with jskel's (``exp``, the reference setting: each run
    casts jskel with the host's copies, jskel on resident rays, then Mitsuba), and the ratios
    are of those medians (``interleaved: true``): timed in separate blocks, both systems' casts
    drifted from one block to the next, and the ratios with them. Each cast is followed by a
    pause of :data:`PAUSE`: with none, jskel's cast with the host's copies read slower right
    after Mitsuba's (Dr.Jit's worker threads are still busy for a moment after a cast)
    (docs/choices.md#interleaved-casts)."""
    out = []
    once, resident = _jskel_casts(exp)
    for v in dict.fromkeys([variant, "scalar_rgb"]):
        try:
            mc = MitsubaCurves(*skeleton, v)
            times = {"once": [], "resident": [], "peer": []}
            casts = []
            for i in range(runs + 1):  # the first round warms all three up
                a, b, c = _paused(once), _paused(resident), _paused(lambda: mc.cast(O, D))
                casts.append(c)
                if i:
                    times["once"].append(a), times["resident"].append(b), times["peer"].append(c[1])
        except Exception as e:  # noqa: BLE001 - a peer that cannot run is recorded, not fatal
            out.append(dict(base, peer="mitsuba", variant=v, error=f"{type(e).__name__}: {e}"))
            continue
        med = median_of(times["peer"])
        row = dict(base, peer="mitsuba", variant=v, curves=mc.n_curves, build_s=round(mc.build_s, 4),
                   cast_s_median=med, runs=runs, mrays_per_s=round(O.shape[0] / med / 1e6, 3), **agreement(casts[-1][0], ref_t))
        j_once, j_res = median_of(times["once"]), median_of(times["resident"])
        row.update(interleaved=True, jskel_cast_s_median=round(j_once, 5), jskel_resident_cast_s_median=round(j_res, 5))
        out.append(_ratios(row, {"render_s_median": jsk.get("render_s_median"), "cast_s_median": j_once, "cast_resident_s_median": j_res},
                           med, resident=True))
        return out, mc
    return out, None


def skeleton(exp, ref_hits, runs: int, rows: list[dict], options: StudyOptions) -> list[dict]:
    """Embree on the Table 1 "GS" tessellations and Mitsuba's curves on the same rays as jskel's
    ``rows`` (the first with ``object.accel`` bvh or auto gives the ratios); with
    ``options.frames`` and an animated generator, one more row of seconds per frame."""
    obj = shape_of(exp, "peer: skeleton")
    O, D = camera_of(exp).ray_arrays()
    ref_t = np.asarray(ref_hits.t, np.float64)
    jsk = next((r for r in rows if r.get("setting", {}).get("object.accel") in ("bvh", "auto")), {})
    base = {"scene": exp.name, "rays": int(O.shape[0])}
    arrays, _, _, joints, radii, _ = host_frusta(obj)
    parents = skeleton_arrays(obj.skeleton, obj.frame)[2]
    level = TABLE1_GS_LEVEL.get(obj.skeleton.procedural, 1)
    out = _embree_rows(arrays, level, O, D, ref_t, runs, base, jsk)
    mitsuba, mc = _mitsuba_rows(exp, (joints, radii, parents), options.mitsuba_variant, O, D, ref_t, runs, base, jsk)
    out += mitsuba
    if options.frames and obj.skeleton.procedural in ANIMATED:
        out.append(frames_row(options.frames, exp, (O, D), level, mc, base, runs))
    return out
