"""The exact relief tracer (``relief.method: exact``): safe skipping through a min/max pyramid of
the height map, then the crossing inside one bilinear cell solved to rounding.

Bhagvat et al. (2009, Sec. 3) march the shell in uniform steps and bisect the first bracket
(``_relief._march``), so a feature narrower than a step is missed and the step count is a
quality knob. Here a ray's window [s_a, s_b] in a segment's shell is traversed in intervals
whose length halves when a bound cannot decide and doubles after a skip (a stackless
descent and ascent, as the maximum mipmaps of Tevs, Ihrke and Seidel 2008 are walked):

* **w** (Eq. 11-12), the ray's height in the shell, is convex along the ray (the distance to
  the axis is a norm of an affine function; the inner radius is linear), so on an interval it
  lies above its tangents at both ends and below its larger end value.
* **(X, Y)**, the texel coordinates: Y is linear in s (v interpolated linearly across the window,
  the paper's approximate v, which is exact for parallel cutting planes), and X follows the
  angle, whose rate along a line is C / rho^2 (C = z dx - x dz is constant along the ray, rho^2
  a convex quadratic): bounds of rho^2 over the interval bound dX/ds, so X is monotone there and
  its range is its ends' (twist adds a constant rate times dv/ds).
* **h**, the bilinear height, lies between the least and greatest texel of the cells its (X, Y)
  range covers: level 0 of the pyramid holds each cell's 4 texels' max and min (the bilinear
  footprint, with u wrapping and v wrapping or clamped as the sampler does), each level above
  2 x 2 of the one below; a range of at most 2^l cells on each axis meets at most 2 x 2 cells of
  level l per contiguous piece (a range that wraps is two pieces).

An interval is skipped when the bounds keep the ray on its side of the surface (above it for a
ray from outside: the least of w above the greatest h; below it for a ray starting below: the
greatest w at most the least h). Inside one cell the bounds are the bilinear's own at the
range's corners, and the gap g = w - h has a derivative bounded by the same ranges (w' between
its ends' slopes; h' from the cell's slopes and the bounds of dX/ds, dY/ds): where that bound
keeps one sign, g is monotone on the interval, so no sign change means no crossing and a sign
change brackets the only one, found by Newton steps kept in the bracket. Nothing is sampled at a
step size: the first crossing is found to rounding. A ray whose interval shrinks to a few ulps
without a decision (a tangent graze of the surface) is recorded as undecided, which the batch
turns into the ``graze`` flag, as the march's bound does; so is one that runs out of ``LOOPS``.

Limits: v must be linear in s (``uv: approximate``, or ``auto`` with parallel cutting planes);
config refuses ``method: exact`` with ``uv: exact`` by name.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import dot3, eps_of, safe_div, safe_sqrt
from ._relief import _TWO_PI, _angle_u, _least_of_upper, sample_height

LOOPS = 1024  # traversal iterations per (ray, segment) before the pair is left undecided
NEWTON = 10  # Newton steps kept in the final bracket (g monotone there)
SLIVER = 1e-3  # texels: a range reaching this far into a neighbouring cell is bounded as its own cell's


def pyramid(height: np.ndarray, v_mode: str):
    """(max (K,) uint8, min (K,) uint8, levels): the min/max pyramid of an (H, W) uint8 map,
    every level flattened into one array; ``levels`` the static (offset, rows, cols) of each.
    Level 0 is a cell per texel x and per row pair: cell (j, i) covers texels i, i + 1 (wrapping)
    and rows j, j + 1 (wrapping, H rows), or clamped rows clip(j), clip(j + 1) for j = -1 .. H - 1
    (row index j + 1, H + 1 rows). Each level above is 2 x 2 of the one below (padded with 0 for
    the max, 255 for the min), up to one cell."""
    t = np.asarray(height, np.uint8)
    H, W = t.shape
    if v_mode == "wrap":
        ra, rb = np.arange(H), (np.arange(H) + 1) % H
    else:
        ra, rb = np.clip(np.arange(-1, H), 0, H - 1), np.clip(np.arange(0, H + 1), 0, H - 1)
    x1 = np.roll(t, -1, axis=1)
    quad = np.stack([t[ra], x1[ra], t[rb], x1[rb]])
    out = []
    for top, fill, red in ((quad.max(0), 0, np.max), (quad.min(0), 255, np.min)):
        lv = [top]
        while max(lv[-1].shape) > 1:
            a = lv[-1]
            a = np.pad(a, ((0, a.shape[0] % 2), (0, a.shape[1] % 2)), constant_values=fill)
            lv.append(red(a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2), axis=(1, 3)))
        out.append(lv)
    flat = [np.concatenate([a.reshape(-1) for a in lv]).astype(np.uint8) for lv in out]
    levels = pyramid_levels(t.shape, v_mode)
    assert levels[-1][0] + levels[-1][1] * levels[-1][2] == flat[0].size
    return flat[0], flat[1], levels


def pyramid_levels(shape, v_mode: str) -> tuple:
    """The static (offset, rows, cols) of each level of :func:`pyramid` for a map of ``shape``."""
    rows, cols = shape[0] + (v_mode != "wrap"), shape[1]
    offs, levels = 0, [(0, rows, cols)]
    while max(rows, cols) > 1:
        offs += rows * cols
        rows, cols = -(-rows // 2), -(-cols // 2)
        levels.append((offs, rows, cols))
    return tuple(levels)


def _pieces(lo, n, size):
    """A range of n + 1 consecutive cells from ``lo`` on a wrapping axis of ``size`` cells, as two
    contiguous pieces (the second a copy of the first when it does not wrap): (lo1, hi1, lo2, hi2)."""
    a = jnp.mod(lo, size)
    wraps = a + n >= size
    return a, jnp.where(wraps, size - 1, a + n), jnp.where(wraps, 0, a), jnp.where(wraps, a + n - size, a + n)


def _pyramid_bounds(mip_max, mip_min, levels, cx0, cx1, cy0, cy1, W: int, Hc: int, wrap_y: bool, whole):
    """(least, greatest) texel over cells [cx0, cx1] x [cy0, cy1] (integers, x unwrapped; y
    already the row index for a clamped map), from the coarsest level needed; ``whole``: the
    whole map's (the top level)."""
    nl = len(levels)
    nx, ny = cx1 - cx0, cy1 - cy0
    span = jnp.maximum(nx, ny) + 1
    lvl = jnp.ceil(jnp.log2(span.astype(jnp.float32))).astype(jnp.int32)
    whole = whole | (nx >= W) | (ny >= Hc)
    lvl = jnp.where(whole, nl - 1, jnp.clip(lvl, 0, nl - 1))
    xs = jnp.stack(_pieces(cx0, jnp.minimum(nx, W - 1), W))
    if wrap_y:
        ys = jnp.stack(_pieces(cy0, jnp.minimum(ny, Hc - 1), Hc))
    else:
        ys = jnp.stack([cy0, cy1, cy0, cy1])
    xs, ys, lvl = _materialised(xs, ys, lvl)
    off = jnp.asarray([o for o, _, _ in levels], jnp.int32)[lvl]
    rows = jnp.asarray([r for _, r, _ in levels], jnp.int32)[lvl]
    cols = jnp.asarray([c for _, _, c in levels], jnp.int32)[lvl]
    bx = jnp.minimum(jnp.right_shift(xs, lvl), cols - 1)
    by = jnp.minimum(jnp.right_shift(ys, lvl), rows - 1)
    idx = off + (by[:, None] * cols + bx[None, :]).reshape(-1)
    lo = mip_min.at[idx].get(mode="promise_in_bounds")
    hi = mip_max.at[idx].get(mode="promise_in_bounds")
    return jnp.min(lo).astype(jnp.float32) / 255.0, jnp.max(hi).astype(jnp.float32) / 255.0


