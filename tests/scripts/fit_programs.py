"""Run by hand (not by the suite): the size and compile cost of the fit's programs, one JSON line
each: jaxpr equations (nested jaxprs counted), lines of the optimized HLO, and trace / lower /
compile seconds (wall, and process CPU, steadier on a shared machine). The problems are
``tests/test_fit.py``'s: the 5-segment bent chain, 3,000 points, Cauchy loss (L-BFGS: its two
starts under ``lax.map``; LM and Gauss-Newton: the host loop's update, whose first pass makes the
initial state, on dense and sparse normal equations, and jaxopt's initial state and update;
``batch``: LM's ``vmap`` over 3 clouds of 600 points).

    env -u JAX_COMPILATION_CACHE_DIR python tests/scripts/fit_programs.py [lbfgs lm lm_sparse lm_jaxopt gn gn_sparse gn_jaxopt batch]
"""
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

from jskel.fit import _fit, load_points, perturbed, sample_surface
from jskel.fit._config import PointsConfig, SolverConfig
from jskel.fit._distance import segments_of
from jskel.fit._problem import normaliser_of, problem_of, residual_count

BENT = np.array([[0, 0, 0], [0, 1, 0], [-0.5736, 1.8192, 0], [-0.7818, 2.7975, -0.0030], [-0.7838, 3.7469, -0.3171],
                 [-0.6022, 4.6581, -0.6968]])
BENT_R = np.array([0.5, 0.46, 0.42, 0.38, 0.34, 0.3])
CHAIN = np.array([-1, 0, 1, 2, 3, 4])


def count_eqns(jaxpr):
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for p in e.params.values():
            for sub in (p if isinstance(p, (list, tuple)) else [p]):
                if isinstance(sub, jcore.ClosedJaxpr):
                    n += count_eqns(sub.jaxpr)
                elif isinstance(sub, jcore.Jaxpr):
                    n += count_eqns(sub)
    return n


def measure(name, fn, *args):
    t0, c0 = time.perf_counter(), time.process_time()
    tr = fn.trace(*args)
    t1, c1 = time.perf_counter(), time.process_time()
    lo = tr.lower()
    t2, c2 = time.perf_counter(), time.process_time()
    co = lo.compile()
    t3, c3 = time.perf_counter(), time.process_time()
    row = dict(program=name, eqns=count_eqns(tr.jaxpr.jaxpr), hlo_lines=co.as_text().count("\n"),
               trace_s=round(t1 - t0, 2), lower_s=round(t2 - t1, 2), compile_s=round(t3 - t2, 2),
               trace_cpu=round(c1 - c0, 2), compile_cpu=round(c3 - c2, 2))
    print(json.dumps(row), flush=True)
    return co


def problem(solver, **kw):
    pc = PointsConfig.model_validate({"synthetic": {"skeleton": {"joints": BENT.tolist(), "radii": BENT_R.tolist(), "parents": CHAIN.tolist()},
                                                    "count": 3000, "noise": 0.01, "outliers": 0.05, "seed": 7}})
    pts, _, _ = load_points(pc)
    j0, r0 = perturbed(BENT, BENT_R, CHAIN, 0.1, np.random.default_rng(3))
    s = SolverConfig(name=solver, loss="cauchy", scale=0.01, maxiter=300, **kw)
    seg = segments_of(j0, r0, CHAIN)
    pr = problem_of(seg, s, len(j0))
    nz = normaliser_of(pts)
    p = _fit.on_device(_fit.data_of(nz.points(pts), pr, np.float32, seg))
    key = _fit.solver_key(s, residual_count(len(pts), pr), 4 * len(j0))
    x0 = jnp.asarray(nz.start(j0, r0, pr), jnp.float32)
    return pr, key, x0, p


def main(which):
    for w in which:
        if w == "lbfgs":
            pr, key, x0, p = problem("lbfgs", restarts=2)
            measure("lbfgs_solve_starts_2", _fit._solve_starts, jnp.stack([x0, x0 * 1.01]), p, pr, key)
        elif w in ("lm", "gn", "lm_sparse", "gn_sparse", "lm_jaxopt", "gn_jaxopt"):
            name = "lm" if w.startswith("lm") else "gauss_newton"
            pr, key, x0, p = problem(name, jacobian=w.split("_")[1] if "_" in w else "dense")
            step = _fit.stepper(pr, key)
            if step.blank is not None:  # the project's solver: the initial state is one pass of the update
                measure(w + "_update", _fit._update, x0, jax.tree_util.tree_map(jnp.asarray, step.blank(x0)), p, pr, key)
                continue
            st0 = measure(w + "_initial", _fit._initial, x0, p, pr, key)(x0, p)
            measure(w + "_update", _fit._update, x0, st0, p, pr, key)
            if w == "lm":
                measure("loss", _fit._loss, x0, p, pr)
        elif w == "batch":
            base = sample_surface(BENT, BENT_R, CHAIN, 600, np.random.default_rng(5))
            s = SolverConfig(name="lm", loss="l2", maxiter=300, tol=1e-7)
            seg = segments_of(BENT, BENT_R, CHAIN)
            pr = problem_of(seg, s, len(BENT))
            key = _fit.solver_key(s, residual_count(600, pr), 24)
            nz = normaliser_of(base)
            x0 = jnp.asarray(np.stack([nz.start(BENT, BENT_R, pr)] * 3), jnp.float32)
            one = _fit.data_of(nz.points(base), pr, np.float32, seg)
            p = _fit.on_device(jax.tree_util.tree_map(lambda a: np.stack([a] * 3), one))
            measure("lm_batch3_solve_clouds", _fit._solve_clouds, x0, p, pr, key)


if __name__ == "__main__":
    main(sys.argv[1:] or ["lbfgs", "lm", "lm_sparse", "lm_jaxopt", "gn", "gn_sparse", "gn_jaxopt", "batch"])
