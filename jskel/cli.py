"""Command line: ``python -m jskel render|bench|sweep|fit ...``.

Every bad input (unknown key, wrong type, bad value, bad skeleton) ends the command before any
compilation with one line per problem on stderr, naming the key path and the value, and exit
code 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from pathlib import Path
from pydantic import ValidationError

from .config import ConfigError, _format, apply_overrides, chunk_of, read_yaml, validate


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


def cmd_render_frames(args, exp, obj) -> int:
    """Render an animation: numbered images and AOVs, animation.gif, one run.json."""
    import imageio.v3 as iio

    from .render import render, write_aovs

    if not exp.is_scene and "frame" not in type(obj).model_fields:
        raise ConfigError([f"--frames: object.type {obj.type!r} has no animation"])
    frames = _frames(args.frames)
    out = Path(args.out)
    images, runs = [], []
    for f in frames:  # host loop over frames: each reuses the one compiled render
        if exp.is_scene:  # a scene's frame poses every animated shape and moves objects with a motion
            e, o = exp.model_copy(update={"frame": f}), obj
        else:
            e, o = exp, obj.model_copy(update={"frame": f})
        res = render(e, o, progress=args.progress)
        tag = f"{int(round(f)):04d}" if float(f).is_integer() else f"{f:09.3f}"
        sub = out / f"frame_{tag}"
        write_aovs(sub, res.hits, res.image, exp.camera.width, exp.camera.height, res.run, res.aovs)
        images.append(res.image)
        runs.append({"frame": f, "render_s": res.run["render_s"], "compile_s": res.run["compile_s"], "build_s": res.run["build_s"]})
        print(f"jskel: frame {f:g}: {res.run['render_s']:.3f} s (compile {res.run['compile_s']:.2f} s) -> {sub}")
    iio.imwrite(out / "animation.gif", np.stack(images), duration=1000 / 24, loop=0)
    (out / "frames.json").write_text(json.dumps({"frames": runs}, indent=2) + "\n")
    print(f"jskel: {len(frames)} frames -> {out / 'animation.gif'}")
    return 0


X64 = ["render.dtype=float64"]  # --x64: the precision switch, set at the entry point only


def cmd_render(args) -> int:
    exp, obj = _load(args.experiment, args.set + (X64 if args.x64 else []))
    if args.frames is not None:
        return cmd_render_frames(args, exp, obj)
    from .render import render, write_aovs

    res = render(exp, obj, progress=args.progress)
    import jax

    if jax.process_index() != 0:  # several hosts: process 0 writes the gathered image
        return 0
    paths = write_aovs(args.out, res.hits, res.image, exp.camera.width, exp.camera.height, res.run, res.aovs)
    r = res.run
    print(
        f"jskel: rendered {exp.name} ({r['info'].get('segments', r['info'].get('primitives', '?'))} primitives) "
        f"{exp.camera.width}x{exp.camera.height} in {r['render_s']:.3f} s "
        f"(compile {r['compile_s']:.2f} s) -> {Path(paths['image']).parent}"
    )
    return 0


def _read_model(model, path, overrides):
    """A bench or sweep file, overridden and validated (every bad key at once, exit 2)."""
    raw = apply_overrides(read_yaml(path), overrides)
    try:
        return model.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e)) from None


def _traversal_stats(exp, obj) -> dict:
    """The representation's deterministic work counts per ray (empty where it declares none)."""
    from . import registry
    from .render import camera_of, dtype_of

    rep = registry.get(obj.type)
    built = rep.build(obj, dtype_of(exp))
    cam = camera_of(exp)
    # in the render's order (screen tiles): packets and bins depend on it
    rays = cam.tiled_rays(exp.render.tile, anchor=built.anchor, dtype=dtype_of(exp))
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in rep.traversal_stats(built, rays, chunk_of(exp.render)).items()}


def cmd_fit_bench(args) -> int:
    """A bench file with a ``fit:`` section: the fitting benchmark (``jskel.fit._bench``)."""
    from .fit import FitBenchFile, run_fit_bench

    b = _read_model(FitBenchFile, args.file, args.set).fit
    out = Path(args.out) if args.out else None
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text("")

    def emit(row):
        line = json.dumps(row)
        print(line, flush=True)
        if out is not None:
            with out.open("a") as f:
                f.write(line + "\n")

    run_fit_bench(b, emit)
    return 0


