"""Compiled executables kept on disk, so a warm process neither traces nor compiles them.

JAX's persistent compilation cache (``jskel.compile.cache``) skips XLA's compile but not tracing: a
fresh process still traces the render's one big program (the chunk map over the bins traversal)
before it can look the compiled program up. Here the executor (``executor.compile_batch_fn``)
looks for the executable itself first: on a miss of its in-process cache it loads a file keyed
by a hash of everything the program depends on (:func:`entry_key`: jskel's own source files,
the JAX and jaxlib versions, the backend, device kind and count, the batch function's qualified
name, the arguments' tree structure with its static aux data, their shapes and dtypes, x64,
``XLA_FLAGS`` and the CPU's vector ISA, ``isa.cpu_isa``) and deserializes it (``jax.experimental.serialize_executable``); only without one
does it trace and compile, then stores the result.

Entries are pickles, that is code, so they are loaded only from a directory this user owns and
no one else may write (one warning line otherwise, and everything compiles as usual), and only
from files this user owns; each file carries the SHA-256 of its body, so a truncated or
corrupt entry is found before anything is unpickled, compiled again and replaced (one warning
line). Files are written to a temporary name and renamed, so a reader never sees half a file.

:func:`jskel.use_compilation_cache` (the CLI's first call) turns this on in the ``executables``
folder of jskel's cache directory (``~/.cache/jskel/jax/executables``, or under
``JSKEL_CACHE_DIR``); ``JSKEL_EXECUTABLES=off`` leaves only JAX's cache on, ``JSKEL_CACHE=off``
turns both off, and with ``JAX_COMPILATION_CACHE_DIR`` set no executables are stored.

The folder is capped at ``JSKEL_EXECUTABLES_MAX_MB`` MiB (default :data:`MAX_MB`): after a
store, the least recently used entries (by modification time, which a load renews) are
removed until the rest fit; the entry just stored is kept even when it alone is larger.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pickle
import stat
import sys
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Callable

import jax
import jaxlib
import numpy as np

from . import events
from .isa import cpu_isa
from .policy import _warn, unsafe_reason

MAGIC = b"jskel-executable-2 "
MAX_MB = 2048.0  # the folder's default cap in MiB (``JSKEL_EXECUTABLES_MAX_MB``)
_state: dict = {"dir": None, "max_bytes": int(MAX_MB * 2**20)}
_counts = {"loaded": 0, "compiled": 0, "stored": 0, "unstorable": 0, "from_jax_cache": 0}


def switched_off(env=None) -> bool:
    """Whether ``JSKEL_EXECUTABLES`` asks for no stored executables (off/0/false); another
    value than on/off is a ``ValueError``."""
    env = os.environ if env is None else env
    v = env.get("JSKEL_EXECUTABLES", "on").strip().lower()
    if v not in ("on", "off", "1", "0", "true", "false", ""):
        raise ValueError(f"JSKEL_EXECUTABLES: {env['JSKEL_EXECUTABLES']!r} is not on or off")
    return v in ("off", "0", "false")


def max_bytes(env=None) -> int:
    """The folder's cap in bytes from ``JSKEL_EXECUTABLES_MAX_MB`` (MiB, default
    :data:`MAX_MB`); anything but a positive number is a ``ValueError`` naming it."""
    env = os.environ if env is None else env
    raw = env.get("JSKEL_EXECUTABLES_MAX_MB", "").strip()
    if not raw:
        return int(MAX_MB * 2**20)
    try:
        mb = float(raw)
    except ValueError:
        mb = float("nan")
    if not mb > 0 or mb == float("inf"):
        raise ValueError(f"JSKEL_EXECUTABLES_MAX_MB: {raw!r} is not a positive number of MiB")
    return int(mb * 2**20)


def evict(folder: Path, limit: int, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used entries of ``folder`` (``.jx`` executables, ``.jxs``
    shapes and ``.jxv`` host values, oldest modification time first) until they take at most ``limit`` bytes; ``keep``
    is never removed. Returns the entries removed (one another process removed first is
    skipped)."""
    entries = []
    for p in (q for q in folder.iterdir() if q.suffix in (".jx", ".jxs", ".jxv")):  # executables, shapes, values
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        entries.append((st.st_mtime_ns, p.name, st.st_size, p))
    total = sum(e[2] for e in entries)
    removed = []
    for _, _, size, p in sorted(entries):
        if total <= limit:
            break
        if keep is not None and p == keep:
            continue
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        total -= size
        removed.append(p)
    return removed


def _touch(path: Path) -> None:
    """Mark ``path`` as used now (its modification time: what :func:`evict` orders by)."""
    try:
        os.utime(path)
    except OSError:
        pass


