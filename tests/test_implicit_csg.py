"""CSG on fields and displacement (Rouiller 2011, Sec. 6.2 and future work) against NumPy."""

from __future__ import annotations

import numpy as np
import pytest

import implicit_reference as iref
import reference as ref
from jskel import implicit
from jskel.rays import FLAG_GRAZE
from test_implicit import cast

T = 0.5
A = ((0.0, 0.0, 0.0), 1.0)
B = ((0.55, 0.15, 0.0), 0.7)


def _f(x, c, r):
    c = np.asarray(c, float)[None]
    return iref.field(x, c, c, np.array([r]), np.array([r]))


def np_csg(op, x):
    fa, fb = _f(x, *A), _f(x, *B)
    return {"sum": fa + fb, "max": np.maximum(fa, fb), "min": np.minimum(fa, fb), "diff": np.minimum(fa, 2 * T - fb)}[op]


def np_first_root(F, O, D, t0=0.0, t1=6.0, n=3000):
    ts = np.linspace(t0, t1, n + 1)
    out = np.full(O.shape[0], np.inf)
    margin = np.full(O.shape[0], np.inf)
    for i in range(0, O.shape[0], 500):
        sl = slice(i, i + 500)
        v = F(O[sl, None] + ts[None, :, None] * D[sl, None]) - T
        ins = v > 0
        found = ins.any(1)
        k = np.argmax(ins, 1)
        # grazing margin before the root, leaving out the approach to the root itself (0.05 long)
        m = int(np.ceil(0.05 / (ts[1] - ts[0])))
        margin[sl] = -np.where(np.arange(n + 1)[None] < np.where(found, k - m, n + 1)[:, None], v, -np.inf).max(1)
        lo, hi = ts[np.maximum(k - 1, 0)], ts[k]
        for _ in range(50):
            m = 0.5 * (lo + hi)
            fin = F(O[sl] + m[:, None] * D[sl]) - T > 0
            hi, lo = np.where(fin, m, hi), np.where(fin, lo, m)
        out[sl] = np.where(found, 0.5 * (lo + hi), np.inf)
    return out, margin


def two_balls(op, method="lipschitz", **kw):
    return implicit.ImplicitConfig.model_validate({
        "type": "implicit", "threshold": T, "method": method, "eps": 1e-3, "steps": 4096,
        "balls": [{"center": list(A[0]), "radius": A[1], "group": "a"}, {"center": list(B[0]), "radius": B[1], "group": "b"}],
        "csg": {"op": op, "children": [{"group": "a"}, {"group": "b"}]}, **kw})


@pytest.mark.parametrize("op,method", [("sum", "lipschitz"), ("max", "lipschitz"), ("min", "lipschitz"), ("diff", "lipschitz"),
                                       ("max", "exact"), ("diff", "exact")])
def test_csg_operations_against_numpy(op, method):
    """Each operation by the Lipschitz march; union and difference also by ``exact`` (the march
    from the first point where the sum of both balls reaches T, found exactly)."""
    rng = np.random.default_rng(11)
    O, D = ref.random_rays(rng, [-1.2, -1.2, -1.2], [1.4, 1.2, 1.2], 3000, spread=1.0)
    O = O - 3.0 * D  # start well outside
    t_ref, margin = np_first_root(lambda x: np_csg(op, x), O, D, 0.0, 12.0, 2400)
    hit = cast(implicit.build(two_balls(op, method)), O, D)
    assert np.all((hit.flags & ~FLAG_GRAZE) == 0) and np.all(np.isfinite(hit.normal))
    clear = margin > 0.005
    assert not np.any(clear & (hit.flags != 0))  # only rays that graze the surface say they might
    assert clear.mean() > 0.9 and 0.02 < np.isfinite(t_ref).mean() < 0.9  # an intersection is small
    same = np.isfinite(hit.t) == np.isfinite(t_ref)
    assert same[clear].all()
    both = clear & np.isfinite(t_ref)
    assert np.abs(hit.t[both] - t_ref[both]).max() < 1e-3


def _np_noise(x, freq):
    """The value noise of jskel.implicit._field written again in NumPy (same hash, smoothstep)."""
    p = x * freq
    p0 = np.floor(p)
    f = p - p0
    w = f * f * (3 - 2 * f)
    i0 = p0.astype(np.int64)
    acc = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                i, j, k = [(i0[..., a] + dd).astype(np.int64) & 0xFFFFFFFF for a, dd in ((0, dx), (1, dy), (2, dz))]
                h = ((i * 73856093) & 0xFFFFFFFF) ^ ((j * 19349663) & 0xFFFFFFFF) ^ ((k * 83492791) & 0xFFFFFFFF)
                h ^= h >> 13
                h = (h * 0x5BD1E995) & 0xFFFFFFFF
                h ^= h >> 15
                v = (h & 0xFFFF) / 32767.5 - 1.0
                acc = acc + v * (w[..., 0] if dx else 1 - w[..., 0]) * (w[..., 1] if dy else 1 - w[..., 1]) * (w[..., 2] if dz else 1 - w[..., 2])
    return acc


