"""``python -m jskel bench FILE``: time scenes, or a grid of settings against a reference.

Without ``sweep`` each scene is timed (``timing``: compile apart, warm-up, median of warm runs)
and printed as one JSON line. With ``sweep`` (a grid, ``grid.expand``) every scene is rendered
at every setting; with ``reference`` overrides each setting is also scored against that
reference render (``metrics.compare``) and error is plotted against time, without one each
setting's time is drawn as a bar (or, with ``stats``, cost against scene size). ``peer`` runs a
peer's study (``peers.studies``) on the reference's rays. A file with a ``fit:`` section is the
fitting benchmark (``jskel.fit``). Rows are JSON lines, also appended to ``--out``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import Field

from .. import registry
from ..compile.cache import count_programs, program_counts
from ..compile.isa import with_max_isa, xla_isa
from ..config import ConfigError, StrictModel, chunk_of, load, read_yaml
from ..fit import FitBenchFile, TreeBenchFile, run_fit_bench, run_tree_bench
from ..probe.cast import timed_cast
from ..probe.metrics import compare
from ..probe.study import Peers, StudyOptions, needed, shape_of
from ..probe.timing import render_runs, spread
from ..render import camera_of, dtype_of, framed, render
from .files import X64, JsonLines, beside, read_model
from .grid import expand, keys_of, overrides_of
from .plots import plot_bars, plot_scaling, plot_sweep


class BenchFile(StrictModel):
    """A benchmark file: experiments rendered at one size, timed over warm runs."""

    scenes: list[str]
    """Experiment files timed (as given, or relative to the bench file's folder)."""
    width: Annotated[int, Field(ge=1, le=16384)] = 1024
    """Image width every scene is rendered at."""
    height: Annotated[int, Field(ge=1, le=16384)] = 768
    """Image height every scene is rendered at."""
    runs: Annotated[int, Field(ge=1, le=1000)] = 5
    """Warm runs timed (median, min and max reported)."""
    warmup: Annotated[int, Field(ge=0, le=100)] = 1
    """Untimed runs after the compile."""
    set: list[str] = []
    """``key=value`` overrides applied to every scene."""
    sweep: dict[str, list[Any]] | list[dict[str, Any]] | None = None
    """Settings to time each scene at: a grid (key -> values), or explicit settings."""
    reference: list[str] = []
    """Overrides of the reference render every setting is scored against (empty: timing only)."""
    metric: str = "depth_rmse"
    """The error plotted against time."""
    peer: Literal["embree_mesh", "embree_same_mesh", "marching_cubes", "skeleton"] | None = None
    """A peer's study run on the reference's rays (``[peers]`` extra)."""
    peer_levels: list[Annotated[int, Field(ge=0, le=4096)]] = [0, 1, 2, 3, 4, 5]
    """The peer's subdivision or grid levels."""
    peer_match: dict[str, Any] | None = None
    """The jskel setting (key -> value) whose error a peer must match."""
    frames: list[float] = []
    """Animated scenes (``peer: skeleton``): frames timed per frame with rebuild, for jskel and the peers."""
    mitsuba_variant: str = "llvm_ad_rgb"
    """The Mitsuba variant tried first."""
    stats: bool = False
    """Frusta BVH: count nodes and leaves visited per ray (one extra untimed pass)."""
    cast: bool = False
    """Also time the cast alone (nearest t and primitive of every ray, no shading; what the peers' cast times
    hold): ``cast_s_median`` in each row."""
    pair_test: bool = False
    """Frusta: also time the (ray, segment) test alone on pairs of the scene's rays and segments
    (``frusta.pair_test_seconds``: ``pair_test_ns_median``) and, with ``stats`` and ``cast``,
    the share of the cast it takes (``pair_test_share_of_cast``)."""
    labels: list[str] | None = None
    """A name per sweep setting (rows and the bar chart of a timing-only sweep)."""
    isa: list[Literal["default", "SSE4_2", "AVX", "AVX2", "AVX512"]] = []
    """CPU vector ISAs to run the whole file under, one fresh process each with ``--xla_cpu_max_isa`` set
    (``default``: the CPU's own), rows together in one output; each row's ``isa`` says which XLA compiled for.
    Empty: this process's. Peers run at their own ISA in every pass."""

    def settings(self) -> list[dict]:
        """The sweep's settings (``grid.expand``; none without a sweep)."""
        return expand(self.sweep) if self.sweep is not None else []

    def study_options(self) -> StudyOptions:
        """The peer keys as the peers' studies take them."""
        return StudyOptions(tuple(self.peer_levels), self.peer_match, tuple(self.frames), self.mitsuba_variant)


class Job(NamedTuple):
    """One timed render: its file, experiment and setting (None outside a sweep)."""

    file: str
    exp: Any
    setting: dict | None


class Group(NamedTuple):
    """A scene's jobs and its reference experiment (or None)."""

    reference: Any
    jobs: list[Job]


def timed_render(exp, runs: int, warmup: int) -> tuple[dict, object]:
    """Render once (compiles; its compile seconds are kept), ``warmup - 1`` more, then ``runs``
    timed renders (``timing.render_runs``). Returns (row, first result)."""
    count_programs()
    before = program_counts()
    first, warm = render_runs(exp, runs, warmup)
    s = spread([w["render_s"] for w in warm])
    r = first.run
    row = {"scene": exp.name, "primitives": r["primitives"], "width": exp.camera.width, "height": exp.camera.height,
           "rays": r["rays"], "dtype": exp.render.dtype, "chunk": chunk_of(exp.render), "compile_s": round(r["compile_s"], 4),
           "render_s_median": round(s.median, 4), "render_s_min": round(s.min, 4), "render_s_max": round(s.max, 4),
           "runs": runs, "mrays_per_s": round(r["rays"] / s.median / 1e6, 4), "hit_fraction": round(r["hit_fraction"], 4),
           "device": r["device"], "jax": r["jax"], "jskel": r["jskel"], "isa": xla_isa()}
    # the build of warm runs (the first also compiles the jitted BVH build for new shapes)
    # what the first render's compile_s was: programs XLA compiled, programs JAX's persistent
    # cache served, executables loaded from disk (with none compiled it was a load: run the
    # bench with JSKEL_CACHE=off to time compiles)
    got = r["programs"]
    row["programs"] = {"compiled": got["compiled"] - before["compiled"], "loaded": got["loaded"] - before["loaded"],
                       "executables_loaded": got["executables"]["loaded"] - before["executables"]["loaded"]}
    row["build_s"] = round(spread([w["build_s"] for w in warm]).median, 4)
    row["build_first_s"] = round(r["build_s"], 4)
    row["us_per_ray"] = round(s.median / r["rays"] * 1e6, 4)
    for k in ("memory", "memory_bytes", "precompute_s", "cache"):
        if k in r["info"]:
            row[k] = r["info"][k]
    for k in ("effects", "secondary_rays", "spp", "flags"):  # scenes; flags: rays flagged, by bit name
        if k in r:
            row[k] = r[k]
    return row, first


def _built_and_rays(exp, key: str):
    """(representation, built object, the camera's rays in the render's tile order) of an
    experiment of one object (``probe.study.shape_of``, ``key`` naming what asks)."""
    obj = shape_of(exp, key)
    rep = registry.get(obj.type)
    built = rep.build(obj, dtype_of(exp))
    return rep, built, camera_of(framed(exp, built.bounds)).tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))


