"""The primitives of an implicit object section on the host (Rouiller 2011): a procedural or
rigged model expanded, balls, tubes and bone tubes posed at an animation frame (``_anim``)
and placed in world units, and the static CSG tree over their groups."""

from __future__ import annotations

import numpy as np

from ._config import ImplicitConfig
from ._field import Shape


def expand(cfg: ImplicitConfig) -> ImplicitConfig:
    """A procedural model with a rig becomes explicit balls, tubes and bones (validated)."""
    from ._models import RIGGED

    if cfg.procedural in RIGGED:
        extra = RIGGED[cfg.procedural](cfg.seed, dict(cfg.options))
        data = cfg.model_dump()
        data.update(procedural=None, **extra)
        return ImplicitConfig.model_validate(data)
    return cfg


def primitives(cfg: ImplicitConfig, frame: float | None = None):
    """Host float64 (a, b, ra, rb) in world units at ``frame`` (default ``cfg.frame``), plus the
    rig: (heads, tails, influence, M (B,4,4) posed-from-rest) or None without bones."""
    frame = cfg.frame if frame is None else frame
    if cfg.procedural is not None:
        from ._models import MODELS

        a, b, ra, rb = MODELS[cfg.procedural](cfg.seed, dict(cfg.options))
        groups = [("main", f"procedural[{i}]") for i in range(a.shape[0])]
        rig = None
    else:
        a, b, ra, rb, groups, rig = _explicit(cfg, frame)
    return _placed(cfg, a, b, ra, rb, rig) + (groups,)


def _explicit(cfg: ImplicitConfig, frame: float):
    """(a, b, ra, rb, groups, rig) of the balls, tubes and bone tubes of ``cfg`` in model units,
    those attached to bones posed at ``frame``; ``groups`` holds each one's (CSG group, config
    path). ValueError for an unknown bone or a primitive of two zero radii."""
    from ._anim import bone_order

    names = [bn.name for bn in cfg.bones]
    order = bone_order(names, [bn.parent for bn in cfg.bones])
    index = {n: i for i, n in enumerate(names)}
    items = [(bl.center, bl.center, bl.radius, bl.radius, bl.bone, f"balls[{i}]", bl.group) for i, bl in enumerate(cfg.balls)]
    items += [(t.a, t.b, t.radius_a, t.radius_b, t.bone, f"tubes[{i}]", t.group) for i, t in enumerate(cfg.tubes)]
    items += [(bn.head, bn.tail, bn.tube[0], bn.tube[1], bn.name, f"bones[{i}].tube", bn.group) for i, bn in enumerate(cfg.bones) if bn.tube is not None]
    for *_, bone, where, _g in items:
        if bone is not None and bone not in index:
            raise ValueError(f"object.{where}.bone: unknown bone {bone!r} (bones: {', '.join(names) or 'none'})")
    for i, (*_, where, _g) in enumerate(items):
        if items[i][2] == 0 and items[i][3] == 0:
            raise ValueError(f"object.{where}: both radii are 0")
    a = np.array([it[0] for it in items], np.float64).reshape(-1, 3)
    b = np.array([it[1] for it in items], np.float64).reshape(-1, 3)
    ra = np.array([it[2] for it in items], np.float64)
    rb = np.array([it[3] for it in items], np.float64)
    bone_of = np.array([-1 if it[4] is None else index[it[4]] for it in items], np.int64)
    groups = [(it[6], it[5]) for it in items]
    rig = _posed(cfg, index, order, bone_of, a, b, frame) if cfg.bones else None
    return a, b, ra, rb, groups, rig


def _posed(cfg: ImplicitConfig, index: dict, order, bone_of, a, b, frame: float):
    """Pose the bones at ``frame`` (Rouiller 2011, Sec. 5: keyed rotations down the hierarchy)
    and move the primitives attached to them (``a``, ``b`` in place, rows ``bone_of >= 0``).
    Returns the rig (posed heads, tails, influence radii, M (B,4,4) posed-from-rest)."""
    from ._anim import apply, pose

    heads = np.array([bn.head for bn in cfg.bones], np.float64)
    tails = np.array([bn.tail for bn in cfg.bones], np.float64)
    for i in range(len(cfg.bones)):
        if not np.linalg.norm(tails[i] - heads[i]) > 0:
            raise ValueError(f"object.bones[{i}].tail: equals its head (a bone needs a length)")
    parents = [-1 if bn.parent is None else index[bn.parent] for bn in cfg.bones]
    keys = [[(k.frame, k.rotate) for k in bn.keys] for bn in cfg.bones]
    M = pose(heads, parents, order, keys, frame)
    att = bone_of >= 0
    a[att] = apply(M[bone_of[att]], a[att])
    b[att] = apply(M[bone_of[att]], b[att])
    infl = np.array([bn.influence or 0.75 * np.linalg.norm(t - h) for bn, h, t in zip(cfg.bones, heads, tails)])
    return (apply(M, heads), apply(M, tails), infl, M)


def _placed(cfg: ImplicitConfig, a, b, ra, rb, rig):
    """(a, b, ra, rb, rig) scaled by ``cfg.scale`` and moved by ``cfg.offset``: the rig's rigid
    motions conjugated by that similarity, so they act on world-unit points."""
    off = np.asarray(cfg.offset, np.float64)
    a, b, ra, rb = a * cfg.scale + off, b * cfg.scale + off, ra * cfg.scale, rb * cfg.scale
    if rig is not None:
        S = np.eye(4) * cfg.scale
        S[3, 3] = 1.0
        S[:3, 3] = off
        Sinv = np.linalg.inv(S)
        M = S @ rig[3] @ Sinv  # the same rigid motions, in scaled world units
        rig = (rig[0] * cfg.scale + off, rig[1] * cfg.scale + off, rig[2] * cfg.scale, M)
    return a, b, ra, rb, rig


def csg_shape(cfg: ImplicitConfig, groups) -> tuple[Shape, np.ndarray]:
    """Static CSG tree over group indices, and each primitive's group index."""
    disp = "none" if cfg.displace is None else cfg.displace.type
    if cfg.csg is None:
        return Shape(("group", 0), 1, disp), np.zeros(len(groups), np.int32)
    names: list[str] = []

    def conv(node):
        if node.op == "group":
            if node.group not in names:
                names.append(node.group)
            return ("group", names.index(node.group))
        return (node.op, conv(node.children[0]), conv(node.children[1]))

    tree = conv(cfg.csg)
    gid = []
    for g, where in groups:
        if g not in names:
            raise ValueError(f"object.{where}.group: group {g!r} is not in object.csg (groups there: {', '.join(names)})")
        gid.append(names.index(g))
    return Shape(tree, len(names), disp), np.asarray(gid, np.int32)
