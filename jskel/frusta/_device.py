"""Frusta rebuilt on the device, in JAX, from new joint positions (issue 6: animated frames).

``_build.build_frusta`` makes the frusta on the host in float64 NumPy; an animation then pays a
host build and a copy every frame. For a skeleton whose topology stays fixed (the same parents,
and the same child continuing each joint), :func:`rebuild` recomputes every frame-dependent
field in one jitted function of (joints, radii): the medial cutting planes of Eq. 3-5 (Sec. 2.2,
with the same collinear, parallel-side-line and elliptic-cut fallbacks as
``_build.cutting_planes``), the caps, the u-aligned frames of Sec. 2.3 (parent by parent, one
depth level per step of a ``fori_loop``), the twist offsets, and the BVH of ``_accel``. The
arithmetic is the host's in the working dtype (float32 by default), so fields agree with the
host build within float rounding; the continuation choice and the side branches come from the
template's topology (``frusta.topology`` on its joints) and are not re-decided per frame.

Not covered (``rebuild`` raises ValueError): relief segments (their groups need the shell split
and block spheres of the host build) and ``match_minor_axes`` (an iteration per joint level).
Because every step is a JAX function of the joints, derivatives of a render with respect to the
joint positions flow through the planes and frames (``jax.grad`` of a hit's t; tested).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import dot3, norm3, safe_div, safe_norm, safe_sqrt
from ._accel import build_bvh
from ._build import _COLLINEAR_SIN, ELLIPSE_MARGIN
from ._intersect import FrustaParams


class DeviceTopology(NamedTuple):
    """A template's topology as device int arrays, padded to the template's padded length."""

    start: jnp.ndarray  # (N,) base joint of each segment row (0 for padding)
    end: jnp.ndarray  # (N,) top joint
    parent: jnp.ndarray  # (N,) row this one continues, -1 (root or side branch, or padding)
    branch: jnp.ndarray  # (N,) row ending at the base joint, -1 at roots
    depth: jnp.ndarray  # (N,) depth level (-1 for padding)
    valid: jnp.ndarray  # (N,) bool


def _unit(v):
    return safe_div(v, safe_norm(v, keepdims=True), 0.0)


def _any_perp(m):
    ax = jnp.eye(3, dtype=m.dtype)[jnp.argmin(jnp.abs(m), axis=-1)]
    return _unit(ax - dot3(ax, m)[..., None] * m)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _cuts_ellipse(n, m, r0, r1, h):
    k = safe_div(r1 - r0, h, 0.0)
    return jnp.abs(dot3(n, m)) > jnp.abs(k) / jnp.sqrt(1.0 + k * k) + ELLIPSE_MARGIN


def cutting_planes(j, ma, ca, ra0, ra1, ha, mb, rb0, rb1, hb):
    """``_build.cutting_planes`` in JAX (Eq. 3-5 at K joints, vectorised; the same construction,
    fallbacks and orientation): unit normals ``n`` (K,3) with n . (ma + mb) > 0 and points ``p``
    (K,3) on them. Differentiable (``numerics.safe_*``); the fit's distances use it too."""
    cr = jnp.cross(ma, mb)
    sin = safe_norm(cr)
    collinear = sin < _COLLINEAR_SIN
    nm = jnp.where(collinear[:, None], _any_perp(ma), safe_div(cr, sin[:, None], 0.0))
    e1 = ma
    e2 = jnp.cross(nm, ma)
    da = jnp.stack([jnp.ones_like(sin), jnp.zeros_like(sin)], -1)
    db = jnp.stack([dot3(mb, e1), dot3(mb, e2)], -1)
    ca2 = jnp.stack([dot3(ca - j, e1), dot3(ca - j, e2)], -1)
    cb2 = db * hb[:, None]

    def side(d):
        return jnp.stack([d[:, 1], -d[:, 0]], -1)

    sa, sb = side(da), side(db)
    zero = jnp.zeros_like(ca2)

    def meet(sign):
        l1 = ca2 - sign * ra0[:, None] * sa
        l2 = zero - sign * ra1[:, None] * sa
        l3 = zero - sign * rb0[:, None] * sb
        l4 = cb2 - sign * rb1[:, None] * sb
        d1, d2 = l2 - l1, l4 - l3
        den = _cross2(d1, d2)
        scale = safe_norm(d1) * safe_norm(d2)
        ok = jnp.abs(den) > 1e-9 * scale
        s = safe_div(_cross2(l3 - l1, d2), jnp.where(ok, den, 0.0), 0.0)
        return l1 + s[:, None] * d1, ok

    a2, oka = meet(1.0)
    b2, okb = meet(-1.0)
    ab = a2 - b2
    ab3 = ab[:, :1] * e1 + ab[:, 1:] * e2
    n = _unit(jnp.cross(ab3, nm))
    p = j + a2[:, :1] * e1 + a2[:, 1:] * e2
    bis = _unit(ma + mb)
    fallback = ~(oka & okb) & ~collinear
    fallback |= ~collinear & ~(_cuts_ellipse(n, ma, ra0, ra1, ha) & _cuts_ellipse(n, mb, rb0, rb1, hb))
    n = jnp.where(fallback[:, None], bis, n)
    p = jnp.where(fallback[:, None], j, p)
    n = jnp.where(collinear[:, None], ma, n)
    p = jnp.where(collinear[:, None], j, p)
    n = n * jnp.where(dot3(n, ma + mb) < 0, -1.0, 1.0)[:, None]
    return n, p