def traversal_stats(exp) -> dict:
    """The representation's deterministic work counts per ray (empty where it declares none),
    over the camera's rays in the render's order (screen tiles: packets and bins depend on it),
    of an experiment of one object (``probe.study.shape_of``)."""
    rep, built, rays = _built_and_rays(exp, "stats")
    stats = rep.traversal_stats(built, rays, chunk_of(exp.render))
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in stats.items()}


def pair_test_row(exp, row: dict) -> dict:
    """The representation's pair test timed alone on the experiment's camera rays
    (``pair_test_seconds``: the frusta's; ConfigError for one that times none) and, where ``row``
    has the cast's median and the pair tests per ray (bins: ``bin_tests_per_ray_mean``, which
    counts walked chunks' leaves too; walks: ``leaf_tests_per_ray_mean``), the share of the
    cast those tests take at that rate."""
    rep, built, rays = _built_and_rays(exp, "pair_test")
    out = rep.pair_test_seconds(built, rays)
    if not out:
        raise ConfigError([f"pair_test: the scene's representation {rep.name!r} times no pair test"])
    per_ray = row.get("bin_tests_per_ray_mean", row.get("leaf_tests_per_ray_mean"))
    if per_ray is not None and row.get("cast_s_median"):
        out["pair_test_share_of_cast"] = round(per_ray * row["rays"] * out["pair_test_ns_median"] * 1e-9 / row["cast_s_median"], 4)
    return out


