"""Counts of the programs a process hands to XLA, from JAX's monitoring events: every program
handed to XLA records ``/jax/core/compile/backend_compile_duration`` (compiled, or loaded from
the persistent cache) and every load records ``/jax/compilation_cache/cache_hits``; compiled is
their difference. Programs reused from JAX's in-memory caches are neither. (``cache.program_counts``
reports them with the stored executables' counts.)"""

from __future__ import annotations

import jax

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
