"""Relief mapping (Bhagvat et al. 2009, Sec. 3) against closed forms and a float64 reference march."""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from conftest import cast
from jskel import frusta
from jskel.rays import FLAG_GRAZE

MAP = 64  # every test map is 64 x 64 so the compiled shapes are shared


def build_relief(tmp_path, height, joints, radii, parents, **relief):
    import imageio.v3 as iio

    path = tmp_path / "h.png"
    iio.imwrite(path, np.asarray(height, np.uint8))
    cfg = frusta.FrustaConfig.model_validate({
        "type": "frusta",
        "skeleton": {"joints": np.asarray(joints, float).tolist(), "radii": list(map(float, radii)), "parents": list(parents)},
        "relief": {"map": str(path), **relief},
    })
    return frusta.build(cfg)


SEG = ([[0, 0, 0], [0, 2, 0]], [0.5, 0.4], [-1, 0])
CHAIN = ([[0, 0, 0], [0, 1, 0], [0, 2, 0]], [0.5, 0.45, 0.4], [-1, 0, 1])  # collinear: planes independent of radii


def _exit_t(segs, O, D, far=100.0):
    """Exit parameter of the (convex) reference solid, by casting back from far along the ray."""
    t_rev, _ = ref.intersect(segs, O + far * D, -D)
    return far - t_rev


@pytest.mark.parametrize("steps", [8, 64])
@pytest.mark.parametrize("level", [0, 102, 255])
def test_constant_height_is_a_frustum(tmp_path, rng, steps, level):
    """h constant: the relief surface is the frustum of radii r + h * T (zeros: inner; ones: outer)."""
    T = 0.1
    joints, radii, parents = CHAIN
    b = build_relief(tmp_path, np.full((MAP, MAP), level), joints, radii, parents, thickness=T, steps=steps, bisection=8)
    h = level / 255.0
    segs = ref.segments(joints, np.asarray(radii) + h * T, parents)
    outer = ref.segments(joints, np.asarray(radii) + T, parents)
    O, D = ref.random_rays(rng, [-0.7, -0.2, -0.7], [0.7, 2.2, 0.7], 20_000)
    t_ref, _ = ref.intersect(segs, O, D)
    hit = cast(b, O, D, culled=True)
    assert not np.any(np.isnan(hit.t)) and np.all(np.isfinite(hit.normal)) and np.all(np.isfinite(hit.uv))
    # the march brackets a crossing when the chord through the relief solid spans > 2 steps
    t_in, _ = ref.intersect(outer, O, D)
    chord_outer = _exit_t(outer, O, D) - t_in
    ds = chord_outer / steps
    chord = _exit_t(segs, O, D) - t_ref
    well = np.isfinite(t_ref) & (chord > 2 * ds)
    missed_ref = ~np.isfinite(t_ref) & ~np.isfinite(t_in)  # misses even the shell
    assert np.all(np.isfinite(hit.t[well]))
    assert np.all(~np.isfinite(hit.t[missed_ref]))
    tol = ds[well] / 2 ** (8 + 1) + 1e-4 * 2.2  # bisection bracket + the float32 term of the frusta tests (1e-4 x scale)
    err = np.abs(hit.t[well] - t_ref[well])
    assert np.all(err <= tol), (err.max(), np.argmax(err - tol))
    assert well.mean() > 0.1


def test_thin_spike_needs_enough_steps(tmp_path):
    """One bright texel: 3 steps step over it, 64 steps find it (accuracy costs steps)."""
    r, T = 0.5, 0.2
    height = np.zeros((MAP, MAP))
    iu, iv = 16, 32  # u = (16 + 0.5) / 64, v = (32 + 0.5) / 64
    height[iv, iu] = 255
    joints = [[0, 0, 0], [0, 2, 0]]
    u = (iu + 0.5) / MAP
    v = (iv + 0.5) / MAP
    ang = 2 * np.pi * u
    radial = np.array([np.sin(ang), 0.0, np.cos(ang)])  # u = atan2(x, z) / 2 pi for a segment along +y
    tangent = np.array([np.cos(ang), 0.0, -np.sin(ang)])
    closest = radial * (r + 0.3 * T) + np.array([0, 2 * v, 0])
    O = (closest - 2.0 * tangent)[None, :]
    D = tangent[None, :]
    found = {}
    for steps in (3, 64):
        b = build_relief(tmp_path, height, joints, [r, r], [-1, 0], thickness=T, steps=steps, bisection=8, scale=[1, 1])
        hit = cast(b, O, D, culled=True)
        found[steps] = np.isfinite(hit.t[0])
        if found[steps]:
            assert abs(hit.t[0] - 2.0) < 0.05  # at the spike, near the chord's middle
        else:  # stepped over: a lost ray, never a silent miss
            assert hit.flags[0] & FLAG_GRAZE
    assert not found[3] and found[64]


def _ref_height(img, uu, vv):
    """Bilinear 8-bit height, u and v wrapping (written here, independently of jskel)."""
    h, w = img.shape
    x = uu * w - 0.5
    y = vv * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    g = lambda yy, xx: img[np.mod(yy, h), np.mod(xx, w)].astype(float)  # noqa: E731
    return ((1 - fx) * (1 - fy) * g(y0, x0) + fx * (1 - fy) * g(y0, x0 + 1) + (1 - fx) * fy * g(y0 + 1, x0) + fx * fy * g(y0 + 1, x0 + 1)) / 255.0