def groups_of(bench: BenchFile, file, extra: list[str]) -> list[Group]:
    """Every scene's jobs, each experiment validated before anything compiles; ``extra``
    overrides (e.g. ``--x64``'s) apply to every scene after the bench's own."""
    common = [f"camera.width={bench.width}", f"camera.height={bench.height}", "render.progress=false", *bench.set, *extra]
    paths = [beside(s, file, f"scenes[{i}]") for i, s in enumerate(bench.scenes)]
    settings = bench.settings()
    if bench.labels is not None and len(bench.labels) != len(settings):
        raise ConfigError([f"labels: {len(bench.labels)} labels for {len(settings)} sweep settings"])
    if bench.sweep is None:
        return [Group(None, [Job(str(p), load(p, common), None) for p in paths])]
    # a sweep with no reference only times its settings (e.g. cost against scene size)
    return [Group(load(p, common + bench.reference) if bench.reference else None,
                  [Job(str(p), load(p, common + overrides_of(st)), st) for st in settings]) for p in paths]


def job_row(bench: BenchFile, job: Job, runs: int, ref) -> dict:
    """One job's row: its timed render, the cast alone (``cast``), traversal counts (``stats``),
    its setting and label, and its errors against the reference render ``ref`` (or None)."""
    row, first = timed_render(job.exp, runs, bench.warmup)
    if bench.cast:
        row.update(timed_cast(job.exp, runs, bench.warmup))
    row["file"] = job.file
    if bench.stats:
        row.update(traversal_stats(job.exp))
    if bench.pair_test:
        row.update(pair_test_row(job.exp, row))
    if job.setting is not None:
        row["setting"] = job.setting
        if bench.labels is not None:
            row["label"] = bench.labels[bench.settings().index(job.setting)]
        if ref is not None:
            errors = compare(first.hits, ref.hits, first.rgb, ref.rgb)
            row.update({k: (round(v, 8) if isinstance(v, float) else v) for k, v in errors.items()})
    return row


def as_rendered(exp, ref):
    """``exp`` with the camera its render ``ref`` used (``camera.frame: auto`` resolved from the
    built object's bounds, as run.json records it), so that a peer casts the same rays."""
    return exp.model_copy(update={"camera": type(exp.camera).model_validate(ref.run["config"]["camera"])})


def run_group(bench: BenchFile, group: Group, runs: int, emit: JsonLines, peers: Peers = Peers()) -> list[dict]:
    """Render the reference (one log line), time every job, then the peer's study (from
    ``peers``): the rows."""
    ref = None
    if group.reference is not None:
        ref = render(group.reference, progress=False)
        emit({"reference": bench.reference, "scene": group.reference.name, "render_s": round(ref.run["render_s"], 4)}, keep=False)
    rows = []
    for job in group.jobs:  # host loop over settings: each compiles its own static options
        rows.append(job_row(bench, job, runs, ref))
        emit(rows[-1])
    if bench.peer is not None and ref is not None:
        study = needed(peers.studies.get(bench.peer), "peer", bench.peer)
        for row in study(as_rendered(group.reference, ref), ref.hits, runs, rows, bench.study_options()):
            emit(row)
            rows.append(row)
    return rows


def _plotted(path):
    if path:
        print(f"jskel: plot -> {path}")


def plot_bench(bench: BenchFile, groups: list[Group], rows_by_group: list[list[dict]], out: Path):
    """Beside ``out``: error against time per scene with a reference; time per setting (bars)
    for a timing-only sweep, or cost against size with ``stats``."""
    keys = keys_of(bench.settings())
    for group, rows in zip(groups, rows_by_group):
        if group.reference is None:
            continue
        name = group.reference.name
        png = out.with_name(f"{out.stem}_{name}.png") if len(groups) > 1 else out.with_suffix(".png")
        _plotted(plot_sweep([r for r in rows if "setting" in r], keys, bench.metric, png,
                            f"{name}: {bench.metric} vs time ({rows[0]['device']})"))
    rows = [r for g in rows_by_group for r in g]
    if bench.sweep is None or bench.reference or not rows:
        return
    head = rows[0]
    if bench.stats:
        _plotted(plot_scaling(rows, out.with_suffix(".png"), f"{head['scene']}: cost per ray against segments ({head['device']})"))
    else:
        _plotted(plot_bars(rows, out.with_suffix(".png"),
                           f"{head['scene']} {head['width']}x{head['height']}: time per setting ({head['device']})"))


