"""Benchmark result files: every row a run keeps carries its provenance (date, commit, machine,
devices, command, versions); the docs show each file's latest run and the tables a page marks
(``docs/hooks/bench_results.py``), and a marker that names a missing file or column fails."""

from __future__ import annotations

import importlib.util
import json
import re
import os
import subprocess
from datetime import datetime, timedelta, timezone
from pathlib import Path

import jax
import pytest
from mkdocs.exceptions import PluginError

from jskel.measure.files import JsonLines
from jskel.measure.result_files import cell, latest_run, read_rows

ROOT = Path(__file__).resolve().parents[1]


def _hook():
    spec = importlib.util.spec_from_file_location("bench_results_hook", ROOT / "docs" / "hooks" / "bench_results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_rows_a_run_keeps_carry_its_provenance(tmp_path, capsys):
    out = tmp_path / "bench_x_cpu.jsonl"
    emit = JsonLines(out, command="python -m jskel bench experiments/bench_x.yaml --out bench_x_cpu.jsonl")
    emit({"scene": "a", "render_s_median": 0.5})
    emit({"reference": "log line"}, keep=False)
    emit({"scene": "b", "render_s_median": 0.25})
    printed = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [p.get("scene") for p in printed] == ["a", None, "b"]
    rows = read_rows(out)
    assert [r["scene"] for r in rows] == ["a", "b"]  # the log line is printed, not kept
    run = rows[0]["run"]
    assert rows[1]["run"] == run
    assert run["command"] == "python -m jskel bench experiments/bench_x.yaml --out bench_x_cpu.jsonl"
    started = datetime.fromisoformat(run["date"])
    assert started.tzinfo is not None and abs(datetime.now(timezone.utc) - started) < timedelta(minutes=5)
    assert run["machine"].startswith(f"{os.cpu_count()}-core ")
    assert run["versions"]["jax"] == jax.__version__ and run["devices"] == sorted({f"{d.platform}:{d.device_kind}" for d in jax.devices()})
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode == 0:  # outside a git checkout the commit is not recorded
        assert run["commit"].split("+")[0] == head.stdout.strip()


def _row(scene, t, date=None, **extra):
    row = {"scene": scene, "render_s_median": t, "device": "cpu:cpu", "jax": "0.10.2", "jskel": "0.1.0", **extra}
    if date is not None:
        row["run"] = {"date": date, "commit": "abc1234", "machine": "2-core Test CPU, AVX2", "devices": ["cpu:cpu"],
                      "command": "python -m jskel bench b.yaml --out x.jsonl", "versions": {"jax": "0.10.2", "jskel": "0.1.0"}}
    return row


def test_the_machine_names_the_cpu_family_and_model_and_its_widest_vector_unit():
    """Two CPUs sold as "AMD EPYC" are told apart by their family and model numbers; the widest
    vector unit is AVX-512 only with avx512f (a CPU with avx2 alone is AVX2)."""
    from jskel.measure.files import _cpu

    info = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel\t\t: 2\n"
            "model name\t: AMD EPYC\nflags\t\t: fpu sse2 avx avx2 fma\n")
    n = os.cpu_count()
    assert _cpu(info) == f"{n}-core AMD EPYC (family 26, model 2), AVX2"
    assert _cpu(info.replace("avx2 fma", "avx2 avx512f fma")) == f"{n}-core AMD EPYC (family 26, model 2), AVX-512"
    assert _cpu("model name\t: Some CPU\n") == f"{n}-core Some CPU"


def test_latest_run_is_the_rows_of_the_latest_date():
    old = [_row("a", 1.0), _row("b", 2.0)]  # written before rows carried a run: older than any dated run
    first = [_row("a", 3.0, "2026-12-01T10:00:00+00:00")]
    last = [_row("a", 4.0, "2026-12-02T09:00:00+00:00", peer="embree"), _row("b", 5.0, "2026-12-02T09:00:00+00:00")]
    run = latest_run(old + last[:1] + first + last[1:])
    assert run.rows == last and run.provenance["date"] == "2026-12-02T09:00:00+00:00"
    assert latest_run(old) == (None, old)


