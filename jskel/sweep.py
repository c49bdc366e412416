"""Sweeps: what accuracy costs in time (issue 8).

``python -m jskel sweep FILE --out DIR`` renders one base experiment at every setting of the
varied config keys, times each (compile apart, warm-up runs, median/min/max of ``runs`` warm
renders, ``block_until_ready`` inside the chunked evaluation before every clock stops), measures
it against a reference render (the same scene at named high-quality overrides, e.g. 4096 steps in
float64) and writes into DIR:

* ``results.csv``: one row per setting: every varied value, compile seconds, warm median, min
  and max seconds, runs, rays per second, each metric, the representation's device bytes, device
  and versions. Rows are appended as they finish, so an interrupted sweep resumes: settings
  whose row is there are skipped (matched by their values, not their position).
* ``pareto.png``: the first metric against time, log axes, the Pareto front marked.
* ``report.md``: the sweep, the environment, the plot and the table.

Nothing is reported that was not measured in this run or read back from ``results.csv``.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from .config import StrictModel

#: metric name -> where it comes from (``metrics.compare``, ``metrics.ssim``, the run's bytes)
METRICS = ("hit_miss_pct", "prim_mismatch_pct", "depth_rmse", "depth_max", "normal_deg_mean", "normal_deg_max",
           "uv_rmse", "image_rmse", "psnr_db", "ssim", "depth_px_p99", "depth_px_max", "memory_bytes")


class Range(StrictModel):
    """``num`` values from ``start`` to ``stop`` inclusive, evenly spaced, or geometrically with
    ``log: true``; ``integer: true`` rounds them (duplicates dropped)."""

    start: float
    stop: float
    num: Annotated[int, Field(ge=1, le=10000)]
    log: bool = False
    integer: bool = False

    @model_validator(mode="after")
    def _positive_for_log(self):
        if self.log and (self.start <= 0 or self.stop <= 0):
            raise ValueError(f"a log range needs start and stop > 0 (got {self.start}, {self.stop})")
        return self

    def values(self) -> list:
        if self.num == 1:
            vals = [self.start]
        elif self.log:
            r = math.log(self.stop / self.start) / (self.num - 1)
            vals = [self.start * math.exp(r * i) for i in range(self.num)]
        else:
            vals = [self.start + (self.stop - self.start) * i / (self.num - 1) for i in range(self.num)]
        if self.integer:
            vals = list(dict.fromkeys(int(round(v)) for v in vals))
        return vals


class SweepFile(StrictModel):
    """A sweep: ``base`` experiment (path relative to the sweep file), overrides for all
    (``set``), the grid ``vary`` (key -> list or range; cartesian product) or explicit
    ``settings``, the ``reference`` overrides (empty list: no reference, no error metrics), the
    metrics and the timing."""

    base: str
    set: list[str] = []
    vary: dict[str, list[Any] | Range] = {}
    settings: list[dict[str, Any]] | None = Field(default=None, validate_default=True)
    reference: list[str] | None = None
    metrics: list[str] = ["hit_miss_pct", "depth_rmse", "psnr_db"]
    runs: Annotated[int, Field(ge=1, le=1000)] = 5
    warmup: Annotated[int, Field(ge=0, le=100)] = 1
    parallel: Annotated[int, Field(ge=1, le=256)] = 1  # worker processes, one setting at a time each
    # Bhagvat Fig. 6: the relief as displaced meshes cast by Embree ([peers] extra), one row per level
    peer: Literal["relief_mesh"] | None = None
    peer_levels: list[Annotated[int, Field(ge=0, le=12)]] = [0, 1, 2, 3, 4, 5, 6]

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
        if self.settings is not None:
            return [dict(s) for s in self.settings]
        keys = list(self.vary)
        lists = [v.values() if isinstance(v, Range) else list(v) for v in self.vary.values()]
        return [dict(zip(keys, vals)) for vals in itertools.product(*lists)]


def setting_key(setting: dict) -> str:
    """The identity of a setting in ``results.csv`` (JSON of its values, keys sorted)."""
    return json.dumps(setting, sort_keys=True)


def read_done(path: Path) -> dict[str, dict]:
    """Rows of an existing ``results.csv`` by setting key (an interrupted sweep's work)."""
    if not path.exists():
        return {}
    with path.open(newline="") as f:
        return {row["setting"]: row for row in csv.DictReader(f)}


def columns(sweep: SweepFile, keys: list[str]) -> list[str]:
    """The columns of results.csv: varied keys, peer columns, timings, metrics, environment."""
    peer = ["peer.level", "triangles", "peer_build_s"] if sweep.peer else []
    return (keys + peer + ["compile_s", "time_median_s", "time_min_s", "time_max_s", "runs", "rays", "rays_per_s"]
            + list(sweep.metrics) + ["hit_fraction", "device", "jax", "dtype", "setting"])


def peer_rows(sweep: SweepFile, ref_job, refs: dict, levels: list[int]) -> list[dict]:
    """Bhagvat et al. 2009, Fig. 6 ("GS+R"): the base experiment's relief as displaced triangle
    meshes (``jskel.peers.relief_mesh``) at subdivision ``levels``, cast by Embree on the same
    rays and scored against the base setting's reference. Time: Embree's warm median cast
    (its BVH build apart, in ``peer_build_s``); memory: the mesh's bytes."""
    from types import SimpleNamespace

    from .bench import peer_embree_mesh
    from .render import render

    if ref_job[0] not in refs:
        refs[ref_job[0]] = render(*ref_job[1], progress=False)
    exp, obj = ref_job[1]
    spec = SimpleNamespace(peer_levels=levels, peer_match=None)
    rows = []
    for r in peer_embree_mesh(spec, exp, obj, refs[ref_job[0]].hits, sweep.runs, []):
        row = {k: v for k, v in r.items() if k in sweep.metrics or k in ("hit_miss_pct", "depth_rmse")}
        row.update({"peer.level": r["level"], "triangles": r["triangles"], "peer_build_s": r["build_s"],
                    "time_median_s": r["render_s_median"], "runs": r["runs"], "rays": r["rays"],
                    "memory_bytes": r["mesh_bytes"], "device": "embree (cpu)", "setting": setting_key({"peer.level": r["level"]})})
        rows.append(row)
    return rows


def equal_error(rows: list[dict], metric: str) -> list[dict]:
    """For each jskel row, the peer row with the fewest triangles whose ``metric`` and hit/miss
    disagreement are both at most jskel's (Fig. 6's "similar quality"), or None."""
    peers = sorted((r for r in rows if str(r.get("peer.level", "")) != ""), key=lambda r: int(r["triangles"]))
    out = []
    for r in rows:
        if str(r.get("peer.level", "")) != "" or _num(r.get(metric)) is None:
            continue
        match = next((p for p in peers if _num(p.get(metric)) is not None and _num(p[metric]) <= _num(r[metric])
                      and _num(p.get("hit_miss_pct", 0)) <= _num(r.get("hit_miss_pct", 0))), None)
        out.append({"setting": r["setting"], "error": _num(r[metric]), "time_s": _num(r["time_median_s"]),
                    "triangles": None if match is None else int(match["triangles"]),
                    "peer_time_s": None if match is None else _num(match["time_median_s"])})
    return out


def measure(exp, obj, ref, sweep: SweepFile) -> dict:
    """Time one setting (compile apart, warm-up, ``runs`` warm renders) and score it."""
    import statistics

    from .metrics import compare, depth_in_pixels, ssim
    from .render import render

    first = render(exp, obj, progress=False)
    for _ in range(max(sweep.warmup - 1, 0)):
        render(exp, obj, progress=False)
    times = [render(exp, obj, progress=False).run["render_s"] for _ in range(sweep.runs)]
    med = statistics.median(times)
    run = first.run
    row = {"compile_s": run["compile_s"], "time_median_s": med, "time_min_s": min(times), "time_max_s": max(times),
           "runs": sweep.runs, "rays": run["rays"], "rays_per_s": run["rays"] / med if med > 0 else None,
           "hit_fraction": run["hit_fraction"], "device": run["device"], "jax": run["jax"], "dtype": exp.render.dtype,
           "memory_bytes": run["params_bytes"]}
    if ref is not None:
        row.update(compare(first.hits, ref.hits, first.rgb, ref.rgb))
        if "ssim" in sweep.metrics:
            row["ssim"] = ssim(first.rgb, ref.rgb, (exp.camera.height, exp.camera.width))
        row.update(depth_in_pixels(first.hits.t, ref.hits.t, exp.camera.fov_deg, exp.camera.height))
    return row


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.6g}"
    return "" if v is None else v


