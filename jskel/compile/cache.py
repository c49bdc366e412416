"""JAX's persistent compilation cache for jskel: where it lives, when it is refused, and how
many programs a process compiled or loaded from it. An explicit call, never an import side
effect.

The CLI calls :func:`use_compilation_cache` first thing (with :func:`jskel.use_host_devices`);
in Python, call it right after ``import jskel``, before any JAX operation (JAX reads the cache
directory when it compiles its first program)::

    import jskel
    jskel.use_compilation_cache()   # ~/.cache/jskel/jax, or JSKEL_CACHE_DIR; JSKEL_CACHE=off: none

The directory is ``$JSKEL_CACHE_DIR``, else ``$XDG_CACHE_HOME/jskel/jax``, else
``~/.cache/jskel/jax``, created with mode 0700. Cache entries are executables the process
loads, so a directory that another user owns, or that group or others may write, is refused
with one warning line (naming the directory and the fix) and the process runs without a cache.
An explicitly set ``JAX_COMPILATION_CACHE_DIR`` wins: JAX's own configuration is then left as
it is.

Counting (:func:`program_counts`) listens to JAX's monitoring events: every program handed to
XLA records ``/jax/core/compile/backend_compile_duration`` (compiled, or loaded from the
persistent cache) and every load records ``/jax/compilation_cache/cache_hits``; compiled is
their difference. Programs reused from JAX's in-memory caches are neither.
"""

from __future__ import annotations

import os
import stat
import sys
from pathlib import Path

import jax

# Every program is written to the cache, however quickly it compiled (JAX's default is 1 s).
# A render also compiles many small programs (the build's jitted pieces, framing, the hits'
# post-processing): each takes tens of milliseconds to compile but adds up to seconds in a
# fresh process, while loading one from disk takes about a millisecond.
MIN_COMPILE_S = 0.0

_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_HIT_EVENT = "/jax/compilation_cache/cache_hits"
_counts = {"requests": 0, "loaded": 0}
_by_name: dict = {}  # program name -> [programs handed to XLA, their seconds]
_listening = False


def _on_event(event: str, **kwargs) -> None:
    if event == _HIT_EVENT:
        _counts["loaded"] += 1


def _on_duration(event: str, duration: float, **kwargs) -> None:
    if event == _COMPILE_EVENT:
        _counts["requests"] += 1
        got = _by_name.setdefault(str(kwargs.get("fun_name", "?")), [0, 0.0])
        got[0] += 1
        got[1] += duration


def count_programs() -> None:
    """Start counting programs compiled and loaded in this process (idempotent; the CLI and
    :func:`use_compilation_cache` call it; a render calls it too, counting from then on)."""
    global _listening
    if not _listening:
        jax.monitoring.register_event_listener(_on_event)
        jax.monitoring.register_event_duration_secs_listener(_on_duration)
        _listening = True


def program_counts() -> dict:
    """Programs handed to XLA in this process since counting started: ``compiled`` (by XLA)
    and ``loaded`` (from the persistent cache), ``by_name`` (each program name, e.g.
    ``jit(frusta_fields)``: how many were handed to XLA, compiled or loaded, and their seconds),
    the cache directory JAX uses (or None), and the executor's ``executables``
    (``jskel.compile.executables.counts``: loaded from disk, neither traced nor handed to XLA, or
    compiled and stored)."""
    from . import executables

    return {"compiled": _counts["requests"] - _counts["loaded"], "loaded": _counts["loaded"],
            "by_name": {k: [n, round(s, 4)] for k, (n, s) in sorted(_by_name.items())},
            "cache_dir": jax.config.jax_compilation_cache_dir, "executables": executables.counts()}


def default_cache_dir(env=None) -> Path | None:
    """The cache directory the environment asks for: None with ``JSKEL_CACHE=off``, else
    ``JSKEL_CACHE_DIR``, ``$XDG_CACHE_HOME/jskel/jax`` or ``~/.cache/jskel/jax``. A value of
    ``JSKEL_CACHE`` other than on/off is a ``ValueError``."""
    env = os.environ if env is None else env
    switch = env.get("JSKEL_CACHE", "on").strip().lower()
    if switch not in ("on", "off", "1", "0", "true", "false", ""):
        raise ValueError(f"JSKEL_CACHE: {env['JSKEL_CACHE']!r} is not on or off")
    if switch in ("off", "0", "false"):
        return None
    if env.get("JSKEL_CACHE_DIR"):
        return Path(env["JSKEL_CACHE_DIR"]).expanduser()
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jskel" / "jax"


def data_dir(name: str, env=None) -> Path | None:
    """The folder ``name`` of jskel's cache directory (:func:`default_cache_dir`), where
    precomputed data are kept beside the compiled programs: ``~/.cache/jskel/jax/<name>``, or
    under ``JSKEL_CACHE_DIR``; None with ``JSKEL_CACHE=off``. Not created here."""
    root = default_cache_dir(env)
    return None if root is None else root / name


def unsafe_reason(path: Path) -> str | None:
    """Why ``path`` (an existing directory) must not hold executables this process loads: not
    a directory, owned by another user, or writable by group or others; None when it is safe."""
    st = path.stat()
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if os.name == "posix" and st.st_uid != os.getuid():
        return f"is owned by uid {st.st_uid}, not this user"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"is writable by group or others (mode {stat.S_IMODE(st.st_mode):o}; fix: chmod 700 {path})"
    return None


def _warn(line: str) -> None:
    print(f"jskel: warning: {line}", file=sys.stderr)


def prepared_dir(path: Path, what: str = "compilation cache") -> Path | None:
    """``path`` created with mode 0700 (its parents as the umask makes them), or None with one
    warning line (naming it as ``what``) when it cannot be made or is unsafe
    (:func:`unsafe_reason`); never raises. Every folder of jskel's cache directory goes through it."""
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        why = unsafe_reason(path)
    except OSError as e:
        _warn(f"{what} {path} cannot be used ({e.strerror or e}); running without it")
        return None
    if why is not None:
        _warn(f"{what} {path} {why}; running without it")
        return None
    return path


def use_compilation_cache(path=None) -> Path | None:
    """Switch JAX's persistent compilation cache on in ``path`` (default:
    :func:`default_cache_dir`), writing every program (:data:`MIN_COMPILE_S`), and start
    counting programs. Returns the directory in use, or None (switched off or refused).
    ``JAX_COMPILATION_CACHE_DIR``, when set, wins and JAX's configuration is left alone. Call
    it before any JAX operation: JAX fixes its cache when it compiles its first program."""
    count_programs()
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    path = default_cache_dir() if path is None else Path(path)
    if path is None:
        return None
    path = prepared_dir(path)
    if path is None:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    from . import executables  # the executor's own programs, stored whole (no tracing when warm)

    executables.use_dir(None if executables.switched_off() else path / "executables")
    return path
