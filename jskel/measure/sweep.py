"""``python -m jskel sweep FILE --out DIR``: what accuracy costs in time (issue 8).

One base experiment is rendered at every setting of the varied config keys (``grid.expand``),
each timed as every measurement is (``timing``: compile apart, warm-up runs, median/min/max of
``runs`` warm renders, ``block_until_ready`` before every clock stops) and measured against a
reference render (the same scene at named high-quality overrides, e.g. 4096 steps in float64).
DIR gets ``results.csv`` (appended as rows finish, so an interrupted sweep resumes: settings whose
row is there are skipped, matched by their values), ``pareto.png`` (the first metric against time,
``plots``) and ``report.md`` (``results``).
"""

from __future__ import annotations

import csv
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Annotated, Any, Literal

import jax
import numpy as np
from jax.experimental import multihost_utils
from pydantic import Field, field_validator, model_validator
from tqdm.auto import tqdm

from ..compile.cache import count_programs, program_counts
from ..config import ConfigError, StrictModel, load
from ..probe.metrics import compare, depth_in_pixels, ssim
from ..probe.study import Peers, StudyOptions, needed
from ..probe.timing import render_runs, spread
from ..progress import quiet
from ..render import render
from .files import beside, provenance, read_model
from .grid import Range, expand, keys_of, overrides_of, setting_key
from .plots import plot_sweep_file
from .results import cell, columns, read_done, write_report

#: metric name -> where it comes from (``metrics.compare``, ``metrics.ssim``, the run's bytes)
METRICS = ("hit_miss_pct", "prim_mismatch_pct", "depth_rmse", "depth_max", "normal_deg_mean", "normal_deg_max",
           "uv_rmse", "image_rmse", "psnr_db", "ssim", "depth_px_p99", "depth_px_max", "memory_bytes")


class SweepFile(StrictModel):
    """A sweep: ``base`` experiment (path relative to the sweep file), overrides for all
    (``set``), the grid ``vary`` (key -> list or range; cartesian product) or explicit
    ``settings``, the ``reference`` overrides (empty list: no reference, no error metrics), the
    metrics and the timing."""

    base: str
    """The base experiment (as given, or relative to the sweep file's folder)."""
    set: list[str] = []
    """``key=value`` overrides for every setting."""
    vary: dict[str, list[Any] | Range] = {}
    """The grid: key -> values or a range; the cartesian product, first key slowest."""
    settings: list[dict[str, Any]] | None = Field(default=None, validate_default=True)
    """Explicit settings (each key -> value) instead of ``vary``."""
    reference: list[str] | None = None
    """Overrides of the reference render (empty or unset: no reference, no error metrics)."""
    metrics: list[str] = ["hit_miss_pct", "depth_rmse", "psnr_db"]
    """Metrics in results.csv; the first is plotted against time."""
    runs: Annotated[int, Field(ge=1, le=1000)] = 5
    """Warm runs timed per setting."""
    warmup: Annotated[int, Field(ge=0, le=100)] = 1
    """Untimed runs after the compile."""
    parallel: Annotated[int, Field(ge=1, le=256)] = 1
    """Worker processes, one setting at a time each."""
    peer: Literal["relief_mesh"] | None = None
    """Bhagvat Fig. 6: the relief as displaced meshes cast by Embree (``[peers]`` extra), one row per level."""
    peer_levels: list[Annotated[int, Field(ge=0, le=12)]] = [0, 1, 2, 3, 4, 5, 6]
    """The peer's subdivision levels."""

    @field_validator("metrics")
    @classmethod
    def _known_metrics(cls, v):
        bad = [m for m in v if m not in METRICS]
        if bad:
            raise ValueError(f"unknown {', '.join(map(repr, bad))} (known: {', '.join(METRICS)})")
        return v

    @field_validator("vary")
    @classmethod
    def _no_empty_lists(cls, v):
        empty = [k for k, x in v.items() if isinstance(x, list) and not x]
        if empty:
            raise ValueError(f"empty list for {', '.join(empty)}")
        return v

    @model_validator(mode="after")
    def _peer_needs_reference(self):
        if self.peer is not None and not self.reference:
            raise ValueError(f"peer: {self.peer} is scored against the reference: give 'reference' too")
        return self

    @field_validator("settings")
    @classmethod
    def _one_grid(cls, v, info):
        vary = info.data.get("vary")
        if not vary and not v:
            raise ValueError("give 'vary' (key -> values) or 'settings' (a list of overrides)")
        if vary and v:
            raise ValueError("give either 'vary' or 'settings', not both")
        return v

    def grid(self) -> list[dict]:
        """The settings, in order: explicit, or the product of ``vary`` (first key slowest)."""
        return expand(self.settings if self.settings is not None else self.vary)


