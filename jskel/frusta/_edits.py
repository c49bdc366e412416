"""The skeleton of a frusta object section (explicit, procedural at an animation frame, or a
file read and repaired by ``jskel.skeletons``) with its edits (``scale``, ``offset``, ``subdivide``, ``replicate``), and its frusta on the host."""

from __future__ import annotations

import numpy as np

from .. import checks, skeletons
from ..config import ConfigError
from ._build import build_frusta
from ._config import FrustaConfig, SkeletonConfig, array_problems
from ._skeleton import topology, validate_skeleton

_SIDE_BRANCH_COLOR_PATH = "object.skeleton.colors"
_FILE_PATH = "object.skeleton.file"


def frusta_from_skeleton(joints, radii, parents, *, twist_deg=0.0, match_minor_axes=False, path="object.skeleton"):
    """Validate a skeleton and build its frusta on the host (float64). Returns (arrays, topo, info)."""
    checks.raise_all([f"{path}.{line}" for line in array_problems(joints, radii, parents)])  # every value problem at once
    j, r, p = validate_skeleton(joints, radii, parents, path)
    topo = topology(j, p, path)
    arrays, info = build_frusta(j, r, topo, twist_turns=twist_deg / 360.0, match_minor_axes=match_minor_axes)
    return arrays, topo, info


ANIMATED = ("dancing_cacti",)


def file_arrays(sk: SkeletonConfig):
    """(joints, radii, parents, colours or None, repairs) of a skeleton ``file``: read, repaired
    by ``sk.repair`` (``jskel.skeletons.load``), coloured by SWC type where it has types and no
    ``colors`` are given; ``repairs`` is the policy and the repair report, for ``run.json``."""
    policy = sk.repair if sk.repair is not None else skeletons.RepairPolicy()
    s, report = skeletons.load(sk.file, sk.format, policy, _FILE_PATH)
    try:  # what repair leaves for the build to reject, named by the file's node ids and lines
        j, _, p = validate_skeleton(s.joints, s.radii, s.parents, "object.skeleton")
        topology(j, p, "object.skeleton")
    except ValueError as e:  # each problem (a ConfigError's lines) named on its own
        lines = [skeletons.name_nodes(x, s, "object.skeleton", _FILE_PATH) for x in getattr(e, "lines", [str(e)])]
        raise ConfigError(lines) from None
    colors = None
    if sk.colors is not None:
        colors = np.asarray(sk.colors, np.float64)
    elif np.any(s.labels != 0):
        colors = skeletons.label_colors(s.labels)
    repairs = {"file": str(sk.file), "policy": policy.model_dump(), "default_policy": sk.repair is None, **report}
    return s.joints, s.radii, s.parents, colors, repairs


def skeleton_arrays(sk: SkeletonConfig, frame: float = 0.0):
    """(joints (J, 3), radii (J,), parents (J,), colours (J, 3) or None) of a skeleton section at
    animation ``frame``: the explicit arrays, the procedural generator's or a file's, with
    ``scale``, ``offset``, ``subdivide`` and ``replicate`` applied (float64, world units)."""
    return skeleton_and_repairs(sk, frame)[:4]


def skeleton_and_repairs(sk: SkeletonConfig, frame: float = 0.0):
    """``skeleton_arrays`` and the repairs of a ``file`` source (None for the others)."""
    repairs = None
    if sk.file is not None:
        j, r, p, colors, repairs = file_arrays(sk)
        if colors is not None and colors.shape[0] != j.shape[0]:
            raise ValueError(f"{_SIDE_BRANCH_COLOR_PATH}: has {colors.shape[0]} entries for {j.shape[0]} joints (after repair)")
    elif sk.procedural is not None:
        from ..scenes import generate

        opts = dict(sk.options)
        if sk.procedural in ANIMATED:
            opts.setdefault("frame", frame)
        j, r, p, colors = generate(sk.procedural, sk.seed, opts)
    else:
        j = np.asarray(sk.joints, np.float64)
        r = np.asarray(sk.radii, np.float64)
        p = np.asarray(sk.parents, np.int64)
        colors = None if sk.colors is None else np.asarray(sk.colors, np.float64)
        if colors is not None and colors.shape[0] != j.shape[0]:
            raise ValueError(f"{_SIDE_BRANCH_COLOR_PATH}: has {colors.shape[0]} entries for {j.shape[0]} joints")
    j = j * sk.scale + np.asarray(sk.offset, np.float64)
    r = r * sk.scale
    if sk.subdivide > 1:
        j, r, p, colors = subdivide_skeleton(j, r, p, colors, sk.subdivide)
    if sk.replicate > 1:
        j, r, p, colors = replicate_skeleton(j, r, p, colors, sk.replicate)
    return j, r, p, colors, repairs


