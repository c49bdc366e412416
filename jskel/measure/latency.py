"""``python -m jskel bench experiments/bench_latency.yaml``: time to first image (issue 27).

Each case is a fresh process (``python -m jskel render|sweep|fit ...``) timed from its start to
its outputs written (the newest file in its output folder; ``wall_s`` is to its exit), first
with an empty persistent compilation cache (a temporary ``JSKEL_CACHE_DIR`` of its own, JAX's
own variable unset), then again with that cache warm. Rows carry the compile, build and render
seconds and the programs compiled and loaded that the process wrote (run.json, fit.json), and a
fit's seconds from its start to its first iteration done (``first_iteration_s``). The
bare-JAX floor (a process that imports JAX and runs one operation) and, when installed,
Mitsuba's ``scalar_rgb`` process for the same skeleton (``peers.mitsuba_image``) are reference
rows of the same run; every case row also says its seconds over the floor. Then, in this
process, a render and a second render after each change (a radius, the camera, the image size,
the skeleton's segment count), each with the programs it compiled.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated, Callable

from pydantic import Field

from ..compile.cache import count_programs, program_counts
from ..config import StrictModel, load, read_yaml
from ..probe.study import Peers, needed
from ..render import render
from .files import JsonLines, beside, read_model

FLOOR = [sys.executable, "-c", "import jax; jax.numpy.zeros(3).block_until_ready()"]


class Case(StrictModel):
    """A sweep or fit file and the overrides that make it small."""

    file: str
    """The sweep or fit file."""
    set: list[str] = []
    """``key=value`` overrides that make it small."""


class LatencySpec(StrictModel):
    """What the latency benchmark times (the ``latency:`` section of its file)."""

    default: bool = True
    """Time the embedded default experiment (``jskel render --out X``)."""
    gallery: list[str] = []
    """Experiment files, rendered as they are (with ``set``)."""
    set: list[str] = []
    """Overrides for every gallery render (the default runs as it is)."""
    sweep: Case | None = None
    """A sweep timed as ``jskel sweep`` processes."""
    fit: Case | None = None
    """A fit timed as ``jskel fit`` processes."""
    rerender: str | None = None
    """A skeleton experiment re-rendered in this process after each change."""
    mitsuba: str | None = None
    """The experiment whose skeleton Mitsuba's process renders."""
    mitsuba_variant: str = "scalar_rgb"
    """Mitsuba's variant."""
    repeats: Annotated[int, Field(ge=1, le=20)] = 1
    """Cold/warm pairs per case."""
    timeout_s: Annotated[float, Field(gt=0)] = 1800.0
    """Limit on each process, seconds."""


class LatencyFile(StrictModel):
    """A latency benchmark file (``python -m jskel bench``)."""

    latency: LatencySpec
    """What is timed."""


