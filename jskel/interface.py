"""The interface every representation offers (see ``shared/DESIGN.md``).

The renderer, the benchmarks and the sweeps talk only to this interface, so they never branch
on a representation's type inside a kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Protocol

import numpy as np
from pydantic import BaseModel


@dataclass(frozen=True)
class Built:
    """What ``build`` returns: device arrays plus host-side static data.

    params: pytree of arrays (traced: changing values never recompiles).
    static: hashable options that change shapes or control flow (recompile when changed).
    anchor: (3,) float64 world point that positions in ``params`` are relative to; rays must be
      expressed relative to it (``Camera.rays(anchor=...)``).
    bounds: ((3,), (3,)) float64 world-space axis-aligned bounds.
    info: JSON-able facts for ``run.json`` (counts, build diagnostics).
    """

    params: Any
    static: Hashable
    anchor: np.ndarray
    bounds: tuple[np.ndarray, np.ndarray]
    info: dict = field(default_factory=dict)


class Representation(Protocol):
    """name, Config (pydantic model of the ``object`` section) and four pure functions."""

    name: str
    Config: type[BaseModel]

    def build(self, cfg: BaseModel, dtype) -> Built: ...

    #: intersect_one(params, static, origin (3,), direction (3,), t_min (), t_max ()) -> Hit
    intersect_one: Callable

    #: albedo(params, static, hit) -> (3,) linear RGB base colour at one hit
    albedo: Callable

    #: inside(params, static, point (3,)) -> bool
    inside: Callable

    # Optional: intersect_batch(params, static, rays) -> Hit (leading ray axis), equal to
    # vmap(intersect_one) but free to skip work at the batch level (block culling, compaction
    # of (ray, primitive) pairs). The renderer uses it when present.
    #
    # Optional, for scenes (jskel.render._scene):
    # * exits_from_inside(cfg) -> bool: a ray starting inside the surface gets its exit as the
    #   hit (analytic surfaces); only such objects may be transparent in a scene;
    # * own_effects(cfg) -> bool: the object section asks for secondary rays the
    #   representation traces itself (``shade_batch``), which a scene does not use;
    # * Built.info["surface_tolerance"]: how far (object units) a returned hit may lie from the
    #   true surface (a marching tracer's last bracket); secondary rays start beyond it.
