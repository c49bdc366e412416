"""The ``object`` section of a frusta experiment (``type: frusta``)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from .. import checks
from ..config import RGB, StrictModel, Vec3
from ..skeletons import RepairPolicy
from ._skeleton import topology_problems

Radius = Annotated[float, Field(ge=0.0)]


class SkeletonConfig(StrictModel):
    """One of explicit ``joints``/``radii``/``parents``, a ``procedural`` generator or a ``file``.

    ``file``: a skeleton file (a path, relative to the working directory) in ``format`` ``swc``
    (NeuroMorpho.Org, neuron tools), ``nodes`` (a CSV node table with id, x, y, z, radius and
    parent columns, as CATMAID and navis export), ``qsm`` (a TreeQSM cylinder table, labels the
    branch order) or ``auto`` (by extension: .swc, .csv, TreeQSM's cylinder*.txt); see
    ``jskel.skeletons``. A file is repaired by ``repair`` (a ``jskel.skeletons.RepairPolicy``;
    unset: its defaults, i.e. an unknown radius (<= 0, NaN) becomes its nearest ancestor's and
    nodes that coincide with their parent are merged), and the build's ``info["repairs"]`` (in
    ``run.json``) holds the policy and, per repair kind, the count and first node ids. Problems
    no policy repairs (duplicate ids, missing parents, cycles, non-finite coordinates, and
    unknown radii under ``unknown_radius: error``) are one error listing all. Where the file has
    SWC types (any nonzero) and no ``colors`` are given, segments take their end node's type
    colour (``jskel.skeletons.TYPE_COLORS``: soma red, axon blue, basal dendrite green, apical
    dendrite magenta, undefined grey, custom orange). Explicit joints keep their strict checks:
    ``repair`` applies to files only.

    ``offset`` translates and ``scale`` scales the whole skeleton (world units): coordinates and
    radii are multiplied by ``scale`` (e.g. 0.001 for a file in nanometres rendered in micrometres)
    and then ``offset`` is added.
    ``options`` are generator-specific (see ``jskel.scenes``); unknown options are errors.
    ``subdivide`` splits every segment into that many collinear pieces (radii interpolated): the
    same surface from more segments, for studies of cost against segment count.
    ``replicate: k`` lays k x k copies, each scaled by 1/k, side by side over the original's
    x-y extent (a wall facing +z): k^2 times the segments, about the same screen coverage and
    depth complexity for a camera on the z axis (issue 6's cost-against-log(segments) study).
    """

    procedural: Literal["saguaro", "aloe", "well", "lsystem_tree", "palm", "pine", "oasis", "dancing_cacti"] | None = None
    """A generated skeleton (``jskel.scenes``); not with ``file`` or explicit joints."""
    seed: int = 0
    """Random seed of a procedural generator."""
    options: dict[str, float] = {}
    """Generator-specific options of ``procedural`` (unknown options are errors)."""
    joints: list[Vec3] | None = None
    """Explicit joint positions (with ``radii`` and ``parents``)."""
    radii: list[Radius] | None = None
    """Explicit radius at each joint."""
    parents: list[int] | None = None
    """Explicit parent index of each joint (-1: a root)."""
    colors: list[RGB] | None = None
    """Linear RGB colour per joint (a segment takes its end joint's); unset: the object's ``color``."""
    file: str | None = None
    """A skeleton file (SWC, CSV node table, TreeQSM cylinder table), relative to the working directory."""
    format: Literal["auto", "swc", "nodes", "qsm"] = "auto"
    """The file's format; ``auto``: by extension (.swc, .csv, TreeQSM's cylinder*.txt)."""
    repair: RepairPolicy | None = None
    """How a file's problems are repaired (files only); unset: the policy's defaults."""
    scale: Annotated[float, Field(gt=0.0)] = 1.0
    """Coordinates and radii are multiplied by this (e.g. 0.001 for nanometres to micrometres)."""
    offset: Vec3 = (0.0, 0.0, 0.0)
    """Translation added after ``scale``, world units."""
    subdivide: Annotated[int, Field(ge=1, le=4096)] = 1
    """Split every segment into this many collinear pieces (the same surface from more segments)."""
    replicate: Annotated[int, Field(ge=1, le=1024)] = 1
    """Lay k x k copies side by side in x-y, each scaled 1/k (k^2 times the segments)."""

    @model_validator(mode="after")
    def _one_source(self):
        explicit = [self.joints is not None, self.radii is not None, self.parents is not None]
        if self.file is not None:
            if self.procedural is not None or any(explicit):
                raise ValueError("give one of 'file', 'procedural' or joints/radii/parents")
            return self
        if self.repair is not None:
            raise ValueError("'repair' applies to a skeleton 'file' only (explicit joints are checked strictly)")
        if self.procedural is None and not all(explicit):
            missing = [n for n, e in zip(("joints", "radii", "parents"), explicit) if not e]
            raise ValueError(f"give 'file', 'procedural' or all of joints, radii, parents (missing: {', '.join(missing)})")
        if self.procedural is not None and any(explicit):
            raise ValueError("give either 'procedural' or joints/radii/parents, not both")
        return self

    @model_validator(mode="wrap")  # after _one_source, so it wraps it (pydantic applies validators in order)
    @classmethod
    def _degenerate(cls, data, handler):
        return checks.validate_with(data, handler, explicit_problems)


def explicit_problems(data: dict) -> list[str]:
    """Explicit joints' problems between fields, all of them (NaN, inf and negative radii are
    the fields' own): counts that differ from the joints', parents out of range, cycles and
    fold-backs (``topology_problems``), segments of zero length (ends within 1e-9 of the
    skeleton's extent, the build's bound) and segments of radius 0 at both ends."""
    j, r, c = checks.floats(data.get("joints"), 3), checks.floats(data.get("radii")), checks.floats(data.get("colors"), 3)
    p = checks.floats(data.get("parents"))
    if j is None:
        return []
    n = j.shape[0]
    lines = [] if r is None else checks.count_mismatch("radii", r.size, n, "joints")
    lines += [] if p is None else checks.count_mismatch("parents", p.size, n, "joints")
    lines += [] if c is None else checks.count_mismatch("colors", c.shape[0], n, "joints")
    if lines or r is None or p is None or r.ndim != 1 or p.ndim != 1 or not np.all(p == np.round(p)):
        return lines  # shapes off or a parent not an integer (the field's own error): the segments are not known
    lines += topology_problems(j, p)  # every bad parent index, cycle and fold-back
    if not np.all((p >= -1) & (p < n)):
        return lines
    p = p.astype(np.int64)
    kids = np.nonzero((p >= 0) & (p != np.arange(n)))[0]
    fin = np.all(np.isfinite(j), axis=1)
    extent = float(np.max(np.ptp(j[fin], axis=0))) if fin.sum() > 1 else 0.0
    with np.errstate(invalid="ignore"):  # inf - inf of non-finite joints, which their own check names
        length = np.linalg.norm(j[kids] - j[p[kids]], axis=1)
    zero = kids[length <= checks.REL_LENGTH * (extent or 1.0)]
    thin = kids[(r[kids] == 0) & (r[p[kids]] == 0)]

    def seg(ids):  # the first SHOW only: the lines name no more
        return [f"{p[i]} -> {i} at {checks.value_str(j[i])}" for i in ids[:checks.SHOW]]

    lines += checks.at("joints", "zero-length segment", zero, seg(zero), "joints")
    return lines + checks.at("radii", "segment of radius 0 at both ends", thin, seg(thin), "joints")


def array_problems(joints, radii, parents) -> list[str]:
    """Every problem of a skeleton's arrays (``frusta_from_skeleton``'s input), relative to the
    skeleton's path: joints or radii not finite, negative radii (a config's own field checks)
    and :func:`explicit_problems`."""
    j, r = checks.floats(joints, 3), checks.floats(radii)
    lines = [] if j is None else checks.nonfinite("joints", j, "joints")
    if r is not None and r.ndim == 1:
        neg = np.nonzero(r < 0)[0]
        lines += checks.nonfinite("radii", r, "joints") + checks.at("radii", "negative radius", neg, r[neg], "joints")
    return lines + explicit_problems({"joints": joints, "radii": radii, "parents": parents})


class ReliefConfig(StrictModel):
    """A height field in a shell over some or all segments (Sec. 3).

    ``map``: an 8-bit image file, or ``brick``/``gravel``/``grass`` (scikit-image's texture
    photographs). ``scale``: repeats of the map per unit u and per unit v (v runs 0..1 per
    segment and continues along a chain, so scale_v = 1/n spans n segments). ``uv: auto`` takes
    the fast approximate v where the paper says it is exact (every relief segment's cutting
    planes parallel) and the exact one otherwise.
    """

    map: str
    """The height map: an 8-bit image file, or ``brick``, ``gravel`` or ``grass``."""
    thickness: Annotated[float, Field(gt=0.0)] = 0.05
    """Shell thickness: the height of a white texel above the frustum, world units."""
    scale: tuple[Annotated[float, Field(gt=0.0)], Annotated[float, Field(gt=0.0)]] = (4.0, 1.0)
    """Repeats of the map per unit u and per unit v (v runs 0..1 per segment)."""
    steps: Annotated[int, Field(ge=1, le=65536)] = 32
    """Linear search steps through the shell (the relief's main quality knob)."""
    bisection: Annotated[int, Field(ge=0, le=64)] = 6
    """Bisection iterations refining a linear step's crossing."""
    uv: Literal["auto", "approximate", "exact"] = "auto"
    """How v is computed in the shell: the paper's fast approximation, exact, or ``auto`` (approximate where it is exact)."""
    v_mode: Literal["wrap", "clamp"] = "wrap"
    """Map lookup beyond [0, 1] in v: repeat or clamp."""
    early_exit: bool = False
    """March in a loop that stops once every ray of the batch has found its bracket, instead of exactly ``steps`` steps."""
    storage: Literal["uint8", "float"] = "uint8"
    """The map on the device: 8-bit texels (Sec. 4), or the same values (0..255) in the build's
    float type, a traced array that derivatives reach (hit distances against each texel, through
    the implicit-function theorem), at 4 or 8 bytes a texel."""
    method: Literal["march", "exact"] = "march"
    """``march``: the paper's uniform steps and bisection (``steps``, ``bisection``); ``exact``: skip through
    a min/max pyramid of the map and solve the crossing in its bilinear cell to rounding (no step
    count), with ``uv`` approximate or exact as the march."""
    segments: list[Annotated[int, Field(ge=0)]] | None = None
    """Indices of the segments that carry relief; unset: all."""
    cull: Literal["auto", "blocks", "tree", "packets"] = "auto"
    """Which (ray, segment) pairs reach the shell test: every segment of each block of ``object.block`` segments
    that a ray of the batch reaches (``blocks``), or the segments of the BVH leaves each ray meets, found by
    per-ray walks (``tree``) or for packets of 64 coherent rays at once (``packets``); ``auto`` picks
    ``tree`` from 32 relief segments, else ``blocks`` (docs/choices.md#relief-cull)."""


class FrustaConfig(StrictModel):
    """Conical frusta skinning a skeleton (Bhagvat et al. 2009)."""

    type: Literal["frusta"]
    """Selects this representation."""
    skeleton: SkeletonConfig
    """The skeleton the frusta skin: a file, a generator or explicit joints."""
    normals: Literal["interpolated", "geometric"] = "interpolated"
    """Shading normals: interpolated across cutting planes (smooth joints) or each cone's own."""
    match_minor_axes: bool = False
    """Rescale continuations' base radii until the minor axes of the two elliptical cuts at each joint agree (Sec. 2.2)."""
    twist_deg: float = 0.0
    """Twist of the texture's u frame along the segments, degrees per unit v (Sec. 2.3)."""
    color: RGB = (0.35, 0.55, 0.3)
    """Linear RGB colour where the skeleton gives none and there is no texture."""
    texture: str | None = None
    """An image file mapped over (u, v); unset: plain colour."""
    texture_scale: tuple[Annotated[float, Field(gt=0.0)], Annotated[float, Field(gt=0.0)]] = (1.0, 1.0)
    """Repeats of the texture per unit u and per unit v."""
    relief: ReliefConfig | None = None
    """A height field in a shell over the frusta (Sec. 3); unset: plain frusta."""
    block: Annotated[int, Field(ge=1, le=4096)] = 64
    """Segments per scan step of the blocks traversal (smaller for small skeletons)."""
    frame: float = 0.0
    """Animation frame, for animated generators (``dancing_cacti``)."""
    accel: Literal["auto", "blocks", "bvh", "none"] = "auto"
    """Plain segments' acceleration: ``auto`` is a BVH from 16 segments, ``none`` brute force."""
    leaf: Annotated[int, Field(ge=1, le=64)] = 4
    """Segments per BVH leaf."""
    group: Annotated[int, Field(ge=1, le=1 << 24)] = 512
    """``traversal: walks``: rays per vmapped group of walks."""
    packet: Annotated[int, Field(ge=0, le=65536)] = 256
    """``traversal: packets``: rays sharing one BVH walk (0: walks)."""
    traversal: Literal["auto", "bins", "packets", "walks", "kernel"] = "auto"
    """How rays find their segments: candidate lists of packets of coherent rays (``bins``, the CPU default), BVH
    packets, per-ray BVH walks under vmap, or the Pallas kernel (the accelerator default); ``auto`` picks by backend."""
    bin_packet: Annotated[int, Field(ge=1, le=65536)] = 64
    """``bins``: consecutive rays sharing one candidate list (64 and ``bin_pairs`` 256 within 9 % of the best under
    AVX-512 and AVX2 alike: docs/choices.md#bins-isa)."""
    bin_candidates: Annotated[int, Field(ge=1, le=65536)] = 128
    """``bins``: segments tested against every packet at once."""
    bin_pairs: Annotated[int, Field(ge=1, le=65536)] = 256
    """``bins``: (packet, segment) pairs cast at once."""
    bin_group: Annotated[int, Field(ge=0, le=65536)] = 32
    """``bins``: leaf slots per BVH node tested before its segments (0: every segment's box)."""
    bin_walk_ratio: Annotated[float, Field(ge=0.0, le=1e6)] = 1.5
    """``bins``: a chunk whose list holds more segments per ray than this walks instead (0: never)."""
    kernel_block: Annotated[int, Field(ge=1, le=1024)] = 32
    """``kernel``: rays per kernel program (a power of two)."""
    kernel_warps: Annotated[int, Field(ge=1, le=32)] = 1
    """``kernel``: warps per kernel program."""

    @field_validator("kernel_block")
    @classmethod
    def _block_pow2(cls, v: int) -> int:
        if v & (v - 1):
            raise ValueError("must be a power of two")
        return v