def reference_overrides(sweep: SweepFile, setting: dict) -> list[str] | None:
    """The overrides of a setting's reference: the sweep's ``set``, the setting, then the
    ``reference`` overrides (which win). Settings that differ only in keys the reference
    overrides (the quality knobs) share one reference render; settings that differ in others
    (a mode, a scene option) get their own. None without a reference."""
    if not sweep.reference:
        return None
    merged: dict[str, str] = {}
    for item in sweep.set + overrides_of(setting) + sweep.reference:
        k, v = item.split("=", 1)
        merged[k.strip()] = v
    return [f"{k}={v}" for k, v in sorted(merged.items())]


def load_sweep(path, overrides: list[str], exp_overrides: list[str] = ()):
    """Read and validate a sweep file and every setting's experiment and reference (x64 is
    switched on here if any of them asks for float64, before anything compiles). Returns
    (sweep, jobs [(setting, experiment)], ref_jobs [(key, experiment) or None], with one more
    reference job at the end, the base setting's, when the sweep has a peer); bad input raises
    ``ConfigError`` naming the setting and key. ``exp_overrides`` (e.g. ``--x64``'s) apply to
    every setting before its own values."""
    sweep = read_model(SweepFile, path, overrides)
    base = beside(sweep.base, path, "base")
    jobs, ref_jobs, seen = [], [], {}

    def ref_job(setting):
        ro = reference_overrides(sweep, setting)
        if ro is None:
            return None
        key = json.dumps(ro)
        return seen.setdefault(key, (key, load(base, ro)))

    for i, st in enumerate(sweep.grid()):
        try:
            jobs.append((st, load(base, sweep.set + list(exp_overrides) + overrides_of(st))))
            ref_jobs.append(ref_job(st))
        except ConfigError as e:
            raise ConfigError([f"setting {i} {json.dumps(st)}: {line}" for line in e.lines]) from None
    if sweep.peer is not None:  # the peer is scored against the base setting's reference
        ref_jobs.append(ref_job({}))
    return sweep, jobs, ref_jobs


def measure(exp, ref, sweep: SweepFile) -> dict:
    """Time one setting (``timing.render_runs``) and score it against ``ref`` (or None)."""
    first, warm = render_runs(exp, sweep.runs, sweep.warmup)
    s = spread([w["render_s"] for w in warm])
    run = first.run
    row = {"compile_s": run["compile_s"], "time_median_s": s.median, "time_min_s": s.min, "time_max_s": s.max,
           "runs": sweep.runs, "rays": run["rays"], "rays_per_s": run["rays"] / s.median if s.median > 0 else None,
           "hit_fraction": run["hit_fraction"], "device": run["device"], "jax": run["jax"], "dtype": exp.render.dtype,
           "memory_bytes": run["params_bytes"]}
    if ref is not None:
        row.update(compare(first.hits, ref.hits, first.rgb, ref.rgb))
        if "ssim" in sweep.metrics:
            row["ssim"] = ssim(first.rgb, ref.rgb, (exp.camera.height, exp.camera.width))
        row.update(depth_in_pixels(first.hits.t, ref.hits.t, exp.camera.fov_deg, exp.camera.height))
    return row