@pytest.mark.parametrize("method", ["lipschitz", "exact"])
def test_displacement_keeps_the_lipschitz_guarantee(method):
    """``exact`` marches from the first root of the undisplaced sum at T / (1 + amp)."""
    amp, freq = 0.4, 6.0
    rng = np.random.default_rng(12)
    O, D = ref.random_rays(rng, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], 2000, spread=0.9)
    O = O - 2.0 * D
    F = lambda x: _f(x, *A) * (1 + amp * _np_noise(x, freq))  # noqa: E731
    t_ref, margin = np_first_root(F, O, D, 0.0, 10.0, 4000)
    cfg = implicit.ImplicitConfig.model_validate({"type": "implicit", "threshold": T, "method": method, "eps": 5e-4,
        "steps": 8192, "balls": [{"center": list(A[0]), "radius": A[1]}], "displace": {"amplitude": amp, "frequency": freq}})
    hit = cast(implicit.build(cfg), O, D)
    capped = hit.flags != 0  # the guarantee holds where the march finished: flagged rays are reported
    assert capped.mean() < 0.01
    clear = (margin > 0.005) & ~capped
    assert np.isfinite(t_ref[clear]).mean() > 0.2
    assert np.all(np.isfinite(hit.t[clear]) == np.isfinite(t_ref[clear]))
    both = clear & np.isfinite(t_ref)
    assert np.abs(hit.t[both] - t_ref[both]).max() < 2e-3
    # the displaced surface really differs from the plain sphere somewhere
    rho = np.sqrt(1 - np.sqrt(T))
    d_plain = np.linalg.norm(hit.position[np.isfinite(hit.t)], axis=1)
    assert np.abs(d_plain - rho).max() > 0.02


def test_csg_bad_input():
    from jskel.config import validate

    base = {"type": "implicit", "balls": [{"center": [0, 0, 0], "radius": 1.0, "group": "a"}]}
    with pytest.raises(ValueError, match=r"object\.csg"):
        validate({"object": {**base, "csg": {"op": "diff", "children": [{"group": "a"}]}}})
    with pytest.raises(ValueError, match=r"object\.balls\[0\]\.group: group 'a' is not in object\.csg"):
        implicit.build(implicit.ImplicitConfig.model_validate({**base, "csg": {"group": "zz"}}))
    with pytest.raises(ValueError, match=r"object\.displace\.amplitude"):
        validate({"object": {**base, "displace": {"amplitude": 1.5}}})


@pytest.mark.parametrize("method", ["lipschitz", "exact"])
def test_image_displacement_keeps_the_lipschitz_guarantee(tmp_path, method):
    """Fig. 14: a height map through a planar projector displaces the surface; the Lipschitz
    march (bound grown by the map's largest texel slope) finds every hit NumPy finds."""
    import imageio.v3 as iio

    from test_relief import _ref_height

    yy, xx = np.mgrid[0:32, 0:32] / 32
    img = np.round(255 * (0.5 + 0.5 * np.sin(2 * np.pi * xx) * np.cos(4 * np.pi * yy))).astype(np.uint8)
    path = tmp_path / "h.png"
    iio.imwrite(path, img)
    amp, su, sv = 0.3, 1.0, 1.0
    # planar projector: axis +z, up +y, side = axis x up = -x
    F = lambda x: _f(x, *A) * (1 + amp * (2 * _ref_height(img, -x[..., 0] * su, x[..., 1] * sv) - 1))  # noqa: E731
    rng = np.random.default_rng(13)
    O, D = ref.random_rays(rng, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], 2000, spread=0.9)
    O = O - 2.0 * D
    t_ref, margin = np_first_root(F, O, D, 0.0, 10.0, 4000)
    cfg = implicit.ImplicitConfig.model_validate({"type": "implicit", "threshold": T, "method": method, "eps": 5e-4,
        "steps": 8192, "balls": [{"center": list(A[0]), "radius": A[1]}],
        "displace": {"type": "image", "amplitude": amp, "map": str(path),
                     "projector": {"type": "planar", "origin": [0, 0, 0], "axis": [0, 0, 1], "up": [0, 1, 0], "scale": [su, sv]}}})
    hit = cast(implicit.build(cfg), O, D)
    capped = hit.flags != 0
    assert capped.mean() < 0.01
    clear = (margin > 0.005) & ~capped
    assert np.isfinite(t_ref[clear]).mean() > 0.2
    assert np.all(np.isfinite(hit.t[clear]) == np.isfinite(t_ref[clear]))
    both = clear & np.isfinite(t_ref)
    assert np.abs(hit.t[both] - t_ref[both]).max() < 2e-3