def replicate_skeleton(joints, radii, parents, colors, k: int):
    """k x k copies of a skeleton, each scaled by 1/k about its box's (x, y) minimum corner and
    placed on a k x k grid over the original's x-y extent (z unchanged in the mean). Copy c has
    joints ``c * J .. (c + 1) * J - 1`` with its parents shifted by ``c * J``."""
    lo, hi = joints.min(0), joints.max(0)
    ext = hi - lo
    nj = joints.shape[0]
    cells = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2)  # (k^2, 2)
    shift = np.zeros((cells.shape[0], 3))
    shift[:, :2] = cells * ext[None, :2] / k
    centre_z = 0.5 * (lo[2] + hi[2])
    local = (joints - np.array([lo[0], lo[1], centre_z])) / k + np.array([lo[0], lo[1], centre_z])
    j = (local[None] + shift[:, None, :]).reshape(-1, 3)
    p = np.asarray(parents)
    pp = np.where(p[None, :] >= 0, p[None, :] + (np.arange(cells.shape[0]) * nj)[:, None], -1).reshape(-1)
    cols = None if colors is None else np.tile(colors, (cells.shape[0], 1))
    return j, np.tile(radii / k, cells.shape[0]), pp, cols


def subdivide_skeleton(joints, radii, parents, colors, n: int):
    """Every segment (parent -> child) split into ``n`` collinear pieces: n - 1 new joints on the
    segment, radii linearly interpolated, colours of the child. The original joints keep their
    indices; the new ones follow, ``n - 1`` per child joint in child order. Collinear joints get
    cutting planes perpendicular to the axis (Eq. 3-5's bisector), so the surface is unchanged."""
    p = np.asarray(parents)
    child = np.nonzero(p >= 0)[0]
    nj = joints.shape[0]
    if child.size == 0:
        return joints, radii, p, colors
    f = (np.arange(1, n) / n)[None, :]  # (1, n-1)
    a, b = joints[p[child]], joints[child]
    new_j = (a[:, None, :] + f[..., None] * (b - a)[:, None, :]).reshape(-1, 3)
    new_r = (radii[p[child], None] + f * (radii[child] - radii[p[child]])[:, None]).reshape(-1)
    ids = nj + np.arange(child.size * (n - 1)).reshape(child.size, n - 1)
    new_p = np.concatenate([p[child][:, None], ids[:, :-1]], axis=1).reshape(-1)
    out_p = p.copy()
    out_p[child] = ids[:, -1]
    cols = None if colors is None else np.concatenate([colors, np.repeat(colors[child], n - 1, axis=0)])
    return np.concatenate([joints, new_j]), np.concatenate([radii, new_r]), np.concatenate([out_p, new_p]), cols


def host_frusta(cfg: FrustaConfig):
    """World-space float64 frusta of an object config: (arrays, topo, info, joints, radii, colors)."""
    j, r, p, colors, repairs = skeleton_and_repairs(cfg.skeleton, cfg.frame)
    arrays, topo, info = frusta_from_skeleton(j, r, p, twist_deg=cfg.twist_deg, match_minor_axes=cfg.match_minor_axes)
    if repairs is not None:
        info = dict(info, repairs=repairs)
    return arrays, topo, info, j, r, colors
