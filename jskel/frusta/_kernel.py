"""The frusta BVH walk as one Pallas kernel, for accelerators (issue 6).

Why a kernel: under ``vmap`` the per-ray walk (``accel.nearest``) is one XLA while loop over the
whole batch, and every iteration computes every lane, finished or not, and ends when the
batch's slowest ray does. On a GPU that costs far more than the walk itself, a few dozen node
visits per ray, and more still in smaller calls and CPU-sized groups (the palm's primary rays:
docs/choices.md#pallas-kernel). Here the same walk runs in a Pallas (Triton)
kernel: each program takes ``block`` consecutive rays (``block`` = 32 with one warp: a lane per
thread, so finished rays idle only until their warp's slowest ray ends), keeps node, bit trail
and best hit in registers, gathers a node's two child boxes and a leaf's packed segment rows
straight from global memory, and runs ``_segment_t`` (the analytic frustum test) unchanged on
per-component vectors (:class:`V3`).

The walk is :func:`jskel.accel.nearest`'s, step for step: the same near-child order, bit trail,
pruning against the best hit, and first-slot-wins ties, so on the CPU (``interpret``) the hits
equal :func:`jskel.frusta._accel.nearest_groups` bit for bit (tested). On a GPU the kernel is
compiled by Triton and XLA's loop by XLA; they may contract multiply-adds differently, so t can
differ in the last bits there (the benchmark reports the agreement it measured).

On a GPU it renders Table 1's scenes several times faster than XLA's walk over the whole
frame, with identical hits, and its cast is below Mitsuba's CUDA variant's
(``experiments/bench_scale_kernel.yaml``, ``bench_scale.yaml``; the figures, dated:
docs/choices.md#pallas-kernel).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..accel import descend
from ._accel import _PACKED, FrustaBVH, miss_is_inf, packed_widths
from ._intersect import SIDE, FrustaParams, _segment_t


class V3:
    """A 3-vector of equally shaped arrays (x, y, z), with the arithmetic ``_segment_t`` uses:
    ``v[..., i]`` is a component, + - * / broadcast, ``dtype`` is the components'. Keeps every
    array of the kernel one-dimensional (Triton wants power-of-two shapes; (B, 3) is not)."""

    __slots__ = ("c",)

    def __init__(self, x, y, z):
        self.c = (x, y, z)

    @property
    def dtype(self):
        return jnp.result_type(self.c[0])

    def __getitem__(self, idx):
        return self.c[idx[-1] if isinstance(idx, tuple) else idx]

    def _op(self, other, f):
        if isinstance(other, V3):
            return V3(*(f(a, b) for a, b in zip(self.c, other.c)))
        return V3(*(f(a, other) for a in self.c))

    def __add__(self, o):
        return self._op(o, lambda a, b: a + b)

    def __radd__(self, o):
        return self._op(o, lambda a, b: b + a)

    def __sub__(self, o):
        return self._op(o, lambda a, b: a - b)

    def __rsub__(self, o):
        return self._op(o, lambda a, b: b - a)

    def __mul__(self, o):
        return self._op(o, lambda a, b: a * b)

    def __rmul__(self, o):
        return self._op(o, lambda a, b: b * a)

    def __neg__(self):
        return V3(*(-a for a in self.c))


def pop(node, trail):
    """``accel._lbvh.pop`` with the trailing-zero count taken on int32 bits: Triton legalises
    a 32-bit population count only for signed integers (uint32 failed to compile)."""
    one = jnp.uint32(1)
    t = jnp.where(trail == 0, one, trail)
    z = jax.lax.population_count(jax.lax.bitcast_convert_type((t & (~t + one)) - one, jnp.int32))
    node = node >> z
    trail = trail >> z.astype(jnp.uint32)
    done = trail == 0
    return jnp.where(done, 0, node ^ 1), jnp.where(done, trail, trail ^ one)


def _row_fields(load, slot, widths, n_cols: int):
    """FrustaParams of V3 / vectors from a leaf slot's packed row (``load(flat index)``)."""
    out, col = {}, 0
    for name, w in zip(_PACKED, widths):
        vals = [load(slot * n_cols + col + k) for k in range(w)]
        out[name] = vals[0] if w == 1 else V3(*vals)
        col += w
    for flag in ("cap_b", "cap_t", "valid"):
        out[flag] = out[flag] > 0.5
    return out


