"""The experiment schema: frozen pydantic models of the camera, lights, shading, render options,
scene objects and environment (an object's own section is its representation's ``Config``,
from the registry), and the automatic chunk sizes."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PrivateAttr, SerializeAsAny, ValidationInfo, field_validator, model_validator



class StrictModel(BaseModel):
    """Base for every config section: frozen, no unknown keys, no NaN or inf."""

    # a string literal right under a field is its description (pydantic >= 2.7), which the
    # configuration reference (``jskel.config.reference_rows``; docs/config.md) shows
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, use_attribute_docstrings=True)


Vec3 = tuple[float, float, float]
RGB = tuple[
    Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)]
]


class CameraConfig(StrictModel):
    """Pinhole look-at camera; ``up`` may not be parallel to ``target - eye``.

    ``frame: auto`` places the camera from what it looks at (a skeleton read from a file, in
    whatever units, renders without a hand-placed eye): the target is the centre of the
    object's (a scene's: all objects') bounding box, and the eye lies along ``view`` from it
    at the distance where the box's bounding sphere fills the narrower field of view
    (``camera.framing``); run.json records the eye and target used. ``eye`` and ``target`` are
    then not given (one or the other would be ignored)."""

    eye: Vec3 = (0.0, 1.0, 6.0)
    """Camera position (world units); not given with ``frame: auto``."""
    target: Vec3 = (0.0, 1.0, 0.0)
    """The point the camera looks at; not given with ``frame: auto``."""
    up: Vec3 = (0.0, 1.0, 0.0)
    """World direction that appears upwards in the image; not parallel to the view direction."""
    fov_deg: Annotated[float, Field(gt=0.0, lt=180.0)] = 40.0
    """Vertical field of view, degrees."""
    width: Annotated[int, Field(ge=1, le=16384)] = 320
    """Image width, pixels."""
    height: Annotated[int, Field(ge=1, le=16384)] = 240
    """Image height, pixels."""
    frame: Literal["manual", "auto"] = "manual"
    """``manual``: ``eye`` and ``target`` as given; ``auto``: placed from the object's bounding box."""
    view: Vec3 = (1.0, 0.5, 1.0)
    """``frame: auto`` only: the direction from the target to the eye."""

    @model_validator(mode="after")
    def _auto_frame(self):
        if self.frame != "auto":
            return self
        given = [k for k in ("eye", "target") if k in self.model_fields_set]
        if given:
            raise ValueError(f"{' and '.join(given)} given with frame: auto (auto places the camera; give frame: manual to place it)")
        v, u = np.asarray(self.view, float), np.asarray(self.up, float)
        if not np.linalg.norm(v) > 0:
            raise ValueError("view is the zero vector")
        if np.linalg.norm(np.cross(v, u)) <= 1e-6 * np.linalg.norm(v) * np.linalg.norm(u):
            raise ValueError(f"view {list(self.view)} is parallel to up {list(self.up)}")
        return self

    @field_validator("target")
    @classmethod
    def _target_not_eye(cls, v, info: ValidationInfo):
        eye = info.data.get("eye")
        if eye is not None and np.allclose(np.asarray(v), np.asarray(eye), rtol=0, atol=0):
            raise ValueError("target equals eye")
        return v

    @field_validator("up")
    @classmethod
    def _up_not_parallel(cls, v, info: ValidationInfo):
        u = np.asarray(v, float)
        nu = np.linalg.norm(u)
        if nu == 0:  # whatever eye and target are (a bad eye is its own error line)
            raise ValueError("up is the zero vector")
        eye, target = info.data.get("eye"), info.data.get("target")
        if eye is None or target is None:
            return v
        f = np.asarray(target, float) - np.asarray(eye, float)
        nf = np.linalg.norm(f)
        if nf > 0 and np.linalg.norm(np.cross(f, u)) <= 1e-6 * nf * nu:
            raise ValueError("camera looks along its up vector")
        return v


