"""Run by hand (not by the suite): what the frusta traversal choice costs a render's program.
For an experiment and a list of settings (``key=value`` overrides, ``auto`` for none), one JSON
line each: StableHLO lines of the render program (the executor's largest), its XLA compile in
process CPU seconds (``lower(...).compile()`` timed by ``time.process_time``), the programs the
cold render compiled, and the warm render's process CPU and wall seconds (median of ``--runs``).
The persistent caches are off, so every program is compiled here; a later setting reuses what an
earlier one compiled (the geometry, the BVH build), so compare ``programs`` one setting per process.

    env -u JAX_COMPILATION_CACHE_DIR JSKEL_CACHE=off JSKEL_EXECUTABLES=off \\
        python tests/scripts/traversal_programs.py default auto object.accel=blocks object.accel=none
    ... tests/scripts/traversal_programs.py experiments/scene_effects.yaml auto objects.4.shape.accel=blocks

Several overrides in one setting are joined by ``+`` (``object.accel=bvh+object.traversal=walks``).
``--bins-one-lane N`` sets ``jskel.frusta._accel.BINS_ONE_LANE`` (0: bins compile every lane size).
"""
import argparse
import json
import statistics
import time

import jax

from jskel import executor
from jskel.compile.cache import count_programs, program_counts
from jskel.config import load as load_experiment
from jskel.render import render

_seen: list[dict] = []
_original = executor.compile_batch_fn


def _measured_compile(batch_fn, example_args, mesh=None):
    """``executor.compile_batch_fn`` for one device, its lowering's lines and compile CPU kept."""
    if mesh is not None:
        return _original(batch_fn, example_args, mesh)
    key = (batch_fn, executor._signature(example_args), jax.config.jax_enable_x64, None)
    hit = executor._COMPILED.get(key)
    if hit is not None:
        return hit, 0.0
    t0 = time.perf_counter()
    lowered = jax.jit(executor._named(batch_fn)).lower(*example_args)
    lines = lowered.as_text().count("\n")
    c0 = time.process_time()
    compiled = lowered.compile()
    _seen.append(dict(program=executor.program_name(batch_fn), stablehlo_lines=lines, compile_cpu=round(time.process_time() - c0, 2)))
    executor._COMPILED[key] = compiled
    return compiled, time.perf_counter() - t0


def measure(path, setting: str, runs: int) -> dict:
    overrides = [] if setting == "auto" else setting.split("+")
    exp = load_experiment(None if path == "default" else path, overrides)
    _seen.clear()
    before = program_counts()
    c0 = time.process_time()
    render(exp, progress=False)
    cold_cpu = time.process_time() - c0
    after = program_counts()
    programs = after["compiled"] - before["compiled"]
    slow = {k: round(s - before["by_name"].get(k, [0, 0.0])[1], 2) for k, (_, s) in after["by_name"].items()}
    slow = {k: v for k, v in slow.items() if v >= 0.2}  # the programs whose compile counts (wall seconds)
    cpu, wall = [], []
    for _ in range(runs):
        c0, w0 = time.process_time(), time.perf_counter()
        render(exp, progress=False)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    big = max(_seen, key=lambda r: r["stablehlo_lines"]) if _seen else {}
    return dict(experiment=path, setting=setting, **big, programs=programs, slow_programs=slow, cold_render_cpu=round(cold_cpu, 2),
                warm_cpu=round(statistics.median(cpu), 3), warm_wall=round(statistics.median(wall), 3))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("experiment", help="an experiment file, or 'default' (the CLI's embedded one)")
    ap.add_argument("settings", nargs="+", help="'auto' or key=value[+key=value...]")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--bins-one-lane", type=int, default=None)
    args = ap.parse_args()
    if args.bins_one_lane is not None:
        from jskel.frusta import _accel

        _accel.BINS_ONE_LANE = args.bins_one_lane
    count_programs()
    executor.compile_batch_fn = _measured_compile
    for s in args.settings:
        print(json.dumps(measure(args.experiment, s, args.runs)), flush=True)


if __name__ == "__main__":
    main()
