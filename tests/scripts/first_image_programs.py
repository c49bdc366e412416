"""Run by hand (not by the suite): what each program of an experiment's cold render costs, and
what XLA's CPU compile options would change (each set compiled once a process: run it again, alternating
the order, for the spread). One fresh process renders the experiment once with
an empty executables folder and JAX's persistent cache off, so every program is traced, lowered
and compiled here; then, per program (the frusta's float64 geometry, its BVH, the render), one
JSON line with its StableHLO ops and lines (deterministic), its lowering and XLA compile in
process CPU seconds (``time.process_time``), and the source functions holding most of its ops
(every function on each op's call stack); then one line per option set: the same
lowered program compiled again with those ``compiler_options`` (CPU seconds) and its run on the
render's own arguments (median wall seconds of ``--runs``).

    env -u JAX_COMPILATION_CACHE_DIR JSKEL_CACHE=off \\
        python tests/scripts/first_image_programs.py default --sets O3,O0

``default`` is the CLI's embedded experiment (README's first command); any experiment file will
do. Option sets: ``O3`` (XLA:CPU's defaults, stated), ``O0`` (``xla_backend_optimization_level``
0), ``noexp`` (``xla_llvm_disable_expensive_passes``), ``O0noexp`` (both: what the frusta build
compiled with before it took XLA's defaults, ``frusta._build._HOST_OPTS``), ``fusion`` and ``elemental`` (XLA:CPU's MLIR fusion
emitters, its default, or its elemental emitters), ``noynn`` (the elemental emitters without
YNNPACK's fusions: the frusta's and meshes' ``Representation.cpu_compiler_options``),
``fusion_noynn`` (the fusion emitters without YNNPACK's fusions).
"""
import argparse
import collections
import json
import re
import statistics
import tempfile
import time

import jax
from jax._src import stages

from jskel.compile import executables

SETS = {
    "O3": {"xla_backend_optimization_level": 3, "xla_llvm_disable_expensive_passes": False},
    "O0": {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": False},
    "noexp": {"xla_backend_optimization_level": 3, "xla_llvm_disable_expensive_passes": True},
    "O0noexp": {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True},
    "fusion": {"xla_cpu_use_fusion_emitters": True, "xla_backend_optimization_level": 3},
    "elemental": {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 3},
    "noynn": {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": "", "xla_backend_optimization_level": 3},
    "fusion_noynn": {"xla_cpu_use_fusion_emitters": True, "xla_cpu_experimental_ynn_fusion_type": "", "xla_backend_optimization_level": 3},
}
_seen: list[dict] = []


def _record():
    """Wrap ``Lowered.compile`` and ``executables.compiled_for``: each program compiled keeps its
    lowered form, compile CPU, its function's name, its arguments and its lowering CPU."""
    compile_, compiled_for = stages.Lowered.compile, executables.compiled_for

    def compile_rec(self, *a, **k):
        c0 = time.process_time()
        out = compile_(self, *a, **k)
        _seen.append(dict(lowered=self, compile_cpu=time.process_time() - c0))
        return out

    def compiled_for_rec(fn, args, mesh, make):
        n, c0 = len(_seen), time.process_time()
        out = compiled_for(fn, args, mesh, make)
        if len(_seen) > n:
            _seen[-1].update(name=executables.fn_name(fn), args=args, total_cpu=time.process_time() - c0)
        return out

    stages.Lowered.compile, executables.compiled_for = compile_rec, compiled_for_rec
    return lambda: setattr(stages.Lowered, "compile", compile_)


def ops_by_function(text: str, top: int) -> dict:
    """StableHLO ops of a debug-info module text counted by every jskel function on each op's
    call stack (inclusive: an op of ``_segment_t`` called from ``nearest_bins`` counts for
    both), the ``top`` largest below the frames around the traced function (which hold every op
    that has a location)."""
    defs = dict(re.findall(r"^#(loc\d+) = loc\((.*)\)$", text, re.M))
    memo: dict = {}

    def stack(loc) -> frozenset:  # the function frames of a location, following call sites
        if loc not in memo:
            memo[loc] = frozenset()
            d = defs.get(loc, "")
            m = re.match(r'"([^"]*)"\(#(loc\d+)\)', d)
            c = re.match(r"callsite\(#(loc\d+) at #(loc\d+)\)", d)
            f = m and re.match(r'"(/[^"]*)"', defs.get(m.group(2), ""))
            if f:  # a function's frame: its name over its file's line
                memo[loc] = frozenset([f"{m.group(1).split('.<locals>.')[-1]} ({f.group(1).rsplit('/jskel/', 1)[-1]})"])
            elif m:  # an op's name-stack path over its frames
                memo[loc] = stack(m.group(2))
            elif c:
                memo[loc] = stack(c.group(1)) | stack(c.group(2))
        return memo[loc]

    counts = collections.Counter()
    for line in text.splitlines():
        m = re.search(r"stablehlo\.\w+.*loc\(#(loc\d+)\)\s*$", line)
        if m:
            counts.update(stack(m.group(1)))
    most = max(counts.values(), default=0)  # the frames around the traced function itself
    return dict([(k, v) for k, v in counts.most_common() if v < most][:top])


def _run_median(compiled, args, runs: int) -> float:
    x64 = any(getattr(x, "dtype", None) == "float64" for x in jax.tree_util.tree_leaves(args))
    ts = []
    with jax.enable_x64(x64):  # the build's geometry runs in float64
        for _ in range(runs):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(*args))
            ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def measure(rec: dict, sets: list[str], runs: int, top: int):
    """One line for the program, then one per option set."""
    low = rec["lowered"]
    text = low.as_text()
    ops = len(re.findall(r"\bstablehlo\.\w+", text))
    yield dict(program=rec.get("name"), stablehlo_ops=ops, stablehlo_lines=text.count("\n"),
               lower_cpu=round(rec.get("total_cpu", 0.0) - rec["compile_cpu"], 2), compile_cpu=round(rec["compile_cpu"], 2),
               ops_by_function=ops_by_function(low.as_text(debug_info=True), top))
    for s in sets:
        c0 = time.process_time()
        compiled = low.compile(compiler_options=SETS[s])
        cpu = time.process_time() - c0
        yield dict(options=s, compile_cpu=round(cpu, 2), run_median_s=round(_run_median(compiled, rec["args"], runs), 4))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("experiment", help="an experiment file, or 'default' (the CLI's embedded one)")
    ap.add_argument("--sets", default="O3,O0", help=f"comma-separated option sets among {sorted(SETS)}")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--top", type=int, default=24)
    args = ap.parse_args()
    sets = list(dict.fromkeys(args.sets.split(",")))  # once each: a repeat returns JAX's in-memory executable
    executables.use_dir(tempfile.mkdtemp())  # empty: every program traced and compiled
    from jskel.config import load as load_experiment
    from jskel.render import render

    exp = load_experiment(None if args.experiment == "default" else args.experiment, [])
    restore = _record()
    c0 = time.process_time()
    render(exp, progress=False)
    print(json.dumps(dict(experiment=args.experiment, cold_render_cpu=round(time.process_time() - c0, 2))), flush=True)
    restore()
    for rec in list(_seen):
        for row in measure(rec, sets, args.runs, args.top):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
