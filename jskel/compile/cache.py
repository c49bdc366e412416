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

Counting (:func:`program_counts`; the listeners are ``events``, the directory rules ``policy``) listens to JAX's monitoring events: every program handed to
XLA records ``/jax/core/compile/backend_compile_duration`` (compiled, or loaded from the
persistent cache) and every load records ``/jax/compilation_cache/cache_hits``; compiled is
their difference. Programs reused from JAX's in-memory caches are neither.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

from . import executables  # the executor's own programs, stored whole (no tracing when warm)
from .events import _by_name, _counts, count_programs
from .policy import _warn, data_dir, default_cache_dir, prepared_dir, unsafe_reason

# Every program is written to the cache, however quickly it compiled (JAX's default is 1 s).
# A render also compiles many small programs (the build's jitted pieces, framing, the hits'
# post-processing): each takes tens of milliseconds to compile but adds up to seconds in a
# fresh process, while loading one from disk takes about a millisecond.
MIN_COMPILE_S = 0.0


def program_counts() -> dict:
    """Programs handed to XLA in this process since counting started: ``compiled`` (by XLA)
    and ``loaded`` (from the persistent cache), ``by_name`` (each program name, e.g.
    ``jit(frusta_fields)``: how many were handed to XLA, compiled or loaded, and their seconds),
    the cache directory JAX uses (or None), and the executor's ``executables``
    (``jskel.compile.executables.counts``: loaded from disk, neither traced nor handed to XLA, or
    compiled and stored)."""
    return {"compiled": _counts["requests"] - _counts["loaded"], "loaded": _counts["loaded"],
            "by_name": {k: [n, round(s, 4)] for k, (n, s) in sorted(_by_name.items())},
            "cache_dir": jax.config.jax_compilation_cache_dir, "executables": executables.counts()}


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
    executables.use_dir(None if executables.switched_off() else path / "executables")
    return path


__all__ = ["MIN_COMPILE_S", "_by_name", "_counts", "_warn", "count_programs", "data_dir", "default_cache_dir", "prepared_dir",
           "program_counts", "unsafe_reason", "use_compilation_cache"]
