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
* **(X, Y)**, the texel coordinates. With ``uv: approximate`` Y is linear in s (v interpolated
  linearly across the window, the paper's approximate v, exact for parallel cutting planes);
  with ``uv: exact`` v is Eq. 7's, A beta / (A beta - B alpha) with A, B affine along the ray
  and alpha, beta functions of the angle, whose range and rate over an interval come from
  interval arithmetic on that expression (``_Field._v_bounds``). X follows the angle, whose rate
  along a line is C / rho^2 (C = z dx - x dz is constant along the ray, rho^2 a convex
  quadratic): bounds of rho^2 over the interval bound dX/ds, so X is monotone there and its
  range is its ends' (twist adds its rate times dv/ds).
* **h**, the bilinear height, lies between the least and greatest texel of the cells its (X, Y)
  range covers: level 0 of the pyramid holds each cell's 4 texels' max and min (the bilinear
  footprint, with u wrapping and v wrapping or clamped as the sampler does), each level above
  2 x 2 of the one below; a range of at most 2^l cells on each axis meets at most 2 x 2 cells of
  level l (a range that wraps on an axis whose size is not a power of two is two pieces).

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

A batch's (ray, segment) pairs take from a few to over a hundred iterations: they run in
persistent lanes (``wavefront.refill_loop``), each refilled with the next pair as its own
finishes, with the bracket's Newton steps as the pair's last iterations (from the secant of g
over the bracket).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import differentiable_root, dot3, eps_of, frozen, safe_div, safe_sqrt
from ._intersect import FrustaParams
from ._relief import _TWO_PI, RELIEF, _angle_u, _least_of_upper, _shell_window, bilinear_taps, exact_v

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


def _pyramid_bounds(mip, levels, cx0, cx1, cy0, cy1, W: int, Hc: int, wrap_y: bool, whole):
    """(least, greatest) texel over cells [cx0, cx1] x [cy0, cy1] (integers, x unwrapped; y
    already the row index for a clamped map), from the coarsest level needed; ``whole``: the
    whole map's (the top level). A range of at most 2^l cells meets at most 2 cells of level l
    on an axis that does not wrap, or on one whose size is a power of two (its levels tile it
    exactly, so a wrapped range's cells are the unwrapped ones modulo the level's size); on a
    wrapping axis of another size the range is split at the seam into two pieces of 2 each."""
    nl = len(levels)
    nx, ny = cx1 - cx0, cy1 - cy0
    span = jnp.maximum(nx, ny) + 1
    lvl = jnp.ceil(jnp.log2(span.astype(jnp.float32))).astype(jnp.int32)
    whole = whole | (nx >= W) | (ny >= Hc)
    lvl = jnp.where(whole, nl - 1, jnp.clip(lvl, 0, nl - 1))
    pow2_x, pow2_y = W & (W - 1) == 0, Hc & (Hc - 1) == 0
    if pow2_x:
        xs = jnp.stack([cx0, cx0 + jnp.minimum(nx, W - 1)])
    else:
        xs = jnp.stack(_pieces(cx0, jnp.minimum(nx, W - 1), W))
    if wrap_y and not pow2_y:
        ys = jnp.stack(_pieces(cy0, jnp.minimum(ny, Hc - 1), Hc))
    else:
        ys = jnp.stack([cy0, cy0 + jnp.minimum(ny, Hc - 1)])
    xs, ys, lvl = _materialised(xs, ys, lvl)
    off = jnp.asarray([o for o, _, _ in levels], jnp.int32)[lvl]
    rows = jnp.asarray([r for _, r, _ in levels], jnp.int32)[lvl]
    cols = jnp.asarray([c for _, _, c in levels], jnp.int32)[lvl]
    bx = jnp.right_shift(xs, lvl)
    bx = jnp.mod(bx, cols) if pow2_x else jnp.minimum(bx, cols - 1)
    by = jnp.right_shift(ys, lvl)
    by = jnp.mod(by, rows) if wrap_y and pow2_y else jnp.minimum(by, rows - 1)
    idx = off + (by[:, None] * cols + bx[None, :]).reshape(-1)
    cells = mip.at[idx].get(mode="promise_in_bounds")  # (cells, 2): max, min
    lo, hi = cells[:, 1], cells[:, 0]
    return jnp.min(lo).astype(jnp.float32) / 255.0, jnp.max(hi).astype(jnp.float32) / 255.0


def _materialised(xs, ys, lvl):
    """(xs, ys, lvl) unchanged, through a product with the identity: XLA fused the arithmetic that
    makes them into the pyramid's gather, running it again for each element gathered (most of the
    cast's time); a dot is not fused into it. A sort by constant keys, an
    ``optimization_barrier`` and a product of the final indices were slower
    (docs/choices.md#identity-product). Cell indices are far below 2^24: exact in float32."""
    nx = xs.shape[0]
    vals = jnp.concatenate([xs, ys, lvl[None]]).astype(jnp.float32)
    vals = jnp.round(jnp.dot(jnp.eye(vals.shape[0], dtype=jnp.float32), vals)).astype(jnp.int32)
    return vals[:nx], vals[nx:-1], vals[-1]


def _mul_range(a_lo, a_hi, b_lo, b_hi):
    p = jnp.stack([a_lo * b_lo, a_lo * b_hi, a_hi * b_lo, a_hi * b_hi])
    return jnp.min(p), jnp.max(p)


class Lane(NamedTuple):
    """One (ray, segment) pair's constants for the traversal: the segment, the ray recentred on
    it (o + t0 d = C1 + e), its window [s_a, s_b] in the shell with v = v_a .. v_b across it,
    whether it starts below the relief surface (``inside0``) or meets it at the shell's entry
    (``hit_at_entry``), ``ok`` (the window is not empty), and what the hit needs: t0, the ray's
    (t_min, t_max] and the shell's entry code."""

    seg: FrustaParams
    e: jnp.ndarray
    d: jnp.ndarray
    s_a: jnp.ndarray
    s_b: jnp.ndarray
    v_a: jnp.ndarray
    v_b: jnp.ndarray
    inside0: jnp.ndarray
    hit_at_entry: jnp.ndarray
    ok: jnp.ndarray
    t0: jnp.ndarray
    t_min: jnp.ndarray
    t_max: jnp.ndarray
    entry: jnp.ndarray


class State(NamedTuple):
    """Where one pair's traversal stands: ``phase`` 0 while intervals are decided (the interval
    [s0, s0 + L], ``geo`` at s0 in g0, ``i`` iterations taken), 1 while Newton steps refine the
    bracket [lo, hi] from ``x`` (``k`` steps taken), 2 when done (``found`` a crossing, at x);
    s_und the start of the first interval left undecided (inf where none)."""

    phase: jnp.ndarray
    i: jnp.ndarray
    s0: jnp.ndarray
    g0: tuple
    L: jnp.ndarray
    lo: jnp.ndarray
    hi: jnp.ndarray
    x: jnp.ndarray
    k: jnp.ndarray
    found: jnp.ndarray
    s_und: jnp.ndarray


def begin(maps, q, seg: FrustaParams, o, d, t_min, t_max):
    """(:class:`Lane`, first :class:`State`) of a ray (o, d, t_min, t_max) against a relief
    segment: its whole window the first interval (done at once where the window is empty or the
    ray meets the surface at the shell's entry)."""
    t0, e, s_a, s_b, ok, entry, from_outside = _shell_window(seg, o, d, t_min, t_max)
    v_a, v_b = exact_v(seg, e + s_a * d)[0], exact_v(seg, e + s_b * d)[0]
    ln = Lane(seg, e, d, s_a, s_b, v_a, v_b, False, False, ok, t0, t_min, t_max, entry)
    g = _Field(maps, q, ln).geo(s_a)
    b0 = g[0] - g[5] <= 0
    ln = ln._replace(inside0=(~from_outside) & b0, hit_at_entry=from_outside & b0)
    zero = jnp.zeros((), jnp.int32)
    done = ln.hit_at_entry | ~ok
    st = State(jnp.where(done, 2, 0).astype(jnp.int32), zero, s_a, g, s_b - s_a, s_a, s_a, s_a, zero,
               ln.hit_at_entry & ok, jnp.asarray(jnp.inf, e.dtype))
    return ln, st


def advance(maps, q, ln: Lane, st: State) -> State:
    """One iteration of a pair's traversal (the module's): an interval decided (skipped,
    halved or found to bracket the one crossing) or, in the bracket, one Newton step kept in
    it. A finished pair's state comes back unchanged."""
    return _Field(maps, q, ln).advance(st)


def result(ln: Lane, st: State):
    """(found, s_root, s_undecided) of a finished :class:`State`."""
    return ln.ok & st.found, jnp.where(ln.hit_at_entry, ln.s_a, st.x), st.s_und


def search(maps, q, ln: Lane, st: State):
    """(found, s_root, s_undecided) of one pair from :func:`begin`, its iterations in one ``while_loop``."""
    st = jax.lax.while_loop(lambda st: st.phase < 2, lambda st: advance(maps, q, ln, st), st)
    return result(ln, st)


def lane_fns(maps, q, steps: int):
    """(begin, advance, done, finish, steps) of the traversal for persistent lanes
    (``_intersect.nearest_batch_compact``'s ``lanes``)."""
    return (lambda seg, o, d, t_min, t_max: begin(maps, q, seg, o, d, t_min, t_max),
            lambda ln, st: advance(maps, q, ln, st),
            lambda st: st.phase == 2,
            lambda ln, st: hit_of(maps, q, ln, *result(ln, st)),
            steps)


def relief_t(maps, q, seg: FrustaParams, o, d, t_min, t_max):
    """(t, s, code, t_undecided) of one ray against one relief segment (``_relief_method.make_relief_t``)
    by the exact traversal."""
    ln, st = begin(maps, q, seg, o, d, t_min, t_max)
    # the walk only finds the crossing: on inputs whose derivatives are cut (numerics.frozen),
    # so a derivative's program holds it once; hit_of differentiates the root it found
    return hit_of(maps, q, ln, *search(frozen(maps), q, frozen(ln), frozen(st)))


def relief_root(maps, q, seg: FrustaParams, o, d, t_min, t_max, s_root):
    """(t, s) of a ray's crossing of one relief segment at ``s_root``, the s :func:`relief_t`
    found for it, with :func:`relief_t`'s derivatives but no walk (``_relief.relief_root``)."""
    ln, _ = begin(frozen(maps), q, seg, o, d, t_min, t_max)
    t, s = hit_of(maps, q, ln, True, jax.lax.stop_gradient(s_root), jnp.asarray(jnp.inf, ln.e.dtype))[:2]
    return t, s


def hit_of(maps, q, ln: Lane, found, root, s_und):
    """(t, s, code, t_undecided) of a pair from its :func:`result`: t inf where it has no
    crossing in (t_min, t_max]; s differentiable by the implicit-function theorem
    (``numerics.differentiable_root``); an entry hit is the shell's own analytic root."""
    fl = _Field(maps, q, ln)

    def gap(s):
        g = fl.geo(s)
        return g[0] - g[5]

    inf = jnp.asarray(jnp.inf, ln.e.dtype)
    s_hit = jnp.where(ln.hit_at_entry, ln.s_a, differentiable_root(gap, root))
    t = ln.t0 + s_hit
    good = ln.ok & found & (t > ln.t_min) & (t <= ln.t_max)
    code = jnp.where(ln.hit_at_entry, ln.entry, RELIEF)
    t_und = jnp.where(ln.ok & jnp.isfinite(s_und), ln.t0 + s_und, inf)
    return jnp.where(good, t, inf), s_hit, code.astype(jnp.int32), t_und


class _Field:
    """The ray's height w, the map's h and the bounds between them along one pair's window."""

    def __init__(self, maps, q, ln: Lane):
        self.maps, self.ln, self.v_mode = maps, ln, q.v_mode
        self.levels = q.levels
        seg, e, d = ln.seg, ln.e, ln.d
        self.hh, self.ww = maps.height.shape
        self.su, self.sv = maps.scale[0], maps.scale[1]
        self.period = self.su * self.ww  # X where u wraps
        self.k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
        self.du, self.dm, self.dz = dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w)
        self.ex, self.ez = dot3(e, seg.u), dot3(e, seg.w)
        self.vr = safe_div(ln.v_b - ln.v_a, ln.s_b - ln.s_a, 0.0)  # dv/ds
        self.cp = self.ez * self.du - self.ex * self.dz  # rho^2 dphi/ds, constant along the ray
        self.tiny = 8 * eps_of(e) * (jnp.abs(ln.s_a) + jnp.abs(ln.s_b) + 1e-30)
        self.exact_v = q.uv == "exact"
        if self.exact_v:  # Eq. 7's v = A beta / (A beta - B alpha) (see ``_v_rate``)
            self.nb3 = (dot3(seg.nb, seg.m), dot3(seg.nb, seg.u), dot3(seg.nb, seg.w))
            self.nt3 = (dot3(seg.nt, seg.m), dot3(seg.nt, seg.u), dot3(seg.nt, seg.w))
            self.a_e, self.a_d = seg.db - dot3(seg.nb, e), -dot3(seg.nb, d)  # A(s) = a_e + a_d s
            self.b_e, self.b_d = seg.dt - dot3(seg.nt, e), -dot3(seg.nt, d)

    def geo(self, s):
        """(w, dw/ds, rho^2, X, Y, h, dh/ds) at e + s d: X, Y the texel coordinates h is read at."""
        ln, seg = self.ln, self.ln.seg
        p = ln.e + s * ln.d
        x, y, z = dot3(p, seg.u), dot3(p, seg.m), dot3(p, seg.w)
        rho2 = x * x + z * z
        rho = safe_sqrt(rho2)
        w = safe_div(rho - (seg.r1 + self.k * y), seg.shell, 0.0)
        dw = safe_div(safe_div(x * self.du + z * self.dz, rho, 0.0) - self.k * self.dm, seg.shell, 0.0)
        dphi = safe_div(self.cp, rho2, 0.0)
        if self.exact_v:
            v = exact_v(seg, p)[0]
            sn, cs = safe_div(x, rho, 0.0), safe_div(z, rho, 1.0)  # the angle's sine and cosine
            vd = self._v_rate(self.a_e + self.a_d * s, self.b_e + self.b_d * s, sn, cs, dphi)
        else:
            v = ln.v_a + self.vr * (s - ln.s_a)
            vd = self.vr
        u = _angle_u(seg, p, v)
        vv = (v + seg.v_off) * self.sv
        fx, fy, t00, t01, t10, t11 = bilinear_taps(self.maps, u * self.su, vv, self.v_mode)
        h = ((1 - fx) * (1 - fy) * t00 + fx * (1 - fy) * t01 + (1 - fx) * fy * t10 + fx * fy * t11) / 255.0
        h_x = ((1 - fy) * (t01 - t00) + fy * (t11 - t10)) / 255.0  # per texel
        h_y = ((1 - fx) * (t10 - t00) + fx * (t11 - t01)) / 255.0
        dx = (dphi / _TWO_PI + seg.twist * vd) * self.period
        dh = h_x * dx + h_y * (vd * self.sv * self.hh)
        g = (w, dw, rho2, u * self.period - 0.5, vv * self.hh - 0.5, h, dh)
        return g + (sn, cs, vd) if self.exact_v else g

    def _v_rate(self, A, B, sn, cs, dphi):
        """dv/ds of Eq. 7's exact v at a point: v = A beta / (A beta - B alpha) with A = d_b - n_b . P
        and B = d_t - n_t . P (affine along the ray), alpha = n_b . g and beta = n_t . g (g = m + k
        r_hat, the generator, a function of the angle alone), so dv/ds = [alpha beta (A B' - A' B)
        + A B (alpha' beta - alpha beta')] / (A beta - B alpha)^2; ``_v_bounds`` bounds the same
        expression over an interval."""
        k = self.k
        (bm, bu, bw), (tm, tu, tw) = self.nb3, self.nt3
        al, be = bm + k * (bu * sn + bw * cs), tm + k * (tu * sn + tw * cs)
        al_d, be_d = k * (bu * cs - bw * sn) * dphi, k * (tu * cs - tw * sn) * dphi
        num = al * be * (A * self.b_d - self.a_d * B) + A * B * (al_d * be - al * be_d)
        den = A * be - B * al
        return safe_div(num, den * den, 0.0)

    def _v_bounds(self, s0, g0, s1, g1, ph_lo, ph_hi):
        """(ylo, yhi, vd_lo, vd_hi): the texel row Y's range over [s0, s1] and dv/ds's. The
        approximate v is linear (its ends and its slope). The exact v (Eq. 7) by interval
        arithmetic on :meth:`_v_rate`'s expression: A and B are affine (their ends), alpha and
        beta and their angle derivatives are c0 + k (a sin phi + b cos phi), which moves at most
        k sqrt(a^2 + b^2) per radian, so over an angle span dphi it stays within half that span's
        reach of its ends' mean; phi' lies in [ph_lo, ph_hi]. v = 1 / (1 + B alpha / (-A beta)) is
        monotone in that ratio (A <= 0 <= B between the planes), so its range comes from the
        ratio's; where dv/ds keeps one sign the range is the ends'."""
        Y0, Y1 = g0[4], g1[4]
        if not self.exact_v:
            return jnp.minimum(Y0, Y1), jnp.maximum(Y0, Y1), self.vr, self.vr
        k = self.k
        (bm, bu, bw), (tm, tu, tw) = self.nb3, self.nt3
        s0n, c0, s1n, c1 = g0[7], g0[8], g1[7], g1[8]
        span = jnp.abs(jnp.arctan2(s0n * c1 - c0 * s1n, c0 * c1 + s0n * s1n))

        def wave(a, b):  # the range of a sin phi + b cos phi over the angles between the ends
            f0, f1, r = a * s0n + b * c0, a * s1n + b * c1, jnp.sqrt(a * a + b * b)
            return jnp.maximum(-r, 0.5 * (f0 + f1 - r * span)), jnp.minimum(r, 0.5 * (f0 + f1 + r * span))

        def scaled(c, lohi):
            lo, hi = _mul_range(k, k, *lohi)
            return c + lo, c + hi

        pos = 1e-30
        al = scaled(bm, wave(bu, bw))
        be = scaled(tm, wave(tu, tw))
        al, be = (jnp.maximum(al[0], pos), jnp.maximum(al[1], pos)), (jnp.maximum(be[0], pos), jnp.maximum(be[1], pos))
        al_d = _mul_range(*_mul_range(k, k, *wave(-bw, bu)), ph_lo, ph_hi)
        be_d = _mul_range(*_mul_range(k, k, *wave(-tw, tu)), ph_lo, ph_hi)
        A0, A1 = self.a_e + self.a_d * s0, self.a_e + self.a_d * s1
        B0, B1 = self.b_e + self.b_d * s0, self.b_e + self.b_d * s1
        A = (jnp.minimum(jnp.minimum(A0, A1), 0.0), jnp.minimum(jnp.maximum(A0, A1), 0.0))
        B = (jnp.maximum(jnp.minimum(B0, B1), 0.0), jnp.maximum(jnp.maximum(B0, B1), 0.0))
        inf = jnp.asarray(jnp.inf, s0.dtype)
        t_lo = safe_div(B[0] * al[0], -A[0] * be[1], inf)
        t_hi = safe_div(B[1] * al[1], -A[1] * be[0], inf)
        v_lo, v_hi = 1.0 / (1.0 + t_hi), 1.0 / (1.0 + t_lo)
        ab_ = (jnp.minimum(A[0] * self.b_d, A[1] * self.b_d) - jnp.maximum(self.a_d * B[0], self.a_d * B[1]),
               jnp.maximum(A[0] * self.b_d, A[1] * self.b_d) - jnp.minimum(self.a_d * B[0], self.a_d * B[1]))
        t1 = _mul_range(al[0] * be[0], al[1] * be[1], *ab_)
        x1, x2 = _mul_range(*al_d, *be), _mul_range(*al, *be_d)
        t2 = _mul_range(*_mul_range(*A, *B), x1[0] - x2[1], x1[1] - x2[0])
        num = (t1[0] + t2[0], t1[1] + t2[1])
        a_b, b_a = _mul_range(*A, *be), _mul_range(*B, *al)
        d_hi = jnp.minimum(a_b[1] - b_a[0], 0.0)  # A beta - B alpha <= 0: its square from |d_hi|^2 to |d_lo|^2
        d_lo = a_b[0] - b_a[1]
        q_lo, q_hi = d_hi * d_hi, d_lo * d_lo
        ok = q_lo > 0
        vd_lo = jnp.where(ok, jnp.minimum(num[0] / jnp.where(ok, q_lo, 1.0), num[0] / jnp.where(ok, q_hi, 1.0)), -inf)
        vd_hi = jnp.where(ok, jnp.maximum(num[1] / jnp.where(ok, q_lo, 1.0), num[1] / jnp.where(ok, q_hi, 1.0)), inf)
        mono = (vd_lo > 0) | (vd_hi < 0)
        hh, sv, off = self.hh, self.sv, self.ln.seg.v_off
        ylo = jnp.where(mono, jnp.minimum(Y0, Y1), (v_lo + off) * sv * hh - 0.5)
        yhi = jnp.where(mono, jnp.maximum(Y0, Y1), (v_hi + off) * sv * hh - 0.5)
        return ylo, yhi, vd_lo, vd_hi

    def crossed(self, g):
        return (g[0] - g[5] <= 0) != self.ln.inside0

    def texel(self, jx, jy):
        hh, ww = self.hh, self.ww
        xa = jnp.mod(jx, ww)
        ya = jnp.mod(jy, hh) if self.v_mode == "wrap" else jnp.clip(jy, 0, hh - 1)
        return self.maps.height[ya, xa].astype(self.ln.e.dtype) / 255.0

    def decide(self, s0, g0, s1, g1):
        """(skip, bracket, cut): the interval [s0, s1] holds no crossing / its only crossing; cut
        the distance from s0 to where the level-0 cell at s0 ends along the ray."""
        ln, seg, maps, v_mode = self.ln, self.ln.seg, self.maps, self.v_mode
        hh, ww, period = self.hh, self.ww, self.period
        du, dz, ex, ez = self.du, self.dz, self.ex, self.ez
        Hc = hh if v_mode == "wrap" else hh + 1
        seamless = jnp.mod(period, ww) == 0  # an integer scale_u: the map's columns continue across u = 1
        inf = jnp.asarray(jnp.inf, ln.e.dtype)
        tiny = self.tiny
        L = s1 - s0
        w0, dw0, r0, X0, Y0 = g0[:5]
        w1, dw1, r1, X1, Y1 = g1[:5]
        w_lo = w0 + _least_of_upper([(0.0 * w0, dw0), (w1 - w0 - dw1 * L, dw1)], L)
        w_hi = jnp.maximum(w0, w1)
        # rho^2 over the interval (a convex quadratic) bounds the angle's rate
        qa, qb = du * du + dz * dz, ex * du + ez * dz  # rho^2 = qa s^2 + 2 qb s + (ex^2 + ez^2)
        sv_ = jnp.clip(safe_div(-qb, qa, s0), s0, s1)
        rmin = jnp.minimum(jnp.minimum(r0, r1), qa * sv_ * sv_ + 2 * qb * sv_ + (ex * ex + ez * ez))
        rmax = jnp.maximum(r0, r1)
        a1, a2 = safe_div(self.cp, jnp.maximum(rmin, 0.0), inf), safe_div(self.cp, rmax, 0.0)
        ph_lo, ph_hi = jnp.minimum(a1, a2), jnp.maximum(a1, a2)
        ylo, yhi, vd_lo, vd_hi = self._v_bounds(s0, g0, s1, g1, ph_lo, ph_hi)
        tw_lo, tw_hi = _mul_range(seg.twist, seg.twist, vd_lo, vd_hi)
        xr_lo = (ph_lo / _TWO_PI + tw_lo) * period
        xr_hi = (ph_hi / _TWO_PI + tw_hi) * period
        yr_lo, yr_hi = vd_lo * self.sv * hh, vd_hi * self.sv * hh
        yr = g0[9] * self.sv * hh if self.exact_v else yr_lo  # at s0 (the next row boundary's estimate)
        mono_x = (xr_lo > 0) | (xr_hi < 0) | ((xr_lo == 0) & (xr_hi == 0))
        dX = X1 - X0
        dX = dX - period * jnp.round(safe_div(dX, period, 0.0))
        xlo, xhi = jnp.minimum(X0, X0 + dX), jnp.maximum(X0, X0 + dX)
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
        h_lo, h_hi = _pyramid_bounds(maps.mip, self.levels, cx0, cx1, cy0, cy1, ww, Hc, v_mode == "wrap", whole)
        # one cell: the bilinear's own bounds (at the range's corners) and its slopes
        one = ~whole & (cx0 == cx1) & (cy0 == cy1)
        jy = cy0 if v_mode == "wrap" else cy0 - 1
        t00, t10, t01, t11 = self.texel(cx0, jy), self.texel(cx0 + 1, jy), self.texel(cx0, jy + 1), self.texel(cx0 + 1, jy + 1)
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
        py = _mul_range(jnp.min(hy), jnp.max(hy), yr_lo, yr_hi)
        g_lo, g_hi = dw0 - (px[1] + py[1]), dw1 - (px[0] + py[0])  # bounds of g' = w' - h'
        mono = one & strict & mono_x & ((g_lo > 0) | (g_hi < 0))
        c1 = self.crossed(g1)
        apart = jnp.where(ln.inside0, w_hi <= h_lo, w_lo > h_hi)
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

    def advance(self, st: State) -> State:
        ln, tiny = self.ln, self.tiny
        inf = jnp.asarray(jnp.inf, ln.e.dtype)
        trav, newt = st.phase == 0, st.phase == 1
        s1 = jnp.where(newt, st.x, jnp.minimum(st.s0 + st.L, ln.s_b))
        g1 = self.geo(s1)  # the next interval's end, or the Newton iterate
        # an interval (phase 0)
        skip, bracket, cut = self.decide(st.s0, st.g0, s1, g1)
        floor = (s1 - st.s0) <= tiny
        stuck = floor & ~skip & ~bracket  # a graze within rounding: left undecided, passed over
        s_und = jnp.where(trav & stuck & ~jnp.isfinite(st.s_und), st.s0, st.s_und)
        move = skip | stuck
        end = move & (s1 >= ln.s_b)
        s0n = jnp.where(move, s1, st.s0)
        g0n = tuple(jnp.where(move, b, a) for a, b in zip(st.g0, g1))
        Ln = jnp.where(move, 2 * st.L, jnp.where(bracket, st.L, jnp.minimum(0.5 * st.L, cut)))
        # the bracket's first iterate: the secant of g over it, inside it
        ga, gb = st.g0[0] - st.g0[5], g1[0] - g1[5]
        sec = st.s0 + (s1 - st.s0) * safe_div(ga, ga - gb, 0.5)
        x0 = jnp.where((sec > st.s0) & (sec < s1), sec, 0.5 * (st.s0 + s1))
        i = st.i + 1
        out = (i >= LOOPS) & ~bracket & ~end  # out of iterations: undecided from where it stopped
        s_und = jnp.where(out, jnp.minimum(s_und, s0n), s_und)
        ph_t = jnp.where(bracket, 1, jnp.where(end | out, 2, 0))
        # a Newton step in the bracket (phase 1): g is monotone there, one crossing
        gx, dg = g1[0] - g1[5], g1[1] - g1[6]
        cx = self.crossed(g1)
        a, b = jnp.where(cx, st.lo, st.x), jnp.where(cx, st.x, st.hi)
        xn = st.x - safe_div(gx, dg, inf)
        xn = jnp.where(gx == 0, st.x, jnp.where((xn >= a) & (xn <= b), xn, 0.5 * (a + b)))
        kn = st.k + 1
        conv = (gx == 0) | (jnp.abs(xn - st.x) <= tiny) | (kn >= NEWTON)
        ph_n = jnp.where(conv, 2, 1)
        pick = lambda t_, n_, keep: jnp.where(trav, t_, jnp.where(newt, n_, keep))  # noqa: E731
        return State(
            phase=pick(ph_t, ph_n, st.phase).astype(jnp.int32),
            i=jnp.where(trav, i, st.i),
            s0=jnp.where(trav, s0n, st.s0),
            g0=tuple(jnp.where(trav, a_, b_) for a_, b_ in zip(g0n, st.g0)),
            L=jnp.where(trav, Ln, st.L),
            lo=pick(st.s0, a, st.lo),
            hi=pick(s1, b, st.hi),
            x=pick(x0, xn, st.x),
            k=jnp.where(newt, kn, st.k),
            found=st.found | (trav & bracket),
            s_und=jnp.where(trav, s_und, st.s_und),
        )