def _ref_shell(img, r1, r2, H, T, O, D):
    """(t_in, t_out, gap) of a single segment along +y from the origin (perpendicular planes):
    the rays' interval in the outer shell (t_in 0 for a ray starting inside it) and the float64
    gap w - h at t ((N,) or (N, S)): w from Eq. 11-12, u = atan2(x, z) / 2 pi, v = y / H (exact
    for parallel planes)."""
    outer = ref.segments([[0, 0, 0], [0, H, 0]], [r1 + T, r2 + T], [-1, 0])
    t_in, _ = ref.intersect(outer, O, D)
    t_in = np.where(np.isfinite(t_in) & (ref.inside(outer, O) == 0), t_in, 0.0)
    k = (r2 - r1) / H

    def gap(t, sl=slice(None)):
        O_, D_ = O[sl], D[sl]
        if t.ndim == 2:
            O_, D_ = O_[:, None, :], D_[:, None, :]
        P = O_ + t[..., None] * D_
        w = (np.hypot(P[..., 0], P[..., 2]) - (r1 + k * P[..., 1])) / T
        return w - _ref_height(img, np.mod(np.arctan2(P[..., 0], P[..., 2]) / (2 * np.pi), 1.0), P[..., 1] / H)

    return t_in, _exit_t(outer, O, D), gap


def _ref_march(img, r1, r2, H, T, O, D, n=4096, nbis=40):
    """Float64 reference: 4096 uniform samples over the outer shell interval, then bisection.

    A single segment along +y from the origin (perpendicular planes): w from Eq. 11-12, u =
    atan2(x, z) / 2 pi, v = y / H (exact for parallel planes).
    """
    t_in, t_out, gap = _ref_shell(img, r1, r2, H, T, O, D)

    def below(t, sl=slice(None)):
        return gap(t, sl) <= 0

    valid = np.isfinite(t_out) & (t_out > t_in)
    a = np.where(valid, t_in, 0.0)
    b = np.where(valid, t_out, 1.0)
    grid = np.linspace(0, 1, n + 1)[None, :]
    first = np.zeros(len(O), int)
    anyb = np.zeros(len(O), bool)
    for i in range(0, len(O), 200):  # rows in batches to bound memory
        sl = slice(i, i + 200)
        bl = below(a[sl, None] + (b - a)[sl, None] * grid, sl)
        first[sl] = np.argmax(bl, axis=1)
        anyb[sl] = bl.any(axis=1)
    found = valid & anyb
    lo = a + (b - a) * np.maximum(first - 1, 0) / n
    hi = a + (b - a) * first / n
    for _ in range(nbis):
        mid = 0.5 * (lo + hi)
        bm = below(mid)
        hi = np.where(bm, mid, hi)
        lo = np.where(bm, lo, mid)
    t = np.where(first == 0, a, 0.5 * (lo + hi))
    return np.where(found, t, np.inf), (b - a) / n


def _smooth_map():
    yy, xx = np.mgrid[0:MAP, 0:MAP] / MAP
    return np.round(255 * (0.5 + 0.45 * np.sin(2 * np.pi * xx) * np.cos(2 * np.pi * yy))).astype(np.uint8)


@pytest.mark.parametrize("kind", ["grazing", "through_plane", "inside_shell"])
def test_hard_rays_match_reference_march(tmp_path, rng, kind):
    r1, r2, H, T = 0.5, 0.4, 2.0, 0.15
    img = _smooth_map()
    n = 4000
    if kind == "grazing":  # nearly tangent to the outer frustum
        y = rng.uniform(0.2, 1.8, n)
        rr = r1 + (r2 - r1) * y / H + T * rng.uniform(0.6, 0.999, n)
        ang = rng.uniform(0, 2 * np.pi, n)
        radial = np.stack([np.sin(ang), 0 * ang, np.cos(ang)], 1)
        tang = np.stack([np.cos(ang), 0 * ang, -np.sin(ang)], 1)
        tilt = rng.normal(0, 0.05, n)
        D = tang + tilt[:, None] * np.array([0, 1.0, 0])
        D /= np.linalg.norm(D, axis=1, keepdims=True)
        O = radial * rr[:, None] + y[:, None] * np.array([0, 1.0, 0]) - 1.5 * D
    elif kind == "through_plane":  # from above, into the shell ring through the top plane
        ang = rng.uniform(0, 2 * np.pi, n)
        rr = r2 + T * rng.uniform(0.05, 0.95, n)
        P = np.stack([rr * np.sin(ang), np.full(n, H), rr * np.cos(ang)], 1)
        D = np.stack([rng.normal(0, 0.3, n), -np.ones(n), rng.normal(0, 0.3, n)], 1)
        D /= np.linalg.norm(D, axis=1, keepdims=True)
        O = P - 0.5 * D
    else:  # origins inside the shell, above the relief, in random directions
        ang = rng.uniform(0, 2 * np.pi, n)
        y = rng.uniform(0.2, 1.8, n)
        rr = r1 + (r2 - r1) * y / H + T * 0.97
        O = np.stack([rr * np.sin(ang), y, rr * np.cos(ang)], 1)
        D = rng.normal(size=(n, 3))
        D /= np.linalg.norm(D, axis=1, keepdims=True)
    t_ref, _ = _ref_march(img, r1, r2, H, T, O, D)
    b = build_relief(tmp_path, img, [[0, 0, 0], [0, H, 0]], [r1, r2], [-1, 0], thickness=T, steps=64, bisection=8, scale=[1, 1], uv="exact")
    hit = cast(b, O, D, culled=True)
    assert not np.any(np.isnan(hit.t)) and np.all(np.isfinite(hit.normal)) and np.all(np.isfinite(hit.uv))
    agree = np.isfinite(hit.t) == np.isfinite(t_ref)
    assert agree.mean() >= 0.99, agree.mean()
    both = np.isfinite(hit.t) & np.isfinite(t_ref)
    ds = 2 * (r1 + T) * 2 / 64  # a step is at most the longest chord over 64
    close = np.abs(hit.t[both] - t_ref[both]) <= ds
    assert close.mean() >= 0.99, close.mean()
    assert both.sum() > n * 0.05  # enough hits to mean something (grazing rays mostly miss)