def reference_overrides(sweep: SweepFile, setting: dict) -> list[str] | None:
    """The overrides of a setting's reference: the sweep's ``set``, the setting, then the
    ``reference`` overrides (which win). Settings that differ only in keys the reference
    overrides (the quality knobs) share one reference render; settings that differ in others
    (a mode, a scene option) get their own. None without a reference."""
    if not sweep.reference:
        return None
    merged: dict[str, str] = {}
    for item in sweep.set + [f"{k}={json.dumps(v)}" for k, v in setting.items()] + sweep.reference:
        k, v = item.split("=", 1)
        merged[k.strip()] = v
    return [f"{k}={v}" for k, v in sorted(merged.items())]


def load_sweep(path, overrides: list[str], exp_overrides: list[str] = ()):
    """Read and validate a sweep file and every setting's experiment and reference (x64 is
    switched on here if any of them asks for float64, before anything compiles). Returns
    (sweep, jobs [(setting, (exp, obj))], ref_jobs [(key, (exp, obj)) or None], with one more
    reference job at the end, the base setting's, when the sweep has a peer); bad input raises
    ``ConfigError`` naming the setting and key. ``exp_overrides`` (e.g. ``--x64``'s) apply to
    every setting before its own values."""
    from .cli import _load, _read_model
    from .config import ConfigError

    sweep = _read_model(SweepFile, path, overrides)
    base = resolve_base(sweep, Path(path))
    if not base.exists():
        raise ConfigError([f"base: file not found (got {sweep.base!r})"])
    jobs, ref_jobs, seen = [], [], {}
    for i, st in enumerate(sweep.grid()):
        try:
            jobs.append((st, _load(base, sweep.set + list(exp_overrides) + [f"{k}={json.dumps(v)}" for k, v in st.items()])))
            ro = reference_overrides(sweep, st)
            if ro is not None:
                key = json.dumps(ro)
                seen.setdefault(key, (key, _load(base, ro)))
            ref_jobs.append(None if ro is None else seen[key])
        except ConfigError as e:
            raise ConfigError([f"setting {i} {json.dumps(st)}: {line}" for line in e.lines]) from None
    if sweep.peer is not None:  # the peer is scored against the base setting's reference
        ro = reference_overrides(sweep, {})
        key = json.dumps(ro)
        seen.setdefault(key, (key, _load(base, ro)))
        ref_jobs.append(seen[key])
    return sweep, jobs, ref_jobs