def use_dir(path) -> Path | None:
    """Load and store executables in ``path`` (created with mode 0700), or none for None.
    A directory that cannot be made, is another user's or that group or others may write is
    refused with one warning line; returns the directory in use or None."""
    _state["dir"] = None
    if path is None:
        return None
    _state["max_bytes"] = max_bytes()
    path = Path(path)
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        why = unsafe_reason(path)
    except OSError as e:
        why = f"cannot be used ({e.strerror or e})"
    if why is not None:
        _warn(f"stored executables {path} {why}; compiling instead of loading")
        return None
    _state["dir"] = path
    return path


def counts() -> dict:
    """This process's executables: ``loaded`` from disk, ``compiled`` (traced and compiled by
    the executor), ``stored``, ``unstorable`` (XLA cannot serialize them), ``from_jax_cache``
    (loaded from JAX's persistent cache while compiling: not stored), and the directory."""
    d = _state["dir"]
    return dict(_counts, dir=None if d is None else str(d))


@lru_cache(maxsize=1)
def source_hash() -> str:
    """SHA-256 of jskel's own Python files (paths and contents): any edit changes every key."""
    root = Path(__file__).resolve().parent.parent  # the package, not this folder
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def fn_name(fn) -> str | None:
    """A name for ``fn`` that is the same in every process: module and qualified name for a
    module-level function; a frozen dataclass of such functions and plain values (the
    executor's ``Grouped(fn, group)``) by its type and fields; None for a closure, a lambda or
    anything else (such programs are not stored)."""
    if dataclasses.is_dataclass(fn) and not isinstance(fn, type):
        parts = [fn_name(v) if callable(v) else repr(v) for v in (getattr(fn, f.name) for f in dataclasses.fields(fn))]
        if any(x is None for x in parts):
            return None
        return f"{type(fn).__module__}.{type(fn).__qualname__}({', '.join(parts)})"
    qual, mod = getattr(fn, "__qualname__", None), getattr(fn, "__module__", None)
    if not isinstance(qual, str) or not isinstance(mod, str) or "<" in qual:
        return None
    return f"{mod}.{qual}"


def entry_key(fn, args, mesh=None) -> str | None:
    """The hex key of ``fn`` compiled for ``args`` (and ``mesh``): None when a part of it has
    no stable text (a closure, or aux data whose repr is an object's address)."""
    name = fn_name(fn)
    leaves, tree = jax.tree_util.tree_flatten(args)
    tree_text = str(tree)
    if name is None or " at 0x" in tree_text or " at 0x" in name:
        return None
    dev = jax.devices()
    parts = (
        source_hash(), jax.__version__, jaxlib.__version__, sys.version_info[:2],
        dev[0].platform, dev[0].device_kind, len(dev),
        None if mesh is None else tuple(d.id for d in mesh.devices.flat),
        name, tree_text, tuple((tuple(np.shape(x)), str(jax.numpy.result_type(x))) for x in leaves),
        bool(jax.config.jax_enable_x64), str(jax.config.jax_default_matmul_precision), os.environ.get("XLA_FLAGS", ""),
        cpu_isa(),  # a cache directory shared by machines: AVX-512 code is never loaded where the CPU lacks it
    )
    return hashlib.sha256(repr(parts).encode()).hexdigest()


