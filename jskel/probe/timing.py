"""How every measurement is timed: compile apart, warm-up, the median of warm runs.

The first call compiles (its seconds are reported apart, never mixed into the warm figures),
``warmup - 1`` more calls are untimed, then ``runs`` calls are timed. Each timed call stops its
clock only after its device work is done (``jax.block_until_ready`` inside the render's chunked
evaluation and the cast, or a peer's own synchronous call), so asynchronous dispatch is counted.
The bench, the sweep and the peers' studies all time through :func:`warm_runs` and report
:func:`spread` (diffrax ``benchmarks/``: warm-up, median, device and versions recorded).
"""

from __future__ import annotations

import statistics
from typing import Any, Callable, NamedTuple

from ..render import render


class Spread(NamedTuple):
    """Median, minimum and maximum of warm seconds."""

    median: float
    min: float
    max: float


class WarmRuns(NamedTuple):
    """The first (compiling) call's result and the ``runs`` timed calls' results."""

    first: Any
    warm: list


def warm_runs(call: Callable[[], Any], runs: int, warmup: int) -> WarmRuns:
    """``call()`` once (it compiles), ``warmup - 1`` more times untimed (at least the first call
    is always a warm-up), then ``runs`` times; each call measures its own seconds."""
    first = call()
    for _ in range(max(warmup - 1, 0)):
        call()
    return WarmRuns(first, [call() for _ in range(runs)])


def spread(seconds: list[float]) -> Spread:
    """The median, minimum and maximum of warm seconds (no rounding)."""
    return Spread(float(statistics.median(seconds)), float(min(seconds)), float(max(seconds)))


def median_of(seconds, digits: int = 5) -> float:
    """The median of ``seconds`` rounded to ``digits`` (the peers' rows)."""
    return round(float(statistics.median(seconds)), digits)


def render_runs(exp, runs: int, warmup: int) -> WarmRuns:
    """Renders of one experiment (each with ``progress`` off): the first result (its ``run``
    holds compile and build seconds) and the ``runs`` warm results' ``run`` dicts."""
    out = warm_runs(lambda: render(exp, progress=False), runs, warmup)
    return WarmRuns(out.first, [r.run for r in out.warm])