def measure_setting(sweep: SweepFile, setting: dict, job, rj, refs: dict) -> dict:
    """One row: the setting measured against its reference (rendered once per key into
    ``refs``)."""
    from .render import render

    ref = None
    if rj is not None:
        if rj[0] not in refs:
            refs[rj[0]] = render(*rj[1], progress=False)
        ref = refs[rj[0]]
    row = measure(*job, ref, sweep)
    row.update(setting)
    row["setting"] = setting_key(setting)
    return row


_WORKER: dict = {}


def _worker_init():
    """A worker process of a parallel sweep: asks XLA for single-threaded Eigen kernels, so N
    workers contend less for the cores (XLA may still run some work on more threads)."""
    import os

    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()


def _worker_row(spec, index: int) -> dict:
    """Measure setting ``index`` of the sweep ``spec`` = (path, overrides, experiment overrides)
    in a worker process;
    the parsed sweep and its reference renders are kept for the worker's next settings."""
    if spec not in _WORKER:
        _WORKER.clear()
        _WORKER[spec] = (load_sweep(spec[0], list(spec[1]), list(spec[2])), {})
    (sweep, jobs, ref_jobs), refs = _WORKER[spec]
    return measure_setting(sweep, *jobs[index], ref_jobs[index], refs)


def _rows_parallel(spec, indices: list[int], workers: int):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    spec = (spec[0], tuple(spec[1]), tuple(spec[2]))
    # spawned workers start with JAX's one host device: only the CLI asks for one per core
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init) as pool:
        futures = [pool.submit(_worker_row, spec, i) for i in indices]
        for fut in as_completed(futures):
            yield fut.result()


