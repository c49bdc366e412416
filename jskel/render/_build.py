"""What the integrator (``render/_scene.py``) traces, assembled on the host: a scene's objects
with their transforms and materials, or a single object as a scene of one.

Both go through :func:`assemble`: every object is built by its representation, placed by a
transform (float64 offsets between the rays' frame and the frame its params are stored in) and
given a material; which effects exist is decided here, statically, from what the experiment
asks for (:class:`Effects`).

The rays' frame. A scene's rays are relative to the camera's eye (camera-relative rendering).
A single object's are relative to its build anchor, as a single-object render always was: with
the identity transform the offsets are exactly zero, so a primary ray reaches the object, and
its hit comes back, as the very floats the representation gives.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .. import progress, registry
from ..numerics import euler_xyz, on_device
from ..shading import Lights, lights_from_config


class XForm(NamedTuple):
    """World (frame-relative) <-> one object's params frame: ``o' = rt o / s + c`` for points,
    ``d' = rt d`` for directions (t' = t / s), ``p = s r p' + g`` back; ``lo``/``hi`` the
    object's world bounding box."""

    rt: jnp.ndarray
    r: jnp.ndarray
    s: jnp.ndarray
    c: jnp.ndarray
    g: jnp.ndarray
    lo: jnp.ndarray
    hi: jnp.ndarray


class Materials(NamedTuple):
    """Per object (leading axis K): colour (3), specular, shininess, reflectivity,
    transparency, ior, ``offset`` (the object's part of how far a secondary ray starts off its
    surface, world units: ``spawning.surface_offset`` scaled by its placement; the spawn adds a
    rounding bound), and how a path through the object ends (1 or 0 each; ``interface.OwnMaterial``
    says what each does): ``last_local`` (a cell object's last reflection bounce, Nürnberg
    2011 Alg. 3.2), ``last_env``, ``local_once`` and ``tint`` (its refraction, Alg. 3.3)."""

    color: jnp.ndarray
    specular: jnp.ndarray
    shininess: jnp.ndarray
    reflect: jnp.ndarray
    transmit: jnp.ndarray
    ior: jnp.ndarray
    offset: jnp.ndarray
    last_local: jnp.ndarray
    last_env: jnp.ndarray
    local_once: jnp.ndarray
    tint: jnp.ndarray


class SceneParams(NamedTuple):
    """Everything traced: changing any value (a radius, a transform, a light, a material's
    reflectivity between non-zero values) reuses the compiled program."""

    objects: tuple
    xforms: tuple
    mat: Materials
    lights: Lights
    shadows: jnp.ndarray  # (L,) bool: light l casts shadows
    ambient: jnp.ndarray
    env: jnp.ndarray  # (3, 3): zenith, horizon, ground


class Effects(NamedTuple):
    """Static: which effects the experiment calls for (derived by :func:`effects_of`)."""

    shadows: bool
    reflection: bool
    refraction: bool
    bounces: int  # levels after the primary one (0 without reflection and refraction)


class SceneStatic(NamedTuple):
    reps: tuple  # representation name per object
    statics: tuple  # each object's static options
    effects: Effects
    lanes: int
    compaction: bool = True  # False: every queue slot traced against every object (masking; for the benchmark)
    single: bool = False  # a scene of one: camera rays traced as one batch, outputs as a single-object render's
    sky: bool = False  # a scene of one whose object carries its own environment: misses see it


class Placed(NamedTuple):
    """One object ready to assemble: its name, representation, build, transform and material."""

    name: str
    rep: object
    built: object
    scale: float
    rotation: np.ndarray  # (3, 3) float64
    translate: np.ndarray  # (3,) float64
    material: object  # config.MaterialConfig


def shadow_lights(exp, single: bool) -> np.ndarray:
    """(L,) bool: which lights cast shadows. In a scene a light's ``shadows`` (default true);
    for a single object only a light whose section sets ``shadows: true`` itself, so a
    single-object experiment written before shadows existed renders as it did, without
    shadow rays."""
    out = [l.shadows and (not single or "shadows" in l.model_fields_set) for l in exp.lights]
    return np.array(out or [False])


