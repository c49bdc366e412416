"""The bisection tracer's batch program (intersect_batch) on test_implicit's 50,000 random rays
(seed 7): warm cast times (chunks of 8,192, after a warm-up), the jaxpr equation count of one
chunk's program (nested jaxprs included), and t / flags saved for a bit-for-bit comparison
between commits. Run from the repository root:
python tests/scripts/bisection_cast.py OUT.npz [casts]"""
import sys, time
sys.path.insert(0, "tests")
import numpy as np, jax
import reference as ref
from test_implicit import arrays, model_cfg
from jskel import implicit
from jskel.rays import make_rays
from jskel.executor import map_chunks
from jskel.interface import Object, intersect as intersect_batch

rng = np.random.default_rng(7)
a, b, ra, rb = arrays()
lo = np.minimum(a, b).min(0) - 1.0
hi = np.maximum(a, b).max(0) + 1.0
O, D = ref.random_rays(rng, lo, hi, 50_000, spread=1.2)
built = implicit.build(model_cfg("bisection"))
obj = Object(built.params, built.static, "implicit")
rays = make_rays(np.asarray(O) - built.anchor, D)
def cast():
    return map_chunks(intersect_batch, obj, rays, chunk=8192, progress=False).out
out = cast()
times = []
for _ in range(int(sys.argv[2]) if len(sys.argv) > 2 else 3):
    t0 = time.perf_counter(); o2 = cast(); jax.block_until_ready(o2.t); times.append(time.perf_counter() - t0)
sub = jax.tree_util.tree_map(lambda x: x[:8192], rays)
jx = jax.make_jaxpr(lambda r: intersect_batch(obj, r))(sub)
def count(j):
    n = 0
    for e in j.eqns:
        n += 1
        for p in e.params.values():
            for v in (p if isinstance(p, (tuple, list)) else [p]):
                if hasattr(v, "jaxpr") and hasattr(v.jaxpr, "eqns"): n += count(v.jaxpr)
                elif hasattr(v, "eqns"): n += count(v)
    return n
print("warm cast s", ["%.2f" % x for x in times], "median %.2f" % np.median(times), "eqns top", len(jx.jaxpr.eqns), "all", count(jx.jaxpr))
np.savez(sys.argv[1], t=np.asarray(out.t), flags=np.asarray(out.flags))
