"""The interface every representation offers, declared whole, with its defaults in one base.

The renderer, the scene integrator, the benchmarks and the sweeps talk only to this interface:
they never ask a representation what it has (no ``hasattr``), never read facts out of strings
(``Built.info`` is for ``run.json`` only) and never name a representation's type.

Two stages, as Mitsuba 3 splits ``ray_intersect_preliminary`` from
``compute_surface_interaction``:

* :meth:`Representation.cast` ``(params, static, rays) -> Preliminary(t, prim, payload)``: the
  nearest hit's distance and primitive for every ray, plus whatever the representation needs to
  finish the hit later (``payload``, a pytree with a leading ray axis). This is all a benchmark's
  cast, a depth pass or a shadow ray needs;
* :meth:`Representation.surface` ``(params, static, rays, pre) -> Hit``: position, normal and
  uv from the preliminary hit, computed only where a ray hit.

:meth:`Representation.intersect_batch` is the two in one program (what the first-hit render
uses), and :meth:`Representation.occluded` the any-hit query of shadow rays.

A representation is one ``final`` subclass of :class:`Representation` in its folder and one line
in ``jskel.registry``; it overrides what it has (an analytic tracer its exit from inside, a
marching one its surface tolerance) and inherits the rest. The conformance suite
(``tests/test_conformance.py``) runs the same checks over every registered representation.
"""

from __future__ import annotations

import sys
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, Hashable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from pydantic import BaseModel

from . import checks
from .rays import Hit, Rays


@dataclass(frozen=True)
class Built:
    """What ``build`` returns: device arrays, host-side static data and declared facts.

    params: pytree of arrays (traced: changing values never recompiles).
    static: hashable options that change shapes or control flow (recompile when changed).
    anchor: (3,) float64 world point that positions in ``params`` are relative to; rays must be
      expressed relative to it (``Camera.rays(anchor=...)``).
    bounds: ((3,), (3,)) float64 world-space axis-aligned bounds; every hit lies inside.
    info: JSON-able diagnostics for ``run.json`` (counts, build timings); nothing reads facts
      from it.
    primitives: how many primitives (segments, blobs, cells) the object holds.
    surface_tolerance: how far (object units) a returned hit may lie from the true surface
      (0 for analytic intersections; a marching tracer's last bisection bracket). A secondary
      ray starts beyond it.
    secondary_offset: how far (object units) a secondary ray's origin moves off the surface
      along the normal, beyond the rounding bound ``jskel.spawn`` adds; None: four times
      ``surface_tolerance``.
    """

    params: Any
    static: Hashable
    anchor: np.ndarray
    bounds: tuple[np.ndarray, np.ndarray]
    info: dict = field(default_factory=dict)
    primitives: int = 0
    surface_tolerance: float = 0.0
    secondary_offset: float | None = None


class OwnMaterial(NamedTuple):
    """The material a single object's section asks for itself (``Representation.own_material``),
    in the integrator's terms: ``reflectivity``/``transparency``/``ior`` as a scene material's,
    ``bounces`` levels of secondary rays, and how a path through the object ends:

    last_local: a hit on the last level takes its local light whole (no (1 - kr - kt) for rays
      that will not be traced);
    last_env: on the last level, the rays a hit would spawn see the environment in their
      direction instead of being traced;
    local_once: local light only where a camera ray hits; on later levels the object passes
      the light on whole (kt = 1);
    tint: a refracted ray entering the object is tinted by 0.5 + 0.5 x the colour where it
      enters (Nürnberg 2011, Sec. 3.2.4)."""

    reflectivity: float = 0.0
    transparency: float = 0.0
    ior: float = 1.5
    bounces: int = 0
    last_local: bool = False
    last_env: bool = False
    local_once: bool = False
    tint: bool = False
    asked_by: str = ""  # the section's setting that asks for it, as an error names it ("mode: 'reflection'")


class Preliminary(NamedTuple):
    """The first stage of an intersection, for a batch of N rays.

    t: (N,) ray parameter of the nearest hit, ``+inf`` on a miss.
    prim: (N,) int32 primitive id, -1 on a miss.
    payload: what :meth:`Representation.surface` needs to finish the hit (a pytree with leading
      axis N, representation-defined; the base keeps the whole ``Hit`` there)."""

    t: jnp.ndarray
    prim: jnp.ndarray
    payload: Any = None


#: the members a representation may give as module-level functions of its folder, picked up by
#: ``Representation.__init_subclass__(module=...)``
FUNCTION_MEMBERS = ("build", "intersect_one", "intersect_batch", "cast", "surface", "occluded", "albedo", "inside",
                    "steps_per_ray", "traversal_stats", "pair_test_seconds", "traced_fields")