def _read(path: Path) -> bytes | None:
    """The body of the entry at ``path`` (None when absent); ValueError when it is not this
    user's, is writable by others, or its digest does not match (truncated or corrupt)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if (os.name == "posix" and st.st_uid != os.getuid()) or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
            raise ValueError("is not this user's own private file")
        data = f.read()
    head, _, body = data.partition(b"\n")
    if not head.startswith(MAGIC) or head[len(MAGIC):] != hashlib.sha256(body).hexdigest().encode():
        raise ValueError("is truncated or corrupt")
    return body


def _load(path: Path, key: str, args, mesh):
    """The executable stored at ``path``, or None (absent, or unusable: one warning line)."""
    from jax.experimental.serialize_executable import deserialize_and_load

    try:
        body = _read(path)
        if body is None:
            return None
        stored_key, payload, out_tree, ids = pickle.loads(body)
        if stored_key != key:
            raise ValueError("holds another program")
        by_id = {d.id: d for d in jax.devices()}
        if not all(i in by_id for i in ids):
            raise ValueError(f"was compiled for devices {ids}, not all of this process's")
        in_tree = jax.tree_util.tree_structure((tuple(args), {}))
        return deserialize_and_load(payload, in_tree, out_tree, execution_devices=[by_id[i] for i in ids])
    except Exception as e:  # noqa: BLE001 - whatever is wrong with an entry, compile instead
        _warn(f"stored executable {path} {e if isinstance(e, ValueError) else type(e).__name__}; compiling it again")
        return None


def _devices(compiled, mesh) -> list[int] | None:
    """Ids of the devices ``compiled`` runs on, in order: the mesh's, or the one device of an
    unsharded program (None when its arguments' shardings name several)."""
    if mesh is not None:
        return [d.id for d in mesh.devices.flat]
    devs = set()
    for sh in jax.tree_util.tree_leaves(compiled.input_shardings):
        devs |= set(sh.device_set)
    return [devs.pop().id] if len(devs) == 1 else None


def _store(path: Path, key: str, compiled, mesh) -> None:
    """Write ``compiled`` to ``path`` atomically (a temporary file in the folder, renamed);
    one XLA cannot serialize is counted as unstorable and not written."""
    from jax.experimental.serialize_executable import serialize

    try:
        ids = _devices(compiled, mesh)
        if ids is None:
            raise ValueError("devices unknown")
        payload, _, out_tree = serialize(compiled)
        body = pickle.dumps((key, payload, out_tree, ids), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001 - e.g. an XLA:CPU thunk without serialization
        _counts["unstorable"] += 1
        return
    if _write(path, body):
        _counts["stored"] += 1


def _write(path: Path, body: bytes) -> bool:
    """Write an entry's ``body`` (after its digest line) to ``path`` atomically (a temporary file
    in the folder, renamed), then keep the folder under its cap (:func:`evict`); False (one
    warning line) when it cannot be written."""
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC + hashlib.sha256(body).hexdigest().encode() + b"\n" + body)
        os.replace(tmp, path)
    except OSError as e:
        _warn(f"stored executables {path.parent}: cannot write ({e.strerror or e})")
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        return False
    try:
        evict(path.parent, _state["max_bytes"], keep=path)
    except OSError as e:
        _warn(f"stored executables {path.parent}: cannot remove old entries ({e.strerror or e})")
    return True


def _memo(tag: str, key: str | None, compute: Callable):
    """``compute()``, kept in the directory in use under ``key`` (with the executables' safety,
    digest and cap): a later call with the same key reads it back instead of computing it."""
    d = _state["dir"]
    if d is None or key is None:
        return compute()
    key = hashlib.sha256(f"{tag} {key}".encode()).hexdigest()
    path = d / f"{key}.jx{tag[0]}"
    try:
        body = _read(path)
        if body is not None:
            stored_key, out = pickle.loads(body)
            if stored_key != key:
                raise ValueError("holds another entry")
            _touch(path)
            return out
    except Exception as e:  # noqa: BLE001 - whatever is wrong with an entry, compute instead
        _warn(f"stored {tag} {path} {e if isinstance(e, ValueError) else type(e).__name__}; computing it again")
    out = compute()
    _write(path, pickle.dumps((key, out), protocol=pickle.HIGHEST_PROTOCOL))
    return out


def eval_shape(fn, *args):
    """``jax.eval_shape(fn, *args)`` kept beside the executables (same key, safety and cap): a
    warm process reads the output's shapes and dtypes instead of tracing ``fn`` (a render asks
    whether a representation's hits carry flags this way)."""
    key = None if _state["dir"] is None else entry_key(fn, args)
    return _memo("shapes", key, lambda: jax.eval_shape(fn, *args))


def stored_value(fn, args, compute: Callable):
    """``compute()``, the value of ``fn`` on ``args`` (host arrays), kept beside the executables
    and keyed as they are plus a digest of every argument's bytes: a warm process that builds the
    same object reads the build's host results (the frusta's geometry and BVH) back instead of
    evaluating them. NumPy arrays in, NumPy arrays out."""
    key = None if _state["dir"] is None else entry_key(fn, args)
    if key is not None:
        h = hashlib.sha256(key.encode())
        for x in jax.tree_util.tree_leaves(args):
            a = np.ascontiguousarray(x)
            h.update(f"{a.dtype.str}{a.shape}".encode() + a.tobytes())
        key = h.hexdigest()
    return _memo("values", key, compute)


def compiled_for(fn, args, mesh, compile_: Callable):
    """``fn``'s executable for ``args``: loaded from the directory in use when an entry for
    its key is there, else ``compile_()`` (trace and compile), stored for the next process."""
    d = _state["dir"]
    key = None if d is None else entry_key(fn, args, mesh)
    path = None if key is None else d / f"{key}.jx"
    if path is not None:
        got = _load(path, key, args, mesh)
        if got is not None:
            _counts["loaded"] += 1
            _touch(path)
            return got
    events.count_programs()  # JAX's cache hits are counted from here on
    hits = events._counts["loaded"]
    compiled = compile_()
    _counts["compiled"] += 1
    if path is not None and events._counts["loaded"] > hits:
        # served by JAX's persistent cache (jskel's source changed, the program did not): XLA:CPU
        # serializes such a deserialized executable without some of its functions (a later
        # process failed with "Function compare_convert_fusion not found"), so it is not stored
        _counts["from_jax_cache"] += 1
        return compiled
    if path is not None:
        # before its first run: once run, XLA:CPU's sort thunks hold a function pointer to their
        # comparator and the executable no longer serializes (`LessThan` is not serializable)
        _store(path, key, compiled, mesh)
    return compiled
