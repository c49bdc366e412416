"""Run by hand (not by the suite; needs the [peers] extra and ``DRJIT_LIBLLVM_PATH``): how timing
jskel's cast in turn with Mitsuba's changes either, in one process (docs/choices.md#interleaved-casts).

For a scene at 1024 x 768, jskel's cast with the host's copies (``probe.cast.cast_once``), its
resident cast (``probe.cast.cast_resident``) and Mitsuba's round-cone curves' cast
(``peers.skeleton.MitsubaCurves``) are timed in turn with no pause, with 0.05 s and with 0.3 s of
sleep after each cast, then each in a block of its own. One JSON line: medians of ``--runs``.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-15.so python tests/scripts/interleave_pause.py oasis"""

import argparse
import json
import statistics
import time

import jskel

jskel.use_host_devices()

from jskel.config import load  # noqa: E402
from jskel.frusta import host_frusta, skeleton_arrays  # noqa: E402
from jskel.measure.files import provenance  # noqa: E402
from jskel.peers.skeleton import MitsubaCurves  # noqa: E402
from jskel.peers.skeleton_study import _jskel_casts  # noqa: E402
from jskel.probe.study import shape_of  # noqa: E402
from jskel.render import camera_of  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    exp = load(f"experiments/{args.scene}.yaml", ["camera.width=1024", "camera.height=768"])
    obj = shape_of(exp, "interleave_pause")
    _, _, _, joints, radii, _ = host_frusta(obj)
    parents = skeleton_arrays(obj.skeleton, obj.frame)[2]
    once, resident = _jskel_casts(exp)
    mc = MitsubaCurves(joints, radii, parents, "llvm_ad_rgb")
    O, D = camera_of(exp).ray_arrays()
    fns = {"jskel_copies": once, "jskel_resident": resident, "mitsuba": lambda: mc.cast(O, D)[1]}
    for f in fns.values():
        f(), f()
    out = {}
    for pause in (0.0, 0.05, 0.3):
        t = {k: [] for k in fns}
        for _ in range(args.runs):
            for k, f in fns.items():
                t[k].append(f())
                time.sleep(pause)
        out[f"in_turn_pause_{pause}"] = {k: round(statistics.median(v), 4) for k, v in t.items()}
    out["blocks"] = {k: round(statistics.median([f() for _ in range(args.runs)]), 4) for k, f in fns.items()}
    print(json.dumps(dict(scene=args.scene, seconds_median=out, run=provenance())))


if __name__ == "__main__":
    main()