def missing_members(cls) -> list[str]:
    """The members of :attr:`Representation.REQUIRED` that ``cls`` neither defines nor inherits
    from a class other than the base, and a ``Config`` that is not a pydantic model whose
    ``type`` is ``Literal[name]``: each named (every one at once, when the class is defined)."""
    out = []
    for m in Representation.REQUIRED:
        own = getattr(cls, m, None)
        if own is None or own is getattr(Representation, m, None):
            out.append(m)
    cfg, name = getattr(cls, "Config", None), getattr(cls, "name", None)
    if cfg is not None and name is not None:
        field = cfg.model_fields.get("type") if isinstance(cfg, type) and issubclass(cfg, BaseModel) else None
        if field is None or typing.get_args(field.annotation) != (name,):
            out.append(f"Config (a pydantic model whose type is Literal[{name!r}])")
    return out


class Representation:
    """Base of every representation: the whole interface, with defaults for what is optional.

    Must be given by a subclass: ``name``, ``Config`` (the pydantic model of an ``object``
    section, with a ``type`` literal equal to ``name``), :meth:`build`, :meth:`intersect_one`,
    :meth:`albedo`, :meth:`inside`; a class that lacks any of them is a ``TypeError`` when it is
    defined, every missing one named (:func:`missing_members`), not at its first call.
    Everything else has a default here that is correct for any representation, and is
    overridden where a representation can do better (``cast``, ``surface``, ``occluded``: the
    two stages of a hit and the shadow-ray test, inherited from ``intersect_batch``).
    """

    name: ClassVar[str]
    Config: ClassVar[type[BaseModel]]

    #: the object carries what its escaping rays see (:meth:`environment`); a single object's
    #: render shows it where a ray misses, instead of the experiment's environment
    own_environment: ClassVar[bool] = False

    #: the section has an animation frame: its ``frame`` field poses it (``--frames``, a scene's
    #: ``frame``; :meth:`at_frame`)
    animated: ClassVar[bool] = False

    #: XLA options its programs compile with on the CPU (``executor.compiler_options``; a
    #: program of several objects takes the options none of them contradicts). Each is a
    #: measured choice, stated where a representation sets it
    cpu_compiler_options: ClassVar[Mapping[str, Any]] = {}

    @classmethod
    def compiler_options_for(cls, static) -> Mapping[str, Any]:
        """The CPU options of a program over an object of static options ``static``: the class's
        :attr:`cpu_compiler_options` unless a representation measured another choice for some
        of its statics (and overrides this)."""
        return cls.cpu_compiler_options

    def __init_subclass__(cls, module: str | None = None, **kw):
        """``class _X(Representation, module=__name__)``: the module's own functions named as
        :data:`FUNCTION_MEMBERS` names them (with the interface's signatures) become the
        representation's static members, so each folder states what it has once, where it
        defines it, instead of rebinding every function by hand."""
        super().__init_subclass__(**kw)
        if module is not None:
            namespace = sys.modules[module].__dict__
            for member in FUNCTION_MEMBERS:
                fn = namespace.get(member)
                if callable(fn) and getattr(fn, "__module__", None) == module and member not in cls.__dict__:
                    setattr(cls, member, staticmethod(fn))
        missing = missing_members(cls)
        if missing:
            raise TypeError(f"{cls.__name__}: a representation must give {', '.join(missing)} (jskel.interface.Representation)")

    # ------------------------------------------------------------------ must be given
    #: what a subclass must give, checked when the class is defined (:func:`missing_members`)
    REQUIRED: ClassVar[tuple[str, ...]] = ("name", "Config", "build", "intersect_one", "albedo", "inside")

    def build(self, cfg: BaseModel, dtype=np.float32) -> Built:
        """Host: validate ``cfg`` and precompute; a :class:`Built`."""
        raise NotImplementedError(f"{type(self).__name__}.build")

    def intersect_one(self, params, static, origin, direction, t_min, t_max) -> Hit:
        """Nearest hit of one ray ``origin + t direction`` with t in ``(t_min, t_max]``."""
        raise NotImplementedError(f"{type(self).__name__}.intersect_one")

    def albedo(self, params, static, hit: Hit):
        """(3,) linear RGB base colour at one hit."""
        raise NotImplementedError(f"{type(self).__name__}.albedo")

    def inside(self, params, static, point):
        """() bool: is ``point`` (3,), relative to the anchor, inside the surface?"""
        raise NotImplementedError(f"{type(self).__name__}.inside")

    # ------------------------------------------------------------------ batch queries

    def intersect_batch(self, params, static, rays: Rays) -> Hit:
        """Nearest hits of a batch (leading ray axis): ``vmap`` of :meth:`intersect_one` unless
        the representation skips work at the batch level (culling, compaction)."""
        one = lambda o, d, a, b: self.intersect_one(params, static, o, d, a, b)  # noqa: E731
        return jax.vmap(one)(*rays)

    def cast(self, params, static, rays: Rays) -> Preliminary:
        """First stage: t and primitive of every ray; by default the whole hit rides along."""
        h = self.intersect_batch(params, static, rays)
        return Preliminary(h.t, h.prim, h)

    def surface(self, params, static, rays: Rays, pre: Preliminary) -> Hit:
        """Second stage: the hit's attributes from :meth:`cast`'s preliminary hit."""
        return pre.payload

    def occluded(self, params, static, rays: Rays):
        """(N,) bool: does each ray meet the surface in ``(t_min, t_max]`` (shadow rays)?"""
        return jnp.isfinite(self.cast(params, static, rays).t)

    # ------------------------------------------------------------------ declared facts

    def exits_from_inside(self, cfg: BaseModel) -> bool:
        """Does a ray starting inside the surface get its exit as the hit? Only such objects
        may be transparent in a scene (analytic tracers; marching ones search entries only)."""
        return False

    def at_frame(self, cfg: BaseModel, frame: float) -> BaseModel:
        """``cfg`` posed at animation ``frame``: an :attr:`animated` section with its ``frame``
        field set to it; any other section as it is."""
        return cfg.model_copy(update={"frame": float(frame)}) if self.animated else cfg

    def skeleton(self, cfg: BaseModel):
        """(joints (J, 3), radii (J,), parents (J,)), float64 world units, of a section whose
        surface is skinned on a skeleton of line segments, at its frame: what the tools that
        take a skeleton read (the latency benchmark's edits, the curve peers); None without one."""
        return None

    def export_mesh(self, cfg: BaseModel, path, level: int = 2, field: str = "path") -> dict:
        """Write the section's surface as a triangle mesh to ``path`` (``jskel export``); the
        representations that can say so. A ValueError naming ``object.type`` otherwise."""
        raise ValueError(f"object.type: export writes a skeleton object's mesh; {self.name!r} objects have no mesh export")

    def own_material(self, cfg: BaseModel) -> OwnMaterial | None:
        """The material a single object's section asks for (its own reflection, bounces), shaded
        by the shared integrator; None: the default material. A scene refuses such a section
        (there the object's ``material`` says it)."""
        return None

    def environment(self, params, static, direction):
        """(3,) linear RGB seen along ``direction`` (3,) by a ray that escapes the object (only
        called where :attr:`own_environment` is set)."""
        raise NotImplementedError(f"{type(self).__name__} has no environment of its own")

    def extra_aovs(self, built: Built, hits) -> dict:
        """More per-pixel outputs of a render, by name (NumPy, leading axis H*W)."""
        return {}

    def steps_per_ray(self, built: Built, rays: Rays, chunk: int = 4096):
        """(N,) int NumPy: each ray's search steps, in the rays' order (``render.steps`` writes
        them as an image); None where the representation counts none."""
        return None

    def traversal_stats(self, built: Built, rays: Rays, chunk: int = 4096) -> dict:
        """Deterministic work counts per ray (nodes, leaves) for the benchmarks; {} if none."""
        return {}

    def pair_test_seconds(self, built: Built, rays: Rays) -> dict:
        """The innermost (ray, primitive) test timed alone, for the benchmarks' ``pair_test``
        (``pair_test_ns_median``, ``pair_tests_timed``, ``pair_test_compile_s``); {} if none."""
        return {}

    def traced_fields(self, params) -> dict:
        """The params' entries :func:`checked_intersect` verifies under jit: ``{field: (array
        (N, ...), kind, valid (N,) or None, ids (N,) or None)}`` as ``jskel.checks.traced``
        takes them (kind ``finite``, ``nonnegative`` or ``positive``); {} by default."""
        return {}

    def __repr__(self) -> str:
        return f"<representation {self.name!r}>"


