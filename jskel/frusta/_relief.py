"""Relief-mapped conical frusta: a height field in a shell (Bhagvat et al. 2009, Sec. 3).

Each relief segment has an outer frustum of radii (r1 + T, r2 + T) sharing its cutting planes
(T = ``shell``). A ray's interval inside that solid (clipped by the cutting planes, possibly
starting inside) is marched in ``steps`` uniform samples, then the first bracket where the ray
crosses the relief surface is refined by ``bisection`` halvings (Sec. 3: "uniform sampling
followed by a bisectional search", after Policarpo et al. 2005).

At a sample P the relief height is w = (d - r_i) / (r_o - r_i) (Eq. 11-12), d the distance of P
from the axis and r_i, r_o the inner and outer radii at P's height; the ray is *below* the
surface where w <= h(u, v). (u, v) per sample either way the paper gives:

* ``exact``: the cone through P concentric with the frustum (same slope k, Sec. 3) gives v from
  the cutting planes along its generator (Sec. 2.3, Eq. 7), u from the angle (Eq. 6);
* ``approximate`` (default): u from the angle, v interpolated linearly between the exact v at
  the ends of the interval. The paper notes this is exact when the cutting planes are parallel.

The step count, the bisection count, thickness, tiling and the height map are traced, so trying
several step or bisection counts compiles once. ``early_exit`` marches
in a ``while_loop`` that stops when every ray of the batch has found its bracket (under vmap the
loop runs while any ray is still marching); the fixed variant is a ``fori_loop`` of exactly
``steps`` iterations.

Shading normals come from the height map's gradient (central differences, one texel apart)
mapped to the surface frame: with P'(u, v) = P0 + h T n_r (n_r radial), the normal is
dP'/du x dP'/dv with dP/du = 2 pi d c_hat + T h_u n_r and dP/dv = L g + T h_v n_r (g the
generator, L its length between the cutting planes).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import differentiable_root, dot3, eps_of, frozen, safe_div, safe_normalize, safe_sqrt
from ..rays import masked_hit
from ._intersect import CAP_BOTTOM, CAP_TOP, FrustaParams, recentre, side_roots

RELIEF = 3
UNDECIDED_SCOPE = "relief_undecided"  # the name scope of the march's graze bound
_TWO_PI = 2.0 * jnp.pi


class ReliefMaps(NamedTuple):
    """height: (H, W) uint8 (8-bit storage, Sec. 4), or float 0..255 (``relief.storage: float``,
    differentiable); scale: (2,) repeats per unit u and v;
    slope: (2,) the largest change of the bilinear height per texel along x and along y
    (:func:`texel_slopes`), the bound the march's ``graze`` test needs; steps: () int32, the
    march's uniform samples (Sec. 3); bisection: () int32, the halvings of the bracket the march
    found (Sec. 3's bisectional search). Both are traced values, so a sweep over either or a
    notebook that tries several compiles one program."""

    height: jnp.ndarray
    scale: jnp.ndarray
    slope: jnp.ndarray
    steps: jnp.ndarray
    bisection: jnp.ndarray
    mip: jnp.ndarray | None = None  # ``exact``: (K, 2) uint8, the height pyramid's (max, min), every level flat (``_relief_exact.pyramid``)


def texel_slopes(height) -> np.ndarray:
    """(2,) float64: the largest |difference| of neighbouring texels along x and along y (both
    wrapping, which bounds the clamped v as well), over 255. The bilinear height's partial
    derivatives in texel units never exceed them (each is an interpolation of such differences)."""
    img = np.asarray(height, np.float64)
    return np.array([np.max(np.abs(np.roll(img, -1, 1) - img)), np.max(np.abs(np.roll(img, -1, 0) - img))]) / 255.0


class ReliefQuality(NamedTuple):
    """Static march options (changing one recompiles; the step and bisection counts are values,
    ``ReliefMaps.steps`` and ``ReliefMaps.bisection``)."""

    uv: str = "approximate"  # or "exact"
    early_exit: bool = False
    v_mode: str = "wrap"  # or "clamp"
    method: str = "march"  # or "exact" (``_relief_exact``: pyramid skipping, the crossing to rounding)
    levels: tuple = ()  # ``exact``: the pyramid's (offset, rows, cols) per level


def sample_height(maps: ReliefMaps, uu, vv, v_mode: str):
    """Bilinear height in [0, 1] at texture coordinates (uu, vv) (already scaled); u wraps."""
    fx, fy, t00, t01, t10, t11 = bilinear_taps(maps, uu, vv, v_mode)
    val = (1 - fx) * (1 - fy) * t00 + fx * (1 - fy) * t01 + (1 - fx) * fy * t10 + fx * fy * t11
    return val / 255.0


def bilinear_taps(maps: ReliefMaps, uu, vv, v_mode: str):
    """(fx, fy, t00, t01, t10, t11): the bilinear weights at (uu, vv) and the four texels
    (0..255, row then column offset) that :func:`sample_height` interpolates; u wraps, v wraps
    or is clamped by ``v_mode``."""
    img = maps.height
    h, w = img.shape
    x = uu * w - 0.5
    y = vv * h - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0
    fy = y - y0
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)
    xa, xb = jnp.mod(x0, w), jnp.mod(x0 + 1, w)
    if v_mode == "wrap":
        ya, yb = jnp.mod(y0, h), jnp.mod(y0 + 1, h)
    else:
        ya, yb = jnp.clip(y0, 0, h - 1), jnp.clip(y0 + 1, 0, h - 1)
    dt = uu.dtype
    f = lambda yy, xx: img[yy, xx].astype(dt)  # noqa: E731
    return fx, fy, f(ya, xa), f(ya, xb), f(yb, xa), f(yb, xb)


def _in_slab(seg, p, tol):
    return (dot3(seg.nb, p) >= seg.db - tol) & (dot3(seg.nt, p) <= seg.dt + tol)


def shell_interval(seg: FrustaParams, e, d):
    """Interval (s_in, s_out) of the line e + s d inside the outer solid frustum, and entry code.

    The outer solid (radii + shell, between the cutting planes) is convex, so its boundary
    crossings are its entry and exit: the smallest and largest valid crossing of its side and
    of its two planes. Returns (s_in, s_out, ok, entry_code).
    """
    inf = jnp.asarray(jnp.inf, e.dtype)
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    r1o = seg.r1 + seg.shell
    tol = 32.0 * eps_of(e) * (seg.h + seg.r1 + seg.r2 + 2 * seg.shell)
    s_lo, s_hi = side_roots(seg, e, d, seg.shell)

    def side_ok(s):
        p = e + s * d
        return jnp.isfinite(s) & _in_slab(seg, p, tol) & (r1o + k * dot3(p, seg.m) >= 0)

    def plane(n, dist):
        s = safe_div(dist - dot3(n, e), dot3(n, d), inf)
        p = e + s * d
        x, y, z = dot3(p, seg.u), dot3(p, seg.m), dot3(p, seg.w)
        ry = r1o + k * y
        ok = jnp.isfinite(s) & (x * x + z * z <= ry * ry) & (ry >= 0) & _in_slab(seg, p, tol)
        return s, ok

    sb, okb = plane(seg.nb, seg.db)
    st, okt = plane(seg.nt, seg.dt)
    ss = jnp.stack([s_lo, s_hi, sb, st])
    ok = jnp.stack([side_ok(s_lo), side_ok(s_hi), okb, okt])
    s_in = jnp.min(jnp.where(ok, ss, inf))
    s_out = jnp.max(jnp.where(ok, ss, -inf))
    codes = jnp.array([RELIEF, RELIEF, CAP_BOTTOM, CAP_TOP], jnp.int32)
    entry = jnp.sum(jnp.where(ok & (ss == s_in), codes, 0) * (jnp.cumsum(ok & (ss == s_in)) == 1))
    good = (jnp.sum(ok) >= 2) & (s_in < s_out)
    return s_in, s_out, good, entry


def exact_v(seg: FrustaParams, p):
    """v of Eq. 7 for a point p (relative to C1) on any cone concentric with the frustum."""
    x, z = dot3(p, seg.u), dot3(p, seg.w)
    rho = safe_sqrt(x * x + z * z)
    radial = safe_div(x * seg.u + z * seg.w, rho, 0.0)
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    g = seg.m + k * radial
    s_l = safe_div(seg.db - dot3(seg.nb, p), dot3(seg.nb, g), 0.0)
    s_u = safe_div(seg.dt - dot3(seg.nt, p), dot3(seg.nt, g), 0.0)
    return safe_div(-s_l, s_u - s_l, 0.0), s_u - s_l, g, radial, rho


def _angle_u(seg, p, v):
    x, z = dot3(p, seg.u), dot3(p, seg.w)
    on_axis = (x == 0) & (z == 0)
    ang = jnp.arctan2(jnp.where(on_axis, 0.0, x), jnp.where(on_axis, 1.0, z))
    return jnp.mod(ang / _TWO_PI + seg.u_off + v * seg.twist, 1.0)


def enters_shell(seg: FrustaParams, o, d, t_min, t_max):
    """True when the ray's (t_min, t_max] overlaps the segment's relief shell (the cheap pre-pass
    that decides which (ray, segment) pairs are marched)."""
    t0, e = recentre(seg, o, d)
    s_in, s_out, ok, _ = shell_interval(seg, e, d)
    return ok & (jnp.maximum(s_in, t_min - t0) < jnp.minimum(s_out, t_max - t0)) & seg.valid & (seg.shell > 0)


def _relief_t(maps: ReliefMaps, q: ReliefQuality, seg: FrustaParams, o, d, t_min, t_max):
    """(t, s, code, t_undecided) of one ray against one relief segment (Sec. 3): the ray's
    interval in the shell (:func:`_shell_window`), marched (:func:`_march`) and bisected
    (:func:`_bisect`) for its first crossing of the relief surface; t inf where it has none in
    (t_min, t_max]; t_undecided as ``_relief_method.make_relief_t`` says."""
    n_steps, n_bis = maps.steps, maps.bisection
    inf = jnp.asarray(jnp.inf, o.dtype)
    t0, e, s_a, s_b, ok, entry, from_outside = _shell_window(seg, o, d, t_min, t_max)
    # the march and bisection only find the crossing: they run on inputs whose derivatives are
    # cut (numerics.frozen), so a derivative's program holds them once, not with a tangent
    # copy; the crossing's derivative is the implicit-function theorem's at it (_root_at)
    sample = _sampler(frozen(maps), q, *frozen((seg, e, d, s_a, s_b)))

    def below(s):
        w, _, hgt, _, _ = sample(s)
        return w - hgt <= 0  # exactly w <= h: a float difference is 0 only when equal

    first = sample(s_a)
    b0 = first[0] - first[2] <= 0
    inside0 = (~from_outside) & b0  # the march starts below the relief surface
    hit_at_entry = from_outside & b0
    period = maps.scale[0] * maps.height.shape[1]
    found, lo, hi, s_und = _march(sample, frozen(maps.slope), period, inside0, hit_at_entry, first, *frozen((s_a, s_b)), n_steps, q.early_exit)
    lo, hi = _bisect(below, inside0, lo, hi, n_bis)
    s_hit = _root_at(maps, q, seg, e, d, s_a, s_b, hit_at_entry, 0.5 * (lo + hi))
    t = t0 + s_hit
    good = ok & found & (t > t_min) & (t <= t_max)
    code = jnp.where(hit_at_entry, entry, RELIEF)
    t_und = jnp.where(ok & jnp.isfinite(s_und), t0 + s_und, inf)
    return jnp.where(good, t, inf), s_hit, code.astype(jnp.int32), t_und


def _root_at(maps: ReliefMaps, q: ReliefQuality, seg: FrustaParams, e, d, s_a, s_b, hit_at_entry, root):
    """s of the crossing at ``root`` (found by the march and bisection), differentiable by the
    implicit-function theorem (``numerics.differentiable_root`` of w - h there); an entry hit is
    the shell's own analytic root s_a."""
    sample = _sampler(maps, q, seg, e, d, s_a, s_b)

    def gap(s):
        w, _, hgt, _, _ = sample(s)
        return w - hgt

    return jnp.where(hit_at_entry, s_a, differentiable_root(gap, root))


def relief_root(maps: ReliefMaps, q: ReliefQuality, seg: FrustaParams, o, d, t_min, t_max, s_root):
    """(t, s) of a ray's crossing of one relief segment at ``s_root``, the s :func:`_relief_t`
    found for it, with the derivatives :func:`_relief_t` gives it but no march: the closed
    form a traversal's derivative takes from its winner (``accel.nearest_tangent``). Its value
    is s_root's (s_a's at an entry hit)."""
    t0, e, s_a, s_b, ok, entry, from_outside = _shell_window(seg, o, d, t_min, t_max)
    first = _sampler(frozen(maps), q, *frozen((seg, e, d, s_a, s_b)))(s_a)
    s_hit = _root_at(maps, q, seg, e, d, s_a, s_b, from_outside & (first[0] - first[2] <= 0), jax.lax.stop_gradient(s_root))
    return t0 + s_hit, s_hit


def _shell_window(seg: FrustaParams, o, d, t_min, t_max):
    """(t0, e, s_a, s_b, ok, entry, from_outside): the ray recentred on the segment (o + t0 d
    = C1 + e), its part [s_a, s_b] inside the shell and (t_min, t_max] (ok: not empty; where it
    is, [0, 1] keeps the march finite), the shell's entry code, and whether the ray enters the
    shell within its window rather than starting inside it."""
    t0, e = recentre(seg, o, d)
    s_in, s_out, ok, entry = shell_interval(seg, e, d)
    lo_lim = t_min - t0
    s_a = jnp.maximum(s_in, lo_lim)
    s_b = jnp.minimum(s_out, t_max - t0)
    ok = ok & (s_a < s_b) & seg.valid & (seg.shell > 0)
    s_a = jnp.where(ok, s_a, 0.0)
    s_b = jnp.where(ok, s_b, 1.0)
    from_outside = s_in > lo_lim
    return t0, e, s_a, s_b, ok, entry, from_outside


def _sampler(maps: ReliefMaps, q: ReliefQuality, seg: FrustaParams, e, d, s_a, s_b):
    """``sample(s) -> (w, dw/ds, h, X, Y)`` at e + s d: the ray height w (Eq. 11-12) and its
    derivative along the ray, the map's height h there, and the texel coordinates (X, Y) it was
    read at; w - h is negative below the relief surface. (u, v) exact per sample or,
    ``approximate``, v linear between the window's ends."""
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    du, dm, dw_ = dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w)
    if q.uv == "approximate":
        v_a = exact_v(seg, e + s_a * d)[0]
        v_b = exact_v(seg, e + s_b * d)[0]
    hh, ww = maps.height.shape

    def sample(s):
        p = e + s * d
        y = dot3(p, seg.m)
        x, z = dot3(p, seg.u), dot3(p, seg.w)
        rho = safe_sqrt(x * x + z * z)
        w = safe_div(rho - (seg.r1 + k * y), seg.shell, 0.0)  # Eq. 11-12
        dw = safe_div(safe_div(x * du + z * dw_, rho, 0.0) - k * dm, seg.shell, 0.0)
        if q.uv == "exact":
            v = exact_v(seg, p)[0]
        else:
            v = v_a + (v_b - v_a) * safe_div(s - s_a, s_b - s_a, 0.0)
        u = _angle_u(seg, p, v)
        uu, vv = u * maps.scale[0], (v + seg.v_off) * maps.scale[1]
        return w, dw, sample_height(maps, uu, vv, q.v_mode), u * (maps.scale[0] * ww), vv * hh

    return sample