def run_sweep(sweep: SweepFile, jobs: list, ref_jobs: list, out: Path, progress: bool | None = None, spec=None) -> list[dict]:
    """Measure every job ``(setting, (exp, obj))`` not already in ``out/results.csv`` against its
    reference job (``ref_jobs[i]``: ``(key, (exp, obj))`` or None; renders shared by key),
    appending rows as they finish; then write the plot and the report. Returns every row.

    With ``parallel: N`` (and ``spec`` = (sweep file, overrides, experiment overrides) for the
    workers to read) the
    settings are measured by N spawned processes (single-threaded Eigen in XLA), one setting at a
    time each, every worker rendering the references it needs once. Their timings then share
    the machine with each other: use it where accuracy is what the sweep is for, or where
    there are more cores than workers.

    Several hosts (the ``JSKEL_*`` variables of ``jskel.distributed``): every process measures
    every setting, each render spread over the hosts as ``jskel render`` does, in the order of
    process 0's list of settings still to do; process 0 alone reads and writes ``out``."""
    import sys

    from tqdm.auto import tqdm

    import jax

    hosts = jax.process_count()
    writer = jax.process_index() == 0
    path = out / "results.csv"
    keys = list(dict.fromkeys(k for s, _ in jobs for k in s))
    cols = columns(sweep, keys)
    done = read_done(path) if writer else {}
    todo_mask = np.array([setting_key(s) not in done for s, _ in jobs])
    if hosts > 1 and sweep.peer is not None:
        raise ValueError(f"peer: {sweep.peer} runs on one host (got {hosts} processes)")
    if hosts > 1:  # several hosts render every setting together: all follow process 0's list
        from jax.experimental import multihost_utils

        todo_mask = np.asarray(multihost_utils.broadcast_one_to_all(todo_mask))
    todo = [i for i in range(len(jobs)) if todo_mask[i]]
    if not writer:  # the other hosts render their share of every setting; process 0 writes
        refs: dict[str, object] = {}
        for i in todo:
            measure_setting(sweep, *jobs[i], ref_jobs[i], refs)
        return []
    out.mkdir(parents=True, exist_ok=True)
    if sweep.parallel > 1 and spec is not None and len(todo) > 1 and hosts == 1:
        rows_iter = _rows_parallel(spec, todo, min(sweep.parallel, len(todo)))
    else:
        refs: dict[str, object] = {}
        rows_iter = (measure_setting(sweep, *jobs[i], ref_jobs[i], refs) for i in todo)  # host loop over settings
    new_file = not path.exists()
    disable = (not sys.stderr.isatty()) if progress is None else (not progress)
    with path.open("a", newline="") as f, tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="settings",
                                               unit="setting", disable=disable) as bar:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        if new_file:
            w.writeheader()
        for row in rows_iter:
            w.writerow({k: _fmt(row.get(k)) for k in cols})
            f.flush()
            bar.update(1)
        if sweep.peer is not None:
            levels = [lv for lv in sweep.peer_levels if setting_key({"peer.level": lv}) not in done]
            if levels:
                for row in peer_rows(sweep, ref_jobs[-1], {}, levels):
                    w.writerow({k: _fmt(row.get(k)) for k in cols})
                    f.flush()
    rows = list(read_done(path).values())
    plot = plot_pareto(rows, keys, sweep.metrics[0], out / "pareto.png")
    write_report(sweep, rows, keys, out / "report.md", plot)
    return rows