def device_topology(topo, n: int) -> DeviceTopology:
    """The host ``Topology`` as padded device arrays of length ``n`` (the padded segment count)."""
    s = topo.seg_start.shape[0]

    def pad(a, fill):
        a = np.asarray(a, np.int32)
        return jnp.asarray(np.concatenate([a, np.full(n - s, fill, np.int32)]))

    return DeviceTopology(pad(topo.seg_start, 0), pad(topo.seg_end, 1), pad(topo.parent_seg, -1),
                          pad(topo.branch_parent, -1), pad(topo.depth, -1), jnp.asarray(np.arange(n) < s))


def frusta_fields(joints, radii, topo: DeviceTopology, twist_turns, levels: int):
    """Every field of ``FrustaParams`` but ``sid`` and ``shell`` (rows in the template's order;
    padding rows are placeholders that no ray hits), from (J, 3) joints relative to the anchor."""
    v = topo.valid
    c1 = joints[topo.start]
    c2 = joints[topo.end]
    seg = c2 - c1
    h = safe_sqrt(dot3(seg, seg))
    m = jnp.where(v[:, None], safe_div(seg, h[:, None], 0.0), jnp.array([0.0, 1.0, 0.0], joints.dtype))
    h = jnp.where(v, h, 1.0)
    r1 = jnp.where(v, radii[topo.start], 0.0)
    r2 = jnp.where(v, radii[topo.end], 0.0)
    # cutting planes at every continued joint, all at once (they depend on the joints only)
    cont = topo.parent >= 0
    a = jnp.maximum(topo.parent, 0)
    n, p = cutting_planes(c1, m[a], c1[a], r1[a], r2[a], h[a], m, r1, r2, h)
    nb = jnp.where(cont[:, None], n, m)
    db = jnp.where(cont, dot3(n, p - c1), 0.0)
    cap_b = ~cont
    # the top of a segment is cut by its continuation's plane (scatter from the child row)
    tgt = jnp.where(cont, topo.parent, h.shape[0])  # out of range: dropped
    nt = m.at[tgt].set(n, mode="drop")
    has_child = jnp.zeros(h.shape, bool).at[tgt].set(True, mode="drop")
    dt = jnp.where(has_child, dot3(nt, jnp.zeros_like(c1).at[tgt].set(p, mode="drop") - c1), h)
    cap_t = ~has_child

    # frames in depth order (Sec. 2.3): roots take +z projected, side branches parallel-transport
    # the frame of the segment they grow from, continuations pass through Q
    twist = jnp.full(h.shape, twist_turns, joints.dtype)
    k = safe_div(r2 - r1, h, 0.0)

    def level(lvl, st):
        w, u_off, v_off = st
        at = topo.depth == lvl
        bp = jnp.maximum(topo.branch, 0)
        ref = jnp.where((topo.branch >= 0)[:, None], w[bp], jnp.array([0.0, 0.0, 1.0], joints.dtype))
        wr = ref - dot3(ref, m)[:, None] * m
        nrm = safe_sqrt(dot3(wr, wr))
        wr = jnp.where((nrm > 1e-6)[:, None], safe_div(wr, jnp.where(nrm > 1e-6, nrm, 1.0)[:, None], 0.0), _any_perp(m))
        base = c1[a] + r1[a][:, None] * w[a]
        dirn = m[a] + k[a][:, None] * w[a]
        den = dot3(nt[a], dirn)
        y = safe_div(dt[a] - dot3(nt[a], base - c1[a]), den, 0.0)
        q = base + y[:, None] * dirn
        wq = q - c1
        wq = wq - dot3(wq, m)[:, None] * m
        nq = safe_sqrt(dot3(wq, wq))
        good = cont & (nq > 1e-9 * (h + r1)) & (den != 0)
        wc = jnp.where(good[:, None], safe_div(wq, nq[:, None], 0.0), wr)
        w_new = jnp.where(cont[:, None], wc, wr)
        w = jnp.where(at[:, None], w_new, w)
        u_off = jnp.where(at & cont, u_off[a] + twist[a], u_off)
        v_off = jnp.where(at & cont, v_off[a] + 1.0, v_off)
        return w, u_off, v_off

    zeros = jnp.zeros(h.shape, joints.dtype)
    w0 = jnp.zeros_like(c1).at[:, 2].set(1.0)
    w, u_off, v_off = jax.lax.fori_loop(0, levels, level, (w0, zeros, zeros))
    u = jnp.cross(m, w)
    return dict(c1=c1, m=m, u=u, w=w, h=h, r1=r1, r2=r2, nb=nb, db=db, nt=nt, dt=dt, cap_b=cap_b, cap_t=cap_t,
                u_off=jnp.mod(u_off, 1.0), twist=twist, v_off=v_off)


