"""The ``object`` section of an implicit experiment (``type: implicit``)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from .. import checks
from ..config import RGB, StrictModel, Vec3

Pos = Annotated[float, Field(gt=0.0)]


class BallConfig(StrictModel):
    """A metaball: centre and effective radius R (Rouiller 2011, Sec. 2.1.1 and 3); ``bone``
    attaches it to a bone (Sec. 5, Fig. 8)."""

    center: Vec3
    """Centre of the ball, model units."""
    radius: Pos
    """Effective radius R: the field reaches zero at this distance."""
    bone: str | None = None
    """Name of the bone it moves with; unset: static."""
    group: str = "main"
    """The primitive group it adds to (a leaf of the ``csg`` tree)."""


class TubeConfig(StrictModel):
    """A metatube: segment a-b with effective radius interpolated from radius_a to radius_b."""

    a: Vec3
    """First end of the segment, model units."""
    b: Vec3
    """Second end of the segment (apart from ``a``)."""
    radius_a: Annotated[float, Field(ge=0.0)]
    """Effective radius at ``a``."""
    radius_b: Annotated[float, Field(ge=0.0)]
    """Effective radius at ``b`` (one of the two is positive)."""
    bone: str | None = None
    """Name of the bone it moves with; unset: static."""
    group: str = "main"
    """The primitive group it adds to (a leaf of the ``csg`` tree)."""

    @model_validator(mode="wrap")
    @classmethod
    def _ends_apart(cls, data, handler):
        return checks.validate_with(data, handler, _tube_problems)


def _point(raw) -> np.ndarray | None:
    """An unvalidated [x, y, z] as (3,) float64, or None where it is not one."""
    a = checks.floats([raw], 3)
    return None if a is None else a[0]


def _both_zero(r, field: str) -> list[str]:
    """A tube of radius 0 at both ends is empty (its effective radius is 0 everywhere)."""
    if r is None or r.shape != (2,) or not np.all(r == 0):
        return []
    return [f"{field}both radii are 0; a tube needs a positive radius at one end at least (got [0, 0])"]


def _tube_problems(d: dict) -> list[str]:
    """A tube whose ends lie within 1e-9 of its larger radius has no axis (Rouiller 2011,
    Sec. 2.1.1's segment distance divides by its length); one of radius 0 at both ends is empty."""
    a, b, r = _point(d.get("a")), _point(d.get("b")), checks.floats([d.get("radius_a"), d.get("radius_b")])
    lines = _both_zero(r, "<root>: ")
    if a is None or b is None:
        return lines
    scale = float(np.max(np.where(np.isfinite(r), np.abs(r), 0.0))) if r is not None and r.ndim == 1 else 0.0
    return lines + checks.same_point("b", a, b, scale, "coincides with a; a tube needs a length")


def _bone_problems(d: dict) -> list[str]:
    """A bone whose tail is its head has no direction to rotate about or to skin along; its
    ``tube`` is a tube (radius > 0 at one end)."""
    a, b = _point(d.get("head")), _point(d.get("tail"))
    lines = _both_zero(checks.floats(d.get("tube")) if d.get("tube") is not None else None, "tube: ")
    return lines + ([] if a is None or b is None else checks.same_point("tail", a, b, 0.0, "equals its head; a bone needs a length"))


def _projector_problems(d: dict) -> list[str]:
    """A projector's axis must be a direction and its up vector must not lie along it (u = 0
    is fixed by up's part perpendicular to the axis, Sec. 6)."""
    lines = []
    ax, up = _point(d.get("axis", (0.0, 1.0, 0.0))), _point(d.get("up", (0.0, 0.0, 1.0)))
    for name, v in (("axis", ax), ("up", up)):
        if v is not None and np.all(v == 0):
            lines.append(f"{name}: is the zero vector (got {checks.value_str(v)})")
    if not lines and ax is not None and up is not None and np.all(np.isfinite(ax)) and np.all(np.isfinite(up)):
        perp = np.linalg.norm(np.cross(ax, up)) / np.linalg.norm(ax)
        if perp <= checks.REL_LENGTH * np.linalg.norm(up):
            lines.append(f"up: is parallel to the axis {checks.value_str(ax)} (got {checks.value_str(up)})")
    return lines


class KeyConfig(StrictModel):
    """A keyframe: XYZ Euler rotation (degrees) of a bone about its head at ``frame``."""

    frame: float
    """The animation frame of this key."""
    rotate: Vec3 = (0.0, 0.0, 0.0)
    """XYZ Euler rotation about the bone's head, degrees (interpolated between keys)."""


class BoneConfig(StrictModel):
    """A bone of the rig (Sec. 5). ``tube: [ra, rb]`` makes the bone a metatube from head to tail
    (the work-flow of Fig. 9). ``influence``: radius of its texture-skinning weight (Sec. 6.1),
    by default 0.75 x its length."""

    name: str
    """The bone's name, referred to by primitives' ``bone`` and other bones' ``parent``."""
    parent: str | None = None
    """The parent bone, whose motion this one inherits; unset: a root."""
    head: Vec3
    """Rest-pose head (the pivot), model units."""
    tail: Vec3
    """Rest-pose tail (apart from the head)."""
    tube: tuple[Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)]] | None = None
    """``[ra, rb]``: the bone is also a metatube from head to tail with these radii."""
    influence: Pos | None = None
    """Radius of its texture-skinning weight (Sec. 6.1); unset: 0.75 x its length."""
    keys: list[KeyConfig] = []
    """Keyframes of its rotation."""
    group: str = "main"
    """The primitive group its tube adds to."""

    @model_validator(mode="wrap")
    @classmethod
    def _has_length(cls, data, handler):
        return checks.validate_with(data, handler, _bone_problems)