def cmd_bench(args) -> int:
    from .bench import BenchFile, plot_sweep, sweep_settings, timed_cast, timed_render

    raw = read_yaml(args.file)
    if isinstance(raw, dict) and "fit" in raw:
        return cmd_fit_bench(args)
    bench = _read_model(BenchFile, args.file, args.set)
    base = Path(args.file).parent
    runs = args.runs or bench.runs
    common = [f"camera.width={bench.width}", f"camera.height={bench.height}", "render.progress=false", *bench.set,
              *(X64 if args.x64 else [])]
    paths = []
    for i, scene in enumerate(bench.scenes):
        p = Path(scene)
        p = p if p.exists() else base / scene
        if not p.exists():
            raise ConfigError([f"scenes[{i}]: file not found (got {scene!r})"])
        paths.append(p)
    # validate every experiment (and every sweep setting) before any compilation
    settings = sweep_settings(bench.sweep) if bench.sweep is not None else []
    if bench.labels is not None and len(bench.labels) != len(settings):
        raise ConfigError([f"labels: {len(bench.labels)} labels for {len(settings)} sweep settings"])
    groups = []  # (reference job or None, [(file, (exp, obj), setting)])
    if bench.sweep is None:
        groups.append((None, [(str(p), _load(p, common), None) for p in paths]))
    else:
        for p in paths:
            # a sweep with no reference only times its settings (e.g. cost against scene size)
            ref_job = _load(p, common + bench.reference) if bench.reference else None
            jobs = [(str(p), _load(p, common + [f"{k}={json.dumps(v)}" for k, v in st.items()]), st)
                    for st in sweep_settings(bench.sweep)]
            groups.append((ref_job, jobs))
    from .metrics import compare
    from .render import render

    rows = []
    for ref_job, jobs in groups:
        ref_hits = ref_rgb = None
        if ref_job is not None:
            ref_res = render(*ref_job, progress=False)
            ref_hits, ref_rgb = ref_res.hits, ref_res.rgb
            print(json.dumps({"reference": bench.reference, "scene": ref_job[0].name, "render_s": round(ref_res.run["render_s"], 4)}), flush=True)
        group_rows = []
        for file, (exp, obj), setting in jobs:
            row, first = timed_render(exp, obj, runs, bench.warmup)
            if bench.cast:
                row.update(timed_cast(exp, obj, runs, bench.warmup))
            row["file"] = file
            if bench.stats:
                row.update(_traversal_stats(exp, obj))
            if setting is not None:
                row["setting"] = setting
                if bench.labels is not None:
                    row["label"] = bench.labels[settings.index(setting)]
            if setting is not None and ref_hits is not None:
                row.update({k: (round(v, 8) if isinstance(v, float) else v) for k, v in compare(first.hits, ref_hits, first.rgb, ref_rgb).items()})
            print(json.dumps(row), flush=True)
            group_rows.append(row)
        if bench.peer is not None and ref_job is not None:
            from .bench import peer_embree_mesh, peer_embree_same_mesh, peer_marching_cubes, peer_skeleton

            peer_fn = {"embree_mesh": peer_embree_mesh, "embree_same_mesh": peer_embree_same_mesh, "marching_cubes": peer_marching_cubes,
                       "skeleton": peer_skeleton}[bench.peer]
            for row in peer_fn(bench, *ref_job, ref_hits, runs, group_rows):
                print(json.dumps(row), flush=True)
                group_rows.append(row)
        rows += group_rows
        if args.out and ref_job is not None:
            out = Path(args.out)
            out.parent.mkdir(parents=True, exist_ok=True)
            png = out.with_name(f"{out.stem}_{ref_job[0].name}.png") if len(groups) > 1 else out.with_suffix(".png")
            keys = list(dict.fromkeys(k for st in sweep_settings(bench.sweep) for k in st))
            done = plot_sweep([r for r in group_rows if "setting" in r], keys, bench.metric, png,
                              f"{ref_job[0].name}: {bench.metric} vs time ({group_rows[0]['device']})")
            if done:
                print(f"jskel: plot -> {done}")
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text("".join(json.dumps(r) + "\n" for r in rows))
        if bench.sweep is not None and not bench.reference and not bench.stats:
            from .bench import plot_bars

            done = plot_bars(rows, out.with_suffix(".png"), f"{rows[0]['scene']} {rows[0]['width']}x{rows[0]['height']}: time per setting ({rows[0]['device']})")
            if done:
                print(f"jskel: plot -> {done}")
        if bench.stats and bench.sweep is not None and not bench.reference:
            from .bench import plot_scaling

            done = plot_scaling(rows, out.with_suffix(".png"), f"{rows[0]['scene']}: cost per ray against segments ({rows[0]['device']})")
            if done:
                print(f"jskel: plot -> {done}")
    return 0


