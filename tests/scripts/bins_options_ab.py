"""Run by hand (not by the suite): the cast (``interface.cast_t_prim``: t and primitive, the
representation's CPU default traversal, the frusta's and the meshes' bins) of every 4,096-ray
chunk of a scene's frame, compiled once per XLA option set in one process and timed in
alternation, so that the machine's drift between processes (which moved
whole-bench casts by 10-25 % from one process to the next on the 2-core CPUs) falls on every set
alike. One device, one call per chunk; the hits (t and segment) of every set are compared with
the first set's. One JSON line per scene.

    python tests/scripts/bins_options_ab.py oasis pine --sets elemental,noynn
    python experiments/meshes/make.py && python tests/scripts/bins_options_ab.py mesh_icosphere mesh_torus
    XLA_FLAGS=--xla_cpu_max_isa=AVX2 python tests/scripts/bins_options_ab.py oasis --sets elemental,noynn

Scenes are ``experiments/NAME.yaml`` at ``--width`` x ``--height`` (1024 x 768, bench_scale's
frame). Option sets: ``elemental`` (the frusta's options before YNNPACK's fusions were turned
off), ``noynn`` (``Representation.cpu_compiler_options`` of the frusta now), ``fusion``
(XLA:CPU's defaults)."""

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

SETS = {
    "fusion": {},
    "elemental": {"xla_cpu_use_fusion_emitters": False},
    "noynn": {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""},
}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--sets", default="elemental,noynn")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    args = ap.parse_args()
    from jskel.compile.isa import xla_isa
    from jskel.config import load as load_experiment
    from jskel.interface import Object, cast_t_prim
    from jskel.measure.bench import _built_and_rays
    from jskel.rays import Rays
    from jskel.probe.study import shape_of
    from jskel.measure.files import provenance

    sets = args.sets.split(",")
    for scene in args.scenes:
        exp = load_experiment(f"experiments/{scene}.yaml", [f"camera.width={args.width}", f"camera.height={args.height}"])
        _, built, rays = _built_and_rays(exp, "bins_options_ab")
        obj = Object(built.params, built.static, shape_of(exp, "bins_options_ab").type)
        n = 4096
        chunks = [Rays(*(jnp.asarray(np.asarray(x)[c * n:(c + 1) * n]) for x in rays)) for c in range(rays.size // n)]
        fn = jax.jit(lambda r: cast_t_prim(obj, r))
        compiled, compile_s = {}, {}
        for s in sets:
            t0 = time.perf_counter()
            compiled[s] = fn.lower(chunks[0]).compile(compiler_options=SETS[s])
            compile_s[s] = round(time.perf_counter() - t0, 2)
        first = [compiled[sets[0]](c) for c in chunks]
        same = {s: all(bool(jnp.array_equal(x[0], y[0]) and jnp.array_equal(x[1], y[1])) for x, y in zip(first, (compiled[s](c) for c in chunks)))
                for s in sets[1:]}
        times = {s: [] for s in sets}
        for _ in range(args.runs):  # alternating: each run times every set once
            for s in sets:
                t0 = time.perf_counter()
                for c in chunks:
                    out = compiled[s](c)
                jax.block_until_ready(out)
                times[s].append(time.perf_counter() - t0)
        med = {s: round(statistics.median(v), 4) for s, v in times.items()}
        print(json.dumps(dict(scene=scene, rays=rays.size, chunks=len(chunks), isa=xla_isa(), cast_s_median=med,
                              over_first={s: round(med[s] / med[sets[0]], 3) for s in sets[1:]}, same_hits=same, compile_s=compile_s,
                              run=provenance())), flush=True)


if __name__ == "__main__":
    main()