class LightConfig(StrictModel):
    """A light. ``directional``: ``direction`` points from the scene *towards* the light;
    ``point``: at ``position``, radiance falling off as 1 / distance^2 (``intensity`` is the
    radiance at distance 1). ``shadows``: whether it casts shadows; unset, true in a scene
    (``objects:``) and false in a file's ``object:`` experiment, so such an experiment written
    before shadows existed renders as it did (``ExperimentFile.experiment`` writes it out)."""

    type: Literal["directional", "point"] = "directional"
    """A light at infinity (``direction``) or at a point (``position``)."""
    direction: Vec3 = (0.4, 0.8, 0.6)
    """Directional light: from the scene towards the light (need not be unit length)."""
    position: Vec3 | None = None
    """Point light: its position (world units); required for ``type: point``, absent otherwise."""
    color: RGB = (1.0, 1.0, 1.0)
    """Linear RGB colour of the light."""
    intensity: Annotated[float, Field(ge=0.0)] = 1.0
    """Radiance scale (a point light's radiance at distance 1)."""
    shadows: bool = True
    """Whether it casts shadows (unset in a file's ``object:`` experiment: false)."""

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v):
        if not any(v):
            raise ValueError("direction is the zero vector")
        return v

    @model_validator(mode="after")
    def _point_has_position(self):
        if self.type == "point" and self.position is None:
            raise ValueError("a point light needs a 'position'")
        if self.type == "directional" and self.position is not None:
            raise ValueError("a directional light has no 'position' (give type: point)")
        return self


class ShadingConfig(StrictModel):
    """Lambert + Blinn-Phong; colours are linear RGB. ``output``: the transfer function from
    linear light to the PNG's 8 bits, the sRGB curve (IEC 61966-2-1) or a plain power 1/gamma."""

    ambient: Annotated[float, Field(ge=0.0)] = 0.15
    """Ambient term, a fraction of the surface colour added regardless of the lights."""
    specular: Annotated[float, Field(ge=0.0)] = 0.25
    """Weight of the Blinn-Phong highlight."""
    shininess: Annotated[float, Field(gt=0.0)] = 32.0
    """Blinn-Phong exponent: larger is a smaller, sharper highlight."""
    background: RGB = (0.82, 0.86, 0.92)
    """Linear RGB colour of pixels whose ray hits nothing (and of unset environment colours)."""
    output: Literal["srgb", "gamma"] = "srgb"
    """Transfer function from linear light to the PNG's 8 bits: the sRGB curve or a power 1/``gamma``."""
    gamma: Annotated[float, Field(gt=0.0)] = 2.2
    """Exponent of ``output: gamma``."""


AUTO_CHUNK_CPU = 4096
AUTO_CHUNK_ACCELERATOR = 1 << 20


def chunk_of(render) -> int:
    """``render.chunk`` resolved: ``auto`` is 4,096 rays per call on the CPU (small calls keep
    per-ray work in cache; docs/performance.md's chunk rows) and 1,048,576 on an accelerator, where one call
    per frame is what fills the device (on a GPU the per-ray walk of the palm at 1024x768 ran
    faster in one call than in 65,536-ray calls; ``experiments/bench_scale_device.yaml``,
    docs/choices.md#auto-chunk)."""
    import jax

    if render.chunk != "auto":
        return int(render.chunk)
    return AUTO_CHUNK_CPU if jax.default_backend() == "cpu" else AUTO_CHUNK_ACCELERATOR


AUTO_CHUNKS_PER_CALL_CPU = 128


def chunks_per_call_of(render) -> int:
    """``render.chunks_per_call`` resolved: ``auto`` is 128 on the CPU and 1 on an accelerator,
    whose auto chunk is already a whole frame. Several chunks per call save the host's per-call
    slicing, transfer and dispatch; with two host devices a 1024x768 frame runs as one call of
    128 chunks per device, 96 of them traced (``executor.calls_grouping``). With 64, a frame
    made two calls, and dispatching the second returned only once the first had run (a
    development timing of the dispatches), so the host's work around them was not hidden
    behind the cast; 128 was measured against 1, 16 and 64 in
    ``experiments/bench_scale_cpu_paths.yaml`` (docs/performance.md, docs/choices.md#chunks-per-call)."""
    import jax

    if render.chunks_per_call != "auto":
        return int(render.chunks_per_call)
    return AUTO_CHUNKS_PER_CALL_CPU if jax.default_backend() == "cpu" else 1


