"""Flag shares of the implicit bisection tracer on test_implicit's random set (50,000 rays, seed
7 or argv[1]) against a float64 1024-sample first root: rays flagged graze / no_bracket, and
how many of them (and of the unflagged) a float64 reference finds wrong. Run from the repository
root: python tests/scripts/bisection_flags.py [seed]. The reference is cached in /tmp."""
import sys, time
sys.path.insert(0, "tests")
import numpy as np
import implicit_reference as iref
import reference as ref
from test_implicit import arrays, model_cfg, cast, T
from jskel import implicit
from jskel.rays import FLAG_GRAZE, FLAG_NO_BRACKET

rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 7)
a, b, ra, rb = arrays()
lo = np.minimum(a, b).min(0) - 1.0
hi = np.maximum(a, b).max(0) + 1.0
O, D = ref.random_rays(rng, lo, hi, 50_000, spread=1.2)
import os
seed = int(sys.argv[1]) if len(sys.argv) > 1 else 7
cache = f"/tmp/bisection_flags_ref{seed}.npz"
if os.path.exists(cache):
    z = np.load(cache); t_ref, margin = z["t"], z["m"]
else:
    t_ref, margin, slope = iref.first_root(O, D, a, b, ra, rb, T, n=1024, batch=1000)
    np.savez(cache, t=t_ref, m=margin)
scale = float(np.linalg.norm(hi - lo))
t0 = time.time()
built = implicit.build(model_cfg("bisection"))
hit = cast(built, O, D)
tol = 1e-4 * scale
print("cast s", time.time() - t0)
g = (hit.flags & FLAG_GRAZE) != 0
nb = (hit.flags & FLAG_NO_BRACKET) != 0
fin = np.isfinite(hit.t)
reff = np.isfinite(t_ref)
# a real miss: the reference's first crossing is more than tol before the tracer's t (or the tracer missed)
wrong = (reff & (~fin | (np.where(fin, hit.t, np.inf) > t_ref + tol))) | (~reff & fin)
print("rays", len(O), "graze %.4f %%" % (100 * g.mean()), "no_bracket %.4f %%" % (100 * nb.mean()),
      "flagged %.4f %%" % (100 * (hit.flags != 0).mean()))
print("wrong (real) %.4f %% (%d), of them graze %d, no_bracket %d, silent %d" % (100 * wrong.mean(), wrong.sum(), (wrong & g).sum(), (wrong & nb).sum(), (wrong & (hit.flags == 0)).sum()))
print("graze real %d false %d; no_bracket real %d false %d" % ((g & wrong).sum(), (g & ~wrong).sum(), (nb & wrong).sum(), (nb & ~wrong).sum()))
silent = wrong & (hit.flags == 0)
if silent.any():
    i = np.nonzero(silent)[0][:5]
    print("silent examples", i, hit.t[i], t_ref[i], margin[i])