def _least_of_upper(lines, ds):
    """min over s in [0, ds] of max_k (c_k + m_k s) for ``lines`` [(c_k, m_k)]: a convex
    piecewise-linear function, least at an end or where two of its lines meet."""
    cands = [jnp.zeros_like(ds), ds]
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            (ci, mi), (cj, mj) = lines[i], lines[j]
            cands.append(jnp.clip(safe_div(cj - ci, mi - mj, 0.0), 0.0, ds))
    vals = [functools.reduce(jnp.maximum, [c + m * x for c, m in lines]) for x in cands]
    return functools.reduce(jnp.minimum, vals)


def _step_undecided(prev, cur, ds, slope, period, inside0):
    """Whether one march step cannot exclude a crossing between its samples ``prev`` and
    ``cur`` (both on the start's side of the surface), from bounds rather than samples.

    h, the bilinear height, changes at most at rate L = (slope_x |dX| + slope_y |dY|) / ds along
    the step (u and v move monotonically over one step; u the short way round), so it stays
    below min(h_a + L s, h_b + L (ds - s)) and above the max of the mirrored lines. w is convex
    along the ray (the distance to the axis is a norm of an affine function; the inner radius
    is linear in s): above its tangents at both ends, below its chord. A ray from outside may
    have crossed where the least of max(tangents) - min(h lines) is <= 0; one starting below
    the surface where the most of chord - max(h lines) is > 0. The paper's uniform march
    (Sec. 3) compares samples only; these are the bounds between them."""
    w_a, dw_a, h_a, x_a, y_a = prev
    w_b, dw_b, h_b, x_b, y_b = cur
    dx = x_b - x_a
    dx = dx - period * jnp.round(safe_div(dx, period, 0.0))  # u wraps at 1, X at ``period``
    rate = safe_div(slope[0] * jnp.abs(dx) + slope[1] * jnp.abs(y_b - y_a), ds, 0.0)
    w_lines = [(w_a, dw_a), (w_b - dw_b * ds, dw_b)]  # tangents at both ends
    h_up = [(h_a, rate), (h_b + rate * ds, -rate)]
    gap_lo = _least_of_upper([(cw - ch, mw - mh) for cw, mw in w_lines for ch, mh in h_up], ds)
    chord = (w_a, safe_div(w_b - w_a, ds, 0.0))
    h_lo = [(h_a, -rate), (h_b - rate * ds, rate)]
    gap_hi = -_least_of_upper([(ch - chord[0], mh - chord[1]) for ch, mh in h_lo], ds)
    return jnp.where(inside0, gap_hi > 0, gap_lo <= 0)