def process_env(cache_dir: Path) -> dict:
    """A fresh process's environment: its own cache directory, JAX's variable unset, no bars."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JSKEL_CACHE")}
    return {**env, "JSKEL_CACHE_DIR": str(cache_dir), "CI": "1"}


def _newest(folder: Path, since: float) -> float | None:
    times = [p.stat().st_mtime for p in folder.rglob("*") if p.is_file()] if folder.exists() else []
    return max(times) - since if times else None


def reported(folder: Path, t0: float | None = None) -> dict:
    """The seconds and program counts a jskel process wrote in ``folder`` (run.json, fit.json, a
    sweep's results.csv: summed over its settings);
    a fit's ``first_iteration_s``: from ``t0`` (``time.time()`` when the process was started)
    to its first iteration done."""
    row = {}
    if (folder / "run.json").exists():
        r = json.loads((folder / "run.json").read_text())
        row.update({k: round(r[k], 4) for k in ("compile_s", "build_s", "render_s")})
        row.update({k: r["programs"][k] for k in ("compiled", "loaded")} if "programs" in r else {})
    if (folder / "fit.json").exists():
        f = json.loads((folder / "fit.json").read_text())
        row.update({"compile_s": round(f["compile_s"], 4), "fit_s": round(f["seconds"], 4), "iterations": f["iterations"]})
        row.update({k: f["programs"][k] for k in ("compiled", "loaded")} if "programs" in f else {})
        if f.get("first_iteration_at") is not None and t0 is not None:
            row["first_iteration_s"] = round(f["first_iteration_at"] - t0, 4)
    if (folder / "results.csv").exists():  # a sweep's rows: the programs each setting compiled and loaded
        import csv

        with (folder / "results.csv").open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        for k in ("compiled", "loaded"):  # as run.json counts them (a peer's rows have none: empty cells)
            got = [int(r[k]) for r in rows if r.get(k) not in (None, "")]
            row[k] = sum(got) if got else None
        secs = [float(r["compile_s"]) for r in rows if r.get("compile_s") not in (None, "")]
        row["compile_s"] = round(sum(secs), 4) if secs else None
    return row


def timed_process(cmd: list[str], env: dict, out: Path | None, timeout: float) -> dict:
    """Run ``cmd``: seconds to its exit (``wall_s``) and to its newest output in ``out``
    (``outputs_s``), with what it reported there; an ``error`` (its last stderr line) if it failed."""
    t0 = time.time()
    try:
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:g} s"}
    row = {"wall_s": round(time.time() - t0, 4)}
    if p.returncode != 0:
        return {**row, "error": (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]}
    if out is not None:
        row["outputs_s"] = round(_newest(out, t0), 4) if _newest(out, t0) is not None else None
        row.update(reported(out, t0))
    return row


def cases(spec: LatencySpec, file, work: Path) -> list[tuple[str, Callable]]:
    """(label, command for an output folder) of every process case, files checked first."""
    jskel = [sys.executable, "-m", "jskel"]
    sets = lambda s: sum((["--set", x] for x in s), [])  # noqa: E731
    out = []
    if spec.default:
        out.append(("default", lambda o: jskel + ["render", "--out", str(o)]))
    for i, g in enumerate(spec.gallery):
        p = beside(g, file, f"latency.gallery[{i}]")
        out.append((p.stem, lambda o, p=p: jskel + ["render", str(p), "--out", str(o), *sets(spec.set)]))
    if spec.sweep is not None:
        p = beside(spec.sweep.file, file, "latency.sweep.file")
        out.append((f"sweep:{p.stem}", lambda o, p=p: jskel + ["sweep", str(p), "--out", str(o), *sets(spec.sweep.set)]))
    if spec.fit is not None:
        p = beside(spec.fit.file, file, "latency.fit.file")
        out.append((f"fit:{p.stem}", lambda o, p=p: jskel + ["fit", str(p), "--out", str(o), *sets(spec.fit.set)]))
    return out


def process_rows(spec: LatencySpec, file, work: Path, emit: JsonLines, peers: Peers = Peers()) -> list[dict]:
    """The floor, each case cold then warm (``repeats`` times), and Mitsuba's process (``peers``)."""
    rows = []
    for rep in range(spec.repeats):
        floor = {"case": "jax_floor", "repeat": rep, **timed_process(FLOOR, process_env(work / "floor"), None, spec.timeout_s)}
        rows.append(floor)
        emit(floor)
        for label, cmd in cases(spec, file, work):
            cache = work / f"{label.replace(':', '_')}_{rep}" / "cache"
            for state in ("cold", "warm"):
                o = cache.parent / state
                row = {"case": label, "cache": state, "repeat": rep, **timed_process(cmd(o), process_env(cache), o, spec.timeout_s)}
                if "wall_s" in row and "wall_s" in floor:
                    row["over_floor_s"] = round((row.get("outputs_s") or row["wall_s"]) - floor["wall_s"], 4)
                rows.append(row)
                emit(row)
        if spec.mitsuba is not None:
            rows.append(mitsuba_row(spec, file, work / f"mitsuba_{rep}", rep, needed(peers.mitsuba_image, "latency.mitsuba", spec.mitsuba)))
            emit(rows[-1])
    return rows


def mitsuba_row(spec: LatencySpec, file, folder: Path, rep: int, prepare) -> dict:
    """Mitsuba's process for ``spec.mitsuba``'s skeleton at the gallery's size, or why not
    (``prepare``: ``Peers.mitsuba_image``, the CLI's ``peers.mitsuba_image.prepare``)."""
    exp = load(beside(spec.mitsuba, file, "latency.mitsuba"), spec.set)
    cmd, png = prepare(exp, folder, spec.mitsuba_variant)
    row = {"case": f"mitsuba_{spec.mitsuba_variant}", "scene": exp.name, "repeat": rep}
    if cmd is None:
        return {**row, "skipped": png}
    return {**row, **timed_process(cmd, dict(os.environ), None, spec.timeout_s), "width": exp.camera.width, "height": exp.camera.height}


def _skeleton_set(j, r, p) -> str:
    return "object.skeleton=" + json.dumps({"joints": j.tolist(), "radii": r.tolist(), "parents": p.tolist()})


def changes(exp) -> dict[str, list[str]]:
    """Overrides of each change a researcher makes between two looks, on the experiment's
    skeleton written out as arrays: none, a radius, the camera, the image size, one more segment."""
    import numpy as np

    from .. import registry

    obj = exp.objects[0].shape
    sk = registry.get(obj.type).skeleton(obj) if len(exp.objects) == 1 and exp.objects[0].at(0) == "object" else None
    if sk is None:
        raise ValueError(f"latency.rerender: {exp.name} is not a file's single skeleton object (object:)")
    j, r, p = sk
    base = [_skeleton_set(j, r, p), "render.progress=false"]
    r2 = r.copy()
    r2[len(r) // 2] *= 1.2
    c = exp.camera
    camera = [f"camera.eye={json.dumps([c.eye[0] + 0.5, c.eye[1], c.eye[2]])}"] if c.frame != "auto" else [f"camera.fov_deg={c.fov_deg + 3}"]
    tip = j[-1] + 0.3 * (j[-1] - j[p[-1]]) if p[-1] >= 0 else j[-1] + np.array([0.0, 0.1, 0.0])
    grown = (np.vstack([j, tip]), np.append(r, 0.8 * r[-1]), np.append(p, len(j) - 1))
    return {"none": base, "radius": [_skeleton_set(j, r2, p), base[1]], "camera": base + camera,
            "image_size": base + [f"camera.width={c.width + 16}", f"camera.height={c.height + 12}"],
            "segments": [_skeleton_set(*grown), base[1]]}


def rerender_rows(spec: LatencySpec, file, emit: JsonLines) -> list[dict]:
    """In this process: a first render, then each change of :func:`changes` from it, timed
    with the programs each compiled (and loaded from the persistent cache)."""
    path = beside(spec.rerender, file, "latency.rerender")
    exp = load(path, spec.set)
    count_programs()
    rows = []
    for i, (change, sets) in enumerate(changes(exp).items()):
        e = load(path, spec.set + sets)
        before = program_counts()
        t0 = time.perf_counter()
        res = render(e, progress=False)
        seconds = time.perf_counter() - t0
        after = program_counts()
        run = res.run
        rows.append({"case": "rerender", "scene": e.name, "change": "first" if i == 0 else change, "seconds": round(seconds, 4),
                     "compile_s": round(run["compile_s"], 4), "build_s": round(run["build_s"], 4), "render_s": round(run["render_s"], 4),
                     "compiled": after["compiled"] - before["compiled"], "loaded": after["loaded"] - before["loaded"],
                     "width": e.camera.width, "height": e.camera.height, "primitives": run["primitives"]})
        emit(rows[-1])
    return rows


def run_latency_bench(spec: LatencySpec, file, out=None, command: str | None = None, peers: Peers = Peers()) -> list[dict]:
    """The whole benchmark: process rows (in a temporary folder), then the in-process re-renders
    (``command``: how it was asked for, in every kept row's provenance; ``peers``: Mitsuba's
    process where ``latency.mitsuba`` asks for it, ``Peers.mitsuba_image``)."""
    if spec.mitsuba is not None:  # before anything runs
        needed(peers.mitsuba_image, "latency.mitsuba", spec.mitsuba)
    emit = JsonLines(out, command)
    with tempfile.TemporaryDirectory(prefix="jskel_latency_") as tmp:
        rows = process_rows(spec, file, Path(tmp), emit, peers)
    if spec.rerender is not None:
        rows += rerender_rows(spec, file, emit)
    return rows


def is_latency_file(file) -> bool:
    """Does the bench file hold a ``latency:`` section (this benchmark)?"""
    raw = read_yaml(file)
    return isinstance(raw, dict) and "latency" in raw


def run_latency_file(file, overrides: list[str], out=None, command: str | None = None, peers: Peers = Peers()) -> list[dict]:
    """``jskel bench FILE`` for a latency file (``--set latency.KEY=VALUE`` overrides)."""
    return run_latency_bench(read_model(LatencyFile, file, overrides).latency, file, out, command, peers)