def _pow2(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def _flat_pow2(a):
    """``a`` flattened and zero-padded to a power-of-two length (Triton's block shapes)."""
    a = a.reshape(-1)
    return jnp.concatenate([a, jnp.zeros((_pow2(a.shape[0]) - a.shape[0],), a.dtype)])


class _Rays(NamedTuple):
    """A program's rays as the walk reads them: origins, directions, their reciprocals (per
    axis, signed infinity for a zero component) and the window's start."""

    o: V3
    d: V3
    inv_d: tuple
    t_min: jax.Array


def _inv(x):
    """1 / x, with x = +-0 giving +-inf (python-float constants: Triton's lowering cannot
    negate a constant array)."""
    return jnp.where(x == 0, jnp.where(jnp.signbit(x), -jnp.inf, jnp.inf), 1.0 / jnp.where(x == 0, 1.0, x))


def _meets(r: _Rays, box_lo, box_hi, t_hi):
    """(met, t0) of every ray against one box per ray (slab test, ``accel.ray_box``'s), met
    only where the box's interval overlaps [t_min, t_hi] and the box is not empty."""
    t0 = t1 = None
    ok = None
    for k in range(3):
        ta = (box_lo[k] - r.o[k]) * r.inv_d[k]
        tb = (box_hi[k] - r.o[k]) * r.inv_d[k]
        a, b = jnp.minimum(ta, tb), jnp.maximum(ta, tb)
        t0 = a if t0 is None else jnp.maximum(t0, a)
        t1 = b if t1 is None else jnp.minimum(t1, b)
        ok = (box_lo[k] <= box_hi[k]) if ok is None else ok & (box_lo[k] <= box_hi[k])
    return (t0 <= t1) & (t1 >= r.t_min) & (t0 <= t_hi) & ok, t0


def _anyv(x):
    """Whether any lane of the boolean vector ``x`` is set (a reduction Triton lowers)."""
    return jnp.max(x.astype(jnp.int32)) > 0


def _to_leaf(r: _Rays, kids, n_leaves: int, node, trail, t_hi, visits):
    """(node, trail, visits) once every ray has descended to a leaf or finished: inner nodes
    are ``0 < node < n_leaves``, each visit gathers the node's row of child boxes from ``kids``
    and takes ``accel.descend``'s step (near child first, bit trail)."""
    def cond(st):
        nd = st[0]
        return _anyv((nd > 0) & (nd < n_leaves))

    def body(st):
        node, trail, v = st
        walking = (node > 0) & (node < n_leaves)
        base = jnp.where(walking, node, 0) * 12
        row = [kids[base + k] for k in range(12)]
        nxt, ntrail = descend(node, trail, row, lambda lo, hi: _meets(r, lo, hi, t_hi), pop)
        return (jnp.where(walking, nxt, node), jnp.where(walking, ntrail, trail), v + walking.astype(jnp.int32))

    return jax.lax.while_loop(cond, body, (node, trail, visits))


def _outer(r: _Rays, kids, rows, order, st, *, n_leaves: int, leaf: int, widths, n_cols: int):
    """One step of the walk: down to the next leaf (:func:`_to_leaf`), its ``leaf`` slots
    tested in order against the best hit (the first of equal t wins, as in ``_leaf_best``),
    then popped to the next subtree."""
    node, trail, bt, bs, bc, bi, visits, leaves = st
    node, trail, visits = _to_leaf(r, kids, n_leaves, node, trail, bt, visits)
    found = node >= n_leaves
    slot0 = (jnp.maximum(node, n_leaves) - n_leaves) * leaf
    t_hi = bt
    for j in range(leaf):
        seg = _row_fields(lambda i: rows[i], slot0 + j, widths, n_cols)
        # u_off, twist, sid, shell, v_off are shading fields _segment_t never reads: placeholders
        seg = FrustaParams(**seg, u_off=t_hi, twist=t_hi, sid=node, shell=t_hi, v_off=t_hi)
        tc, sc, cc = _segment_t(seg, r.o, r.d, r.t_min, t_hi)
        better = found & (tc < bt)
        bt = jnp.where(better, tc, bt)
        bs = jnp.where(better, sc, bs)
        bc = jnp.where(better, cc, bc)
        bi = jnp.where(better, order[slot0 + j], bi)
    pn, pt = pop(node, trail)
    return (jnp.where(found, pn, 0), jnp.where(found, pt, trail), bt, bs, bc, bi, visits, leaves + found.astype(jnp.int32))


def _kernel(ox, oy, oz, dx, dy, dz, tmin, tmax, kids, lo, hi, rows, order,
            t_out, s_out, c_out, i_out, v_out, l_out, *, n_leaves: int, leaf: int, widths, n_cols: int):
    """One program: ``block`` rays walk the tree (see the module docstring and ``accel.nearest``)."""
    o = V3(ox[...], oy[...], oz[...])
    d = V3(dx[...], dy[...], dz[...])
    t_min, t_max = tmin[...], tmax[...]
    dt = t_min.dtype
    inf = jnp.asarray(jnp.inf, dt)
    r = _Rays(o, d, (_inv(d[0]), _inv(d[1]), _inv(d[2])), t_min)
    root, _ = _meets(r, [lo[3 + k] for k in range(3)], [hi[3 + k] for k in range(3)], t_max)
    z = jnp.zeros_like(t_min)
    zi = z.astype(jnp.int32)
    st = (jnp.where(root, 1, 0).astype(jnp.int32), zi.astype(jnp.uint32), jnp.minimum(inf + z, t_max), z, zi + SIDE, zi - 1, zi, zi)
    outer = functools.partial(_outer, r, kids, rows, order, n_leaves=n_leaves, leaf=leaf, widths=widths, n_cols=n_cols)
    st = jax.lax.while_loop(lambda st: _anyv(st[0] > 0), outer, st)
    _, _, bt, bs, bc, bi, visits, leaves = st
    t_out[...] = bt
    s_out[...] = bs
    c_out[...] = bc
    i_out[...] = jnp.where(jnp.isfinite(bt), bi, -1)
    v_out[...] = visits
    l_out[...] = leaves


@functools.partial(jax.jit, static_argnames=("f_shape", "leaf", "block", "num_warps", "interpret"))
def _walk(fb: FrustaBVH, o, d, t_min, t_max, *, f_shape, leaf: int, block: int, num_warps: int, interpret: bool):
    from jax.experimental import pallas as pl

    n = o.shape[0]
    n_pad = -(-n // block) * block

    def pad(x):
        return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (n_pad - n,) + x.shape[1:])]) if n_pad > n else x

    o, d, t_min, t_max = pad(o), pad(d), pad(t_min), pad(t_max)
    n_leaves = fb.tree.lo.shape[0] // 2
    widths, n_cols = f_shape
    # one gather per lookup: each table a flat power-of-two vector indexed by computed offsets
    kids, lo, hi, rows = (_flat_pow2(a) for a in (fb.tree.children, fb.tree.lo, fb.tree.hi, fb.rows))
    order = _flat_pow2(fb.tree.order)
    ray_spec = pl.BlockSpec((block,), lambda i: (i,))
    tables = (kids, lo, hi, rows, order)
    table_specs = [pl.BlockSpec((a.shape[0],), lambda i: (0,)) for a in tables]
    dt = o.dtype
    out_shape = [jax.ShapeDtypeStruct((n_pad,), x) for x in (dt, dt, jnp.int32, jnp.int32, jnp.int32, jnp.int32)]
    kw = {}
    if not interpret:
        from jax.experimental.pallas import triton as pltriton

        kw["compiler_params"] = pltriton.CompilerParams(num_warps=num_warps, num_stages=1)
    kern = functools.partial(_kernel, n_leaves=n_leaves, leaf=leaf, widths=widths, n_cols=n_cols)
    outs = pl.pallas_call(kern, out_shape=out_shape, grid=(n_pad // block,), in_specs=[ray_spec] * 8 + table_specs,
                          out_specs=[ray_spec] * 6, interpret=interpret, **kw)(
        o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2], t_min, t_max, *tables)
    return tuple(x[:n] for x in outs)


def nearest_kernel(f: FrustaParams, fb: FrustaBVH, leaf: int, origins, directions, t_min, t_max,
                   block: int = 32, num_warps: int = 1, interpret: bool | None = None):
    """(t, s, code, idx, visits, leaves) per ray, as :func:`jskel.frusta._accel.nearest_groups`
    gives them, from the Pallas kernel. ``interpret`` (default: when the backend is the CPU)
    runs the kernel through Pallas's interpreter, which is how it is tested without a GPU."""
    if interpret is None:
        interpret = jax.default_backend() == "cpu"
    widths = packed_widths(f)
    t, *rest = _walk(fb, origins, directions, t_min, t_max, f_shape=(widths, sum(widths)), leaf=leaf,
                     block=block, num_warps=num_warps, interpret=interpret)
    return (miss_is_inf(t, rest[2]), *rest)