def effects_of(exp, single: bool = False, own=None) -> Effects:
    """The effects an experiment calls for (host, static). A single object has the default
    material (neither reflection nor refraction) unless its section asks for its own (``own``,
    an ``interface.OwnMaterial``: its reflectivity, transparency and bounces)."""
    mats = ([] if own is None else [own]) if single else [o.material for o in exp.objects]
    refl = any(m.reflectivity > 0 for m in mats)
    refr = any(m.transparency > 0 for m in mats)
    casts = shadow_lights(exp, single)
    shadows = any(bool(c) and l.intensity > 0 for c, l in zip(casts, exp.lights))
    bounces = exp.render.bounces if own is None else own.bounces
    return Effects(shadows, refl, refr, bounces if (refl or refr) else 0)


def object_transform(o, frame: float):
    """(scale, rotation (3,3), translation (3,)) of scene object ``o`` at ``frame`` (float64)."""
    t = np.asarray(o.transform.translate, np.float64)
    e = np.asarray(o.transform.rotate_deg, np.float64)
    if o.motion is not None:
        t = t + frame * np.asarray(o.motion.translate, np.float64)
        e = e + frame * np.asarray(o.motion.rotate_deg, np.float64)
    return float(o.transform.scale), euler_xyz(e), t


def _shape_at(shape, rep, frame: float):
    """``shape`` moved on by the scene's ``frame`` where it is animated (``rep.animated``)."""
    return rep.at_frame(shape, shape.frame + frame) if frame != 0.0 and rep.animated else shape


def _check_shape(i: int, o, shape, rep):
    """Host checks of what a representation can do in a scene (interface flags, not types)."""
    if o.material.transparency > 0 and not rep.exits_from_inside(shape):
        raise ValueError(
            f"objects[{i}].material.transparency: {o.material.transparency} on a {shape.type} object, whose tracer "
            "searches for the first entry only (a transparent object must report the exit of a ray from inside: plain frusta do)")
    own = rep.own_material(shape)
    if own is not None:
        raise ValueError(
            f"objects[{i}].shape.{own.asked_by}; in a scene an object is shaded by its material "
            "(material.reflectivity / transparency), not by effects of its own: give mode: first_hit")


def _world_corners(p: Placed) -> np.ndarray:
    """(8, 3) float64: the corners of the object's bounds, placed in the world."""
    lo, hi = (np.asarray(b, np.float64) for b in p.built.bounds)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return p.scale * corners @ p.rotation.T + p.translate


def _xform(p: Placed, origin: np.ndarray, dtype) -> XForm:
    """The object's offsets from the rays' frame (``origin``) in float64, then cast."""
    s, r, t = p.scale, p.rotation, p.translate
    a = np.asarray(p.built.anchor, np.float64)
    c = r.T @ (origin - t) / s - a
    g = s * (r @ a) + t - origin
    w = _world_corners(p) - origin
    pad = 1e-5 * (np.max(np.abs(w)) + np.max(w.max(0) - w.min(0)))  # float32 rounding of the box test
    return XForm(*(on_device(v, dtype) for v in (r.T, r, s, c, g, w.min(0) - pad, w.max(0) + pad)))


def _offset(p: Placed) -> float:
    """World distance a secondary ray starts off the object's surface (``Built.secondary_offset``,
    by default four times its surface tolerance)."""
    off = p.built.secondary_offset
    return p.scale * (4.0 * p.built.surface_tolerance if off is None else off)