def run_bench(file, overrides: list[str], runs: int | None = None, out=None, x64: bool = False,
              command: str | None = None, peers: Peers = Peers()) -> list[dict]:
    """Run a bench file (``--set`` ``overrides`` of its keys, ``runs`` instead of its own, rows
    also to ``out``, every scene in float64 with ``x64``; ``command``: how it was asked for, in
    every kept row's provenance; ``peers``: the studies a ``peer:`` may name,
    ``jskel.peers.PEERS`` from the CLI). Returns the rows."""
    raw = read_yaml(file)
    if isinstance(raw, dict) and "fit" in raw:
        return run_fit_bench(read_model(FitBenchFile, file, overrides).fit, JsonLines(out, command))
    if isinstance(raw, dict) and "fit_trees" in raw:  # branching synthetic truths
        return run_tree_bench(read_model(TreeBenchFile, file, overrides).fit_trees, JsonLines(out, command))
    if isinstance(raw, dict) and "fit_real" in raw:  # real meshes beside a skeletonizer (a peer)
        model, fn = needed(peers.fit_real, "fit_real", "skeletor")
        return fn(read_model(model, file, overrides).fit_real, JsonLines(out, command))
    bench = read_model(BenchFile, file, overrides)
    if bench.isa:
        return run_per_isa(bench, file, overrides, runs, out, x64, command)
    groups = groups_of(bench, file, X64 if x64 else [])
    emit = JsonLines(out, command)
    if bench.peer is not None:  # before anything renders
        needed(peers.studies.get(bench.peer), "peer", bench.peer)
    rows_by_group = [run_group(bench, g, runs or bench.runs, emit, peers) for g in groups]
    if out is not None:
        plot_bench(bench, groups, rows_by_group, Path(out))
    return [r for g in rows_by_group for r in g]


def run_pass(argv: list[str], env: dict) -> subprocess.CompletedProcess:
    """One ISA's pass of :func:`run_per_isa`: the process, its rows to the file its ``--out`` names."""
    return subprocess.run(argv, env=env, stdout=subprocess.DEVNULL)


def run_per_isa(bench: BenchFile, file, overrides: list[str], runs: int | None, out, x64: bool, command: str | None) -> list[dict]:
    """The bench file run once per ISA of ``bench.isa``, each in a fresh ``python -m jskel bench``
    whose ``XLA_FLAGS`` cap the ISA (``compile.isa.with_max_isa``: XLA reads them when its CPU
    backend starts, so one process cannot compile for two), one after the other; their rows,
    each with its ``isa``, go to one output (plots: none). Returns the rows."""
    emit = JsonLines(out, command)
    rows: list[dict] = []
    for isa in bench.isa:
        with tempfile.TemporaryDirectory() as tmp:
            part = Path(tmp) / "rows.jsonl"
            argv = [sys.executable, "-m", "jskel", "bench", str(file), *(a for o in overrides for a in ("--set", o)), "--set", "isa=[]",
                    "--out", str(part), *(["--runs", str(runs)] if runs else []), *(["--x64"] if x64 else [])]
            env = {**os.environ, "XLA_FLAGS": with_max_isa(isa)}
            emit({"isa_pass": isa, "xla_flags": env["XLA_FLAGS"]}, keep=False)
            done = run_pass(argv, env)
            got = [json.loads(line) for line in part.read_text().splitlines() if line.strip()] if part.exists() else []
        for row in got:
            row.pop("run", None)  # the pass's own provenance: this file's run, and the row's isa, say it
            row["isa_pass"] = isa
            emit(row)
            rows.append(row)
        if done.returncode != 0:
            raise RuntimeError(f"isa: the {isa} pass exited with {done.returncode} ({' '.join(argv)})")
    return rows
