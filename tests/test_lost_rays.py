"""No ray lost silently: every way a tracer can fail to decide a ray has its own flag bit
(``jskel.rays.FLAG_NAMES``, the one table in docs/numerics.md), and a ray either hits within
tolerance of a float64 NumPy reference written here or carries a flag.

Constructed rays, one per flag: Rouiller's Fig. 7 (two balls that only just blend, a ray
through the bridge whose Sec. 4.2.1 inside points are both outside), a ray from 1e6 away with a
tolerance of 1e-9 (below float32's spacing there), a ray tangent to a ball's threshold sphere,
a step cap and a candidate overflow; for cells, a ray from far away and a step cap. Then fuzzed
rays over 20 decades of scale with origins up to 1e5 sizes away.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import whole_chunks
from jskel import cells, implicit, rays
from jskel.interface import Object, intersect_each
from jskel.rays import FLAG_FLOAT_SPACING, FLAG_GRAZE, FLAG_NAMES, FLAG_NO_BRACKET, FLAG_OVERFLOW, FLAG_STEP_CAP, make_rays

T = 0.5
RHO = np.sqrt(1 - np.sqrt(T))  # a lone ball of R = 1: (1 - rho^2)^2 = T
CHUNK = 64  # one chunk shape for every cast here: one compile per tracer setting
EPS32 = float(np.finfo(np.float32).eps)


# ---------------------------------------------------------------- float64 NumPy reference


def np_field(x, a, b, ra, rb):
    """F(x) = sum of (1 - r^2/R^2)^2 within R, r the distance to a point or segment, R
    interpolated along it (Rouiller 2011, Sec. 3); x (..., 3)."""
    ab = b - a
    ax = x[..., None, :] - a
    den = np.sum(ab * ab, -1)
    s = np.clip(np.where(den > 0, np.sum(ax * ab, -1) / np.where(den > 0, den, 1.0), 0.0), 0.0, 1.0)
    e = ax - s[..., None] * ab
    R = ra + (rb - ra) * s
    q = np.sum(e * e, -1) / (R * R)
    return np.sum(np.where(q < 1, (1 - q) ** 2, 0.0), -1)


def np_first_root(O, D, a, b, ra, rb, n=8192, batch=16):
    """First t > 0 with F > T (inf: none) by a dense uniform march over the union of the
    influence spheres, then 60 bisections of the first bracket; float64."""
    c = 0.5 * (a + b)
    reach = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(ra, rb)
    dd = np.sum(D * D, 1)
    oc = c[None] - O[:, None]
    tc = np.sum(oc * D[:, None], -1) / dd[:, None]
    d2 = np.sum((oc - tc[..., None] * D[:, None]) ** 2, -1)
    half = np.sqrt(np.maximum(reach**2 - d2, 0) / dd[:, None])
    met = d2 < reach**2
    lo = np.where(met, np.maximum(tc - half, 0.0), np.inf).min(1)
    hi = np.where(met, tc + half, -np.inf).max(1)
    out = np.full(len(O), np.inf)
    u = np.linspace(0.0, 1.0, n + 1)
    todo = np.nonzero(hi > lo)[0]
    for i in np.array_split(todo, max(1, todo.size // batch)) if todo.size else ():
        ts = lo[i, None] + (hi - lo)[i, None] * u
        inside = np_field(O[i, None] + ts[..., None] * D[i, None], a, b, ra, rb) > T
        found = inside.any(1)
        k = np.argmax(inside, 1)
        tl, th = ts[np.arange(i.size), np.maximum(k - 1, 0)], ts[np.arange(i.size), k]
        for _ in range(60):
            m = 0.5 * (tl + th)
            fin = np_field(O[i] + m[:, None] * D[i], a, b, ra, rb) > T
            th, tl = np.where(fin, m, th), np.where(fin, tl, m)
        out[i] = np.where(found, np.where(k == 0, ts[:, 0], th), np.inf)
    return out


# ---------------------------------------------------------------- casting


def implicit_model(balls, tubes=(), **kw):
    cfg = {"type": "implicit", "threshold": T, "balls": [{"center": list(map(float, c)), "radius": float(r)} for c, r in balls],
           "tubes": [{"a": list(map(float, p)), "b": list(map(float, q)), "radius_a": float(r1), "radius_b": float(r2)} for p, q, r1, r2 in tubes]}
    return implicit.build(implicit.ImplicitConfig.model_validate({**cfg, **kw}))


def arrays(balls, tubes=()):
    a = np.array([c for c, _ in balls] + [t[0] for t in tubes], float)
    b = np.array([c for c, _ in balls] + [t[1] for t in tubes], float)
    ra = np.array([r for _, r in balls] + [t[2] for t in tubes], float)
    rb = np.array([r for _, r in balls] + [t[3] for t in tubes], float)
    return a, b, ra, rb


def cast(built, O, D, name="implicit", t_max=np.inf):
    """Rays (float64 world) relative to the anchor as the tracer gets them (float32); returns the
    NumPy Hit and those rays in float64 (the exact rays traced, for the reference)."""
    r = make_rays(np.asarray(O, np.float64) - built.anchor, D, t_max=t_max)
    out = whole_chunks(intersect_each, Object(built.params, built.static, name), r, CHUNK)
    return out, np.asarray(r.origins, np.float64) + built.anchor, np.asarray(r.directions, np.float64)


# ---------------------------------------------------------------- the one table


def test_flag_bits_are_distinct_named_once_and_counted_by_name():
    bits = list(FLAG_NAMES)
    assert all(b > 0 and b & (b - 1) == 0 for b in bits) and len(set(bits)) == len(bits)
    assert len(set(FLAG_NAMES.values())) == len(bits)
    assert {FLAG_OVERFLOW, FLAG_STEP_CAP, FLAG_NO_BRACKET, FLAG_FLOAT_SPACING, FLAG_GRAZE} <= set(bits)
    # docs/numerics.md: one table, a row per bit, in bit order, with the same names
    text = (Path(__file__).parent.parent / "docs" / "numerics.md").read_text()
    rows = re.findall(r"^\| `(\d+)` \| `(\w+)` \|", text, flags=re.M)
    assert [(int(b), n) for b, n in rows] == list(FLAG_NAMES.items())
    # run.json's counts: per bit, by name
    from jskel.render import _flag_counts

    f = np.random.default_rng(0).integers(0, 2 * max(bits), size=500).astype(np.int32)
    want = {n: int(sum(((int(v) >> (b.bit_length() - 1)) & 1) for v in f)) for b, n in FLAG_NAMES.items()}
    assert rays.flag_counts(f) == want and _flag_counts(f) == want


def test_flags_scattered_to_pixels_keep_every_bit():
    """Several rays of one pixel (samples, secondary levels): their flags OR together; a max
    of the bit sets (what a scatter offers) would keep 4 of 4 | 1 and lose the 1."""
    import jax.numpy as jnp

    base = np.array([0, 2, 0, 0], np.int32)
    index = np.array([0, 0, 1, 3, 7])  # 7: out of range, dropped
    values = np.array([FLAG_NO_BRACKET, FLAG_OVERFLOW, FLAG_GRAZE | FLAG_STEP_CAP, 0, FLAG_GRAZE], np.int32)
    got = np.asarray(rays.or_flags_at(jnp.asarray(base), jnp.asarray(index), jnp.asarray(values)))
    want = base.copy()
    for i, v in zip(index, values):
        if i < len(want):
            want[i] |= v
    np.testing.assert_array_equal(got, want)
    assert got[0] == FLAG_NO_BRACKET | FLAG_OVERFLOW and got[1] == 2 | FLAG_GRAZE | FLAG_STEP_CAP


# ---------------------------------------------------------------- constructed rays

S = 0.68  # two balls of R = 1 that only just blend (Fig. 7)
FIG7 = [((-S, 0.0, 0.0), 1.0), ((S, 0.0, 0.0), 1.0)]
U = np.array([0.6, 0.0, 0.8])  # through the bridge at (0, 0.15, 0), tilted along the axis
FIG7_O, FIG7_D = np.array([[0.0, 0.15, 0.0]]) - 3.0 * U, U[None]


def test_figure7_ray_is_flagged_not_silently_missed():
    a, b, ra, rb = arrays(FIG7)
    # the case itself, in float64: the bridge point is inside, both centre projections are not
    proj = [FIG7_O[0] + np.dot(c - FIG7_O[0], U) * U for c in a]
    assert np_field(np.array([0.0, 0.15, 0.0]), a, b, ra, rb) > T
    assert all(np_field(p, a, b, ra, rb) < T for p in proj)
    t_ref = np_first_root(FIG7_O, FIG7_D, a, b, ra, rb)
    assert np.isfinite(t_ref[0])
    bis, _, _ = cast(implicit_model(FIG7, method="bisection"), FIG7_O, FIG7_D)
    assert not np.isfinite(bis.t[0]) and bis.flags[0] & FLAG_NO_BRACKET  # Sec. 4.2.2's miss, said
    lip, _, _ = cast(implicit_model(FIG7), FIG7_O, FIG7_D)
    assert lip.flags[0] == 0 and abs(lip.t[0] - t_ref[0]) < 2e-3


def test_bisection_that_brackets_a_later_crossing_is_flagged():
    """Sec. 4.2.2: the bracket from the entry into the first sphere of influence to the inside
    point of a third ball 4 along the ray straddles Fig. 7's bridge (inside points outside) and
    the ball; the first halving lands past the bridge, so the bisection converges on the ball.
    That hit is flagged; the Lipschitz march finds the bridge."""
    balls = FIG7 + [(tuple(np.array([0.0, 0.15, 0.0]) + 4.0 * U), 1.0)]
    t_ref = np_first_root(FIG7_O, FIG7_D, *arrays(balls))
    assert 2.5 < t_ref[0] < 3.0  # the case, in float64: the bridge is the first crossing
    bis, _, _ = cast(implicit_model(balls, method="bisection"), FIG7_O, FIG7_D)
    assert bis.t[0] > t_ref[0] + 1.0 and bis.flags[0] & FLAG_GRAZE
    lip, _, _ = cast(implicit_model(balls), FIG7_O, FIG7_D)
    assert lip.flags[0] == 0 and abs(lip.t[0] - t_ref[0]) < 2e-3


def test_bisection_miss_that_the_bound_excludes_is_not_flagged():
    """A ray through one ball's influence sphere but outside its surface: the field's bound on
    the ray, kernel(distance to the line), is below T, so the miss is decided."""
    O, D = np.array([[0.0, RHO + 0.05, -3.0]]), np.array([[0.0, 0.0, 1.0]])
    hit, _, _ = cast(implicit_model([((0, 0, 0), 1.0)], method="bisection"), O, D)
    assert not np.isfinite(hit.t[0]) and hit.flags[0] == 0


def test_far_ray_with_a_tolerance_below_the_float_spacing_is_a_flagged_hit():
    """eps = 1e-9 at t = 1e6: float32's spacing there is 0.0625, so t + eps == t. The march
    steps by a few ulps of t instead (no stall into the step cap) and says so."""
    balls = [((0, 0, 0), 1.0)]
    O, D = np.array([[0.0, 0.1, -1e6], [0.0, 0.1, -3.0]]), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    built = implicit_model(balls, eps=1e-9, method="lipschitz")
    hit, Of, Df = cast(built, O, D)
    t_ref = np_first_root(Of - built.anchor, Df, *arrays([((0, 0, 0) - built.anchor, 1.0)]))
    assert np.all(hit.flags & FLAG_FLOAT_SPACING) and not np.any(hit.flags & FLAG_STEP_CAP)
    assert np.all(np.isfinite(hit.t))
    np.testing.assert_allclose(hit.t, t_ref, rtol=8 * EPS32, atol=1e-6)
    # a tolerance above the spacing: no flag
    ok, _, _ = cast(implicit_model(balls, eps=1e-3, method="lipschitz"), O[1:], D[1:])
    assert ok.flags[0] == 0 and abs(ok.t[0] - t_ref[1]) < 1e-3


@pytest.mark.parametrize("method", ["lipschitz", "naive"])
def test_tangent_ray_is_flagged_graze_and_a_dipping_one_hits(method):
    """Rays along z at a distance rho + 1e-5 (outside, tangent within the tolerance) and
    rho - 1e-4 (inside for a chord of 2 sqrt(rho^2 - y^2)) from a lone ball's centre."""
    ys = np.array([RHO + 1e-5, RHO - 1e-4])
    O = np.stack([np.zeros(2), ys, np.full(2, -3.0)], 1)
    D = np.tile([0.0, 0.0, 1.0], (2, 1))
    hit, _, _ = cast(implicit_model([((0, 0, 0), 1.0)], method=method, step=0.05), O, D)
    assert not np.isfinite(hit.t[0]) and hit.flags[0] & FLAG_GRAZE
    t_exact = 3.0 - np.sqrt(RHO**2 - ys[1] ** 2)
    assert np.isfinite(hit.t[1]) and hit.flags[1] == 0 and abs(hit.t[1] - t_exact) < 1e-3


