"""The persistent compilation cache: where it lives, when it is refused, and run.json's counts
of programs compiled and loaded (``jskel.compile.cache``)."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from jskel.compile import cache

ROOT = Path(__file__).resolve().parent.parent


def test_the_directory_follows_the_environment():
    home = os.path.expanduser("~")
    assert cache.default_cache_dir({}) == Path(home) / ".cache" / "jskel" / "jax"
    assert cache.default_cache_dir({"XDG_CACHE_HOME": "/x/c"}) == Path("/x/c/jskel/jax")
    assert cache.default_cache_dir({"XDG_CACHE_HOME": "/x/c", "JSKEL_CACHE_DIR": "/y/j"}) == Path("/y/j")
    for off in ("off", "OFF", "0", "false"):
        assert cache.default_cache_dir({"JSKEL_CACHE": off, "JSKEL_CACHE_DIR": "/y/j"}) is None
    assert cache.default_cache_dir({"JSKEL_CACHE": "on", "JSKEL_CACHE_DIR": "/y/j"}) == Path("/y/j")
    with pytest.raises(ValueError, match=r"^JSKEL_CACHE: 'maybe' is not on or off$"):
        cache.default_cache_dir({"JSKEL_CACHE": "maybe"})


def test_a_new_directory_is_private_and_an_open_one_is_refused(tmp_path, capsys, monkeypatch):
    new = tmp_path / "a" / "b" / "jax"
    assert cache.prepared_dir(new) == new
    assert stat.S_IMODE(new.stat().st_mode) == 0o700
    assert capsys.readouterr().err == ""
    shared = tmp_path / "shared"
    shared.mkdir()
    for mode in (0o770, 0o707, 0o777):
        os.chmod(shared, mode)
        assert cache.prepared_dir(shared) is None
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and str(shared) in err[0] and f"chmod 700 {shared}" in err[0] and "without it" in err[0], err
    not_dir = tmp_path / "file"
    not_dir.write_text("")
    assert cache.prepared_dir(not_dir) is None  # cannot be made: a warning, never a crash
    assert len(capsys.readouterr().err.splitlines()) == 1
    # the whole switch refuses before it touches JAX's configuration
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("JSKEL_CACHE_DIR", str(shared))
    before = cache.jax.config.jax_compilation_cache_dir
    assert cache.use_compilation_cache() is None
    assert cache.jax.config.jax_compilation_cache_dir == before
    assert str(shared) in capsys.readouterr().err
    monkeypatch.setenv("JSKEL_CACHE", "off")
    assert cache.use_compilation_cache() is None
    # an explicit JAX_COMPILATION_CACHE_DIR wins, and JAX's configuration is left alone
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jaxs"))
    assert cache.use_compilation_cache() == tmp_path / "jaxs"
    assert cache.jax.config.jax_compilation_cache_dir == before


def _render(out: Path, env: dict) -> dict:
    """run.json's program counts of the README's default experiment (the embedded saguaro) at 16x12."""
    cmd = [sys.executable, "-m", "jskel", "render", "--out", str(out),
           "--set", "camera.width=16", "--set", "camera.height=12", "--set", "render.progress=false"]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "warning" not in p.stderr, p.stderr
    return json.loads((out / "run.json").read_text())["programs"]


# the default experiment's one program: the render (intersection, shading and every AOV it
# writes); no conversion of host data, no statistic, no program of an AOV it does not write; the
# build's float64 geometry and BVH are evaluated by NumPy (``jskel.compile.host_eval``), not compiled
DEFAULT_PROGRAMS = {"jit(scene_call)"}


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    """Two CLI renders of the default experiment with the same fresh cache directory
    (``JSKEL_CACHE_DIR``, JAX's own variable unset): the first loads nothing and compiles
    exactly its programs (:data:`DEFAULT_PROGRAMS`, by name), storing each as an executable
    (``jskel.compile.executables``); the second traces and compiles none of them and hands none to XLA:
    it loads the stored executables. The directories are created private, and the
    two images and AOVs are equal bit for bit."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JSKEL_EXECUTABLES")}
    env["JSKEL_CACHE_DIR"] = str(tmp_path / "cache")
    first = _render(tmp_path / "o1", env)
    assert first["loaded"] == 0 and first["cache_dir"] == env["JSKEL_CACHE_DIR"]
    assert set(first["by_name"]) == DEFAULT_PROGRAMS and first["compiled"] == len(DEFAULT_PROGRAMS), first["by_name"]
    ex = first["executables"]
    assert ex["dir"] == str(tmp_path / "cache" / "executables") and ex["loaded"] == 0, ex
    assert ex["compiled"] == len(DEFAULT_PROGRAMS) and ex["stored"] == ex["compiled"] and ex["unstorable"] == 0, ex
    for d in (tmp_path / "cache", tmp_path / "cache" / "executables"):
        assert stat.S_IMODE(d.stat().st_mode) == 0o700
    assert len(list((tmp_path / "cache" / "executables").glob("*.jx"))) == ex["stored"]
    second = _render(tmp_path / "o2", env)
    assert second["executables"]["loaded"] == ex["stored"] and second["executables"]["compiled"] == 0, second
    assert second["compiled"] == 0 and second["loaded"] == 0 and second["by_name"] == {}, (first, second)
    names = sorted(p.name for p in (tmp_path / "o1").iterdir() if p.name != "run.json")
    assert "image.png" in names and names == sorted(p.name for p in (tmp_path / "o2").iterdir() if p.name != "run.json")
    for name in names:
        assert (tmp_path / "o1" / name).read_bytes() == (tmp_path / "o2" / name).read_bytes(), name


def test_the_cli_warns_once_and_runs_on_without_an_open_cache(tmp_path):
    """A group-writable JSKEL_CACHE_DIR: the CLI says so in one line and carries on (here to a
    bad experiment's own error line and exit code 2, before anything compiles); JSKEL_CACHE
    with a bad value is one error line naming the variable."""
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o775)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nobject: {type: nothing}\n")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    cmd = [sys.executable, "-m", "jskel", "render", str(bad), "--out", str(tmp_path / "o")]
    p = subprocess.run(cmd, env=dict(env, JSKEL_CACHE_DIR=str(shared)), capture_output=True, text=True, timeout=120)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 2, p.stderr
    assert lines[0].startswith("jskel: warning: compilation cache") and f"chmod 700 {shared}" in lines[0]
    assert lines[1].startswith("jskel: error: object")
    assert stat.S_IMODE(shared.stat().st_mode) == 0o775 and list(shared.iterdir()) == []
    p = subprocess.run(cmd, env=dict(env, JSKEL_CACHE="sometimes"), capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr.strip() == "jskel: error: JSKEL_CACHE: 'sometimes' is not on or off"