def test_early_exit_equals_fixed_and_approximate_uv_is_exact_for_parallel_planes(tmp_path, rng):
    r1, r2, H, T = 0.5, 0.4, 2.0, 0.15
    img = _smooth_map()
    O, D = ref.random_rays(rng, [-0.7, -0.1, -0.7], [0.7, 2.1, 0.7], 8000)
    seg = ([[0, 0, 0], [0, H, 0]], [r1, r2], [-1, 0])
    fixed = cast(build_relief(tmp_path, img, *seg, thickness=T, steps=64, bisection=8, scale=[1, 1], uv="exact"), O, D, culled=True)
    early = cast(build_relief(tmp_path, img, *seg, thickness=T, steps=64, bisection=8, scale=[1, 1], uv="exact", early_exit=True), O, D, culled=True)
    np.testing.assert_array_equal(fixed.t, early.t)
    np.testing.assert_array_equal(fixed.prim, early.prim)
    approx = cast(build_relief(tmp_path, img, *seg, thickness=T, steps=64, bisection=8, scale=[1, 1]), O, D, culled=True)
    both = np.isfinite(approx.t) & np.isfinite(fixed.t)
    assert np.mean(np.isfinite(approx.t) == np.isfinite(fixed.t)) > 0.995
    assert np.quantile(np.abs(approx.t[both] - fixed.t[both]), 0.99) < 1e-3


def test_texture_spans_segments_along_a_chain(tmp_path):
    """A ramp in v with scale_v = 0.5 runs once over two unit segments: radius r + T h(y / 2)."""
    r, T = 0.4, 0.2
    img = np.repeat((4 * np.arange(MAP))[:, None], MAP, axis=1).astype(np.uint8)
    b = build_relief(tmp_path, img, [[0, 0, 0], [0, 1, 0], [0, 2, 0]], [r, r, r], [-1, 0, 1],
                     thickness=T, steps=64, bisection=12, scale=[1, 0.5], v_mode="clamp")
    ys = np.linspace(0.05, 1.95, 39)
    O = np.stack([np.full_like(ys, 3.0), ys, np.zeros_like(ys)], 1)
    D = np.tile([-1.0, 0, 0], (len(ys), 1))
    hit = cast(b, O, D, culled=True)
    row = np.clip(ys / 2 * MAP - 0.5, 0, MAP - 1)
    h = 4 * row / 255.0  # the ramp is linear, so bilinear sampling is exact
    np.testing.assert_allclose(3.0 - hit.t, r + T * h, atol=2e-4)
    assert set(np.unique(hit.prim)) == {0, 1}


def test_compacted_march_equals_masked_march(tmp_path, rng):
    """intersect_batch marches only the (ray, segment) pairs that enter a shell; vmap of
    intersect_one marches every pair under a mask. Same hits (t up to float32 program noise)."""
    img = _smooth_map()
    joints, radii, parents = CHAIN
    b = build_relief(tmp_path, img, joints, radii, parents, thickness=0.1, steps=64, bisection=8, scale=[1, 1], uv="exact")
    O, D = ref.random_rays(rng, [-0.7, -0.2, -0.7], [0.7, 2.2, 0.7], 8000)
    compact = cast(b, O, D, culled=True)
    masked = cast(b, O, D, culled=False)
    np.testing.assert_array_equal(np.isfinite(compact.t), np.isfinite(masked.t))
    h = np.isfinite(compact.t)
    assert h.mean() > 0.1
    np.testing.assert_array_equal(compact.prim[h], masked.prim[h])
    np.testing.assert_allclose(compact.t[h], masked.t[h], atol=1e-3)
    assert np.mean(compact.flags == masked.flags) >= 0.998  # (a flag compares t: program noise may flip one)


def test_uv_auto_is_approximate_only_where_the_paper_says_it_is_exact(tmp_path):
    img = np.zeros((MAP, MAP))
    straight = build_relief(tmp_path, img, *CHAIN, thickness=0.1)
    bent = build_relief(tmp_path, img, [[0, 0, 0], [0, 1, 0], [0.5, 1.8, 0]], [0.3, 0.3, 0.3], [-1, 0, 1], thickness=0.1)
    assert straight.info["relief_uv"] == "approximate" and straight.static.relief.uv == "approximate"
    assert bent.info["relief_uv"] == "exact" and bent.static.relief.uv == "exact"