class ProjectorConfig(StrictModel):
    """A texture projector applied in the rest pose (Sec. 6, 6.1): planar (u, v along two axes
    perpendicular to ``axis``), cylindrical (angle about ``axis``, height along it) or
    spherical (azimuth and polar angle about ``axis``); ``up`` fixes u = 0."""

    type: Literal["planar", "cylindrical", "spherical"] = "cylindrical"
    """The projection."""
    origin: Vec3 = (0.0, 0.0, 0.0)
    """Centre of the projection, rest-pose model units."""
    axis: Vec3 = (0.0, 1.0, 0.0)
    """The projection's axis (not zero)."""
    up: Vec3 = (0.0, 0.0, 1.0)
    """Fixes u = 0 (its part perpendicular to ``axis``; not parallel to it)."""
    scale: tuple[Pos, Pos] = (1.0, 1.0)
    """Repeats of the texture per unit u and per unit v."""

    @model_validator(mode="wrap")
    @classmethod
    def _directions(cls, data, handler):
        return checks.validate_with(data, handler, _projector_problems)


class RegionConfig(StrictModel):
    """A ball of the rest pose (world units) where a local projector applies."""

    center: Vec3
    """Centre of the region, rest-pose world units."""
    radius: Pos
    """Radius of the region."""


class LocalProjectorConfig(ProjectorConfig):
    """A local projector (Sec. 6.1: "an arbitrary number of projectors with different
    projections"): used at rest-pose points inside ``region``, with its own ``texture``
    (default: the model's)."""

    region: RegionConfig
    """Where this projector applies."""
    texture: str | None = None
    """Its own texture image; unset: the model's ``texture``."""


class CSGNode(StrictModel):
    """A node of the CSG tree over primitive groups (the thesis' future work, after Wyvill's
    BlobTree): ``{group: name}`` is a leaf (the blended sum of that group's primitives); an
    operation has ``op`` sum (blend), max (union), min (intersection) or diff (a minus b) and two
    ``children``."""

    op: Literal["group", "sum", "max", "min", "diff"] = "group"
    """A leaf (``group``) or an operation on two children: blend, union, intersection, difference."""
    group: str | None = None
    """A leaf's primitive group."""
    children: list["CSGNode"] = []
    """An operation's two operands (nodes of this same form)."""

    @model_validator(mode="after")
    def _shape(self):
        if self.op == "group":
            if self.group is None or self.children:
                raise ValueError("a leaf names a 'group' and has no children")
        elif len(self.children) != 2 or self.group is not None:
            raise ValueError(f"operation {self.op!r} needs exactly two children and no 'group'")
        return self


class DisplaceConfig(StrictModel):
    """Displacement (Sec. 6.2): F (1 + amplitude * n(x)), n in [-1, 1] either a 3D value noise
    of ``frequency`` or 2 h(uv) - 1 of a height ``map`` (an image file or brick/gravel/grass/
    checker) through a planar ``projector`` (Fig. 14). The Lipschitz tracer's bound grows to keep
    its guarantee (so only planar projection, whose uv gradient is bounded, is accepted)."""

    type: Literal["noise", "image"] = "noise"
    """3D value noise, or a height map through a planar projector."""
    amplitude: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.2
    """Relative displacement: F is scaled by 1 + amplitude x n(x)."""
    frequency: Pos = 4.0
    """``noise``: noise cells per model unit."""
    map: str | None = None
    """``image``: an image file or brick, gravel, grass or checker."""
    projector: ProjectorConfig | None = None
    """``image``: the planar projector giving the map's uv."""

    @model_validator(mode="after")
    def _image_needs_map(self):
        if self.type == "image":
            if self.map is None or self.projector is None:
                raise ValueError("an image displacement needs a 'map' and a planar 'projector'")
            if self.projector.type != "planar":
                raise ValueError(f"an image displacement needs a planar projector (got {self.projector.type!r}): its uv gradient is bounded")
        return self