def cmd_sweep(args) -> int:
    """``jskel sweep FILE --out DIR``: see ``jskel.sweep``."""
    from .sweep import load_sweep, run_sweep

    sweep, jobs, ref_jobs = load_sweep(args.file, args.set, X64 if args.x64 else [])
    out = Path(args.out)
    rows = run_sweep(sweep, jobs, ref_jobs, out, progress=args.progress,
                     spec=(str(args.file), list(args.set), X64 if args.x64 else []))
    print(f"jskel: {len(rows)} settings -> {out / 'results.csv'}, {out / 'report.md'}")
    return 0


def cmd_fit(args) -> int:
    """``jskel fit FILE --out DIR``: see ``jskel.fit``."""
    raw = apply_overrides(read_yaml(args.file), args.set)
    from .fit import FitFile, run_fit

    try:
        cfg = FitFile.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e)) from None
    if args.x64 or cfg.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
        cfg = cfg.model_copy(update={"dtype": "float64"})
    info = run_fit(cfg, Path(args.out), Path(args.file).parent)
    res = info["residuals"]
    print(f"jskel: fitted {info['segments']} segments to {info['points']['points']} points with {cfg.solver.name} in "
          f"{info['seconds']:.2f} s ({info['iterations']} iterations, compile {info['compile_s']:.2f} s); "
          f"residual rms {res['rms']:.4g}, inliers {res['inlier_fraction']:.1%} -> {Path(args.out) / 'fitted.yaml'}")
    return 0


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="jskel", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render an experiment to image.png and AOVs")
    r.add_argument("experiment", nargs="?", default=None, help="experiment YAML (default: the embedded default)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key (repeatable)")
    r.add_argument("--frames", default=None, metavar="A:B[:STEP]", help="render an animation (frames A..B inclusive): frame_NNNN/ folders and animation.gif")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--progress", dest="progress", action="store_true", default=None)
    g.add_argument("--no-progress", dest="progress", action="store_false")
    r.add_argument("--x64", action="store_true", help="float64 throughout (render.dtype=float64; x64 switched on here)")
    r.set_defaults(func=cmd_render)
    b = sub.add_parser("bench", help="time renders (compile apart, median of warm runs), JSON lines out")
    b.add_argument("file", help="benchmark YAML")
    b.add_argument("--runs", type=int, default=None, help="override the number of timed runs")
    b.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a bench key")
    b.add_argument("--out", default=None, help="also write the JSON lines to this file")
    b.add_argument("--x64", action="store_true", help="every scene in float64 (render.dtype=float64)")
    b.set_defaults(func=cmd_bench)
    w = sub.add_parser("sweep", help="vary config keys, measure error against a reference and time: results.csv, pareto.png, report.md")
    w.add_argument("file", help="sweep YAML")
    w.add_argument("--out", required=True, help="output folder (an existing results.csv there is resumed)")
    w.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a sweep key")
    g = w.add_mutually_exclusive_group()
    g.add_argument("--progress", dest="progress", action="store_true", default=None)
    g.add_argument("--no-progress", dest="progress", action="store_false")
    w.add_argument("--x64", action="store_true", help="every setting in float64 unless it sets render.dtype itself")
    w.set_defaults(func=cmd_sweep)
    f = sub.add_parser("fit", help="fit a skeleton's joints and radii to a point cloud: fitted.yaml, fit.json, fit.png")
    f.add_argument("file", help="fit YAML")
    f.add_argument("--out", required=True, help="output folder")
    f.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a fit key")
    f.add_argument("--x64", action="store_true", help="fit in float64")
    f.set_defaults(func=cmd_fit)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        from .devices import use_host_devices
        from .distributed import init_from_env

        use_host_devices()  # before JAX starts: one XLA host device per core (JSKEL_HOST_DEVICES sets the count)
        init_from_env()
        return args.func(args)
    except ConfigError as e:
        for line in e.lines:
            print(f"jskel: error: {line}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"jskel: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