@pytest.mark.parametrize("method", ["lipschitz", "naive", "bisection"])
def test_rays_near_tangent_hit_the_reference_or_carry_a_flag(method):
    """Rays tangent to a ball's threshold sphere, offset by 1e-7 .. 1e-1 (log-uniform, either
    side, seeded): each hits within tolerance of the float64 march or carries a flag."""
    rng = np.random.default_rng(5)
    u = rng.normal(size=(CHUNK, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = rng.normal(size=(CHUNK, 3))
    w -= np.sum(w * u, 1, keepdims=True) * u
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    delta = 10.0 ** rng.uniform(-7, -1, CHUNK) * rng.choice([-1.0, 1.0], CHUNK)
    O = w * (RHO + delta)[:, None] - 3.0 * u
    built = implicit_model([((0, 0, 0), 1.0)], method=method, step=0.05)
    hit, Of, Df = cast(built, O, u)
    t_ref = np_first_root(Of - built.anchor, Df, *arrays([(-built.anchor, 1.0)]), n=32768, batch=4)
    assert 0.2 < np.mean(np.isfinite(t_ref)) < 0.8
    both = np.isfinite(hit.t) & np.isfinite(t_ref)
    ok = (~np.isfinite(hit.t) & ~np.isfinite(t_ref)) | (both & (np.abs(np.where(both, hit.t, 0) - np.where(both, t_ref, 0)) <= 2e-3))
    flag = hit.flags != 0
    assert not np.any(~ok & ~flag), (delta[~ok & ~flag], hit.t[~ok & ~flag], t_ref[~ok & ~flag])
    assert np.any(flag) and np.any(ok & ~flag)


@pytest.mark.parametrize("method", ["lipschitz", "naive", "bisection", "exact"])
def test_a_surface_just_before_the_rays_far_end_is_found(method):
    """A ray whose window ends ``delta`` past a lone ball's surface (1e-6 .. 1e-2, log-uniform,
    seeded; the step is 0.05 and eps 1e-3, so the march's next sample lies beyond t_max) hits it
    at the closed-form t, 3 - sqrt(rho^2 - y^2), or carries a flag; one ending ``delta`` before
    it misses. The march once tested no sample in its last step's piece, and read a crossing
    there as excluded because the field is 0 past the primitives' reach, which t_max cut short:
    a silent miss (found by ``jskel.refine``'s short recasts)."""
    rng = np.random.default_rng(11)
    y = rng.uniform(0.0, 0.9 * RHO, CHUNK)
    delta = 10.0 ** rng.uniform(-6, -2, CHUNK)
    t0 = 3.0 - np.sqrt(RHO**2 - y**2)
    after = np.arange(CHUNK) % 4 != 0  # a quarter end before the surface
    O = np.stack([np.zeros(CHUNK), y, np.full(CHUNK, -3.0)], 1)
    D = np.tile([0.0, 0.0, 1.0], (CHUNK, 1))
    built = implicit_model([((0, 0, 0), 1.0)], method=method, step=0.05)
    hit, _, _ = cast(built, O, D, t_max=np.where(after, t0 + delta, t0 - delta))
    found = after & np.isfinite(hit.t) & (np.abs(hit.t - t0) <= 1e-3)
    silent = after & ~found & (hit.flags == 0)
    assert not np.any(silent), (np.sum(silent), delta[silent][:4], hit.t[silent][:4])
    assert np.mean(found[after]) > 0.9
    assert not np.any(np.isfinite(hit.t[~after]))


_SADDLES: dict = {}


def _saddle_rays(gap: float):
    """Two balls of R = 1 whose blend at the origin is ``T + gap``, rays along z passing 1e-6 ..
    1e-2 from it in x and y (seeded), and the float64 march's first roots on them (computed once)."""
    if gap not in _SADDLES:
        rng = np.random.default_rng(int(17 + 1e6 * abs(gap)))
        s = np.sqrt(1.0 - np.sqrt((T + gap) / 2.0))
        off = 10.0 ** rng.uniform(-6, -2, (CHUNK, 2)) * rng.choice([-1.0, 1.0], (CHUNK, 2))
        O = np.stack([off[:, 0], off[:, 1], np.full(CHUNK, -3.0)], 1)
        D = np.tile([0.0, 0.0, 1.0], (CHUNK, 1))
        balls = [((-s, 0, 0), 1.0), ((s, 0, 0), 1.0)]
        anchor = implicit_model(balls).anchor
        r = make_rays(O - anchor, D)  # the rays as the tracer gets them (float32)
        Of, Df = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)
        t_ref = np_first_root(Of, Df, *arrays([(np.array(c) - anchor, rad) for c, rad in balls]), n=65536, batch=4)
        _SADDLES[gap] = balls, O, D, t_ref
    return _SADDLES[gap]


@pytest.mark.parametrize("method", ["lipschitz", "naive", "bisection"])
def test_rays_through_a_saddle_of_the_field_hit_the_reference_or_carry_a_flag(method):
    """A saddle (issue 29, class 1): two balls of R = 1 at x = +-s blend at the origin with
    F = 2 (1 - s^2)^2, a minimum along x and a maximum across it. Three pairs of balls put that
    value at T - 1e-3, T - 1e-6 and T + 1e-4; rays along z pass 1e-6 .. 1e-2 (log-uniform, either
    side) from the saddle in x and y, so the field along each peaks within a hair of T on either
    side. Each ray hits within tolerance of the float64 march or carries a flag, never a silent
    miss or a wrong hit; the set holds rays of both outcomes, and the Lipschitz march and the
    bisection decide more than half a chunk of the hits without a flag."""
    ok_all, flag_all, hits_ref = [], [], []
    for gap in (-1e-3, -1e-6, 1e-4):
        balls, O, D, t_ref = _saddle_rays(gap)
        hit, _, _ = cast(implicit_model(balls, method=method, step=0.05), O, D)
        both = np.isfinite(hit.t) & np.isfinite(t_ref)
        close = np.abs(np.where(both, hit.t, 0) - np.where(both, t_ref, 0)) <= 2e-3
        ok_all.append((~np.isfinite(hit.t) & ~np.isfinite(t_ref)) | (both & close))
        flag_all.append(hit.flags != 0)
        hits_ref.append(np.isfinite(t_ref))
    ok, flag, ref = (np.concatenate(x) for x in (ok_all, flag_all, hits_ref))
    assert 0.1 < ref.mean() < 0.9
    assert not np.any(~ok & ~flag), np.nonzero(~ok & ~flag)[0]
    assert np.any(flag)
    if method != "naive":  # (the naive march's step, 0.05, is longer than every chord here: it flags them all)
        assert np.sum(ok & ~flag & ref) > CHUNK // 2


def test_step_cap_and_overflow_are_flagged():
    O, D = np.array([[0.0, 0.3, -3.0]]), np.array([[0.0, 0.0, 1.0]])
    capped, _, _ = cast(implicit_model([((0, 0, 0), 1.0)], steps=2, method="lipschitz"), O, D)
    assert not np.isfinite(capped.t[0]) and capped.flags[0] & FLAG_STEP_CAP
    over, _, _ = cast(implicit_model(FIG7, capacity=1), np.array([[0.0, 0.0, -3.0]]), D)
    assert over.flags[0] & FLAG_OVERFLOW


# ---------------------------------------------------------------- fuzz: hit or flag, never a silent miss


def _fuzz_models(rng, n_models=8, n_rays=CHUNK):
    """Models of 3 balls and a tube at scales 10^-10 .. 10^10 (log-uniform), rays from 3 to
    1e5 sizes away (log-uniform) aimed at the model's box."""
    for scale in 10.0 ** np.linspace(-10, 10, n_models):
        balls = [(tuple(rng.uniform(-0.6, 0.6, 3) * scale), rng.uniform(0.5, 0.9) * scale) for _ in range(3)]
        p = rng.uniform(-0.6, 0.6, 3)
        tubes = [(tuple(p * scale), tuple((p + rng.normal(size=3) * 0.5) * scale), rng.uniform(0.4, 0.7) * scale,
                  rng.uniform(0.4, 0.7) * scale)]
        centre = rng.uniform(-1, 1, 3) * scale * 10.0 ** rng.uniform(0, 5)  # the model anywhere
        balls = [(tuple(np.add(c, centre)), r) for c, r in balls]
        tubes = [(tuple(np.add(a, centre)), tuple(np.add(b, centre)), r1, r2) for a, b, r1, r2 in tubes]
        u = rng.normal(size=(n_rays, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        O = centre + u * scale * 10.0 ** rng.uniform(0.5, 5, (n_rays, 1))
        D = centre + rng.uniform(-1.2, 1.2, (n_rays, 3)) * scale - O
        yield scale, balls, tubes, O, D / np.linalg.norm(D, axis=1, keepdims=True)


@pytest.mark.parametrize("method", ["lipschitz", "naive", "bisection", "exact"])
def test_fuzzed_rays_hit_the_float64_reference_or_carry_a_flag(method):
    """Every ray either hits within tolerance of the reference (or misses with it) or carries a
    flag, for every method: the thesis' bisection flags a hit whose bracket may hold an earlier
    crossing (Sec. 4.2.2) and a miss its bound cannot confirm (Fig. 7)."""
    rng = np.random.default_rng(29)
    agree = flagged = 0
    for scale, balls, tubes, O, D in _fuzz_models(rng):
        built = implicit_model(balls, tubes, method=method, eps=1e-3 * scale, step=0.01 * scale)
        hit, Of, Df = cast(built, O, D)
        a, b, ra, rb = arrays(balls, tubes)
        Or = Of - built.anchor  # the reference in float64 on the very rays traced
        t_ref = np_first_root(Or, Df, a - built.anchor, b - built.anchor, ra, rb)
        tol = 2e-3 * scale + 64 * EPS32 * (np.abs(np.where(np.isfinite(t_ref), t_ref, 0)) + np.linalg.norm(Or, axis=1))
        both_miss = ~np.isfinite(hit.t) & ~np.isfinite(t_ref)
        close = np.isfinite(hit.t) & np.isfinite(t_ref) & (np.abs(np.where(np.isfinite(hit.t), hit.t, 0) - t_ref) <= tol)
        ok = both_miss | close
        flag = hit.flags != 0
        silent_miss = ~np.isfinite(hit.t) & np.isfinite(t_ref) & ~flag
        assert not np.any(silent_miss), (scale, O[silent_miss], D[silent_miss], t_ref[silent_miss])
        wrong = ~ok & ~flag
        assert not np.any(wrong), (scale, hit.t[wrong], t_ref[wrong], hit.flags[wrong])
        agree += int(np.sum(ok & ~flag))
        flagged += int(np.sum(flag))
    n = 8 * CHUNK
    print(f"{method}: {agree} agree, {flagged} flagged, of {n}")
    assert agree > 0.5 * n  # most rays are decided (the far ones carry FLOAT_SPACING)


# ---------------------------------------------------------------- the build's check that a surface exists


def test_build_accepts_a_surface_whose_maximum_lies_between_centres():
    """Two balls of R = 1 at distance sqrt(0.5): F = 1 + (1 - 0.5)^2 = 1.25 at each centre,
    2 (1 - 0.5 / 4)^2 = 1.53 halfway. T = 1.4 has a surface (around the midpoint) that a check
    sampling F at the centres rejected; the bound accepts it, and rays find that surface."""
    h = np.sqrt(0.5) / 2
    balls = [((-h, 0.0, 0.0), 1.0), ((h, 0.0, 0.0), 1.0)]
    a, b, ra, rb = arrays(balls)
    x = np.linspace(-1.5, 1.5, 3001)[:, None] * [1.0, 0.0, 0.0]
    F = np_field(x, a, b, ra, rb)
    centres = np_field(a, a, b, ra, rb)
    assert np.all(centres < 1.4) and F.max() > 1.4 and abs(x[np.argmax(F), 0]) < 1e-3  # the case, in float64
    built = implicit_model(balls, threshold=1.4)
    assert built.info["max_field_bound"] >= F.max()
    O = np.array([[0.0, -3.0, 0.0], [0.0, 0.0, -3.0]])
    D = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    hit, Of, Df = cast(built, O, D)
    # the surface crossing along each ray through the midpoint, in float64: 2 (1 - (h^2 + s^2))^2 = 1.4
    s = np.sqrt(1 - np.sqrt(0.7) - h * h)
    np.testing.assert_allclose(hit.t, 3.0 - s, atol=1e-3)
    assert np.all(hit.flags == 0)
    # a threshold no point reaches is still refused: F <= 2 everywhere (two kernels of at most 1)
    with pytest.raises(ValueError, match=r"object\.threshold: 2\.1 is not below a bound"):
        implicit_model(balls, threshold=2.1)


# ---------------------------------------------------------------- cells: the linear search


def test_cells_far_ray_and_step_cap_are_flagged(tmp_path):
    """A cell torus (Nürnberg Sec. 3.2's linear search, steps of 1/256 tile): from 1e5 away the
    step is below float32's spacing at t and is raised to it, flagged; from 3 away it is not;
    with max_steps = 2 a ray that needs more samples is flagged STEP_CAP."""
    base = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
            "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 6,
            "search": "linear", "steps_per_tile": 256, "bisection": 10, "cache": str(tmp_path / "cache")}
    built = cells.build(cells.CellsConfig.model_validate(base))
    O = np.array([[1.0, 0.0, -1e5], [1.0, 0.0, -3.0]])
    D = np.tile([0.0, 0.0, 1.0], (2, 1))
    hit, _, _ = cast(built, O, D, "cells")
    size = float(built.bounds[1][0] - built.bounds[0][0]) / 6
    assert size / 256 < 4 * EPS32 * 1e5  # the case: the step is below a few ulps of t = 1e5
    assert hit.flags[0] & FLAG_FLOAT_SPACING and hit.flags[1] == 0
    assert np.all(np.isfinite(hit.t))
    # the same line: the far ray finds the near one's cell, within its raised step (and t's spacing)
    assert hit.prim[0] == hit.prim[1]
    assert abs((hit.t[0] + O[0, 2]) - (hit.t[1] + O[1, 2])) <= 8 * EPS32 * 1e5
    capped, _, _ = cast(cells.build(cells.CellsConfig.model_validate({**base, "max_steps": 2})), O[1:], D[1:], "cells")
    assert not np.isfinite(capped.t[0]) and capped.flags[0] & FLAG_STEP_CAP


def test_cells_part_stepped_over_between_samples_is_flagged(tmp_path):
    """A cell that is a box of tile-map voxels (16 per tile edge), a linear step of 1/24 tile (2/3
    of a voxel: Nürnberg Sec. 5.3's knob) and rays across one edge of the box, inside it by up to
    0.2 voxel: their chord through the box is shorter than a step, so the samples straddle it.
    Against ray-box slabs in float64: every ray the box stops is a hit or flagged ``graze`` (the
    voxels between two samples looked up, ``cells._trace.stepped_over``), never a silent miss,
    and no ray the box does not stop is flagged."""
    tile = np.zeros((16, 16, 16), np.int64)
    tile[4:12, 3:13, 5:11] = 1
    np.save(tmp_path / "tile.npy", tile)
    cfg = {"type": "cells", "base": {"type": "sphere", "radius": 1.0}, "tiles": 1, "search": "linear", "steps_per_tile": 24,
           "tile_map": {"type": "file", "path": str(tmp_path / "tile.npy")}, "cache": None}
    built = cells.build(cells.CellsConfig.model_validate(cfg))
    size = built.info["tile_size"]
    vox = size / 16
    blo, bhi = built.bounds[0] + vox * np.array([4, 3, 5]), built.bounds[0] + vox * np.array([12, 13, 11])
    rng = np.random.default_rng(3)
    D = np.stack([np.ones(CHUNK), -rng.uniform(0.5, 2, CHUNK), rng.uniform(-0.3, 0.3, CHUNK)], 1)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    edge = np.stack([np.full(CHUNK, blo[0]), np.full(CHUNK, blo[1]), rng.uniform(blo[2] + vox, bhi[2] - vox, CHUNK)], 1)
    inward = np.cross(D, [0.0, 0.0, 1.0])
    inward *= np.sign(inward[:, :1] + inward[:, 1:2]) / np.linalg.norm(inward, axis=1, keepdims=True)
    O = edge + inward * vox * rng.uniform(-0.2, 0.2, (CHUNK, 1)) - 2.0 * size * D
    hit, Of, Df = cast(built, O, D, "cells")
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (blo - Of) / Df, (bhi - Of) / Df
    near, far = np.minimum(ta, tb).max(1), np.maximum(ta, tb).min(1)
    stops = near <= far
    graze = (hit.flags & FLAG_GRAZE) != 0
    got = np.isfinite(hit.t)
    assert np.sum(stops & ~got) > 5  # the case: chords between samples
    assert np.all(got | graze | ~stops) and not np.any(graze & ~stops)
    assert np.all(np.abs(hit.t[got] - near[got]) <= size / 24)  # the hits: within one step of the box


@pytest.mark.parametrize("search", ["linear", "voxels"])
def test_cells_surface_just_before_the_rays_far_end_is_found(tmp_path, search):
    """The box cell above (steps of 1/24 tile, 2/3 of a voxel), rays across its face x = lo whose
    window ends ``delta`` past that face (1e-4 .. 0.5 of a step: the linear search's next sample
    lies beyond t_max): each hits within one step of the float64 slab entry, or carries a
    flag; a window ending before the face misses. The linear search once stopped at its last
    sample inside the window and left the piece up to t_max unsearched: a silent miss."""
    tile = np.zeros((16, 16, 16), np.int64)
    tile[4:12, 3:13, 5:11] = 1
    np.save(tmp_path / "tile.npy", tile)
    cfg = {"type": "cells", "base": {"type": "sphere", "radius": 1.0}, "tiles": 1, "steps_per_tile": 24,
           "tile_map": {"type": "file", "path": str(tmp_path / "tile.npy")}, "cache": None, "search": search}
    built = cells.build(cells.CellsConfig.model_validate(cfg))
    size = built.info["tile_size"]
    vox, step = size / 16, size / 24
    blo, bhi = built.bounds[0] + vox * np.array([4, 3, 5]), built.bounds[0] + vox * np.array([12, 13, 11])
    rng = np.random.default_rng(17)
    P = rng.uniform(blo + vox, bhi - vox, (CHUNK, 3))
    P[:, 0] = blo[0]  # on the face; tilted rays, so that no sample lands on it
    D = np.stack([np.ones(CHUNK), rng.uniform(-0.3, 0.3, CHUNK), rng.uniform(-0.3, 0.3, CHUNK)], 1)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    t_face = np.full(CHUNK, 0.6 * size)
    O = P - t_face[:, None] * D
    delta = step * 10.0 ** rng.uniform(-4, np.log10(0.5), CHUNK)
    after = np.arange(CHUNK) % 4 != 0
    r = make_rays(np.asarray(O, np.float64) - built.anchor, D, t_max=np.where(after, t_face + delta, t_face - delta))
    hit = whole_chunks(intersect_each, Object(built.params, built.static, "cells"), r, CHUNK)
    found = after & np.isfinite(hit.t) & (np.abs(hit.t - t_face) <= step)
    silent = after & ~found & (hit.flags == 0)
    assert not np.any(silent), (np.sum(silent), (delta / step)[silent][:4], hit.t[silent][:4])
    assert np.mean(found[after]) > 0.9
    assert not np.any(np.isfinite(hit.t[~after]))


# ---------------------------------------------------------------- the renderer keeps them


def test_render_keeps_the_flags_of_rays_that_miss_and_counts_them_by_name():
    """One ball (R = 1, T = 0.5, Lipschitz L = 8 / (3 sqrt 3)) with ``steps: 1``: the march's
    one sample is the entry into the sphere of influence (F = 0), its next step T / L; a ray
    whose chord 2 sqrt(1 - b^2) through that sphere is longer than T / L (b: its distance from
    the centre) stops at the cap, a miss that must reach ``flags.npy`` and ``run.json``."""
    from jskel.config import validate
    from jskel.render import camera_of, render

    exp = validate({"object": {"type": "implicit", "threshold": T, "method": "lipschitz", "steps": 1, "balls": [{"center": [0, 0, 0], "radius": 1.0}]},
                     "camera": {"eye": [0.0, 0.0, 4.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_deg": 40,
                                "width": 16, "height": 12}})
    res = render(exp)
    O, D = camera_of(exp).ray_arrays()
    b = np.linalg.norm(np.cross(-O, D), axis=1) / np.linalg.norm(D, axis=1)
    step = T / (8 / (3 * np.sqrt(3)))
    capped = 2 * np.sqrt(np.maximum(1 - b * b, 0)) > step
    clear = (np.abs(b - np.sqrt(1 - (step / 2) ** 2)) > 1e-3) & (np.abs(b - 1) > 1e-3)
    flags = np.asarray(res.hits.flags).reshape(-1)
    assert 0 < capped.sum() < capped.size and not np.any(np.isfinite(res.hits.t))
    np.testing.assert_array_equal((flags[clear] & FLAG_STEP_CAP) != 0, capped[clear])
    counts = res.run["flags"]
    assert set(counts) == set(FLAG_NAMES.values())
    assert counts["step_cap"] == int(np.sum((flags & FLAG_STEP_CAP) != 0)) >= int(np.sum(capped & clear))
    assert all(v == 0 for k, v in counts.items() if k != "step_cap")
