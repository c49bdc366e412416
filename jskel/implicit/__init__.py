"""Skeletal implicit surfaces, Rouiller 2011 (seeds 002 and 003): metaballs and metatubes.

Public API: :func:`build` (host: validate, pose, Morton-sort, pad, cast), :func:`intersect_one`
(pure, one ray) with the tracers of ``_trace`` selected by ``object.method``,
:func:`intersect_batch` (the same over a batch, retracing culling overflows with flat culling,
compacted), bones (``_anim``), texture projectors with rest-pose skinning, displacement and CSG
(``_field``); ``REPRESENTATION`` for the registry."""

from ._scene import Displace as Displace
from ._scene import ImplicitConfig as ImplicitConfig
from ._scene import ImplicitScene as ImplicitScene
from ._scene import OVERFLOW as OVERFLOW
from ._scene import Prims as Prims
from ._scene import Projector as Projector
from ._scene import Quality as Quality
from ._scene import REPRESENTATION as REPRESENTATION
from ._scene import STEP_CAP as STEP_CAP
from ._scene import Shape as Shape
from ._scene import Skin as Skin
from ._scene import Static as Static
from ._scene import Tuning as Tuning
from ._scene import albedo as albedo
from ._scene import build as build
from ._scene import csg_shape as csg_shape
from ._scene import displace_params as displace_params
from ._scene import expand as expand
from ._scene import field as field
from ._scene import gradient as gradient
from ._scene import inside as inside
from ._scene import intersect_batch as intersect_batch
from ._scene import intersect_one as intersect_one
from ._scene import lipschitz as lipschitz
from ._scene import primitives as primitives
from ._scene import project as project
from ._scene import rest_position as rest_position
from ._scene import shaped_field as shaped_field

__all__ = ["Displace", "ImplicitConfig", "ImplicitScene", "OVERFLOW", "Prims", "Projector", "Quality", "REPRESENTATION", "STEP_CAP", "Shape", "Skin", "Static", "Tuning", "albedo", "build", "csg_shape", "displace_params", "expand", "field", "gradient", "inside", "intersect_batch", "intersect_one", "lipschitz", "primitives", "project", "rest_position", "shaped_field"]
