"""Command line: ``python -m jskel render|bench|sweep|fit|export ...``: parses arguments and calls.

``bench`` and ``sweep`` are ``jskel.measure`` (one harness: timing, grid, plots, experiment
loading), ``fit`` is ``jskel.fit``. Every bad input (unknown key, wrong type, bad value, bad
skeleton) ends the command before any compilation with one line per problem on stderr, naming
the key path and the value, and exit code 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np

from . import registry
from .compile.cache import use_compilation_cache
from .compile.devices import use_host_devices
from .config import ConfigError, load
from .distributed import init_from_env
from .measure.files import X64, read_model
from .render import aov_sheet, render, write_aovs


def _frames(spec: str) -> list[float]:
    """``a:b`` or ``a:b:step`` (b inclusive) or a single frame."""
    try:
        parts = [float(x) for x in spec.split(":")]
    except ValueError:
        raise ConfigError([f"--frames: expected start:stop[:step] (got {spec!r})"]) from None
    if len(parts) == 1:
        return parts
    if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] <= 0) or parts[1] < parts[0]:
        raise ConfigError([f"--frames: expected start:stop[:step] with stop >= start and step > 0 (got {spec!r})"])
    step = parts[2] if len(parts) == 3 else 1.0
    n = int(round((parts[1] - parts[0]) / step)) + 1
    return [parts[0] + i * step for i in range(n)]


def cmd_render_frames(args, exp) -> int:
    """Render an animation: numbered images and AOVs, animation.gif, one run.json. Frame ``f``
    is the experiment's ``frame``: it poses every animated shape (at its own ``frame`` + f) and
    moves every object with a ``motion``."""
    moving = [o for o in exp.objects if o.motion is not None or registry.get(o.shape.type).animated]
    if not moving:
        types = ", ".join(sorted({repr(o.shape.type) for o in exp.objects}))
        where = exp.objects[0].at(0) if len(exp.objects) == 1 else "objects[]"
        raise ConfigError([f"--frames: {where}.type {types} has no animation"])
    frames = _frames(args.frames)
    out = Path(args.out)
    images, runs = [], []
    for f in frames:  # host loop over frames: each reuses the one compiled render
        res = render(exp.model_copy(update={"frame": f}), progress=args.progress)
        tag = f"{int(round(f)):04d}" if float(f).is_integer() else f"{f:09.3f}"
        sub = out / f"frame_{tag}"
        write_aovs(sub, res.hits, res.image, exp.camera.width, exp.camera.height, res.run, res.aovs)
        if args.aov_sheet:
            aov_sheet(sub)
        images.append(res.image)
        runs.append({"frame": f, "render_s": res.run["render_s"], "compile_s": res.run["compile_s"], "build_s": res.run["build_s"]})
        print(f"jskel: frame {f:g}: {res.run['render_s']:.3f} s (compile {res.run['compile_s']:.2f} s) -> {sub}")
    iio.imwrite(out / "animation.gif", np.stack(images), duration=1000 / 24, loop=0)
    (out / "frames.json").write_text(json.dumps({"frames": runs}, indent=2) + "\n")
    print(f"jskel: {len(frames)} frames -> {out / 'animation.gif'}")
    return 0


def cmd_render(args) -> int:
    exp = load(args.experiment, args.set + (X64 if args.x64 else []))
    if args.frames is not None:
        return cmd_render_frames(args, exp)
    res = render(exp, progress=args.progress)
    if jax.process_index() != 0:  # several hosts: process 0 writes the gathered image
        return 0
    paths = write_aovs(args.out, res.hits, res.image, exp.camera.width, exp.camera.height, res.run, res.aovs)
    if args.aov_sheet:
        aov_sheet(args.out)  # read back from the files just written: the sheet shows what is on disk
    r = res.run
    print(
        f"jskel: rendered {exp.name} ({r['info'].get('segments', r['info'].get('primitives', '?'))} primitives) "
        f"{exp.camera.width}x{exp.camera.height} in {r['render_s']:.3f} s "
        f"(compile {r['compile_s']:.2f} s) -> {Path(paths['image']).parent}"
    )
    return 0


def cmd_bench(args) -> int:
    """``jskel bench FILE``: see ``jskel.measure.bench`` (time to first image: ``jskel.measure.latency``)."""
    from .measure.bench import run_bench  # imported by the command that needs it: a render's start skips them
    from .measure.latency import is_latency_file, run_latency_file
    from .peers.studies import PEERS

    if is_latency_file(args.file):
        run_latency_file(args.file, args.set, args.out, command=args.command, peers=PEERS)
    else:
        run_bench(args.file, args.set, args.runs, args.out, args.x64, command=args.command, peers=PEERS)
    return 0


def cmd_sweep(args) -> int:
    """``jskel sweep FILE --out DIR``: see ``jskel.measure.sweep``."""
    from .measure.sweep import load_sweep, run_sweep
    from .peers.studies import PEERS

    x64 = X64 if args.x64 else []
    sweep, jobs, ref_jobs = load_sweep(args.file, args.set, x64)
    out = Path(args.out)
    rows = run_sweep(sweep, jobs, ref_jobs, out, progress=args.progress, spec=(str(args.file), list(args.set), x64),
                     command=args.command, peers=PEERS)
    print(f"jskel: {len(rows)} settings -> {out / 'results.csv'}, {out / 'report.md'}")
    return 0


def cmd_fit(args) -> int:
    """``jskel fit FILE --out DIR``: see ``jskel.fit``."""
    from .fit import FitFile, run_fit

    cfg = read_model(FitFile, args.file, args.set)
    if args.x64 or cfg.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
        cfg = cfg.model_copy(update={"dtype": "float64"})
    info = run_fit(cfg, Path(args.out), Path(args.file).parent)
    res = info["residuals"]
    print(f"jskel: fitted {info['segments']} segments to {info['points']['points']} points with {cfg.solver.name} in "
          f"{info['seconds']:.2f} s ({info['iterations']} iterations, compile {info['compile_s']:.2f} s); "
          f"residual rms {res['rms']:.4g}, inliers {res['inlier_fraction']:.1%} -> {Path(args.out) / 'fitted.yaml'}")
    return 0


def cmd_export(args) -> int:
    """``jskel export EXPERIMENT --out mesh.ply``: the object as a triangle mesh (its
    representation's ``export_mesh``: the frusta tessellated, ``jskel.frusta.export_mesh``)."""
    exp = load(args.experiment, args.set)
    if len(exp.objects) != 1 or exp.objects[0].is_placed:
        raise ConfigError([f"objects: export writes one skeleton object in its own frame (got {len(exp.objects)} objects"
                           f"{', placed by a transform or motion' if len(exp.objects) == 1 else ''})"])
    obj = exp.objects[0].shape
    info = registry.get(obj.type).export_mesh(obj, args.out, args.level, "--out")
    print(f"jskel: exported {info['segments']} segments at level {info['level']}: {info['faces']} triangles -> {info['path']}")
    return 0


def _command(sub, name: str, help: str, file_help: tuple, set_help: str, x64_help: str, progress: bool = False):
    """A subcommand with its input file, ``--set`` overrides, ``--x64`` and (optionally) progress."""
    c = sub.add_parser(name, help=help)
    c.add_argument(file_help[0], **file_help[1])
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help=set_help)
    if progress:
        g = c.add_mutually_exclusive_group()
        g.add_argument("--progress", dest="progress", action="store_true", default=None)
        g.add_argument("--no-progress", dest="progress", action="store_false")
    c.add_argument("--x64", action="store_true", help=x64_help)
    return c


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="jskel", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = _command(sub, "render", "render an experiment to image.png and AOVs",
                 ("experiment", dict(nargs="?", default=None, help="experiment YAML (default: the embedded default)")),
                 "override a config key (repeatable)", "float64 throughout (render.dtype=float64; x64 switched on here)", progress=True)
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--frames", default=None, metavar="A:B[:STEP]", help="render an animation (frames A..B inclusive): frame_NNNN/ folders and animation.gif")
    r.add_argument("--aov-sheet", action="store_true", help="also write aov_sheet.png: image, depth, normals, uv, ids and flags side by side")
    r.set_defaults(func=cmd_render)
    b = _command(sub, "bench", "time renders (compile apart, median of warm runs), JSON lines out", ("file", dict(help="benchmark YAML")),
                 "override a bench key", "every scene in float64 (render.dtype=float64)")
    b.add_argument("--runs", type=int, default=None, help="override the number of timed runs")
    b.add_argument("--out", default=None, help="also write the JSON lines to this file")
    b.set_defaults(func=cmd_bench)
    w = _command(sub, "sweep", "vary config keys, measure error against a reference and time: results.csv, pareto.png, report.md",
                 ("file", dict(help="sweep YAML")), "override a sweep key", "every setting in float64 unless it sets render.dtype itself",
                 progress=True)
    w.add_argument("--out", required=True, help="output folder (an existing results.csv there is resumed)")
    w.set_defaults(func=cmd_sweep)
    f = _command(sub, "fit", "fit a skeleton's joints and radii to a point cloud: fitted.yaml, fit.json, fit.png", ("file", dict(help="fit YAML")),
                 "override a fit key", "fit in float64")
    f.add_argument("--out", required=True, help="output folder")
    f.set_defaults(func=cmd_fit)
    e = sub.add_parser("export", help="write a skeleton object's frusta as a triangle mesh (.ply, .obj, .glb, .stl)")
    e.add_argument("experiment", help="experiment YAML")
    e.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key (repeatable)")
    e.add_argument("--out", required=True, help="mesh file; its extension picks the format")
    e.add_argument("--level", type=int, default=2, help="subdivision level m: 16 x 4^m triangles a segment (Table 1)")
    e.set_defaults(func=cmd_export)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.command = shlex.join(["python", "-m", "jskel", *(sys.argv[1:] if argv is None else argv)])  # in provenance records
    try:
        use_host_devices()  # before JAX starts: one XLA host device per core (JSKEL_HOST_DEVICES sets the count)
        use_compilation_cache()  # before anything compiles: ~/.cache/jskel/jax (JSKEL_CACHE_DIR moves it, JSKEL_CACHE=off)
        init_from_env()
        return args.func(args)
    except ConfigError as e:
        for line in e.lines:
            print(f"jskel: error: {line}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"jskel: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
