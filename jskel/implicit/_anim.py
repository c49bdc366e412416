"""Bones and forward kinematics (Rouiller 2011, Sec. 5), on the host in float64.

A bone has a rest ``head`` and ``tail`` (world), an optional parent and rotation keyframes
(XYZ Euler degrees about its head, in its parent's frame; linear in the angles between keys,
held constant outside them). The rest pose has every bone unrotated, so the rest world transform
of bone b is the translation to its head. At frame f,

    W_b(f) = W_parent(f) . T(head_b - head_parent) . R_b(f),   W_root(f) = T(head_root) . R_root(f),

and a point attached to b moves by the rigid motion M_b(f) = W_b(f) . T(-head_b). Both of the
thesis' work-flows are supported: primitives sculpted first and attached to bones by name
(Fig. 8), and bones that are themselves metatubes from head to tail (Fig. 9).

Positions are recomputed per frame on the host and passed as traced arrays, so an animation
compiles once.
"""

from __future__ import annotations

import numpy as np

from ..numerics import euler_xyz as euler_xyz


def key_angles(keys, frame: float) -> np.ndarray:
    """Euler angles at ``frame`` from (frame, angles) keys, linear between keys."""
    if not keys:
        return np.zeros(3)
    fr = np.array([k[0] for k in keys], np.float64)
    an = np.array([k[1] for k in keys], np.float64)
    order = np.argsort(fr)
    fr, an = fr[order], an[order]
    return np.array([np.interp(frame, fr, an[:, i]) for i in range(3)])


def bone_order(names: list[str], parents: list[str | None], path: str = "object.bones") -> list[int]:
    """Topological order of bones; ValueError naming an unknown parent or a cycle."""
    index = {n: i for i, n in enumerate(names)}
    if len(index) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"{path}: bone name {dup!r} is used twice")
    par = []
    for i, p in enumerate(parents):
        if p is not None and p not in index:
            raise ValueError(f"{path}[{i}].parent: unknown bone {p!r}")
        par.append(-1 if p is None else index[p])
    order, state = [], [0] * len(names)

    def visit(i, stack):
        if state[i] == 2:
            return
        if state[i] == 1:
            raise ValueError(f"{path}[{i}].parent: bone parents make a cycle ({' -> '.join(names[j] for j in stack + [i])})")
        state[i] = 1
        if par[i] >= 0:
            visit(par[i], stack + [i])
        state[i] = 2
        order.append(i)

    for i in range(len(names)):
        visit(i, [])
    return order


def pose(heads: np.ndarray, parents: list[int], order: list[int], keys: list, frame: float) -> np.ndarray:
    """(B, 4, 4) skinning matrices M_b(frame) = W_b(frame) . T(-head_b)."""
    nb = heads.shape[0]
    world = np.zeros((nb, 4, 4))
    for b in order:  # host loop over bones (tens), once per frame
        local = np.eye(4)
        local[:3, :3] = euler_xyz(key_angles(keys[b], frame))
        p = parents[b]
        local[:3, 3] = heads[b] - (heads[p] if p >= 0 else 0.0)
        world[b] = (world[p] if p >= 0 else np.eye(4)) @ local
    back = np.tile(np.eye(4), (nb, 1, 1))
    back[:, :3, 3] = -heads
    return world @ back


def apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Apply (4,4) matrices (N,4,4) or one (4,4) to points (N,3)."""
    return np.einsum("...ij,...j->...i", m[..., :3, :3], x) + m[..., :3, 3]