# ---------------------------------------------------------------------- static data in the pytree


@jax.tree_util.register_pytree_node_class
@dataclass(frozen=True)
class Object:
    """A built object as one pytree: ``params`` are its children (traced) and the
    representation's name with its static options its aux data (STYLE.md item 4, equinox's
    ``field(static=True)``, MJX's ``Model``). The tree structure therefore carries the static
    part, so one module-level function (:func:`intersect`, :func:`cast`, :func:`occluded`)
    jitted once is cached by JAX, and by the executor (``compile_batch_fn`` keys on the tree
    structure), per (representation, static options): new values reuse the executable, a
    changed static compiles once more.

    params: pytree of arrays (``Built.params``).
    static: hashable options (``Built.static``).
    rep: the registered name of the representation (``object.type``).
    """

    params: Any
    static: Hashable
    rep: str

    @classmethod
    def of(cls, rep: "Representation", built: Built) -> "Object":
        """The object ``rep.build`` returned as ``built``."""
        return cls(built.params, built.static, rep.name)

    def tree_flatten(self):
        return (self.params,), (self.rep, self.static)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(children[0], aux[1], aux[0])

    @property
    def representation(self) -> "Representation":
        from . import registry  # (the registry imports representations lazily, which import this module)

        return registry.get(self.rep)

    def compiler_options(self) -> dict:
        """The XLA options its programs compile with on the CPU (``compiler_options_for``)."""
        return agreed_options([self.rep], [self.static])


