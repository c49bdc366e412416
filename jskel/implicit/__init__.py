"""Skeletal implicit surfaces, Rouiller 2011 (seeds 002 and 003): metaballs and metatubes.

Public API: :func:`build` (host: validate, pose, Morton-sort, pad, cast), :func:`intersect_one`
(pure, one ray) with the tracers of ``_trace`` selected by ``object.method``,
:func:`intersect_batch` (the same over a batch, retracing culling overflows with flat culling,
compacted), bones (``_anim``), texture projectors with rest-pose skinning, displacement and CSG
(``_field``); ``REPRESENTATION`` for the registry."""

from ._field import Displace as Displace
from ._config import ImplicitConfig as ImplicitConfig
from ._scene import ImplicitScene as ImplicitScene
from ._trace import OVERFLOW as OVERFLOW
from ._field import Prims as Prims
from ._projectors import Projector as Projector
from ._trace import Quality as Quality
from ._scene import REPRESENTATION as REPRESENTATION
from ._trace import STEP_CAP as STEP_CAP
from ._field import Shape as Shape
from ._projectors import Skin as Skin
from ._scene import Static as Static
from ._trace import Tuning as Tuning
from ._scene import albedo as albedo
from ._scene import build as build
from ._primitives import csg_shape as csg_shape
from ._projectors import displace_params as displace_params
from ._primitives import expand as expand
from ._field import field as field
from ._field import gradient as gradient
from ._scene import inside as inside
from ._scene import intersect_batch as intersect_batch
from ._scene import intersect_one as intersect_one
from ._field import lipschitz as lipschitz
from ._primitives import primitives as primitives
from ._projectors import project as project
from ._projectors import rest_position as rest_position
from ._field import shaped_field as shaped_field

__all__ = ["Displace", "ImplicitConfig", "ImplicitScene", "OVERFLOW", "Prims", "Projector", "Quality", "REPRESENTATION", "STEP_CAP", "Shape", "Skin", "Static", "Tuning", "albedo", "build", "csg_shape", "displace_params", "expand", "field", "gradient", "inside", "intersect_batch", "intersect_one", "lipschitz", "primitives", "project", "rest_position", "shaped_field"]
