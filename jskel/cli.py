"""Command line: ``python -m jskel render|bench ...``.

Every bad input (unknown key, wrong type, bad value, bad skeleton) ends the command before any
compilation with one line per problem on stderr, naming the key path and the value, and exit
code 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Annotated

from pydantic import Field, ValidationError

from .config import ConfigError, StrictModel, _format, apply_overrides, read_yaml, validate


def _enable_x64_if_asked(raw: dict):
    render = raw.get("render") if isinstance(raw, dict) else None
    if isinstance(render, dict) and render.get("dtype") == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)


def _load(path, overrides):
    raw = apply_overrides(read_yaml(path), overrides)
    exp, obj = validate(raw)
    _enable_x64_if_asked(raw)
    return exp, obj


def cmd_render(args) -> int:
    exp, obj = _load(args.experiment, args.set)
    from .render import render, write_aovs

    res = render(exp, obj, progress=args.progress)
    paths = write_aovs(args.out, res.hits, res.image, exp.camera.width, exp.camera.height, res.run)
    r = res.run
    print(
        f"jskel: rendered {exp.name} ({r['info'].get('segments', '?')} segments) "
        f"{exp.camera.width}x{exp.camera.height} in {r['render_s']:.3f} s "
        f"(compile {r['compile_s']:.2f} s) -> {Path(paths['image']).parent}"
    )
    return 0


class BenchFile(StrictModel):
    """A benchmark file: experiments rendered at one size, timed over warm runs."""

    scenes: list[str]
    width: Annotated[int, Field(ge=1, le=16384)] = 1024
    height: Annotated[int, Field(ge=1, le=16384)] = 768
    runs: Annotated[int, Field(ge=1, le=1000)] = 5
    warmup: Annotated[int, Field(ge=0, le=100)] = 1
    set: list[str] = []


def cmd_bench(args) -> int:
    raw = read_yaml(args.file)
    raw = apply_overrides(raw, args.set)
    try:
        bench = BenchFile.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e)) from None
    base = Path(args.file).parent
    runs = args.runs or bench.runs
    loaded = []
    for i, scene in enumerate(bench.scenes):  # validate every scene before any compilation
        p = Path(scene)
        p = p if p.exists() else base / scene
        if not p.exists():
            raise ConfigError([f"scenes[{i}]: file not found (got {scene!r})"])
        ov = [f"camera.width={bench.width}", f"camera.height={bench.height}", "render.progress=false", *bench.set]
        loaded.append((scene, _load(p, ov)))
    from .render import render

    results = []
    for scene, (exp, obj) in loaded:
        first = render(exp, obj, progress=False)
        for _ in range(max(bench.warmup - 1, 0)):
            render(exp, obj, progress=False)
        times = [render(exp, obj, progress=False).run["render_s"] for _ in range(runs)]
        med = statistics.median(times)
        row = {
            "scene": exp.name,
            "file": scene,
            "segments": first.run["info"].get("segments"),
            "width": exp.camera.width,
            "height": exp.camera.height,
            "rays": first.run["rays"],
            "dtype": exp.render.dtype,
            "chunk": exp.render.chunk,
            "compile_s": round(first.run["compile_s"], 4),
            "render_s_median": round(med, 4),
            "render_s_min": round(min(times), 4),
            "render_s_max": round(max(times), 4),
            "runs": runs,
            "mrays_per_s": round(first.run["rays"] / med / 1e6, 4),
            "hit_fraction": round(first.run["hit_fraction"], 4),
            "device": first.run["device"],
            "jax": first.run["jax"],
            "jskel": first.run["jskel"],
        }
        print(json.dumps(row), flush=True)
        results.append(row)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("".join(json.dumps(r) + "\n" for r in results))
    return 0


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="jskel", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render an experiment to image.png and AOVs")
    r.add_argument("experiment", nargs="?", default=None, help="experiment YAML (default: the embedded default)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key (repeatable)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--progress", dest="progress", action="store_true", default=None)
    g.add_argument("--no-progress", dest="progress", action="store_false")
    r.set_defaults(func=cmd_render)
    b = sub.add_parser("bench", help="time renders (compile apart, median of warm runs), JSON lines out")
    b.add_argument("file", help="benchmark YAML")
    b.add_argument("--runs", type=int, default=None, help="override the number of timed runs")
    b.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a bench key")
    b.add_argument("--out", default=None, help="also write the JSON lines to this file")
    b.set_defaults(func=cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.func(args)
    except ConfigError as e:
        for line in e.lines:
            print(f"jskel: error: {line}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"jskel: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
