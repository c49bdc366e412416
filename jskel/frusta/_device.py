"""Frusta rebuilt on the device, in JAX, from new joint positions (issue 6: animated frames).

``_build.build_frusta`` makes the frusta on the host in float64; an animation then pays a host
build and a copy every frame. For a skeleton whose topology stays fixed (the same parents, and
the same child continuing each joint), :func:`rebuilder` recomputes every frame-dependent field
in one jitted function of (joints, radii): ``_geometry.frusta_fields``, the same function the
host build runs in float64 (the medial cutting planes of Eq. 3-5, Sec. 2.2, the caps, the
u-aligned frames and twist of Sec. 2.3), here in the working dtype (float32 by default), then
the BVH of ``_accel``. Fields agree with the host build within float rounding; the continuation
choice and the side branches come from the template's topology (``frusta.topology`` on its
joints) and are not re-decided per frame.

Not covered (``rebuild`` raises ValueError): relief segments (their groups need the shell split
and block spheres of the host build) and ``match_minor_axes`` (an iteration per joint level).
Because every step is a JAX function of the joints, derivatives of a render with respect to the
joint positions flow through the planes and frames (``jax.grad`` of a hit's t; tested).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ._accel import build_bvh
from ._geometry import PIECE_REACH, SegmentTopology, frusta_fields, padded_topology
from ._intersect import FrustaParams


def params_from(fields: dict, template: FrustaParams) -> FrustaParams:
    """``FrustaParams`` with the template's padding rows, ids and shell, and the new fields on its rows."""
    v = template.valid
    out = {}
    for name, x in fields.items():
        old = getattr(template, name)
        x = x.astype(old.dtype)
        out[name] = jnp.where(v.reshape(v.shape + (1,) * (x.ndim - 1)), x, old)
    return template._replace(**out)


def _core(joints, radii, twist_turns, topo: SegmentTopology, template: FrustaParams, leaf: int, levels: int):
    fields, _ = frusta_fields(joints.astype(template.h.dtype), radii.astype(template.h.dtype), topo,
                           jnp.asarray(twist_turns, template.h.dtype), levels)
    params = params_from(fields, template)
    return params, build_bvh(params, leaf)


_core_jit = jax.jit(_core, static_argnums=(5, 6))


def rebuilder(cfg, dtype=np.float32):
    """``(joints, radii) -> Built`` for new world joint positions (J, 3) and radii (J,) of the
    skeleton of ``cfg`` (same parents): the first call's host build is the template (its
    topology, anchor, colours, padding and static options); every call after rebuilds the plain
    segments' fields and BVH on the device (:func:`frusta_fields`, one jitted function). The
    joints are validated on the host (NaN, negative radii, zero-length segments: ValueError).
    For joints and radii that are JAX values (traced, or kept on the device), ``fn.params``
    rebuilds the params alone, unchecked, and ``fn.checked`` the same with ``checkify``
    checks naming a bad joint, radius or segment (:func:`_traced_rebuild`)."""
    from ._config import array_problems
    from ._edits import host_frusta
    from ._pack import Group
    from ._scene import build
    from ._skeleton import validate_skeleton

    if cfg.relief is not None or cfg.match_minor_axes:
        raise ValueError("object: a device rebuild covers plain segments without match_minor_axes (relief or match_minor_axes given)")
    tpl = build(cfg, dtype)
    if tpl.static.accel != "bvh":
        raise ValueError(f"object.accel: a device rebuild needs the BVH ({tpl.static.accel!r} resolved)")
    _, topo, _, j0, _, _ = host_frusta(cfg)
    parents = np.full(j0.shape[0], -1, np.int64)
    parents[topo.seg_end] = topo.seg_start
    g = tpl.params.plain
    dtopo = padded_topology(topo, g.frusta.h.shape[0])
    levels = int(topo.depth.max()) + 1
    twist = cfg.twist_deg / 360.0

    def fn(joints, radii):
        checks.raise_all([f"object.skeleton.{x}" for x in array_problems(joints, radii, parents)])  # every bad joint at once
        j, r, _ = validate_skeleton(joints, radii, parents)
        rel = j - tpl.anchor[None, :]
        params, bvh = _core_jit(jnp.asarray(rel, g.frusta.h.dtype), jnp.asarray(r, g.frusta.h.dtype), twist, dtopo,
                                g.frusta, tpl.static.leaf, levels)
        rmax = PIECE_REACH * r[:, None]  # every piece lies within PIECE_REACH radii of its segment
        scene = tpl.params._replace(plain=Group(params, g.block_c, g.block_r, bvh))
        return dataclasses.replace(tpl, params=scene, bounds=(np.min(j - rmax, 0), np.max(j + rmax, 0)))

    fn.params, fn.checked = _traced_rebuild(tpl, topo, dtopo, twist, levels)
    return fn


def _traced_rebuild(tpl, topo, dtopo, twist, levels):
    """The rebuild's device part for traced joints and radii, unchecked and checked:

    * ``params(joints, radii) -> FrustaScene``: world joints (J, 3) and radii (J,) as JAX
      values (under ``jit``, ``grad``, an optimiser's loop), the anchor subtracted in the
      working dtype; nothing is validated (a NaN gives NaN fields);
    * ``checked(joints, radii) -> FrustaScene``: the same compiled with ``checkify`` checks
      (joints finite, radii finite and not negative, every segment longer than 0, by its end
      joint): one ValueError with a line per failing field naming the index and the value, e.g.
      ``object.skeleton.radii[3]: not finite (got nan); 1 of 12 entries`` (``jskel.checks.checked``)."""
    from ._pack import Group

    g, dtype = tpl.params.plain, tpl.params.plain.frusta.h.dtype
    anchor = jnp.asarray(tpl.anchor, dtype)

    def params(joints, radii):
        p, bvh = _core(jnp.asarray(joints, dtype) - anchor, jnp.asarray(radii, dtype), twist, dtopo, g.frusta, tpl.static.leaf, levels)
        return tpl.params._replace(plain=Group(p, g.block_c, g.block_r, bvh))

    def _problems(joints, radii):
        length = jnp.sqrt(jnp.sum((joints[topo.seg_end] - joints[topo.seg_start]) ** 2, axis=1))
        return (checks.traced("object.skeleton.joints", joints) + checks.traced("object.skeleton.radii", radii, "nonnegative")
                + checks.traced("object.skeleton.segment_length", length, "positive", ids=topo.seg_end))

    compiled = checks.checked(params, _problems)

    def checked(joints, radii):
        return compiled(jnp.asarray(joints, dtype), jnp.asarray(radii, dtype))

    checked.program = compiled.program
    return params, checked