class RenderConfig(StrictModel):
    """How rays are evaluated: rays per compiled call, screen tile order, precision, progress bar.

    Rays are ordered in ``tile`` x ``tile`` screen tiles so a chunk of ``chunk = tile**2`` rays
    covers one compact tile (see ``jskel.camera.tile_order``). ``devices``: ``all`` shards the
    rays over every local device (``chunk`` rays per device per call; the image is the same bit
    for bit as on one device), ``one`` or a count. ``memory_mb``: a budget (MiB per device) for
    one compiled call; ``chunk`` is then an upper bound, halved until XLA's memory analysis of
    the call (arguments, outputs, temporaries) fits (``jskel.executor.chunk_for_budget``).
    ``chunks_per_call``: batches of at least min(that many, 8) chunks run up to that many chunks
    per compiled call (a power of two of them, padding chunks skipped; each chunk computed as
    alone, the host's per-call work saved); not with ``memory_mb``.

    ``spp`` jittered samples per pixel (the first at the pixel centre; AOVs come from it) from
    ``seed``. ``bounces`` bounds reflection and refraction depth; ``lanes`` is the size of the
    dense sub-batches that compacted rays are traced in.
    """

    chunk: Annotated[int, Field(ge=1, le=1 << 24)] | Literal["auto"] = "auto"
    """Rays per chunk (per device); ``auto``: 4,096 on the CPU, 1,048,576 on an accelerator (``chunk_of``)."""
    chunks_per_call: Annotated[int, Field(ge=1, le=4096)] | Literal["auto"] = "auto"
    """Chunks in one compiled call (a loop over them) on big batches; ``auto``: 64 on the CPU, 1 on an accelerator."""
    tile: Annotated[int, Field(ge=1, le=4096)] = 64
    """Edge of the square screen tiles rays are ordered in, pixels."""
    dtype: Literal["float32", "float64"] = "float32"
    """Floating-point precision of the build and of every ray computation."""
    progress: bool | None = None
    """Show a progress bar; unset: when standard error is a terminal."""
    devices: Literal["all", "one"] | Annotated[int, Field(ge=1, le=4096)] = "all"
    """Local devices the rays are sharded over: all, one, or a count."""
    memory_mb: Annotated[float, Field(gt=0.0, le=1 << 24)] | None = None
    """Device memory budget of one compiled call, MiB: ``chunk`` is halved until the call fits."""
    spp: Annotated[int, Field(ge=1, le=1024)] = 1
    """Jittered samples per pixel (the first at the pixel centre)."""
    steps: bool = False
    """Also write ``steps.npy`` (H, W): each pixel's camera ray's search steps (cells: the voxels
    and skipped tiles or blocks of the walk, or the linear search's samples), counted in one more
    pass over the camera rays after the timed render. A scene of one object of a representation
    that counts them (``Representation.steps_per_ray``; cells)."""
    seed: int = 0
    """Seed of the sample jitter."""
    bounces: Annotated[int, Field(ge=0, le=16)] = 2
    """Reflection and refraction depth (a cell object's mode gives its own)."""
    lanes: Annotated[int, Field(ge=1, le=1 << 20)] = 256
    """Rays per dense sub-batch that compacted rays are traced in."""
    compaction: bool = True
    """Gather the rays an effect needs (true) or trace every queue slot against every object (false, masking; for comparison)."""


Unit = Annotated[float, Field(ge=0.0, le=1.0)]


class TransformConfig(StrictModel):
    """Object to world: scale uniformly by ``scale``, rotate by XYZ Euler angles (degrees, X
    first), then translate. Uniform scale keeps every representation's distances exact."""

    translate: Vec3 = (0.0, 0.0, 0.0)
    """Translation, world units, applied last."""
    rotate_deg: Vec3 = (0.0, 0.0, 0.0)
    """XYZ Euler angles, degrees, X first."""
    scale: Annotated[float, Field(gt=0.0)] = 1.0
    """Uniform scale, applied first."""