def test_bad_relief_input_names_the_field(tmp_path):
    with pytest.raises(ValueError, match=r"object\.relief\.map"):
        frusta.load_height_map(str(tmp_path / "nope.png"))
    img = np.zeros((MAP, MAP))
    with pytest.raises(ValueError, match=r"object\.relief\.segments\[0\]"):
        build_relief(tmp_path, img, *CHAIN, thickness=0.1, segments=[7])
    from jskel.config import validate

    with pytest.raises(ValueError, match=r"object\.relief\.thickness"):
        validate({"object": {"type": "frusta", "skeleton": {"procedural": "well"}, "relief": {"map": "brick", "thickness": -1}}})


def _rays_into_shell(rng, r, T, H, n):
    """Rays from outside the outer cylinder of radius r + T towards random points of its shell."""
    ang, y, rr = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.2, H - 0.2, n), r + T * rng.uniform(0, 1, n)
    P = np.stack([rr * np.sin(ang), y, rr * np.cos(ang)], 1)
    D = rng.normal(size=(n, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    O = P - 1.5 * D
    keep = np.hypot(O[:, 0], O[:, 2]) > r + T + 1e-3
    return O[keep], D[keep]


@pytest.mark.parametrize("kind,steps", [("spikes", 3), ("smooth", 64)])
def test_unflagged_rays_agree_with_a_dense_float64_march(tmp_path, rng, kind, steps):
    """A coarse march steps over bumps thinner than a step (Sec. 3 samples only): such rays
    carry ``graze`` (the bound between two samples, ``_relief._step_undecided``), and every ray
    without it, hit or miss, agrees with the 4096-step float64 march of the same height field.
    The steps match test_thin_spike_needs_enough_steps' builds (their programs are reused)."""
    r, H, T = 0.5, 2.0, 0.2
    if kind == "spikes":  # 60 one-texel spikes: thinner than 3 steps of a chord
        img = np.zeros((MAP, MAP), np.uint8)
        img[rng.integers(0, MAP, 60), rng.integers(0, MAP, 60)] = 255
    else:
        img = _smooth_map()
    O, D = _rays_into_shell(rng, r, T, H, 1000)
    t_ref, ds_ref = _ref_march(img, r, r, H, T, O, D)
    b = build_relief(tmp_path, img, [[0, 0, 0], [0, H, 0]], [r, r], [-1, 0], thickness=T, steps=steps, bisection=8, scale=[1, 1])
    hit = cast(b, O, D, culled=True)
    flagged = (hit.flags & FLAG_GRAZE) != 0
    same = np.isfinite(hit.t) == np.isfinite(t_ref)
    with np.errstate(invalid="ignore"):  # inf - inf where both miss
        near = np.abs(np.where(np.isfinite(t_ref), hit.t - t_ref, 0.0)) <= ds_ref * 4096 / steps + 1e-4  # within one step
    agree = same & (near | ~np.isfinite(t_ref))
    assert np.all(agree[~flagged]), np.flatnonzero(~agree & ~flagged)[:5]
    if kind == "spikes":
        assert np.sum(~agree) > 20 and np.all(flagged[~agree]) and 0.3 < np.mean(flagged) < 0.75  # the coarse march errs; flagged
    else:
        assert np.all(agree) and np.mean(flagged) < 0.1  # a smooth map: few rays the bound cannot decide
    assert np.sum(np.isfinite(hit.t) & ~flagged) > 100


def test_plain_frusta_trace_no_flag_work(tmp_path):
    """Without relief the frusta programs contain none of the march's bound (its name scope)
    and their hits no flags; with relief both programs contain it."""
    import jax

    from jskel.frusta._relief import UNDECIDED_SCOPE
    from jskel.rays import make_rays

    rays = make_rays(np.zeros((8, 3)), np.tile([1.0, 0, 0], (8, 1)))
    joints, radii, parents = SEG
    plain = frusta.build(frusta.FrustaConfig.model_validate(
        {"type": "frusta", "skeleton": {"joints": joints, "radii": radii, "parents": parents}}))
    relief = build_relief(tmp_path, np.zeros((MAP, MAP)), *SEG, thickness=0.1, steps=3, bisection=8, scale=[1, 1])
    for b, has in ((plain, False), (relief, True)):
        for f in (frusta.intersect, frusta.intersect_batch):
            fn = jax.jit(lambda rr, f=f, b=b: f(b.params, b.static, rr))
            assert (UNDECIDED_SCOPE in fn.lower(rays).as_text(debug_info=True)) == has, (f.__name__, has)
            assert (jax.eval_shape(fn, rays).flags is not None) == has


def test_render_counts_relief_rays_that_cannot_decide(tmp_path, rng):
    """The render's flags AOV and run.json carry the relief's ``graze``: the same pixels as a
    cast of the camera's rays (16 x 12 pixels at 60 one-texel spikes, 3 steps)."""
    import imageio.v3 as iio

    from jskel.config import validate
    from jskel.render import camera_of, render

    img = np.zeros((MAP, MAP), np.uint8)
    img[rng.integers(0, MAP, 60), rng.integers(0, MAP, 60)] = 255
    iio.imwrite(tmp_path / "h.png", img)
    relief = {"map": str(tmp_path / "h.png"), "thickness": 0.2, "steps": 3, "bisection": 8, "scale": [1, 1]}
    exp = validate({"object": {"type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 2, 0]], "radii": [0.5, 0.5], "parents": [-1, 0]},
                               "relief": relief},
                    "camera": {"eye": [0.0, 1.0, 4.0], "target": [0.0, 1.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_deg": 40,
                               "width": 16, "height": 12}})
    res = render(exp)
    flags = np.asarray(res.hits.flags).reshape(-1)
    O, D = camera_of(exp).ray_arrays()
    b = build_relief(tmp_path, img, [[0, 0, 0], [0, 2, 0]], [0.5, 0.5], [-1, 0], thickness=0.2, steps=3, bisection=8, scale=[1, 1])
    own = (cast(b, O, D, culled=True).flags & FLAG_GRAZE) != 0
    assert 0 < own.sum() < own.size
    assert np.mean(((flags & FLAG_GRAZE) != 0) == own) >= 0.99
    assert res.run["flags"]["graze"] == int(np.sum((flags & FLAG_GRAZE) != 0))


def test_another_step_or_bisection_count_renders_without_a_program_and_marches_as_many(tmp_path):
    """The step and bisection counts are traced values (``ReliefMaps.steps``, ``.bisection``): a
    render at 3 steps and 8 halvings, then at 64 steps, then at 64 steps and no halving hands XLA
    no program after the first, and each render's depth is its own counts' march: its t equals
    the cast of the camera's rays through an object built with those counts (within rounding);
    3 and 64 steps differ on some pixels (1-texel spikes, which 3 steps step over), and so do 8
    halvings and none (the hit moves within the march's bracket)."""
    import imageio.v3 as iio

    from jskel.compile.cache import count_programs, program_counts
    from jskel.config import validate
    from jskel.render import camera_of, render

    img = np.zeros((MAP, MAP), np.uint8)
    img[np.random.default_rng(4).integers(0, MAP, (2, 200))] = 255
    iio.imwrite(tmp_path / "h.png", img)
    skel = {"joints": [[0, 0, 0], [0, 2, 0]], "radii": [0.5, 0.5], "parents": [-1, 0]}
    cam = {"eye": [0.0, 1.0, 4.0], "target": [0.0, 1.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_deg": 40, "width": 16, "height": 12}
    ts = []
    for steps, bisection in ((3, 8), (64, 8), (64, 0)):
        relief = {"map": str(tmp_path / "h.png"), "thickness": 0.2, "steps": steps, "bisection": bisection, "scale": [1, 1]}
        exp = validate({"object": {"type": "frusta", "skeleton": skel, "relief": relief}, "camera": cam})
        count_programs()
        before = program_counts()
        res = render(exp)
        after = program_counts()
        if ts:
            assert after["compiled"] + after["loaded"] == before["compiled"] + before["loaded"]
        O, D = camera_of(exp).ray_arrays()
        b = build_relief(tmp_path, img, skel["joints"], skel["radii"], skel["parents"], thickness=0.2, steps=steps, bisection=bisection,
                         scale=[1, 1])
        t, want = np.asarray(res.hits.t, np.float64).reshape(-1), cast(b, O, D, culled=True).t
        np.testing.assert_array_equal(np.isfinite(t), np.isfinite(want))
        np.testing.assert_allclose(t[np.isfinite(t)], want[np.isfinite(t)], rtol=1e-6)  # (two programs: rounding apart)
        ts.append(t)
    assert np.any(ts[0] != ts[1]) and np.any(ts[1] != ts[2])


def test_a_bad_traced_step_or_bisection_count_is_named(tmp_path):
    """``checked_intersect``'s checks (``interface._problems``, the fields a checked program
    verifies) name a relief step count below 1 and a negative bisection count with its value."""
    import jax.numpy as jnp

    from jskel.checks import checked
    from jskel.interface import Object, _problems
    from jskel.rays import make_rays

    b = build_relief(tmp_path, np.zeros((MAP, MAP)), *SEG, thickness=0.1, steps=8, bisection=4)
    rays = make_rays(np.zeros((4, 3)), np.tile([0.0, 0.0, 1.0], (4, 1)))
    only_checks = checked(lambda obj, r: jnp.zeros(()), _problems)
    only_checks(Object(b.params, b.static, "frusta"), rays)  # good values: nothing raised
    maps = b.params.maps._replace(steps=jnp.int32(0), bisection=jnp.int32(-1))
    with pytest.raises(ValueError) as e:
        only_checks(Object(b.params._replace(maps=maps), b.static, "frusta"), rays)
    assert e.value.lines == ["relief.steps[0]: not positive (got 0); 1 of 1 entries",
                             "relief.bisection[0]: negative (got -1); 1 of 1 entries"]


# ---------------------------------------------------------------- the exact tracer (method: exact)


def _ref_dense(img, r1, r2, H, T, O, D, n=20000, nbis=50):
    """(t, clear) of a single segment along +y (:func:`_ref_shell`, :func:`_ref_crossing`)."""
    return _ref_crossing(*_ref_shell(img, r1, r2, H, T, O, D), len(O), n, nbis)


def _ref_crossing(t_in, t_out, gap, count, n=20000, nbis=50):
    """(t, clear): the float64 first crossing of the relief surface by ``n`` uniform samples of
    the shell interval [t_in, t_out] and bisection of ``gap(t)`` (w - h, negative below the
    surface), and whether the reference decides the ray clearly: its gap stays 1e-3 above 0 at
    every sample before the last 0.02 of t before the crossing (at every sample on a miss) and it
    crosses at a slope (a graze the tracer may decide either way within rounding is not counted)."""
    valid = np.isfinite(t_out) & (t_out > t_in)
    a, b = np.where(valid, t_in, 0.0), np.where(valid, t_out, 1.0)
    grid = np.linspace(0, 1, n + 1)[None, :]
    first, anyb, clear = np.zeros(count, int), np.zeros(count, bool), np.zeros(count, bool)
    for i in range(0, count, 50):
        sl = slice(i, i + 50)
        g = gap(a[sl, None] + (b - a)[sl, None] * grid, sl)
        bl = g <= 0
        first[sl], anyb[sl] = np.argmax(bl, axis=1), bl.any(axis=1)
        step = (b - a)[sl, None] / n
        m = np.ceil(0.02 / step[:, 0]).astype(int)  # the approach to the root: the last 0.02 of t before it
        before = np.arange(n + 1)[None, :] < np.where(anyb[sl], first[sl] - m, n + 1)[:, None]
        j = np.maximum(first[sl], 1)
        rows = np.arange(g.shape[0])
        slope = (g[rows, j - 1] - g[rows, j]) / step[:, 0]  # how steeply it crosses
        clear[sl] = np.all(np.where(before, g > 1e-3, True), axis=1) & (~anyb[sl] | (slope > 1e-2))
    lo, hi = a + (b - a) * np.maximum(first - 1, 0) / n, a + (b - a) * first / n
    for _ in range(nbis):
        mid = 0.5 * (lo + hi)
        bm = gap(mid, slice(None)) <= 0
        hi, lo = np.where(bm, mid, hi), np.where(bm, lo, mid)
    t = np.where(first == 0, a, hi)
    # a ray that misses the outer solid is decided; one starting below the relief is not compared
    # (the tracer then reports where it leaves the relief)
    return np.where(valid & anyb, t, np.inf), ~valid | (clear & ~(anyb & (first == 0)))


def _spikes_map():
    """Ridges one texel wide every 8 texels in u, on the smooth map (the features a march of
    few steps steps over)."""
    img = _smooth_map().astype(int)
    img[:, ::8] = 255
    return img.astype(np.uint8)


@pytest.mark.parametrize("which", ["smooth", "spikes", "thin"])
def test_exact_tracer_finds_the_float64_first_crossing(tmp_path, rng, which):
    """``method: exact`` against a 20,000-sample float64 march with 50 bisections on the same
    bilinear field: rays from outside the shell at any angle, rays nearly tangent to the outer
    frustum (grazing the shell) and rays from inside it above the relief; a smooth map, ridges one
    texel wide, and a thin shell (thickness 1e-3 of the radius); on the rays the reference
    decides clearly, the same hit or miss and t within 64 float32 epsilons of the ray's reach
    (the segment is 2 long)."""
    r1, r2, H = 0.5, 0.4, 2.0
    T = 5e-4 if which == "thin" else 0.15
    img = _spikes_map() if which == "spikes" else _smooth_map()
    n = 1500
    O, D = ref.random_rays(rng, [-0.7, -0.1, -0.7], [0.7, 2.1, 0.7], n)
    m = n // 3
    y = rng.uniform(0.2, 1.8, m)
    ang = rng.uniform(0, 2 * np.pi, m)
    radial = np.stack([np.sin(ang), 0 * ang, np.cos(ang)], 1)
    rr = r1 + (r2 - r1) * y / H + T * 0.97
    Oi = radial * rr[:, None] + y[:, None] * np.array([0, 1.0, 0])  # inside the shell, above the relief
    Di = rng.normal(size=(m, 3))
    tang = np.stack([np.cos(ang), 0 * ang, -np.sin(ang)], 1) + rng.normal(0, 0.05, m)[:, None] * np.array([0, 1.0, 0])
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    rg = r1 + (r2 - r1) * y / H + T * rng.uniform(0.3, 0.999, m)  # passing this far from the axis
    Og = radial * rg[:, None] + y[:, None] * np.array([0, 1.0, 0]) - 1.5 * tang
    O = np.vstack([O, Oi, Og])
    D = np.vstack([D, Di / np.linalg.norm(Di, axis=1, keepdims=True), tang])
    t_ref, clear = _ref_dense(img, r1, r2, H, T, O, D)
    b = build_relief(tmp_path, img, [[0, 0, 0], [0, H, 0]], [r1, r2], [-1, 0], thickness=T, scale=[1, 1], method="exact")
    _agrees_with_reference(cast(b, O, D, culled=True), t_ref, clear)


def _agrees_with_reference(hit, t_ref, decided):
    """The exact tracer's hits against a float64 reference's t (inf: a miss) on the rays it
    decides clearly: no NaN, the same hit or miss where the tracer raises no flag, t within 64
    float32 epsilons of the rays' reach (about 4), flags on under 1 % of the rays."""
    assert not np.any(np.isnan(hit.t)) and np.all(np.isfinite(hit.normal))
    assert decided.mean() > 0.8
    same = np.isfinite(hit.t) == np.isfinite(t_ref)
    assert np.all(same[decided & (hit.flags == 0)]), np.nonzero(~same & decided)[0][:5]
    both = decided & np.isfinite(hit.t) & np.isfinite(t_ref)
    assert both.sum() > 100
    err = np.abs(hit.t[both] - t_ref[both])
    assert err.max() <= 64 * np.finfo(np.float32).eps * 4.0, err.max()
    assert np.mean(hit.flags != 0) < 0.01


def _ref_chain_exact_v(img, joints, radii, parents, T, O, D):
    """Per segment of a chain, (t_in, t_out, gap) with Eq. 7's exact v: the point's generator
    (m + k r_hat) met with the segment's two cutting planes (``reference.segments``, the inner
    radii's planes, shared by the outer solid of radii + T), v = -s_l / (s_u - s_l) plus the
    segments before it; the height a function of v alone (``img`` constant along u, so the u
    frame does not enter). Float64, written here."""
    inner = ref.segments(joints, radii, parents)
    out = []
    for j, sg in enumerate(inner):
        # the segment's own outer solid, closed by both its planes (``capped``)
        outer = dict(sg, r1=sg["r1"] + T, r2=sg["r2"] + T, bottom=sg["bottom"][:2] + (True,), top=sg["top"][:2] + (True,))
        t_in, _ = ref.intersect([outer], O, D)
        t_in = np.where(np.isfinite(t_in) & (ref.inside([outer], O) == 0), t_in, 0.0)
        k = (sg["r2"] - sg["r1"]) / sg["h"]
        (nb, pb, _), (nt, pt, _) = sg["bottom"], sg["top"]

        def gap(t, sl, sg=sg, k=k, nb=nb, pb=pb, nt=nt, pt=pt, j=j):
            O_, D_ = O[sl], D[sl]
            if t.ndim == 2:
                O_, D_ = O_[:, None, :], D_[:, None, :]
            P = O_ + t[..., None] * D_
            rel = P - sg["c1"]
            y = rel @ sg["m"]
            radial = rel - y[..., None] * sg["m"]
            rho = np.linalg.norm(radial, axis=-1)
            g = sg["m"] + k * radial / rho[..., None]
            s_l = ((pb - P) @ nb) / (g @ nb)
            s_u = ((pt - P) @ nt) / (g @ nt)
            v = -s_l / (s_u - s_l) + j
            w = (rho - (sg["r1"] + k * y)) / T
            return w - _ref_height(img, 0.0 * v, v)

        out.append((t_in, _exit_t([outer], O, D), gap))
    return out


def test_exact_tracer_with_exact_v_on_a_bent_chain(tmp_path, rng):
    """``method: exact`` with ``uv: exact`` (Eq. 7's v, not linear along a ray where the cutting
    planes tilt) on a chain bent 35 degrees at its joint, against the float64 first crossing of
    each segment's relief (:func:`_ref_chain_exact_v`, 20,000 samples and 50 bisections), the
    nearer of the two: a map of random rows (every row a feature one texel high), rays from
    outside at any angle and rays grazing the shell at the joint; the same hit or miss on the
    rays the reference decides clearly and t within 64 float32 epsilons of the ray's reach."""
    img = (rng.integers(0, 256, (MAP, 1)) * np.ones((1, MAP))).astype(np.uint8)
    bend = np.radians(35.0)
    joints = np.array([[0, 0, 0], [0, 1.0, 0], [np.sin(bend), 1.0 + np.cos(bend), 0]])
    radii, parents, T = np.array([0.5, 0.45, 0.4]), [-1, 0, 1], 0.12
    n = 900
    O, D = ref.random_rays(rng, [-0.7, -0.1, -0.7], [1.0, 2.1, 0.7], n)
    ang = rng.uniform(0, 2 * np.pi, n // 3)  # across the joint's tilted plane, nearly tangent to the shell
    tang = np.stack([np.cos(ang), rng.normal(0, 0.3, ang.size), -np.sin(ang)], 1)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    rg = 0.45 + T * rng.uniform(0.3, 0.999, ang.size)
    Og = np.stack([np.sin(ang), 0 * ang, np.cos(ang)], 1) * rg[:, None] + np.array([0, 1.0, 0]) - 1.5 * tang
    O, D = np.vstack([O, Og]), np.vstack([D, tang])
    per = [_ref_crossing(*r, len(O)) for r in _ref_chain_exact_v(img, joints, radii, parents, T, O, D)]
    t_ref = np.minimum(per[0][0], per[1][0])
    decided = per[0][1] & per[1][1]
    b = build_relief(tmp_path, img, joints, radii, parents, thickness=T, scale=[1, 1], method="exact", uv="exact")
    assert b.static.relief.uv == "exact"
    _agrees_with_reference(cast(b, O, D, culled=True), t_ref, decided)


@pytest.mark.parametrize("shape", [(20, 37), (16, 32)])
def test_exact_tracer_pyramid_bounds_every_range(rng, shape):
    """The min/max pyramid's bound of the cells [x0, x1] x [y0, y1] (x wrapping, y wrapping or
    clamped) against the least and greatest texel of those cells' bilinear footprints, from
    NumPy, on a random map and ranges of every size: 37 x 20 (neither side a power of two: a
    wrapped range is split at the seam) and 32 x 16 (both: its levels tile the map, a wrapped
    range's cells are taken modulo each level's size)."""
    import jax.numpy as jnp

    from jskel.frusta import _relief_exact as rx

    img = rng.integers(0, 256, shape).astype(np.uint8)
    H, W = img.shape
    for mode in ("wrap", "clamp"):
        mx, mn, levels = rx.pyramid(img, mode)
        for _ in range(300):
            x0 = int(rng.integers(-50, 50))
            nx = int(rng.integers(0, W + 3))
            y0 = int(rng.integers(-25, 25)) if mode == "wrap" else int(rng.integers(-1, H))
            ny = int(rng.integers(0, H + 3)) if mode == "wrap" else int(rng.integers(0, H - y0))
            xs = np.arange(x0, x0 + nx + 1)
            ys = np.arange(y0, y0 + ny + 1)
            rows = np.concatenate([ys, ys + 1])
            rows = np.mod(rows, H) if mode == "wrap" else np.clip(rows, 0, H - 1)
            cols = np.mod(np.concatenate([xs, xs + 1]), W)
            block = img[np.ix_(rows, cols)].astype(float) / 255.0
            yy0, yy1 = (y0, y0 + ny) if mode == "wrap" else (y0 + 1, y0 + ny + 1)
            lo, hi = rx._pyramid_bounds(jnp.asarray(np.stack([mx, mn], -1)), levels, jnp.int32(x0), jnp.int32(x0 + nx),
                                        jnp.int32(yy0), jnp.int32(yy1), W, H + (mode != "wrap"), mode == "wrap", jnp.asarray(False))
            assert float(lo) <= block.min() + 1e-7 and float(hi) >= block.max() - 1e-7, (mode, x0, nx, y0, ny)


@pytest.mark.parametrize("v_mode", ["wrap", "clamp"])
def test_exact_tracer_memory_counts_its_pyramid(tmp_path, v_mode):
    """The exact tracer keeps the 8-bit map plus a (max, min) byte pair per pyramid cell: for a
    12 x 20 map, levels of ceil-halved sides down to one cell (12 or 13 rows: a clamped map has a
    row of cells below its first), counted here from the sides alone; the march keeps no pyramid."""
    img = np.zeros((12, 20), np.uint8)
    rows, cols, cells = 12 + (v_mode == "clamp"), 20, 0
    while True:
        cells += rows * cols
        if rows == cols == 1:
            break
        rows, cols = -(-rows // 2), -(-cols // 2)
    mem = build_relief(tmp_path, img, *SEG, method="exact", v_mode=v_mode).info["memory"]
    assert mem["pyramid_bytes"] == 2 * cells and mem["relief_map_bytes"] == img.size
    assert mem["representation_bytes"] == mem["frusta_bytes"] + img.size + 2 * cells
    assert build_relief(tmp_path, img, *SEG).info["memory"]["pyramid_bytes"] == 0
    floats = build_relief(tmp_path, img, *SEG, storage="float").info["memory"]
    assert floats["relief_map_bytes"] == 4 * img.size  # float32 texels (the build's type)


@pytest.mark.parametrize("method", ["march", "exact"])
def test_texel_derivatives_of_a_constant_map_raise_a_cylinder(tmp_path, method):
    """``relief.storage: float``: the texels are a traced array and hit distances have
    derivatives against each of them (the implicit-function theorem at the root). On a cylinder
    of radius r with a constant map of level L the surface is the cylinder of radius
    R = r + T L / 255, and raising every texel by one raises it by T / 255: for a ray at distance
    b from the axis, t = 3 - sqrt(R^2 - b^2), so the derivatives over all texels sum to
    -(T / 255) R / sqrt(R^2 - b^2), from the four texels of the hit's bilinear cell."""
    import jax
    import jax.numpy as jnp

    from jskel.interface import Object, intersect
    from jskel.rays import make_rays

    r, T, level = 0.5, 0.1, 100
    b = build_relief(tmp_path, np.full((MAP, MAP), level), [[0, 0, 0], [0, 2, 0]], [r, r], [-1, 0], thickness=T,
                     steps=64, bisection=20, method=method, storage="float")
    assert jnp.issubdtype(b.params.maps.height.dtype, jnp.floating)
    R = r + T * level / 255.0
    off = np.array([0.0, 0.1, 0.25, 0.4])  # the ray's distance from the axis
    O = np.stack([np.full(4, 3.0), np.full(4, 1.0), off], 1)
    rays = make_rays(O - b.anchor, np.tile([-1.0, 0, 0], (4, 1)))

    def t_of(height):
        params = b.params._replace(maps=b.params.maps._replace(height=height))
        return intersect(Object(params, b.static, "frusta"), rays).t

    t = np.asarray(t_of(b.params.maps.height))
    np.testing.assert_allclose(t, 3.0 - np.sqrt(R * R - off * off), atol=2e-5)
    grads = jax.jacrev(t_of)(b.params.maps.height)  # (4, H, W)
    total = np.asarray(grads.sum(axis=(1, 2)))
    # t = 3 - sqrt(R^2 - b^2) with R = r + T h / 255: dt/dh = -(T / 255) R / sqrt(R^2 - b^2)
    np.testing.assert_allclose(total, -(T / 255.0) * R / np.sqrt(R * R - off * off), rtol=1e-3)
    assert np.count_nonzero(np.asarray(grads[0])) <= 4  # the bilinear footprint of the hit