def _march(sample, slope, period, inside0, hit_at_entry, first, s_a, s_b, n_steps, early_exit: bool):
    """(found, lo, hi, s_undecided): ``n_steps`` uniform samples of [s_a, s_b] (Sec. 3), the
    first bracket [lo, hi] where the side of the surface changes from the start's, and the
    start of the first step before it that :func:`_step_undecided` could not decide (inf where
    none). ``early_exit`` stops the loop once found (a ``while_loop``), else a ``fori_loop``
    of exactly ``n_steps`` (a traced int32: the loop's bound is a value). ``first``: the sample
    at s_a; slope, period: the map's texel slopes and the texel X where u wraps."""
    ds = (s_b - s_a) / n_steps.astype(s_a.dtype)

    def visit(i, carry):
        found, lo, hi, prev, s_und = carry
        s_i = s_a + ds * i
        cur = sample(s_i)
        c = (~found) & ((cur[0] - cur[2] <= 0) != inside0)
        with jax.named_scope(UNDECIDED_SCOPE):  # (tests/test_relief.py: plain frusta never trace it)
            und = (~found) & (~c) & _step_undecided(prev, cur, ds, slope, period, inside0)
        s_und = jnp.where(und & ~jnp.isfinite(s_und), s_i - ds, s_und)
        return found | c, jnp.where(c, s_i - ds, lo), jnp.where(c, s_i, hi), cur, s_und

    init = (hit_at_entry, s_a, s_a, first, jnp.asarray(jnp.inf, s_a.dtype))
    if early_exit:
        def cond(st):
            return (st[0] < n_steps + 1) & ~st[1][0]

        def body(st):
            i, carry = st
            return i + 1, visit(i, carry)

        _, (found, lo, hi, _, s_und) = jax.lax.while_loop(cond, body, (jnp.int32(1), init))
    else:
        found, lo, hi, _, s_und = jax.lax.fori_loop(1, n_steps + 1, visit, init)
    return found, lo, hi, s_und


