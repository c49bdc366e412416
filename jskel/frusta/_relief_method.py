"""The relief test a segment is cast with, chosen by ``object.relief.method``: the sampled
march and bisection of Bhagvat et al. 2009, Sec. 3 (``_relief``), or the exact walk over the
height map's texels (``_relief_exact``). It sits above both, so that neither imports the other
back (the exact walk reuses the sampled method's shell window and texel lookups)."""

from __future__ import annotations

import functools

from ._relief import ReliefMaps, ReliefQuality, _relief_t, relief_root
from ._relief_exact import relief_root as exact_root
from ._relief_exact import relief_t


def make_relief_t(maps: ReliefMaps, q: ReliefQuality):
    """Per-segment relief test ``(seg, o, d, t_min, t_max) -> (t, s, code, t_undecided)`` for
    nearest_* (``undecided=True``): t_undecided is the ray's t at the start of the first march
    step that could not exclude a crossing (``_relief._step_undecided``; inf where none; the
    exact walk's first undecided interval)."""
    return functools.partial(relief_t if q.method == "exact" else _relief_t, maps, q)


def make_relief_root(maps: ReliefMaps, q: ReliefQuality):
    """``(seg, o, d, t_min, t_max, s_root) -> (t, s)``: the crossing :func:`make_relief_t`'s test
    found at ``s_root``, with that test's derivatives (the implicit-function theorem's at the
    root) and no march or walk: what a traversal's derivative needs of its winner."""
    return functools.partial(exact_root if q.method == "exact" else relief_root, maps, q)