class MotionConfig(StrictModel):
    """Rigid motion per frame, added to the transform at ``frame``: translation and Euler
    angles (degrees) per frame (rigidly moving objects, e.g. cell objects, issue 7)."""

    translate: Vec3 = (0.0, 0.0, 0.0)
    """Translation per frame, world units."""
    rotate_deg: Vec3 = (0.0, 0.0, 0.0)
    """XYZ Euler angles per frame, degrees."""


class MaterialConfig(StrictModel):
    """Surface response. ``color`` multiplies the representation's own colour (skeleton colours,
    textures); ``specular``/``shininess`` default to the ``shading`` section's. A fraction
    ``reflectivity`` of the light is mirrored, ``transparency`` refracted with index ``ior``
    (total internal reflection turns into reflection); the rest is shaded locally."""

    color: RGB = (1.0, 1.0, 1.0)
    """Linear RGB factor on the representation's own colour."""
    specular: Annotated[float, Field(ge=0.0)] | None = None
    """Weight of the highlight; unset: ``shading.specular``."""
    shininess: Annotated[float, Field(gt=0.0)] | None = None
    """Blinn-Phong exponent; unset: ``shading.shininess``."""
    reflectivity: Unit = 0.0
    """Fraction of the light mirrored."""
    transparency: Unit = 0.0
    """Fraction of the light refracted; ``reflectivity + transparency`` is at most 1."""
    ior: Annotated[float, Field(gt=0.0, le=10.0)] = 1.5
    """Index of refraction of a transparent material."""

    @model_validator(mode="after")
    def _energy(self):
        if self.reflectivity + self.transparency > 1.0:
            raise ValueError(f"reflectivity + transparency must not exceed 1 (got {self.reflectivity} + {self.transparency})")
        return self


def _registered_shape(v):
    """An object's own section as its representation's validated ``Config``: a mapping is
    validated by the model the registry holds for its ``type`` (imported then, not before), a
    model of a registered representation passes as it is. The representations' ``Config``
    models, told apart by their ``type`` literal, are the union; the registry is its list, read
    lazily, so reading an experiment imports only the representations it names."""
    from .. import registry

    if isinstance(v, BaseModel):
        kind = getattr(v, "type", None)
        if kind in registry.names() and isinstance(v, registry.get(kind).Config):
            return v
        raise ValueError(f"not the configuration of a registered representation (got {type(v).__name__})")
    if not isinstance(v, dict):
        raise ValueError(f"must be a mapping with a 'type' key (got {v!r})")
    kind = v.get("type")
    if kind not in registry.names():
        raise ValueError(f"unknown representation (got {kind!r}; known: {', '.join(registry.names())})")
    return registry.get(kind).Config.model_validate(v)


#: A representation's section (``object:``, a scene object's ``shape:``): the ``Config`` of the
#: representation its ``type`` names (``_registered_shape``), dumped as that model.
Shape = Annotated[SerializeAsAny[BaseModel], BeforeValidator(_registered_shape)]


class SceneObjectConfig(StrictModel):
    """One object of a scene: a ``shape`` (any representation's ``object`` section, validated by
    the registry), its transform, material and motion."""

    name: str | None = None
    """A name for the object (error messages, run.json)."""
    shape: Shape
    """The object's own section: any representation's ``object`` section, with its ``type``."""
    transform: TransformConfig = TransformConfig()
    """Object to world placement."""
    material: MaterialConfig = MaterialConfig()
    """Surface response in the scene."""
    motion: MotionConfig | None = None
    """Rigid motion per animation frame; unset: static."""

    _at: str | None = PrivateAttr(None)  # where the file wrote it, for messages: "object" for an ``object:`` section

    def at(self, i: int) -> str:
        """The key path of this object, the ``i``-th of its experiment, as its file wrote it:
        ``object`` for a file's ``object:`` section, ``objects[i]`` otherwise."""
        return self._at or f"objects[{i}]"

    @property
    def is_placed(self) -> bool:
        """Whether a transform or motion moves the object (a file's ``object:`` section never does)."""
        return self.transform != TransformConfig() or self.motion is not None