def programs_since(before: dict) -> dict:
    """The programs handed to XLA since ``before`` (``program_counts()``), as run.json counts
    them: ``compiled``, ``loaded`` from JAX's persistent cache, and ``executables_loaded``
    (stored executables read back: neither traced nor handed to XLA)."""
    after = program_counts()
    return {"compiled": after["compiled"] - before["compiled"], "loaded": after["loaded"] - before["loaded"],
            "executables_loaded": after["executables"]["loaded"] - before["executables"]["loaded"]}


def _reference(rj, refs: dict):
    """The render of reference job ``rj`` (key, experiment), rendered once per key into ``refs``."""
    if rj[0] not in refs:
        refs[rj[0]] = render(rj[1], progress=False)
    return refs[rj[0]]


def measure_setting(sweep: SweepFile, setting: dict, job, rj, refs: dict) -> dict:
    """One row: the setting measured against its reference (or none)."""
    count_programs()
    before = program_counts()
    row = measure(job, None if rj is None else _reference(rj, refs), sweep)
    row.update(programs_since(before))
    row.update(setting)
    row["setting"] = setting_key(setting)
    return row


def peer_rows(sweep: SweepFile, ref_job, refs: dict, levels: list[int], embree_mesh) -> list[dict]:
    """Bhagvat et al. 2009, Fig. 6 ("GS+R"): the base experiment's relief as displaced triangle
    meshes (``embree_mesh``: ``Peers.mesh``, the CLI's ``peers.mesh_studies.embree_mesh``) at subdivision ``levels``, cast by Embree on the
    same rays and scored against the base setting's reference. Time: Embree's warm median cast
    (its BVH build apart, in ``peer_build_s``); memory: the mesh's bytes."""
    rows = []
    for r in embree_mesh(ref_job[1], _reference(ref_job, refs).hits, sweep.runs, [], StudyOptions(levels=tuple(levels))):
        row = {k: v for k, v in r.items() if k in sweep.metrics or k in ("hit_miss_pct", "depth_rmse")}
        row.update({"peer.level": r["level"], "triangles": r["triangles"], "peer_build_s": r["build_s"],
                    "time_median_s": r["render_s_median"], "runs": r["runs"], "rays": r["rays"],
                    "memory_bytes": r["mesh_bytes"], "device": "embree (cpu)", "setting": setting_key({"peer.level": r["level"]})})
        rows.append(row)
    return rows


_WORKER: dict = {}


def _worker_init():
    """A worker process of a parallel sweep: asks XLA for single-threaded Eigen kernels, so N
    workers contend less for the cores (XLA may still run some work on more threads)."""
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()


def _worker_row(spec, index: int) -> dict:
    """Measure setting ``index`` of the sweep ``spec`` = (path, overrides, experiment overrides)
    in a worker process; the parsed sweep and its reference renders are kept for the worker's
    next settings."""
    if spec not in _WORKER:
        _WORKER.clear()
        _WORKER[spec] = (load_sweep(spec[0], list(spec[1]), list(spec[2])), {})
    (sweep, jobs, ref_jobs), refs = _WORKER[spec]
    return measure_setting(sweep, *jobs[index], ref_jobs[index], refs)


def _rows_parallel(spec, indices: list[int], workers: int):
    spec = (spec[0], tuple(spec[1]), tuple(spec[2]))
    # spawned workers start with JAX's one host device: only the CLI asks for one per core
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init) as pool:
        futures = [pool.submit(_worker_row, spec, i) for i in indices]
        for fut in as_completed(futures):
            yield fut.result()


