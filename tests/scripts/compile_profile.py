"""Where the test suite's time goes to XLA: a pytest plugin that records, for every test run in
a worker, its wall time and each compile JAX reports through ``jax.monitoring`` (tracing,
lowering to MLIR, XLA's backend compile with the jitted function's name, and the time the
persistent cache saved), one JSON line per test in ``$JSKEL_COMPILE_PROFILE/profile_<worker>.jsonl``;
run as a script on that folder it sums them.

    PYTHONPATH=tests/scripts JSKEL_COMPILE_PROFILE=/tmp/prof python -m pytest -q -p compile_profile
    python tests/scripts/compile_profile.py /tmp/prof

Tests that run a subprocess (the float64 derivative checks, the notebooks, the sweep workers)
show their wall time with none of the subprocess' compiles. Empty the JAX cache first
(``.jax_cache`` in the checkout) to see what a fresh clone compiles."""

from __future__ import annotations

import collections
import json
import os
import sys
import time
from pathlib import Path

_current: list = []
_out = None


def _listener(event: str, duration: float, **kw) -> None:
    if event.startswith("/jax/core/compile/") or event == "/jax/compilation_cache/compile_time_saved_sec":
        _current.append((event.rsplit("/", 1)[-1], round(duration, 4), str(kw.get("fun_name", ""))))


def pytest_configure(config):
    from jax._src import monitoring

    monitoring.register_event_duration_secs_listener(_listener)


def _pytest_hooks():
    import pytest

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        global _out
        if _out is None:
            folder = Path(os.environ.get("JSKEL_COMPILE_PROFILE", "compile_profile"))
            folder.mkdir(parents=True, exist_ok=True)
            _out = open(folder / f"profile_{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl", "a")
        _current.clear()
        t = time.perf_counter()
        yield
        _out.write(json.dumps({"test": item.nodeid, "wall": round(time.perf_counter() - t, 3), "events": list(_current)}) + "\n")
        _out.flush()

    return pytest_runtest_protocol


if __name__ != "__main__":
    pytest_runtest_protocol = _pytest_hooks()


def summary(folder: Path, top: int = 25) -> str:
    """Totals by event, the programs that took the most backend compile (count, seconds, test
    files) and the tests with the most compile time."""
    rows = [json.loads(line) for f in sorted(folder.glob("profile_*.jsonl")) for line in f.read_text().splitlines() if line]
    total = collections.Counter()
    count = collections.Counter()
    programs = collections.defaultdict(lambda: [0, 0.0, set()])
    lines = [f"{len(rows)} tests, {sum(r['wall'] for r in rows):.0f} s of test wall time in the workers"]
    for r in rows:
        for event, seconds, name in r["events"]:
            total[event] += seconds
            count[event] += 1
            if event == "backend_compile_duration":
                p = programs[name]
                p[0], p[1] = p[0] + 1, p[1] + seconds
                p[2].add(r["test"].split("::")[0])
    lines += [f"  {e}: {total[e]:.0f} s in {count[e]} events" for e in sorted(total)]
    lines.append("programs by backend compile time: seconds, compiles, test files, name")
    for name, (n, s, files) in sorted(programs.items(), key=lambda kv: -kv[1][1])[:top]:
        lines.append(f"  {s:7.1f} {n:5d} {len(files):3d}  {name}")
    lines.append("tests by compile time (trace + lowering + backend): compile s, wall s, test")
    own = [(sum(s for e, s, _ in r["events"] if e != "compile_time_saved_sec"), r["wall"], r["test"]) for r in rows]
    for c, w, t in sorted(own, reverse=True)[:top]:
        lines.append(f"  {c:6.1f} {w:6.1f}  {t}")
    return "\n".join(lines)


if __name__ == "__main__":
    print(summary(Path(sys.argv[1] if len(sys.argv) > 1 else "compile_profile")))
