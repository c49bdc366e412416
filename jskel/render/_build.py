"""What the integrator (``render/_scene.py``) traces, assembled on the host from the one
experiment value (``config.Experiment``): its objects with their transforms and materials.

Every object is built by its representation (:func:`place_objects`), placed by a transform
(float64 offsets between the rays' frame and the frame its params are stored in) and given a
material (:func:`assemble`); which effects exist is decided here, statically, from what the
experiment asks for (:class:`Effects`).

The rays' frame. A scene of several objects has its rays relative to the camera's eye
(camera-relative rendering); a scene of one, relative to its object's anchor placed in the
world. An object at its own anchor (a file's ``object:`` section: no transform) then has
offsets of exactly zero, so a primary ray reaches it, and its hit comes back, as the very floats
the representation gives (``SceneStatic.identity``: the transform is skipped).
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
    identity: tuple = ()  # per object: its placement is exactly the identity in the rays' frame (skipped);
    # static, so a scene of one turned or scaled away from it compiles once more (moving it does not: its rays follow its anchor)
    sky: bool = False  # a scene of one whose object carries its own environment: misses see it
    paths: tuple = ()  # per object: its key path as the file wrote it (``object``, ``objects[i]``), for messages


class Placed(NamedTuple):
    """One object ready to assemble: its key path, name, representation, build, transform,
    material and the material of its own it asks for (``interface.OwnMaterial``; None)."""

    at: str
    name: str
    rep: object
    built: object
    scale: float
    rotation: np.ndarray  # (3, 3) float64
    translate: np.ndarray  # (3,) float64
    material: object  # config.MaterialConfig
    own: object = None


def shadow_lights(exp) -> np.ndarray:
    """(L,) bool: which lights cast shadows (each light's ``shadows``; a file's ``object:``
    section sets it false where the light's section did not set it, ``ExperimentFile.experiment``)."""
    return np.array([l.shadows for l in exp.lights] or [False])


def effects_of(exp, placed: list[Placed]) -> Effects:
    """The effects an experiment calls for (host, static): reflection where a material has
    ``reflectivity > 0``, refraction where one has ``transparency > 0`` (an object's own
    material, a cell object's mode, counts as its material), shadows where a light of non-zero
    intensity casts them, bounces only with reflection or refraction (an own material's)."""
    mats = [p.material for p in placed]
    refl = any(m.reflectivity > 0 for m in mats)
    refr = any(m.transparency > 0 for m in mats)
    shadows = any(bool(c) and l.intensity > 0 for c, l in zip(shadow_lights(exp), exp.lights))
    own = [p.own for p in placed if p.own is not None]
    bounces = own[0].bounces if own else exp.render.bounces
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


def _check_shape(i: int, o, shape, rep, alone: bool):
    """Host checks of what a representation can do in a scene (interface flags, not types);
    returns the material of its own the shape asks for (``Representation.own_material``)."""
    if o.material.transparency > 0 and not rep.exits_from_inside(shape):
        raise ValueError(
            f"objects[{i}].material.transparency: {o.material.transparency} on a {shape.type} object, whose tracer "
            "searches for the first entry only (a transparent object must report the exit of a ray from inside: plain frusta do)")
    own = rep.own_material(shape)
    if own is not None and not alone:
        raise ValueError(
            f"objects[{i}].shape.{own.asked_by}; in a scene an object is shaded by its material "
            "(material.reflectivity / transparency), not by effects of its own: give mode: first_hit")
    if own is not None and o.material != type(o.material)():
        raise ValueError(f"objects[{i}].material: set on an object shaded by effects of its own (shape.{own.asked_by}): "
                         "leave the material unset, or give mode: first_hit")
    return own


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


def _is_identity(p: Placed, origin: np.ndarray) -> bool:
    """Whether the object's placement in the rays' frame is exactly the identity (scale 1, no
    rotation, zero offsets in float64): its rays and hits then skip the transform."""
    a = np.asarray(p.built.anchor, np.float64)
    c = p.rotation.T @ (origin - p.translate) / p.scale - a
    g = p.scale * (p.rotation @ a) + p.translate - origin
    return p.scale == 1.0 and np.array_equal(p.rotation, np.eye(3)) and not np.any(c) and not np.any(g)


def origin_of(exp, placed: list[Placed]) -> np.ndarray:
    """The point the rays are relative to (host, float64): a scene of one's object anchor placed
    in the world (its own anchor where it is not moved), else the camera's eye."""
    if len(placed) == 1:
        p = placed[0]
        return p.scale * (p.rotation @ np.asarray(p.built.anchor, np.float64)) + p.translate
    return np.asarray(exp.camera.eye, np.float64)


def _offset(p: Placed) -> float:
    """World distance a secondary ray starts off the object's surface (``Built.secondary_offset``,
    by default four times its surface tolerance)."""
    off = p.built.secondary_offset
    return p.scale * (4.0 * p.built.surface_tolerance if off is None else off)


def assemble(exp, placed: list[Placed], dtype):
    """Scene arrays of placed objects, rays relative to :func:`origin_of` (host). Returns
    (params, static, origin, info per object)."""
    origin = origin_of(exp, placed)
    mats = [p.material for p in placed]
    sh = exp.shading
    cols = [m.color for m in mats]
    spec = [sh.specular if m.specular is None else m.specular for m in mats]
    shin = [sh.shininess if m.shininess is None else m.shininess for m in mats]
    off = [_offset(p) for p in placed]
    ends = [[float(p.own is not None and getattr(p.own, f)) for p in placed] for f in ("last_local", "last_env", "local_once", "tint")]
    mat = Materials(*(on_device(np.asarray(v, np.float64), dtype) for v in (
        cols, spec, shin, [m.reflectivity for m in mats], [m.transparency for m in mats], [m.ior for m in mats], off, *ends)))
    bg = np.asarray(sh.background, np.float64)
    ev = exp.environment
    env = np.array([bg if v is None else v for v in (ev.zenith, ev.horizon, ev.ground)], np.float64)
    lights = lights_from_config(exp.lights, dtype, origin=origin)
    params = SceneParams(tuple(p.built.params for p in placed), tuple(_xform(p, origin, dtype) for p in placed), mat, lights,
                         on_device(shadow_lights(exp)), on_device(sh.ambient, dtype), on_device(env, dtype))
    sky = len(placed) == 1 and placed[0].rep.own_environment and ev == type(ev)()
    static = SceneStatic(tuple(p.rep.name for p in placed), tuple(p.built.static for p in placed), effects_of(exp, placed),
                         int(exp.render.lanes), bool(exp.render.compaction), tuple(_is_identity(p, origin) for p in placed),
                         bool(sky), tuple(p.at for p in placed))
    info = [{"name": p.name, "type": p.rep.name, "primitives": p.built.primitives, **p.built.info} for p in placed]
    return params, static, origin, info


#: a build says what it is building (``jskel.progress.notice_after``) once it has taken this
#: long: a large skeleton, mesh or cell precompute; the fractions of a second most take say nothing
BUILD_NOTICE_S = 1.0


def place_objects(exp, dtype) -> list[Placed]:
    """Build every object of the experiment and place it (host); an object whose shape asks for
    a material of its own (a cell object's reflection or refraction mode, alone in its scene)
    gets it as its material."""
    from ..config import MaterialConfig

    placed, n = [], len(exp.objects)
    for i, o in enumerate(exp.objects):
        shape = o.shape
        rep = registry.get(shape.type)
        own = _check_shape(i, o, shape, rep, n == 1)
        name = o.name or o.at(i)
        what = f"building {name} ({shape.type}, {i + 1} of {n})" if n > 1 else f"building the object ({shape.type})"
        with progress.notice_after(BUILD_NOTICE_S, what):
            built = rep.build(_shape_at(shape, rep, exp.frame), dtype)
        s, r, t = object_transform(o, exp.frame)
        mat = o.material if own is None else MaterialConfig(reflectivity=own.reflectivity, transparency=own.transparency, ior=own.ior)
        placed.append(Placed(o.at(i), name, rep, built, s, r, t, mat, own))
    return placed


def world_bounds(placed: list[Placed]):
    """(lo, hi) float64: the world box around every placed object's transformed bounds."""
    w = np.concatenate([_world_corners(p) for p in placed])
    return w.min(0), w.max(0)


def build_scene(exp, dtype, placed: list[Placed] | None = None):
    """Build every object of the experiment (or take them already ``placed``) and the scene's
    arrays (host). Returns (params, static, origin, info per object, primitives in all)."""
    placed = place_objects(exp, dtype) if placed is None else placed
    params, static, origin, info = assemble(exp, placed, dtype)
    return params, static, origin, info, int(sum(i["primitives"] for i in info))


__all__ = ["Effects", "Materials", "Placed", "SceneParams", "SceneStatic", "XForm", "assemble", "build_scene",
           "effects_of", "object_transform", "origin_of", "place_objects", "shadow_lights", "world_bounds"]