def agreed_options(reps, statics) -> dict:
    """The CPU compiler options of a program over objects of the representations ``reps``
    (registered names) with static options ``statics`` (``Representation.compiler_options_for``):
    every option some of them set, except one they set to different values (it keeps XLA's
    default). A representation that sets none takes the others': the measured choice for the
    mixed scenes (docs/choices.md#elemental-emitters: scene_cacti's render faster with the
    frusta's, scene_effects' slightly slower for a shorter compile)."""
    from . import registry

    out, clash = {}, set()
    for name, static in zip(reps, statics):
        for k, v in registry.get(name).compiler_options_for(static).items():
            clash |= {k} if out.get(k, v) != v else set()
            out.setdefault(k, v)
    return {k: v for k, v in out.items() if k not in clash}


def intersect(obj: Object, rays: Rays) -> Hit:
    """Nearest hits of a batch: :meth:`Representation.intersect_batch` of ``obj``."""
    return obj.representation.intersect_batch(obj.params, obj.static, rays)


def intersect_each(obj: Object, rays: Rays) -> Hit:
    """Nearest hits of a batch as ``vmap`` of :meth:`Representation.intersect_one` (no batch-level
    culling): the reference the batch queries are tested against."""
    rep = obj.representation
    return jax.vmap(lambda o, d, a, b: rep.intersect_one(obj.params, obj.static, o, d, a, b))(*rays)


def cast(obj: Object, rays: Rays) -> Preliminary:
    """First stage of a batch: :meth:`Representation.cast` of ``obj``."""
    return obj.representation.cast(obj.params, obj.static, rays)


def cast_t_prim(obj: Object, rays: Rays):
    """``(t, prim)`` of :func:`cast` with nothing else kept (XLA drops whatever payload no
    output needs): what a benchmark's cast computes."""
    pre = cast(obj, rays)
    return pre.t, pre.prim


def surface(obj: Object, rays: Rays, pre: Preliminary) -> Hit:
    """Second stage of a batch: :meth:`Representation.surface` of ``obj``."""
    return obj.representation.surface(obj.params, obj.static, rays, pre)


def occluded(obj: Object, rays: Rays):
    """(N,) bool any-hit of a batch (shadow rays): :meth:`Representation.occluded` of ``obj``."""
    return obj.representation.occluded(obj.params, obj.static, rays)


def _problems(obj: Object, rays: Rays, *_):
    """``jskel.checks.traced`` on the rays' origins and directions (finite, not zero) and on every
    entry of the representation's :meth:`Representation.traced_fields`."""
    found = checks.traced("rays.origins", rays.origins) + checks.traced("rays.directions", rays.directions, "nonzero")
    for name, (a, kind, valid, ids) in obj.representation.traced_fields(obj.params).items():
        found += checks.traced(name, a, kind, valid, ids)
    return found


#: :func:`intersect`, :func:`occluded`, :func:`cast` and :func:`surface` with their traced inputs
#: checked inside the compiled function (``jskel.checks.checked``): values that turn bad under
#: jit (a NaN ray, a radius an optimiser drove negative, a NaN centre) raise one ValueError
#: (``ConfigError``) with a line per failing field naming the index and the value, e.g.
#: ``rays.origins[5]: not finite (got [nan, 0.0, 1.0]); 1 of 64 entries``, instead of silent
#: misses. Each is one module-level jit (``.program``), cached per representation and static
#: options as the unchecked function is; the unchecked functions hold no check.
checked_intersect = checks.checked(intersect, _problems)
checked_occluded = checks.checked(occluded, _problems)
checked_cast = checks.checked(cast, _problems)
checked_surface = checks.checked(surface, _problems)
