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

from .. import checks
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
    """Topological order of bones (every bone after its parent); one ValueError
    (``jskel.config.ConfigError``) naming every name used twice, every unknown parent and every
    cycle of the parents (each by its bones, from its lowest index)."""
    index: dict[str, int] = {}
    for i, n in enumerate(names):
        index.setdefault(n, i)
    lines = [f"{path}: bone name {n!r} is used twice" for n in index if names.count(n) > 1]
    lines += [f"{path}[{i}].parent: unknown bone {p!r}" for i, p in enumerate(parents) if p is not None and p not in index]
    par = [index.get(p, -1) if p is not None else -1 for p in parents]  # an unknown parent: named above, a root here
    order, cycles, state = [], [], [0] * len(names)  # state: 0 unseen, 1 on this walk, 2 placed
    for s in range(len(names)):  # host loop over bones (tens): walk up to a placed bone or a root
        walk, k = [], s
        while k >= 0 and state[k] == 0:
            state[k] = 1
            walk.append(k)
            k = par[k]
        if k >= 0 and state[k] == 1:  # the walk met itself
            cyc = walk[walk.index(k):]
            low = cyc.index(min(cyc))
            cycles.append(cyc[low:] + cyc[:low])
        for j in reversed(walk):
            state[j] = 2
            order.append(j)
    checks.raise_all(lines + [f"{path}[{c[0]}].parent: bone parents make a cycle ({' -> '.join(names[j] for j in c + c[:1])})" for c in cycles])
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
