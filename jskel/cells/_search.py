"""A cell object's first hit: the search its config chooses (``search``: Alg. 3.1's linear and
binary search, ``_trace.march``, or the exact voxel walk, ``_voxels.walk``), from the ray's entry
into the object's box."""

from __future__ import annotations

import jax.numpy as jnp

from ._trace import CellParams, March, TraceOptions, march, object_interval, starts_inside
from ._voxels import walk


def first_hit(p: CellParams, o, d, t_min, t_max, opt: TraceOptions, two_sided: bool = False) -> March:
    """Alg. 3.1 from the ray's entry into the object's box (``_trace``'s module docstring), or
    with ``opt.voxels`` the exact walk through the tile map's voxels (``_voxels``): the first
    entry into an INSIDE cell. ``two_sided`` (the refraction mode): a ray that starts in
    an inside cell (:func:`starts_inside`) searches for its exit instead (Alg. 3.3 rows 3-17);
    then ``t`` is the first sample outside and ``t_out`` the last one inside."""
    t0, t1 = object_interval(p, o, d, t_min, t_max)
    want = ~starts_inside(p, o, d, t_min) if two_sided else True
    cut = t_max < object_interval(p, o, d, t_min, jnp.inf)[1]  # t_max ends the window inside the box
    m = walk(p, o, d, t0, t1, want, opt.skip, opt.pyramid) if opt.voxels else march(p, o, d, t0, t1, want, opt, cut)
    inf = jnp.asarray(jnp.inf, o.dtype)
    live = t0 <= t1
    return m._replace(t=jnp.where(live, m.t, inf), found=m.found & live, floored=m.floored & live, stepped=m.stepped & live)