def _num(x):
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


def plot_pareto(rows: list[dict], keys: list[str], metric: str, path: Path):
    """Error against warm median time on log axes, the Pareto front marked (``bench.pareto_plot``);
    None when no row has a positive value of ``metric`` (e.g. a sweep without a reference)."""
    from .bench import pareto_plot

    pts = [(r, _num(r.get("time_median_s")), _num(r.get(metric))) for r in rows]
    pts = [(r, t, e) for r, t, e in pts if t is not None and e is not None and e > 0]
    if not pts:
        return None
    mesh = [str(r.get("peer.level", "")) != "" for r, _, _ in pts]
    labels = [f"mesh {r['peer.level']}" if m else ",".join(str(r.get(k, "")) for k in keys) for (r, _, _), m in zip(pts, mesh)]
    title = f"{metric} against time ({rows[0].get('device', '')}); labels: " + ", ".join(k.split(".")[-1] for k in keys)
    return pareto_plot([p[1] for p in pts], [p[2] for p in pts], labels, path, metric, title, mesh, "displaced mesh, Embree")


def write_report(sweep: SweepFile, rows: list[dict], keys: list[str], path: Path, plot):
    """report.md: the sweep's file, environment, a table of every setting and the plot."""
    import platform

    import jax

    cols = keys + ["time_median_s", "time_min_s", "time_max_s", "compile_s"] + list(sweep.metrics)
    lines = [f"# Sweep of {sweep.base}", "",
             f"Varied: {', '.join(keys)}. Reference: {', '.join(sweep.reference) if sweep.reference else 'none'}. "
             f"Timing: median of {sweep.runs} warm runs after {sweep.warmup} warm-up, compile apart"
             + (f"; {sweep.parallel} worker processes shared the machine." if sweep.parallel > 1 else "."),
             f"Device: {rows[0].get('device', '?') if rows else '?'}; jax {jax.__version__}; Python {platform.python_version()}; "
             f"{platform.machine()}.", ""]
    if plot is not None:
        lines += [f"![{sweep.metrics[0]} against time]({Path(plot).name})", ""]
    if sweep.peer is not None:
        cols = keys + ["peer.level", "triangles"] + cols[len(keys):]
    lines += ["| " + " | ".join(c.split(".")[-1] if c != "peer.level" else "mesh level" for c in cols) + " |",
              "| " + " | ".join("---" for _ in cols) + " |"]
    for r in rows:
        lines.append("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    if sweep.peer is not None:
        m = sweep.metrics[0]
        lines += ["", f"Equal error (Fig. 6): the smallest mesh whose {m} and hit/miss % are at most the setting's.", "",
                  f"| setting | {m} | time s | mesh triangles | Embree cast s |", "| --- | --- | --- | --- | --- |"]
        for e in equal_error(rows, m):
            tri = "none up to the largest level" if e["triangles"] is None else f"{e['triangles']:,}"
            pt = "" if e["peer_time_s"] is None else f"{e['peer_time_s']:.4g}"
            lines.append(f"| {e['setting']} | {e['error']:.4g} | {e['time_s']:.4g} | {tri} | {pt} |")
    path.write_text("\n".join(lines) + "\n")
    return path


def resolve_base(sweep: SweepFile, sweep_path: Path) -> Path:
    """The base experiment's path, as given or relative to the sweep file."""
    p = Path(sweep.base)
    return p if p.exists() else sweep_path.parent / sweep.base

