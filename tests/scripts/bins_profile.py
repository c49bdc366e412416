"""Run by hand (not by the suite): where the frusta bins' cast spends its time, from a
``jax.profiler`` trace. The scene's frame (``experiments/NAME.yaml`` at 1024 x 768) is cut into
4,096-ray chunks; the bins' cast (``frusta._accel.nearest_bins``, compiled with the frusta's CPU
options, ``Representation.cpu_compiler_options``) runs on each, one call per chunk on one
device, three times under the profiler. Every executed op's self time (its time less the ops
nested in it, per thread) is summed by the jskel source line its HLO instruction came from (the
innermost two frames in ``accel/_bins.py``, ``frusta/_accel.py``, ``frusta/_intersect.py`` or
``numerics.py``, read from the compiled module's stack frames); the runtime's own work (the
thunk executor, loop and conditional control) is listed by name, the call's own host work
apart (one call per chunk here, where a render makes one call of 64 chunks). One JSON
line: the chunks, the untraced median wall time of the frame and the top entries in
microseconds per chunk and as a share of the traced total.

    python tests/scripts/bins_profile.py oasis --chunks dense
    XLA_FLAGS=--xla_cpu_max_isa=AVX2 python tests/scripts/bins_profile.py oasis --chunks all

``--chunks all``: every chunk of the frame; ``dense``: the ``--dense`` chunks that take longest
(timed once each first). The profiler's own cost inflates the traced times (about 2x on the
2-core CPUs), so the shares, not the microseconds, are what compare with a cast."""

import argparse
import collections
import glob
import gzip
import json
import re
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

KEEP = ("_bins.py", "_accel.py", "_intersect.py", "numerics.py")
#: a call's own host work (dispatch, argument handling, output buffers), reported apart
CALL = ("CommonPjRt", "PjitFunction", "AllocateOutputBuffers", "Handle inputs", "ExecutePrepare")


def _self_times(events):
    """Self time and count of each named complete event: its duration less its children's on
    the same thread."""
    by_thread = collections.defaultdict(list)
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            by_thread[(e.get("pid"), e.get("tid"))].append(e)
    own, count = collections.Counter(), collections.Counter()
    for es in by_thread.values():
        es.sort(key=lambda e: (e["ts"], -e["dur"]))
        stack = []
        for e in es:
            while stack and stack[-1]["ts"] + stack[-1]["dur"] <= e["ts"]:
                stack.pop()
            if stack:
                own[stack[-1]["name"]] -= e["dur"]
            own[e["name"]] += e["dur"]
            count[e["name"]] += 1
            stack.append(e)
    return own, count


def _sources(hlo: str) -> dict:
    """HLO instruction name -> 'function:line/function:line' of its innermost jskel frames."""
    sec, cur = {}, None
    for line in hlo.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            cur, sec[line] = line, {}
        elif not line.strip():
            cur = None
        elif cur:
            k, v = line.split(" ", 1)
            sec[cur][int(k)] = v
    files = {k: v.strip('"').rsplit("/", 1)[-1] for k, v in sec.get("FileNames", {}).items()}
    funcs = {k: v.strip('"') for k, v in sec.get("FunctionNames", {}).items()}
    locs, frames = {}, {}
    for k, v in sec.get("FileLocations", {}).items():
        d = dict(re.findall(r"(\w+)=(\d+)", v))
        locs[k] = (files[int(d["file_name_id"])], funcs[int(d["function_name_id"])], int(d["line"]))
    for k, v in sec.get("StackFrames", {}).items():
        d = dict(re.findall(r"(\w+)=(\d+)", v))
        frames[k] = (int(d["file_location_id"]), int(d["parent_frame_id"]))
    out = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*stack_frame_id=(\d+)", line)
        if not m:
            continue
        fid, seen, chain = int(m.group(2)), set(), []
        while fid in frames and fid not in seen:
            seen.add(fid)
            loc, fid = frames[fid]
            chain.append(locs[loc])
        ours = [c for c in chain if c[0] in KEEP]
        out[m.group(1)] = "/".join(f"{c[1].split('.<locals>.')[-1]}:{c[2]}" for c in ours[:2]) if ours else "other"
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--chunks", choices=["all", "dense"], default="dense")
    ap.add_argument("--dense", type=int, default=3)
    ap.add_argument("--top", type=int, default=24)
    args = ap.parse_args()
    from jskel import registry
    from jskel.compile.isa import xla_isa
    from jskel.config import load as load_experiment
    from jskel.frusta._accel import nearest_bins
    from jskel.measure.bench import _built_and_rays
    from jskel.measure.files import provenance

    exp = load_experiment(f"experiments/{args.scene}.yaml", ["camera.width=1024", "camera.height=768"])
    _, built, rays = _built_and_rays(exp, "bins_profile")
    g, st = built.params.plain, built.static
    n = 4096
    chunks = [[jnp.asarray(np.asarray(x)[c * n:(c + 1) * n]) for x in rays] for c in range(rays.size // n)]
    fn = jax.jit(lambda o, d, a, b: nearest_bins(g.frusta, g.bvh, *st.bins, o, d, a, b, leaf=st.leaf, walk_group=st.group)[:4:3])
    opts = dict(registry.get("frusta").cpu_compiler_options)
    compiled = fn.lower(*chunks[0]).compile(compiler_options=opts)
    if args.chunks == "dense":
        once = []
        for c in chunks:
            jax.block_until_ready(compiled(*c))
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(*c))
            once.append(time.perf_counter() - t0)
        chunks = [chunks[i] for i in np.argsort(once)[-args.dense:]]
    walls = []
    for _ in range(5):
        t0 = time.perf_counter()
        for c in chunks:
            out = compiled(*c)
        jax.block_until_ready(out)
        walls.append(time.perf_counter() - t0)
    traced = tempfile.mkdtemp()
    with jax.profiler.trace(traced, create_perfetto_trace=True):
        for _ in range(3):
            for c in chunks:
                out = compiled(*c)
            jax.block_until_ready(out)
    events = json.load(gzip.open(glob.glob(f"{traced}/**/*.trace.json.gz", recursive=True)[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    own, _ = _self_times(events)
    src = _sources(compiled.as_text())
    by, call = collections.Counter(), 0.0
    for name, us in own.items():
        if "wait for completion" in name or name.startswith("$"):  # the host thread waiting; Python frames
            continue
        if name.startswith(CALL):  # one call per chunk here; a render groups 128 chunks a call
            call += us
            continue
        by[src.get(name, "runtime:" + name.split(".")[0])] += us
    total = sum(by.values())
    per = 3 * len(chunks)
    print(json.dumps(dict(scene=args.scene, chunks=args.chunks, chunk_count=len(chunks), isa=xla_isa(), options=opts,
                          frame_ms_median=round(statistics.median(walls) * 1e3, 2), traced_us_per_chunk=round(total / per, 1), call_us_per_chunk=round(call / per, 1),
                          top=[dict(source=k, us_per_chunk=round(v / per, 1), share=round(v / total, 4)) for k, v in by.most_common(args.top)],
                          run=provenance())), flush=True)


if __name__ == "__main__":
    main()