def assemble(exp, placed: list[Placed], origin, dtype, single: bool = False, own=None):
    """Scene arrays of placed objects, rays relative to ``origin`` (host); ``own``: a single
    object's own material (``interface.OwnMaterial``). Returns (params, static, info per object)."""
    origin = np.asarray(origin, np.float64)
    mats = [p.material for p in placed]
    sh = exp.shading
    cols = [m.color for m in mats]
    spec = [sh.specular if m.specular is None else m.specular for m in mats]
    shin = [sh.shininess if m.shininess is None else m.shininess for m in mats]
    off = [_offset(p) for p in placed]
    ends = [[float(own is not None and getattr(own, f))] * len(placed) for f in ("last_local", "last_env", "local_once", "tint")]
    mat = Materials(*(on_device(np.asarray(v, np.float64), dtype) for v in (
        cols, spec, shin, [m.reflectivity for m in mats], [m.transparency for m in mats], [m.ior for m in mats], off, *ends)))
    bg = np.asarray(sh.background, np.float64)
    ev = exp.environment
    env = np.array([bg if v is None else v for v in (ev.zenith, ev.horizon, ev.ground)], np.float64)
    lights = lights_from_config(exp.lights, dtype, origin=origin)
    params = SceneParams(tuple(p.built.params for p in placed), tuple(_xform(p, origin, dtype) for p in placed), mat, lights,
                         on_device(shadow_lights(exp, single)), on_device(sh.ambient, dtype), on_device(env, dtype))
    static = SceneStatic(tuple(p.rep.name for p in placed), tuple(p.built.static for p in placed), effects_of(exp, single, own),
                         int(exp.render.lanes), bool(exp.render.compaction), single, single and placed[0].rep.own_environment)
    info = [{"name": p.name, "type": p.rep.name, "primitives": p.built.primitives, **p.built.info} for p in placed]
    return params, static, info


#: a build says what it is building (``jskel.progress.notice_after``) once it has taken this
#: long: a large skeleton, mesh or cell precompute; the fractions of a second most take say nothing
BUILD_NOTICE_S = 1.0


def place_objects(exp, shapes, dtype) -> list[Placed]:
    """Build every object of a scene (``objects:``) and place it (host)."""
    placed = []
    for i, (o, shape) in enumerate(zip(exp.objects, shapes)):
        rep = registry.get(shape.type)
        _check_shape(i, o, shape, rep)
        name = o.name or f"objects[{i}]"
        with progress.notice_after(BUILD_NOTICE_S, f"building {name} ({shape.type}, {i + 1} of {len(shapes)})"):
            built = rep.build(_shape_at(shape, rep, exp.frame), dtype)
        s, r, t = object_transform(o, exp.frame)
        placed.append(Placed(name, rep, built, s, r, t, o.material))
    return placed


def world_bounds(placed: list[Placed]):
    """(lo, hi) float64: the world box around every placed object's transformed bounds."""
    w = np.concatenate([_world_corners(p) for p in placed])
    return w.min(0), w.max(0)


def build_scene(exp, shapes, dtype, placed: list[Placed] | None = None):
    """Build every object of a scene (``objects:``; or take them already ``placed``) and the
    scene's arrays (host). Returns (params, static, eye, info per object, primitives in all)."""
    eye = np.asarray(exp.camera.eye, np.float64)
    placed = place_objects(exp, shapes, dtype) if placed is None else placed
    params, static, info = assemble(exp, placed, eye, dtype)
    return params, static, eye, info, int(sum(i["primitives"] for i in info))


def build_single(exp, obj, dtype):
    """A single object (``object:``) as a scene of one: identity transform, the default
    material (colour 1, the shading section's specular and shininess, no reflection or
    refraction) or the one its section asks for (``Representation.own_material``: a cell
    object's reflection mode), rays relative to its anchor. Returns (params, static, built)."""
    from ..config import MaterialConfig

    rep = registry.get(obj.type)
    own = rep.own_material(obj)
    with progress.notice_after(BUILD_NOTICE_S, f"building the object ({obj.type})"):
        built = rep.build(obj, dtype)
    mat = MaterialConfig() if own is None else MaterialConfig(reflectivity=own.reflectivity, transparency=own.transparency, ior=own.ior)
    p = Placed("object", rep, built, 1.0, np.eye(3), np.zeros(3), mat)
    params, static, _ = assemble(exp, [p], built.anchor, dtype, single=True, own=own)
    return params, static, built


__all__ = ["Effects", "Materials", "Placed", "SceneParams", "SceneStatic", "XForm", "assemble", "build_scene", "build_single",
           "effects_of", "object_transform", "place_objects", "shadow_lights", "world_bounds"]