class EnvironmentConfig(StrictModel):
    """What rays that escape the scene see: a sky gradient over the world y axis, ``horizon``
    at y = 0 blending to ``zenith`` upwards and ``ground`` downwards. Unset colours take
    ``shading.background`` (all unset: a constant background)."""

    zenith: RGB | None = None
    """Linear RGB colour straight up; unset: ``shading.background``."""
    horizon: RGB | None = None
    """Linear RGB colour at y = 0; unset: ``shading.background``."""
    ground: RGB | None = None
    """Linear RGB colour straight down; unset: ``shading.background``."""


class _Common(StrictModel):
    """What an experiment file and the experiment value share: everything but the objects."""

    name: str = "experiment"
    """The experiment's name (run.json, benchmark rows)."""
    camera: CameraConfig = CameraConfig()
    """The pinhole camera."""
    lights: list[LightConfig] = [LightConfig()]
    """The lights; by default one white directional light."""
    shading: ShadingConfig = ShadingConfig()
    """Local shading and output transfer."""
    environment: EnvironmentConfig = EnvironmentConfig()
    """What rays escaping a scene see."""
    render: RenderConfig = RenderConfig()
    """How rays are evaluated."""
    frame: float = 0.0
    """Animation frame of a scene (shapes with a ``frame`` key, motions)."""


class ExperimentFile(_Common):
    """An experiment as a file writes it: one ``object`` (validated by the registered
    representation) or a scene of several ``objects`` with materials, an ``environment`` and a
    ``frame``. ``jskel.config.load`` turns it into the one value the code takes,
    :class:`Experiment` (:meth:`experiment`)."""

    object: Shape | None = None
    """One object: its ``type`` names the representation whose section this is (see below); not with ``objects``."""
    objects: list[SceneObjectConfig] | None = None
    """A scene: several placed objects with materials; not with ``object``."""

    @model_validator(mode="after")
    def _object_or_objects(self):
        if (self.object is None) == (self.objects is None):
            raise ValueError("give either 'object' (one representation) or 'objects' (a scene), not both" if self.object is not None
                             else "give 'object' (one representation) or 'objects' (a scene)")
        if self.objects is not None and not self.objects:
            raise ValueError("objects: a scene needs at least one object")
        return self

    def experiment(self) -> "Experiment":
        """The experiment value: a file's ``object:`` becomes a scene of one (``objects:``, one
        object, no transform, the default material) whose lights cast shadows only where their
        section says ``shadows: true`` (an ``object:`` file written before shadows existed renders
        as it did); a scene's lights cast them unless told not to. Its run.json writes it so."""
        common = {k: getattr(self, k) for k in _Common.model_fields}
        if self.objects is not None:
            return Experiment(**common, objects=tuple(self.objects))
        one = SceneObjectConfig(shape=self.object)
        one._at = "object"
        lights = [l if "shadows" in l.model_fields_set else l.model_copy(update={"shadows": False}) for l in self.lights]
        return Experiment(**{**common, "lights": lights}, objects=(one,))


class Experiment(_Common):
    """The one experiment value every entry takes (``jskel.render.render``, the benchmarks,
    the sweeps, the viewer): a scene of ``objects`` (a file's single ``object:`` is a
    scene of one, :meth:`ExperimentFile.experiment`), each object's ``shape`` already validated
    by its representation, with the camera, lights, shading, environment and render options."""

    objects: tuple[SceneObjectConfig, ...]
    """The scene's objects (at least one), each a shape placed with a material."""

    @field_validator("objects")
    @classmethod
    def _some(cls, v):
        if not v:
            raise ValueError("a scene needs at least one object")
        return v

    def with_shapes(self, *shapes) -> "Experiment":
        """The experiment with its objects' shapes replaced, one per object in order, each object
        keeping its name, placement and material (a fitted skeleton, an animation frame's pose);
        each a registered representation's model, or a mapping validated by it."""
        if len(shapes) != len(self.objects):
            raise ValueError(f"objects: {len(shapes)} shapes given for {len(self.objects)} objects")
        objs = tuple(o.model_copy(update={"shape": _registered_shape(s)}) for o, s in zip(self.objects, shapes))
        return self.model_copy(update={"objects": objs})