def _todo(sweep: SweepFile, jobs: list, done: dict) -> list[int]:
    """The indices of settings without a row; several hosts all follow process 0's list."""
    todo_mask = np.array([setting_key(s) not in done for s, _ in jobs])
    if jax.process_count() > 1 and sweep.peer is not None:
        raise ValueError(f"peer: {sweep.peer} runs on one host (got {jax.process_count()} processes)")
    if jax.process_count() > 1:
        todo_mask = np.asarray(multihost_utils.broadcast_one_to_all(todo_mask))
    return [i for i in range(len(jobs)) if todo_mask[i]]


def _append(path: Path, cols: list[str], rows_iter, total: int, initial: int, progress: bool | None):
    """Append rows to ``results.csv`` as they finish (header first in a new file)."""
    new_file = not path.exists()
    if not new_file:  # a file written before a column was added keeps its own columns
        with path.open(newline="") as f:
            cols = next(csv.reader(f), None) or cols
    disable = quiet() if progress is None else (not progress)
    with path.open("a", newline="") as f, tqdm(total=total, initial=initial, desc="settings", unit="setting", disable=disable) as bar:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        if new_file:
            w.writeheader()
        for row in rows_iter:
            w.writerow({k: cell(row.get(k)) for k in cols})
            f.flush()
            bar.update(1)


def run_sweep(sweep: SweepFile, jobs: list, ref_jobs: list, out: Path, progress: bool | None = None, spec=None,
              command: str | None = None, peers: Peers = Peers()) -> list[dict]:
    """Measure every job ``(setting, experiment)`` not already in ``out/results.csv`` against its
    reference job (``ref_jobs[i]``: ``(key, experiment)`` or None; renders shared by key),
    appending rows as they finish; then write the plot and the report. Returns every row.

    With ``parallel: N`` (and ``spec`` = (sweep file, overrides, experiment overrides) for the
    workers to read) the settings are measured by N spawned processes (single-threaded Eigen in
    XLA), one setting at a time each, every worker rendering the references it needs once. Their
    timings then share the machine with each other: use it where accuracy is what the sweep is
    for, or where there are more cores than workers.

    Several hosts (the ``JSKEL_*`` variables of ``jskel.distributed``): every process measures
    every setting, each render spread over the hosts as ``jskel render`` does, in the order of
    process 0's list of settings still to do; process 0 alone reads and writes ``out``.
    ``command`` (how the sweep was asked for) goes into the report's provenance line. ``peers``:
    the Embree mesh study a ``peer:`` asks for (``Peers.mesh``; the CLI passes ``jskel.peers.PEERS``)."""
    if sweep.peer is not None:  # before anything renders
        needed(peers.mesh, "peer", sweep.peer)
    writer = jax.process_index() == 0
    path = out / "results.csv"
    keys = keys_of([s for s, _ in jobs])
    cols = columns(sweep, keys)
    done = read_done(path) if writer else {}
    todo = _todo(sweep, jobs, done)
    refs: dict[str, object] = {}
    if not writer:  # the other hosts render their share of every setting; process 0 writes
        for i in todo:
            measure_setting(sweep, *jobs[i], ref_jobs[i], refs)
        return []
    out.mkdir(parents=True, exist_ok=True)
    if sweep.parallel > 1 and spec is not None and len(todo) > 1 and jax.process_count() == 1:
        rows_iter = _rows_parallel(spec, todo, min(sweep.parallel, len(todo)))
    else:
        rows_iter = (measure_setting(sweep, *jobs[i], ref_jobs[i], refs) for i in todo)  # host loop over settings
    _append(path, cols, rows_iter, len(jobs), len(jobs) - len(todo), progress)
    if sweep.peer is not None:
        levels = [lv for lv in sweep.peer_levels if setting_key({"peer.level": lv}) not in done]
        if levels:
            _append(path, cols, peer_rows(sweep, ref_jobs[-1], {}, levels, needed(peers.mesh, "peer", sweep.peer)), len(levels), 0, False)
    rows = list(read_done(path).values())
    plot = plot_sweep_file(rows, keys, sweep.metrics[0], out / "pareto.png")
    write_report(sweep, rows, keys, out / "report.md", plot, provenance(command))
    return rows