def _materialised(xs, ys, lvl):
    """(xs, ys, lvl) unchanged, through a product with the identity: XLA fused the arithmetic that
    makes them into the pyramid's gather, running it again for each of the 16 elements gathered
    (1.06 s of a 1.24 s cast of 4,096 rays, one-off profile, 2026-12-06); a dot is not fused
    into it (a sort by constant keys did the same: the 64 x 64 column cast took 104 ms with it, 74 with the dot)."""
    vals = jnp.concatenate([xs, ys, lvl[None]]).astype(jnp.float32)  # small integers: exact
    vals = jnp.round(jnp.dot(jnp.eye(vals.shape[0], dtype=jnp.float32), vals)).astype(jnp.int32)
    return vals[:4], vals[4:8], vals[8]


def _mul_range(a_lo, a_hi, b_lo, b_hi):
    p = jnp.stack([a_lo * b_lo, a_lo * b_hi, a_hi * b_lo, a_hi * b_hi])
    return jnp.min(p), jnp.max(p)


def search(maps, mips, levels, v_mode: str, seg, e, d, s_a, s_b, v_a, v_b, inside0, hit_at_entry, ok):
    """(found, s_root, s_undecided) of one ray's window [s_a, s_b] in one segment's shell (the
    module's traversal): the first s where the ray crosses the relief surface from the side it
    starts on, to rounding; s_undecided the start of the first interval left undecided (inf
    where none). ``mips``: the pyramid's (max, min) arrays; v = v_a .. v_b linearly over the window;
    ``ok``: the window is not empty (else nothing is traversed)."""
    mip_max, mip_min = mips
    dt = e.dtype
    hh, ww = maps.height.shape
    Hc = hh if v_mode == "wrap" else hh + 1
    su, sv = maps.scale[0], maps.scale[1]
    period = su * ww  # X where u wraps
    seamless = jnp.mod(period, ww) == 0  # an integer scale_u: the map's columns continue across u = 1
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    du, dm, dz = dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w)
    ex, ez = dot3(e, seg.u), dot3(e, seg.w)
    vr = safe_div(v_b - v_a, s_b - s_a, 0.0)  # dv/ds
    cp = ez * du - ex * dz  # rho^2 dphi/ds, constant along the ray
    qa, qb = du * du + dz * dz, ex * du + ez * dz  # rho^2 = qa s^2 + 2 qb s + (ex^2 + ez^2)
    tiny = 8 * eps_of(e) * (jnp.abs(s_a) + jnp.abs(s_b) + 1e-30)
    inf = jnp.asarray(jnp.inf, dt)

    def geo(s):
        p = e + s * d
        x, y, z = dot3(p, seg.u), dot3(p, seg.m), dot3(p, seg.w)
        rho2 = x * x + z * z
        rho = safe_sqrt(rho2)
        w = safe_div(rho - (seg.r1 + k * y), seg.shell, 0.0)
        dw = safe_div(safe_div(x * du + z * dz, rho, 0.0) - k * dm, seg.shell, 0.0)
        v = v_a + vr * (s - s_a)
        u = _angle_u(seg, p, v)
        vv = (v + seg.v_off) * sv
        h = sample_height(maps, u * su, vv, v_mode)
        return w, dw, rho2, u * period - 0.5, vv * hh - 0.5, h

    def gap(s):
        g = geo(s)
        return g[0] - g[5]

    def crossed(g):
        return (g[0] - g[5] <= 0) != inside0

    def texel(jx, jy):
        xa = jnp.mod(jx, ww)
        if v_mode == "wrap":
            ya = jnp.mod(jy, hh)
        else:
            ya = jnp.clip(jy, 0, hh - 1)
        return maps.height[ya, xa].astype(dt) / 255.0

    def decide(s0, g0, s1, g1):
        """(skip, bracket): the interval [s0, s1] holds no crossing / its only crossing."""
        L = s1 - s0
        w0, dw0, r0, X0, Y0, _ = g0
        w1, dw1, r1, X1, Y1, _ = g1
        w_lo = w0 + _least_of_upper([(0.0 * w0, dw0), (w1 - w0 - dw1 * L, dw1)], L)
        w_hi = jnp.maximum(w0, w1)
        # rho^2 over the interval (a convex quadratic) bounds the angle's rate
        sv_ = jnp.clip(safe_div(-qb, qa, s0), s0, s1)
        rmin = jnp.minimum(jnp.minimum(r0, r1), qa * sv_ * sv_ + 2 * qb * sv_ + (ex * ex + ez * ez))
        rmax = jnp.maximum(r0, r1)
        a1, a2 = safe_div(cp, jnp.maximum(rmin, 0.0), inf), safe_div(cp, rmax, 0.0)
        ph_lo, ph_hi = jnp.minimum(a1, a2), jnp.maximum(a1, a2)
        xr_lo = (ph_lo / _TWO_PI + seg.twist * vr) * period
        xr_hi = (ph_hi / _TWO_PI + seg.twist * vr) * period
        yr = vr * sv * hh
        mono_x = (xr_lo > 0) | (xr_hi < 0) | ((xr_lo == 0) & (xr_hi == 0))
        dX = X1 - X0
        dX = dX - period * jnp.round(safe_div(dX, period, 0.0))
        xlo, xhi = jnp.minimum(X0, X0 + dX), jnp.maximum(X0, X0 + dX)
        ylo, yhi = jnp.minimum(Y0, Y1), jnp.maximum(Y0, Y1)
        seam = ((xlo < -0.5) | (xhi >= period - 0.5)) & ~seamless
        # cells met, less a sliver of SLIVER texels at either end (a range that starts on a cell's
        # boundary, rounded either way); the bounds grow by the map's slope over a sliver below
        cx0 = jnp.floor(xlo + SLIVER).astype(jnp.int32)
        cx1 = jnp.maximum(cx0, jnp.ceil(xhi - SLIVER).astype(jnp.int32) - 1)
        cy0 = jnp.floor(ylo + SLIVER).astype(jnp.int32)
        cy1 = jnp.maximum(cy0, jnp.ceil(yhi - SLIVER).astype(jnp.int32) - 1)
        grow = SLIVER * (maps.slope[0] + maps.slope[1])
        if v_mode != "wrap":  # rows beyond the map repeat its edge: cells -1 .. H - 1, index + 1
            cy0, cy1 = jnp.clip(cy0, -1, hh - 1) + 1, jnp.clip(cy1, -1, hh - 1) + 1
        whole = seam | ~mono_x | ~jnp.isfinite(xlo + xhi + ylo + yhi)
        cx0 = jnp.where(whole, 0, cx0)
        cx1 = jnp.where(whole, 0, cx1)
        cy0 = jnp.where(whole, 0, cy0)
        cy1 = jnp.where(whole, 0, cy1)
        h_lo, h_hi = _pyramid_bounds(mip_max, mip_min, levels, cx0, cx1, cy0, cy1, ww, Hc, v_mode == "wrap", whole)
        # one cell: the bilinear's own bounds (at the range's corners) and its slopes
        one = ~whole & (cx0 == cx1) & (cy0 == cy1)
        jy = cy0 if v_mode == "wrap" else cy0 - 1
        t00, t10, t01, t11 = texel(cx0, jy), texel(cx0 + 1, jy), texel(cx0, jy + 1), texel(cx0 + 1, jy + 1)
        fx = jnp.clip(jnp.stack([xlo, xhi]) - cx0, 0.0, 1.0)
        fy = jnp.clip(jnp.stack([ylo, yhi]) - (cy0 if v_mode == "wrap" else cy0 - 1), 0.0, 1.0)
        if v_mode != "wrap":  # a clamped row beyond the map: the edge rows, fy immaterial
            fy = jnp.where((jy < 0) | (jy >= hh - 1), 0.0, fy)
        corners = jnp.stack([(1 - a) * (1 - b) * t00 + a * (1 - b) * t10 + (1 - a) * b * t01 + a * b * t11
                             for a in (fx[0], fx[1]) for b in (fy[0], fy[1])])
        h_lo = jnp.where(one, jnp.min(corners), h_lo) - grow
        h_hi = jnp.where(one, jnp.max(corners), h_hi) + grow
        strict = (jnp.floor(xlo) >= jnp.ceil(xhi) - 1) & (jnp.floor(ylo) >= jnp.ceil(yhi) - 1)  # no sliver
        hx = jnp.stack([(t10 - t00) * (1 - b) + (t11 - t01) * b for b in (fy[0], fy[1])])
        hy = jnp.stack([(t01 - t00) * (1 - a) + (t11 - t10) * a for a in (fx[0], fx[1])])
        px = _mul_range(jnp.min(hx), jnp.max(hx), xr_lo, xr_hi)
        py = _mul_range(jnp.min(hy), jnp.max(hy), yr, yr)
        g_lo, g_hi = dw0 - (px[1] + py[1]), dw1 - (px[0] + py[0])  # bounds of g' = w' - h'
        mono = one & strict & mono_x & ((g_lo > 0) | (g_hi < 0))
        c1 = crossed(g1)
        apart = jnp.where(inside0, w_hi <= h_lo, w_lo > h_hi)
        skip = ~c1 & (apart | mono)
        bracket = c1 & (mono | (L <= tiny))
        # where the current level-0 cell ends along the ray (a cut for the next interval: halving
        # alone would approach a cell's boundary without reaching it)
        up = xr_hi > 0
        xb = jnp.where(up, jnp.floor(X0 + SLIVER) + 1, jnp.ceil(X0 - SLIVER) - 1)
        phb = _TWO_PI * ((xb + 0.5) / period - seg.u_off)
        den = du * jnp.cos(phb) - dz * jnp.sin(phb)
        sx = safe_div(ez * jnp.sin(phb) - ex * jnp.cos(phb), den, inf)
        yb = jnp.where(yr > 0, jnp.floor(Y0 + SLIVER) + 1, jnp.ceil(Y0 - SLIVER) - 1)
        sy = s0 + safe_div(yb - Y0, yr, inf)
        cand = jnp.stack([jnp.where(seg.twist == 0, sx, inf), sy])
        cut = jnp.min(jnp.where(cand > s0 + tiny, cand, inf)) - s0
        return skip, bracket, cut

    def body(st):
        i, s0, g0, L, done, lo, hi, s_und = st
        s1 = jnp.minimum(s0 + L, s_b)
        g1 = geo(s1)
        skip, bracket, cut = decide(s0, g0, s1, g1)
        floor = (s1 - s0) <= tiny
        stuck = floor & ~skip & ~bracket  # a graze within rounding: left undecided, passed over
        s_und = jnp.where(stuck & ~jnp.isfinite(s_und), s0, s_und)
        move = skip | stuck
        end = move & (s1 >= s_b)
        lo, hi = jnp.where(bracket, s0, lo), jnp.where(bracket, s1, hi)
        s0n = jnp.where(move, s1, s0)
        g0n = jax.tree_util.tree_map(lambda a, b: jnp.where(move, b, a), g0, g1)
        Ln = jnp.where(move, 2 * L, jnp.where(bracket, L, jnp.minimum(0.5 * L, cut)))
        return i + 1, s0n, g0n, Ln, done | bracket | end, lo, hi, s_und

    st0 = (jnp.int32(0), s_a, geo(s_a), s_b - s_a, hit_at_entry | ~ok, s_a, s_a, inf)
    i, s0, _, _, done, lo, hi, s_und = jax.lax.while_loop(lambda st: (st[0] < LOOPS) & ~st[4], body, st0)
    found = ok & (hit_at_entry | (done & (hi > lo)))
    s_und = jnp.where(~done, jnp.minimum(s_und, s0), s_und)  # out of iterations: undecided from there

    # the one crossing in [lo, hi] (g monotone there): Newton steps kept in the bracket
    def newton(_, lh):
        a, b, x = lh
        gx, dg = jax.jvp(gap, (x,), (jnp.ones_like(x),))
        cx = (gx <= 0) != inside0
        a, b = jnp.where(cx, a, x), jnp.where(cx, x, b)
        xn = x - safe_div(gx, dg, inf)
        # inclusive: a converged step lands on the end the last sample just moved there
        return a, b, jnp.where(gx == 0, x, jnp.where((xn >= a) & (xn <= b), xn, 0.5 * (a + b)))

    _, _, x = jax.lax.fori_loop(0, NEWTON, newton, (lo, hi, 0.5 * (lo + hi)))
    return found, jnp.where(hit_at_entry, s_a, x), s_und