def params_from(fields: dict, template: FrustaParams) -> FrustaParams:
    """``FrustaParams`` with the template's padding rows, ids and shell, and the new fields on its rows."""
    v = template.valid
    out = {}
    for name, x in fields.items():
        old = getattr(template, name)
        x = x.astype(old.dtype)
        out[name] = jnp.where(v.reshape(v.shape + (1,) * (x.ndim - 1)), x, old)
    return template._replace(**out)


def _core(joints, radii, twist_turns, topo: DeviceTopology, template: FrustaParams, leaf: int, levels: int):
    fields = frusta_fields(joints.astype(template.h.dtype), radii.astype(template.h.dtype), topo,
                           jnp.asarray(twist_turns, template.h.dtype), levels)
    params = params_from(fields, template)
    return params, build_bvh(params, leaf)


_core_jit = jax.jit(_core, static_argnums=(5, 6))


def rebuilder(cfg, dtype=np.float32):
    """``(joints, radii) -> Built`` for new world joint positions (J, 3) and radii (J,) of the
    skeleton of ``cfg`` (same parents): the first call's host build is the template (its
    topology, anchor, colours, padding and static options); every call after rebuilds the plain
    segments' fields and BVH on the device (:func:`frusta_fields`, one jitted function). The
    joints are validated on the host (NaN, negative radii, zero-length segments: ValueError)."""
    from ._scene import Group, build, host_frusta
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
    dtopo = device_topology(topo, g.frusta.h.shape[0])
    levels = int(topo.depth.max()) + 1
    twist = cfg.twist_deg / 360.0

    def fn(joints, radii):
        j, r, _ = validate_skeleton(joints, radii, parents)
        rel = j - tpl.anchor[None, :]
        params, bvh = _core_jit(jnp.asarray(rel, g.frusta.h.dtype), jnp.asarray(r, g.frusta.h.dtype), twist, dtopo,
                                g.frusta, tpl.static.leaf, levels)
        rmax = r[:, None]
        scene = tpl.params._replace(plain=Group(params, g.block_c, g.block_r, bvh))
        return dataclasses.replace(tpl, params=scene, bounds=(np.min(j - rmax, 0), np.max(j + rmax, 0)))

    return fn