def test_a_marker_becomes_the_latest_runs_table_with_its_provenance(tmp_path):
    rows = [_row("a", 9.0, "2026-12-01T10:00:00+00:00"), _row("a", 0.12345, "2026-12-02T09:00:00+00:00"),
            _row("b", 12345.6, "2026-12-02T09:00:00+00:00", rays=786432), _row("a", 1.5, "2026-12-02T09:00:00+00:00", peer="embree")]
    (tmp_path / "bench_x_cpu.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    text = _hook().marked_table("bench_x_cpu.jsonl scene render_s_median rays peer=-", tmp_path, "sub/page.md")
    lines = text.splitlines()
    assert lines[0] == "| `scene` | `render_s_median` | `rays` |" and lines[1] == "| --- | ---: | ---: |"
    assert lines[2:4] == ["| a | 0.1235 |  |", "| b | 12,346 | 786,432 |"]  # the earlier run and the peer's row left out
    where = lines[5]
    for part in ("`docs/bench_x_cpu.jsonl`", "`python -m jskel bench b.yaml --out x.jsonl`", "2-core Test CPU, AVX2",
                 "2026-12-02T09:00:00+00:00", "`abc1234`", "jax 0.10.2", "(../results.md#bench_x_cpujsonl)"):
        assert part in where, part
    peer = _hook().marked_table("bench_x_cpu.jsonl scene render_s_median peer=embree", tmp_path, "page.md")
    assert peer.splitlines()[2] == "| a | 1.5 |"


@pytest.mark.parametrize("spec, message", [
    ("missing.jsonl scene", "not a file under docs/"),
    ("bench_x_cpu.jsonl scene no_such_key", "no row has ['no_such_key']"),
    ("bench_x_cpu.jsonl scene scene=zzz", "no row matches"),
])
def test_a_marker_that_shows_nothing_true_fails_the_build(tmp_path, spec, message):
    (tmp_path / "bench_x_cpu.jsonl").write_text(json.dumps(_row("a", 1.0)) + "\n")
    with pytest.raises(PluginError, match=re.escape(message)):
        _hook().marked_table(spec, tmp_path, "page.md")


def test_rows_without_provenance_say_what_is_not_recorded(tmp_path):
    (tmp_path / "bench_y_cpu.jsonl").write_text(json.dumps(_row("a", 1.0)) + "\n")
    text = _hook().section(tmp_path / "bench_y_cpu.jsonl")
    assert "command and machine not recorded in the file (device cpu:cpu)" in text and "jax 0.10.2" in text
    assert "not committed" in text  # a file git does not hold has no date to show


def test_rows_without_provenance_say_what_git_history_tells(tmp_path):
    (tmp_path / "bench_y_cpu.jsonl").write_text(json.dumps(_row("a", 1.0)) + "\n")
    entry = {"commit": "abc1234", "date": "2026-11-24", "machine": "2-core Test CPU", "command": "python -m jskel bench y.yaml", "note": "in parts"}
    (tmp_path / "result_files_history.json").write_text(json.dumps({"files": {"bench_y_cpu.jsonl": entry}}))
    where = _hook().marked_table("bench_y_cpu.jsonl scene", tmp_path, "page.md").splitlines()[-1]
    for part in ("not recorded in the file", "run 2026-11-24 on the code of commit `abc1234`", "on 2-core Test CPU",
                 "by `python -m jskel bench y.yaml` (in parts)"):
        assert part in where, part


def _git(*args):
    out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
    return out.returncode, out.stdout.strip()


def test_every_result_file_without_provenance_has_its_history():
    if _git("rev-parse", "--git-dir")[0] != 0:
        pytest.skip("not a git checkout: the history's commits cannot be checked")
    history = json.loads((ROOT / "docs" / "result_files_history.json").read_text())["files"]
    bare = sorted(p.name for p in (ROOT / "docs").glob("*.jsonl") if latest_run(read_rows(p)).provenance is None)
    assert sorted(history) == bare, "docs/result_files_history.json: entries differ from the files whose rows carry no run"
    wrong = []
    for name, h in history.items():
        last = _git("log", "-1", "--format=%H", "--", f"docs/{name}")[1]
        code, date = _git("show", "-s", "--format=%cs", h["commit"])
        # the rows cannot come from code later than the commit that wrote the file, and the date is that code's
        if code != 0 or date != h["date"] or _git("merge-base", "--is-ancestor", h["commit"], last)[0] != 0:
            wrong.append(f"{name}: commit {h['commit']} date {h['date']} (git: {date or 'no such commit'})")
        if not h["machine"] or not h["command"]:
            wrong.append(f"{name}: machine or command empty")
    assert not wrong, "; ".join(wrong)


def test_cells():
    assert [cell(x) for x in (None, True, 786432, 0.012344, 123456.7, {"object.steps": 32}, "a|b")] == \
        ["", "true", "786,432", "0.01234", "123,457", 'object.steps=32', "a&#124;b"]


def test_a_result_files_plots_are_its_own(tmp_path):
    for name in ("bench_a.jsonl", "bench_a_b.jsonl", "bench_a.png", "bench_a_x.png", "bench_a_b.png", "bench_a_b_y.png", "bench_c.png"):
        (tmp_path / name).write_text(json.dumps(_row("s", 1.0)) + "\n" if name.endswith(".jsonl") else "")
    hook = _hook()
    assert [p.name for p in hook.plots(tmp_path / "bench_a.jsonl")] == ["bench_a.png", "bench_a_x.png"]
    assert [p.name for p in hook.plots(tmp_path / "bench_a_b.jsonl")] == ["bench_a_b.png", "bench_a_b_y.png"]
    assert "![bench_a_x.png](bench_a_x.png)" in hook.section(tmp_path / "bench_a.jsonl")
