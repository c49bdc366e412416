"""Stored executables (``jskel.compile.executables``): loaded instead of traced, keyed on what the
program depends on, refused from an open directory or file, recompiled and replaced when an
entry is truncated or corrupt. One tiny program; the CLI's two-process check is in
tests/test_cache.py."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys

import jax
import numpy as np
import pytest

from jskel.compile import executables

ARGS = (np.float32(3.0), np.arange(8, dtype=np.float32))
TRUTH = 3.0 * np.arange(8, dtype=np.float64) + 1.0  # exact in float32


def _affine(a, x):
    return a * x + 1.0


# a constant of this process in the compiled program (times a traced zero, so that it stays
# there): JAX's persistent cache (the tests' .jax_cache, kept between runs in one checkout) then
# never serves it from an earlier run, and a program that cache serves is not stored
# (``executables.counts()['from_jax_cache']``): a second run of this file in one checkout found
# nothing stored. Within the process, JAX's own in-memory cache of ``_affine_here`` serves repeats.
_PID = float(os.getpid())


def _affine_here(a, x):
    return _affine(a, x) + (a - a) * _PID


def _compile():
    return jax.jit(_affine_here).lower(*ARGS).compile()


def _get():
    """(output, loaded?, compiled?) of one request for ``_affine``."""
    n0 = dict(executables._counts)
    out = executables.compiled_for(_affine, ARGS, None, _compile)(*ARGS)
    n1 = executables._counts
    return np.asarray(out), n1["loaded"] - n0["loaded"], n1["compiled"] - n0["compiled"]


def test_a_stored_executable_is_loaded_and_computes_the_same(store, capsys):
    assert stat.S_IMODE(store.stat().st_mode) == 0o700
    out, loaded, compiled = _get()
    assert (loaded, compiled) == (0, 1) and len(list(store.glob("*.jx"))) == 1
    out2, loaded, compiled = _get()
    assert (loaded, compiled) == (1, 0)
    np.testing.assert_array_equal(out, TRUTH)
    np.testing.assert_array_equal(out2, TRUTH)
    assert capsys.readouterr().err == ""


def test_a_change_of_source_or_versions_misses(store, monkeypatch):
    key = executables.entry_key(_affine, ARGS)
    _get()
    monkeypatch.setattr(executables, "source_hash", lambda: "an edited jskel")
    assert executables.entry_key(_affine, ARGS) != key
    assert _get()[1:] == (0, 1)
    monkeypatch.undo()
    monkeypatch.setattr(executables.jax, "__version__", "0.0.1")
    assert executables.entry_key(_affine, ARGS) != key
    assert _get()[1:] == (0, 1)
    monkeypatch.undo()
    assert _get()[1:] == (1, 0)  # the first entry is still there for the original key
    assert executables.entry_key(_affine, (ARGS[0], ARGS[1][:4])) != key  # shapes are part of the key
    assert executables.entry_key(lambda a, x: a, ARGS) is None  # a lambda has no stable name: not stored


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_damaged_entry_is_compiled_again_and_replaced(store, capsys, damage):
    _get()
    (path,) = store.glob("*.jx")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if damage == "truncate" else data[:-100] + bytes([data[-100] ^ 1]) + data[-99:])
    out, loaded, compiled = _get()
    assert (loaded, compiled) == (0, 1)
    np.testing.assert_array_equal(out, TRUTH)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(path) in err[0] and "truncated or corrupt" in err[0] and "compiling it again" in err[0], err
    assert path.read_bytes() != b"" and _get()[1:] == (1, 0)  # replaced by a whole entry


def test_an_open_directory_or_file_is_refused(tmp_path, store, capsys):
    _get()
    (path,) = store.glob("*.jx")
    os.chmod(path, 0o666)
    assert _get()[1:] == (0, 1)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(path) in err[0] and "private" in err[0], err
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o775)
    assert executables.use_dir(shared) is None
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(shared) in err[0] and f"chmod 700 {shared}" in err[0], err
    out, loaded, compiled = _get()  # everything compiles as usual, nothing is written
    assert (loaded, compiled) == (0, 1) and list(shared.iterdir()) == []
    np.testing.assert_array_equal(out, TRUTH)


def test_an_unsharded_program_is_loaded_onto_its_one_device_of_two(tmp_path):
    """Two processes with two host devices: the second loads the first's one-device program
    (deserialized onto the device it was compiled for, not onto every device) and computes 3 x."""
    code = ("import json, operator, numpy as np, jax; from jskel.compile import executables as ex; "
            f"ex.use_dir({str(tmp_path / 'x')!r}); a = (np.float32(3), np.arange(8, dtype=np.float32)); "
            "c = ex.compiled_for(operator.mul, a, None, lambda: jax.jit(operator.mul).lower(*a).compile()); "
            "print(json.dumps([np.asarray(c(*a)).tolist(), ex.counts()['loaded'], len(jax.devices())]))")
    # JAX's persistent cache of this test's own (an earlier run's would serve the program, which is then not stored)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax"))
    for loaded in (0, 1):
        p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert p.returncode == 0 and "warning" not in p.stderr, p.stderr[-2000:]
        out, n_loaded, n_devices = json.loads(p.stdout)
        assert (n_loaded, n_devices) == (loaded, 2), p.stdout
        np.testing.assert_array_equal(out, 3.0 * np.arange(8))


def test_the_switch_reads_on_and_off():
    assert not executables.switched_off({}) and not executables.switched_off({"JSKEL_EXECUTABLES": "on"})
    assert executables.switched_off({"JSKEL_EXECUTABLES": "OFF"}) and executables.switched_off({"JSKEL_EXECUTABLES": "0"})
    with pytest.raises(ValueError, match=r"^JSKEL_EXECUTABLES: 'later' is not on or off$"):
        executables.switched_off({"JSKEL_EXECUTABLES": "later"})


def _entry_for(n: int):
    """(output, the entry's path) of ``_affine`` on ``n`` values: one entry per size."""
    args = (np.float32(3.0), np.arange(n, dtype=np.float32))
    before = set(executables._state["dir"].glob("*.jx"))
    out = executables.compiled_for(_affine, args, None, lambda: jax.jit(_affine_here).lower(*args).compile())(*args)
    np.testing.assert_array_equal(out, 3.0 * np.arange(n) + 1.0)
    new = set(executables._state["dir"].glob("*.jx")) - before
    return new.pop() if new else None


def test_the_folder_keeps_under_its_cap_removing_the_least_recently_used(store, monkeypatch):
    """Three entries (4, 8 and 16 values) stored in that order, then the first loaded again:
    with a cap that holds three of them, the fourth's store removes the second (the least
    recently used), not the first (used last) nor the fourth (just stored)."""
    monkeypatch.setitem(executables._state, "max_bytes", 2**40)
    a, b, c = (_entry_for(n) for n in (4, 8, 16))
    for k, p in enumerate((a, b, c)):  # distinct times whatever the clock's resolution
        os.utime(p, (1e9 + k, 1e9 + k))
    loaded = executables._counts["loaded"]
    assert _entry_for(4) is None and executables._counts["loaded"] == loaded + 1
    assert a.stat().st_mtime > 1e9 + 2  # loaded: marked as used now
    sizes = [p.stat().st_size for p in (a, b, c)]
    monkeypatch.setitem(executables._state, "max_bytes", sum(sizes) + min(sizes) // 2)
    d = _entry_for(32)
    assert sorted(store.glob("*.jx")) == sorted([a, c, d])


def test_eviction_orders_by_time_and_keeps_the_new_entry(tmp_path):
    """Files of 100 bytes at times 1, 2, 3 (a, b, c): a cap of 250 removes a; a cap of 150
    with a kept removes b and c, oldest first."""
    paths = []
    for k, name in enumerate("abc"):
        p = tmp_path / f"{name}.jx"
        p.write_bytes(b"x" * 100)
        os.utime(p, (k + 1, k + 1))
        paths.append(p)
    assert executables.evict(tmp_path, 250) == [paths[0]]
    paths[0].write_bytes(b"x" * 100)
    os.utime(paths[0], (1, 1))
    assert executables.evict(tmp_path, 150, keep=paths[0]) == [paths[1], paths[2]]
    assert sorted(tmp_path.iterdir()) == [paths[0]]


def test_the_cap_reads_positive_mib_only():
    assert executables.max_bytes({}) == int(executables.MAX_MB * 2**20)
    assert executables.max_bytes({"JSKEL_EXECUTABLES_MAX_MB": "0.5"}) == 2**19
    for bad in ("0", "-3", "lots", "inf", "nan"):
        with pytest.raises(ValueError, match=rf"^JSKEL_EXECUTABLES_MAX_MB: '{bad}' is not a positive number of MiB$"):
            executables.max_bytes({"JSKEL_EXECUTABLES_MAX_MB": bad})


def test_a_program_served_by_jax_cache_is_not_stored(store, monkeypatch):
    """A compile that JAX's persistent cache answered (its hit event counted) is used but not
    stored: XLA:CPU re-serializes such an executable without some of its functions, and a later
    process that loaded it failed ("Function compare_convert_fusion not found")."""
    from jskel.compile import cache

    cache.count_programs()
    monkeypatch.setitem(cache._counts, "loaded", cache._counts["loaded"])  # restored after

    def served():
        cache._counts["loaded"] += 1  # what JAX's cache-hit event records
        return _compile()

    before = executables._counts["from_jax_cache"]
    out = executables.compiled_for(_affine, ARGS, None, served)(*ARGS)
    np.testing.assert_array_equal(out, TRUTH)
    assert list(store.glob("*.jx")) == [] and executables._counts["from_jax_cache"] == before + 1
    assert _get()[1:] == (0, 1) and len(list(store.glob("*.jx"))) == 1  # a compile of its own is stored


def _halves(x):
    return {"half": x[: x.shape[0] // 2] * 2.0, "flags": None}


def test_shapes_are_stored_and_read_back_untraced(store, monkeypatch):
    """``executables.eval_shape``: the first call traces and stores the output's shapes, the
    second reads them back (tracing would raise) and gets the same tree, None leaf included."""
    x = np.zeros(6, np.float32)
    first = executables.eval_shape(_halves, x)
    assert first["half"].shape == (3,) and first["half"].dtype == np.float32 and first["flags"] is None
    assert len(list(store.glob("*.jxs"))) == 1 and list(store.glob("*.jx")) == []

    def no_trace(*a, **k):
        raise AssertionError("traced again")

    monkeypatch.setattr(executables.jax, "eval_shape", no_trace)
    assert executables.eval_shape(_halves, x) == first