class ImplicitConfig(StrictModel):
    """Skeletal implicit surface F = T (Rouiller 2011) and how it is ray traced."""

    type: Literal["implicit"]
    """Selects this representation."""
    threshold: Pos = 0.5
    """The iso-value T of the surface F = T."""
    balls: list[BallConfig] = []
    """Metaballs."""
    tubes: list[TubeConfig] = []
    """Metatubes."""
    procedural: Literal["gecko", "blob_grid", "spider", "dinosaur"] | None = None
    """A generated model instead of explicit primitives."""
    seed: int = 0
    """Random seed of a procedural model."""
    options: dict[str, float] = {}
    """Options of the procedural model."""
    scale: Pos = 1.0
    """Scale of the model about the origin."""
    offset: Vec3 = (0.0, 0.0, 0.0)
    """Translation after ``scale``, world units."""
    method: Literal["naive", "bisection", "lipschitz", "exact"] = "exact"
    """Root search: constant steps (Alg. 1), inside points (Alg. 2), Lipschitz steps (guaranteed), or
    exact (default: the first root of the field's polynomial on each interval between primitives'
    breakpoints, to rounding; with ``csg`` or ``displace``, the Lipschitz march from the first
    point where the sum of kernels can reach the surface, found exactly)."""
    step: Pos = 0.02
    """``naive``: march step, world units."""
    eps: Pos = 1e-3
    """``lipschitz`` (and ``exact`` with ``csg`` or ``displace``): the smallest step; inside
    intervals shorter than this may be missed."""
    steps: Annotated[int, Field(ge=1, le=1 << 20)] = 2048
    """Most march steps per ray (a ray that runs out is flagged)."""
    bisection: Annotated[int, Field(ge=0, le=64)] = 12
    """Bisection iterations refining the bracket."""
    capacity: Annotated[int, Field(ge=1, le=4096)] = 32
    """Candidate primitives kept per ray after culling (more: the ray is flagged as overflowing)."""
    block_size: Annotated[int, Field(ge=0, le=1024)] = 16
    """Primitives per culling block (BVH leaf); 0: flat culling."""
    block_capacity: Annotated[int, Field(ge=1, le=4096)] | None = None
    """Culling blocks kept per ray (more: the ray is retraced with flat culling); unset: 16 for ``tree``,
    32 for ``blocks`` (block spheres are looser than the tree's leaf boxes)."""
    cull: Literal["blocks", "tree", "packets"] = "tree"
    """How a ray finds its blocks: walk the shared BVH (``tree``), find the same leaves for packets
    of 64 rays at once (``packets``, ``accel.collect_packets``; not faster on the CPU's blob
    slabs, docs/choices.md#cull-packets), or test every block sphere (``blocks``)."""
    early_exit: bool = True
    """March in a loop that ends at the bracket, instead of exactly ``steps`` steps."""
    color: RGB = (0.75, 0.45, 0.3)
    """Linear RGB colour where there is no texture."""
    bones: list[BoneConfig] = []
    """The rig (Sec. 5)."""
    frame: float = 0.0
    """Animation frame of the rig's keys."""
    texture: str | None = None
    """An image mapped by the projector(s); unset: plain colour."""
    projector: ProjectorConfig | None = None
    """The global texture projector (Sec. 6)."""
    projectors: list[LocalProjectorConfig] = []
    """Local projectors, each applying inside its region (Sec. 6.1)."""
    csg: CSGNode | None = None
    """A CSG tree over the primitive groups; unset: every primitive blended in one sum."""
    displace: DisplaceConfig | None = None
    """Displacement of the field (Sec. 6.2); unset: none."""

    @model_validator(mode="after")
    def _has_primitives(self):
        if self.procedural is None and not (self.balls or self.tubes or any(b.tube for b in self.bones)):
            raise ValueError("give balls and/or tubes (or tube bones), or a procedural model")
        if self.texture is not None and self.projector is None and not self.projectors:
            raise ValueError("a texture needs a projector (planar, cylindrical or spherical)")
        for i, p in enumerate(self.projectors):
            if p.texture is None and self.texture is None:
                raise ValueError(f"projectors[{i}]: has no texture and the model has none")
        return self
