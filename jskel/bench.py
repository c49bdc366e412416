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
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import Field

from .config import StrictModel


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
    peer: Literal["embree_mesh", "marching_cubes"] | None = None
    peer_levels: list[Annotated[int, Field(ge=0, le=4096)]] = [0, 1, 2, 3, 4, 5]
    peer_match: dict[str, Any] | None = None


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


def timed_render(exp, obj, runs: int, warmup: int) -> tuple[dict, object]:
    """Render once (compiles; its compile seconds are kept), ``warmup - 1`` more, then ``runs``
    timed renders. Returns (row, first result)."""
    from .render import render

    first = render(exp, obj, progress=False)
    for _ in range(max(warmup - 1, 0)):
        render(exp, obj, progress=False)
    times = [render(exp, obj, progress=False).run["render_s"] for _ in range(runs)]
    med = statistics.median(times)
    r = first.run
    row = {
        "scene": exp.name,
        "primitives": r["info"].get("segments", r["info"].get("primitives")),
        "width": exp.camera.width,
        "height": exp.camera.height,
        "rays": r["rays"],
        "dtype": exp.render.dtype,
        "chunk": exp.render.chunk,
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
    row["build_s"] = round(r["build_s"], 4)
    for k in ("memory", "memory_bytes", "precompute_s", "cache"):
        if k in r["info"]:
            row[k] = r["info"][k]
    return row, first


def sweep_settings(sweep) -> list[dict]:
    """Settings of a sweep: the cartesian product of a mapping, or an explicit list."""
    if isinstance(sweep, list):
        return [dict(s) for s in sweep]
    keys = list(sweep)
    return [dict(zip(keys, vals)) for vals in itertools.product(*(sweep[k] for k in keys))]


def plot_sweep(rows: list[dict], keys: list[str], metric: str, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .metrics import pareto_front

    ok = [r for r in rows if r.get(metric) is not None and r[metric] > 0]
    if not ok:
        return None
    t = np.array([r["render_s_median"] for r in ok])
    e = np.array([r[metric] for r in ok])
    front = pareto_front(t, e)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.scatter(t[~front], e[~front], c="0.6", s=18, label="setting")
    order = np.argsort(t[front])
    ax.plot(t[front][order], e[front][order], "o-", c="C3", label="Pareto front")
    for r, ti, ei in zip(ok, t, e):
        ax.annotate(",".join(str(r["setting"].get(k, "-")) for k in keys), (ti, ei), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm median render time [s]")
    ax.set_ylabel(metric)
    ax.set_title(title + "\nlabels: " + ", ".join(k.split(".")[-1] for k in keys) + " (- where a setting omits one)", fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