def _bisect(below, inside0, lo, hi, n_bis):
    """The bracket [lo, hi] halved ``n_bis`` times (a traced int32; 0 leaves it as the march
    found it), keeping the half where ``below`` changes (Sec. 3's bisectional search). The
    loop's trip count is a value, so it is never differentiated: :func:`_relief_t` takes the
    derivative of the root at its midpoint (``numerics.differentiable_root``)."""
    def bis(_, lh):
        lo, hi = lh
        mid = 0.5 * (lo + hi)
        c = below(mid) != inside0
        return jnp.where(c, lo, mid), jnp.where(c, mid, hi)

    return jax.lax.fori_loop(0, n_bis, bis, (lo, hi))


def make_relief_finish(maps: ReliefMaps, q: ReliefQuality):
    """Hit attributes at a relief hit (exact uv at the hit; normal from the height gradient)."""

    def finish(params: FrustaParams, origin, direction, t, s, code, idx):
        hit = jnp.isfinite(t)
        seg = jax.tree_util.tree_map(lambda a: a[jnp.maximum(idx, 0)], params)
        t0, e = recentre(seg, origin, direction)
        p = e + jnp.where(hit, s, 0.0) * direction
        v, length, g, radial, rho = exact_v(seg, p)
        v = jnp.clip(v, 0.0, 1.0)
        u = _angle_u(seg, p, v)
        c_hat = jnp.cross(seg.m, radial)
        hw, hh = maps.height.shape[1], maps.height.shape[0]
        su, sv = maps.scale[0], maps.scale[1]
        uu, vv = u * su, (v + seg.v_off) * sv
        du, dv = 1.0 / hw, 1.0 / hh
        h_u = (sample_height(maps, uu + du, vv, q.v_mode) - sample_height(maps, uu - du, vv, q.v_mode)) / (2 * du) * su
        h_v = (sample_height(maps, uu, vv + dv, q.v_mode) - sample_height(maps, uu, vv - dv, q.v_mode)) / (2 * dv) * sv
        dpdu = _TWO_PI * rho * c_hat + seg.shell * h_u * radial
        dpdv = length * g + seg.shell * h_v * radial
        n = safe_normalize(jnp.cross(dpdu, dpdv))
        n = jnp.where(dot3(n, radial) < 0, -n, n)
        n = jnp.where(code == CAP_BOTTOM, -seg.nb, jnp.where(code == CAP_TOP, seg.nt, n))
        n = jnp.where(dot3(n, n) > 0.5, n, radial)
        return masked_hit(t, seg.c1 + p, n, jnp.stack([u, v]), seg.sid)

    return finish
