"""The ISA XLA compiles for (``jskel.compile.isa``), and a bench file run once per ISA: each pass a
fresh process whose ``XLA_FLAGS`` cap the ISA, the rows together in one output."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from jskel.compile import isa
from jskel.measure import bench

AVX512_CPU = "processor\t: 0\nflags\t\t: fpu sse4_2 avx avx2 fma avx512f avx512bw\n"
AVX2_CPU = "processor\t: 0\nflags\t\t: fpu sse4_2 avx avx2 fma\n"


@pytest.mark.parametrize(("cpu", "flags", "want"), [
    (AVX512_CPU, "", "AVX512"),
    (AVX512_CPU, "--xla_cpu_max_isa=AVX2", "AVX2"),
    (AVX512_CPU, "--xla_force_host_platform_device_count=2 --xla_cpu_max_isa=avx", "AVX"),
    (AVX512_CPU, "--xla_cpu_max_isa=AVX2 --xla_cpu_max_isa=AVX512", "AVX512"),  # the last one wins
    (AVX2_CPU, "--xla_cpu_max_isa=AVX512", "AVX2"),  # a cap above the CPU does not widen it
    (AVX2_CPU, "--xla_cpu_max_isa=AVX512_VNNI", "AVX2"),
    ("", "--xla_cpu_max_isa=AVX2", "AVX2"),  # no flags line: as XLA was told
])
def test_the_isa_is_the_cpus_capped_by_xla_flags(cpu, flags, want):
    assert isa.xla_isa(flags, cpu) == want


def test_with_max_isa_replaces_every_cap_and_keeps_other_flags():
    given = "--xla_cpu_max_isa=AVX --xla_force_host_platform_device_count=2 --xla_cpu_max_isa=SSE4_2"
    assert isa.with_max_isa("AVX2", given) == "--xla_force_host_platform_device_count=2 --xla_cpu_max_isa=AVX2"
    assert isa.with_max_isa("default", given) == "--xla_force_host_platform_device_count=2"


def test_a_bench_file_runs_once_per_isa_in_processes_capped_by_xla_flags(tmp_path, monkeypatch):
    """``isa: [default, AVX2]``: two ``python -m jskel bench`` processes of the same file and
    overrides (``isa`` emptied, so none recurses), the first with no ``--xla_cpu_max_isa``, the
    second capped at AVX2; each pass's rows come back in order, marked with the pass, into one
    output file. (The passes are stood in for: each writes the rows a pass would, with the ISA
    its ``XLA_FLAGS`` give, which is what ``timed_render`` records.)"""
    file = tmp_path / "b.yaml"
    file.write_text("scenes: [s.yaml]\nisa: [default, AVX2]\n")
    calls = []

    def fake_run(argv, env):
        calls.append((argv, env["XLA_FLAGS"]))
        out = argv[argv.index("--out") + 1]
        seen = isa.xla_isa(env["XLA_FLAGS"], AVX512_CPU)
        rows = [{"scene": "s", "isa": seen, "render_s_median": 0.1, "run": {"commit": "x"}}, {"peer": "embree", "scene": "s"}]
        with open(out, "w") as f:
            f.write("\n".join(json.dumps(r) for r in rows) + "\n")
        return subprocess.CompletedProcess(argv, 0)

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX --xla_cpu_enable_fast_math=false")
    monkeypatch.setattr(bench, "run_pass", fake_run)
    rows = bench.run_bench(file, ["width=64"], runs=2, out=tmp_path / "rows.jsonl")
    assert [a[:4] for a, _ in calls] == [[sys.executable, "-m", "jskel", "bench"]] * 2
    for argv, _ in calls:
        assert argv[4] == str(file) and argv[argv.index("--runs") + 1] == "2"
        sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
        assert sets == ["width=64", "isa=[]"]
    assert [f for _, f in calls] == ["--xla_cpu_enable_fast_math=false", "--xla_cpu_enable_fast_math=false --xla_cpu_max_isa=AVX2"]
    assert [(r.get("isa"), r["isa_pass"]) for r in rows] == [("AVX512", "default"), (None, "default"), ("AVX2", "AVX2"), (None, "AVX2")]
    kept = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert [r["isa_pass"] for r in kept] == ["default", "default", "AVX2", "AVX2"]
    assert all(r["run"]["commit"] != "x" for r in kept)  # the file's own provenance, not the pass's


def test_a_failed_pass_is_an_error_after_its_rows_are_kept(tmp_path, monkeypatch):
    file = tmp_path / "b.yaml"
    file.write_text("scenes: [s.yaml]\nisa: [AVX2]\n")
    monkeypatch.setattr(bench, "run_pass", lambda argv, env: subprocess.CompletedProcess(argv, 3))
    with pytest.raises(RuntimeError, match="AVX2 pass exited with 3"):
        bench.run_bench(file, [], out=tmp_path / "rows.jsonl")
