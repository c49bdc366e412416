"""jskel.optics against closed forms: Snell's law written with angles in float64 NumPy, the
identities of reflection and refraction, total internal reflection on either side of the
critical angle, and the integrator's ``tir`` flag on the pixels Snell's law predicts."""

from __future__ import annotations

import copy

import jax.numpy as jnp
import numpy as np

from jskel.config import validate
from jskel.optics import reflect, refract, refract_surface
from jskel.rays import FLAG_NAMES, FLAG_TIR
from jskel.render import render

RNG = np.random.default_rng(29)


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _pairs(n=2000):
    """Random unit directions d and unit normals n facing against them (d . n < 0)."""
    d, n_ = _unit(RNG.normal(size=(n, 3))), _unit(RNG.normal(size=(n, 3)))
    return d, np.where((np.sum(d * n_, 1) > 0)[:, None], -n_, n_)


def _snell(d, n, eta):
    """The refracted direction from angles: theta_i from d and n, sin theta_t = eta sin theta_i,
    the direction sin theta_t along d's part in the surface plus cos theta_t along -n; and
    whether sin theta_t > 1 (no refracted ray)."""
    cos_i = -np.sum(d * n, 1)
    theta_i = np.arccos(np.clip(cos_i, -1, 1))
    sin_t = eta * np.sin(theta_i)
    tangent = _unit(d + cos_i[:, None] * n)
    theta_t = np.arcsin(np.clip(sin_t, -1, 1))
    return np.sin(theta_t)[:, None] * tangent - np.cos(theta_t)[:, None] * n, sin_t > 1


def test_refract_is_snells_law_in_float64_and_float32():
    d, n = _pairs()
    for eta in (1 / 1.5, 1.5, 1 / 2.4, 2.4):
        want, want_tir = _snell(d, n, eta)
        sin_t = eta * np.sqrt(1 - np.sum(d * n, 1) ** 2)
        clear = np.abs(sin_t - 1) > 1e-3
        got, tir = refract(jnp.asarray(d, jnp.float32), jnp.asarray(n, jnp.float32), eta)
        got, tir = np.asarray(got, np.float64), np.asarray(tir)
        np.testing.assert_array_equal(tir[clear], want_tir[clear])
        ok = clear & ~want_tir
        assert ok.sum() > 100
        np.testing.assert_allclose(got[ok], want[ok], atol=2e-5)
        mirror = d - 2 * np.sum(d * n, 1)[:, None] * n  # beyond the critical angle: the mirror direction
        np.testing.assert_allclose(got[clear & want_tir], mirror[clear & want_tir], atol=2e-6)
        assert (eta < 1) or (clear & want_tir).sum() > 200  # from the denser side, TIR is exercised


def test_reflection_and_refraction_identities():
    d, n = _pairs()
    r = np.asarray(reflect(jnp.asarray(d), jnp.asarray(n)), np.float64)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-6)  # energy: a unit ray stays unit
    np.testing.assert_allclose(np.sum(r * n, 1), -np.sum(d * n, 1), atol=1e-6)  # angle of reflection = incidence
    np.testing.assert_allclose(np.sum(np.cross(d, n) * r, 1), 0.0, atol=1e-6)  # in the plane of incidence
    np.testing.assert_allclose(np.asarray(reflect(jnp.asarray(r), jnp.asarray(n))), d, atol=1e-6)  # an involution
    eta = 1 / 1.5
    t, tir = refract(jnp.asarray(d), jnp.asarray(n), eta)
    t = np.asarray(t, np.float64)
    assert not np.asarray(tir).any()  # into the denser medium: never
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, atol=1e-5)
    # the tangential components scale by eta (n1 sin i = n2 sin t, as vectors)
    tan_d, tan_t = d - np.sum(d * n, 1)[:, None] * n, t - np.sum(t * n, 1)[:, None] * n
    np.testing.assert_allclose(tan_t, eta * tan_d, atol=1e-5)
    # reversibility: back out through the surface with 1 / eta gives the ray that came in
    # (not within 3 degrees of grazing: float32 rounding grows as 1 / cos there, and the way back meets its critical angle)
    back, tir_back = refract(jnp.asarray(-t, jnp.float32), jnp.asarray(-n, jnp.float32), 1 / eta)
    away = -np.sum(d * n, 1) > 0.05
    assert not np.asarray(tir_back)[away].any()
    np.testing.assert_allclose(np.asarray(back, np.float64)[away], -d[away], atol=3e-5)


def test_total_internal_reflection_begins_at_the_critical_angle():
    """From glass (1.5) to air: theta_c = asin(1 / 1.5); a ray 1e-4 rad below it is refracted
    (nearly grazing, sin theta_t = 1.5 sin(theta_c - 1e-4)), 1e-4 above it is mirrored."""
    eta = 1.5
    theta_c = np.arcsin(1 / eta)
    n = np.array([0.0, 0.0, 1.0])
    for eps, want_tir in ((-1e-4, False), (1e-4, True)):
        th = theta_c + eps
        d = np.array([np.sin(th), 0.0, -np.cos(th)])
        t, tir = refract(jnp.asarray(d, jnp.float32), jnp.asarray(n, jnp.float32), eta)
        t = np.asarray(t, np.float64)
        assert bool(tir) == want_tir
        if want_tir:
            np.testing.assert_allclose(t, [np.sin(th), 0.0, np.cos(th)], atol=1e-6)
        else:
            sin_t = eta * np.sin(th)
            np.testing.assert_allclose(t, [sin_t, 0.0, -np.sqrt(1 - sin_t**2)], atol=2e-4)  # float32 near grazing


def test_refract_surface_turns_the_normal_and_the_ratio_by_side():
    d, n = _pairs(500)
    ior = 1.5
    into, tir_in = refract_surface(jnp.asarray(d * 3.0), jnp.asarray(n), ior)  # d against n: entering
    want_in, _ = _snell(d, n, 1 / ior)
    np.testing.assert_allclose(np.asarray(into), want_in, atol=2e-5)
    assert not np.asarray(tir_in).any()
    out, tir_out = refract_surface(jnp.asarray(d), jnp.asarray(-n), ior)  # d along the outward normal: leaving
    want_out, want_tir = _snell(d, n, ior)
    clear = np.abs(ior * np.sqrt(1 - np.sum(d * n, 1) ** 2) - 1) > 1e-3
    np.testing.assert_array_equal(np.asarray(tir_out)[clear], want_tir[clear])
    ok = clear & ~want_tir
    np.testing.assert_allclose(np.asarray(out)[ok], want_out[ok], atol=2e-5)


# ------------------------------------------------------------------ the integrator's flag

R, H, IOR = 2.0, 4.0, 1.5
EYE = (1.3, 2.0, 0.0)  # inside a glass cylinder of radius 2 about the y axis, off its axis
CAM = {"eye": list(EYE), "target": [1.3, 2.0, -5.0], "up": [0, 1, 0], "fov_deg": 70.0, "width": 24, "height": 16}


def _inside_glass():
    raw = {"objects": [{"name": "glass", "material": {"transparency": 1.0, "ior": IOR},
                        "shape": {"type": "frusta", "normals": "geometric",
                                  "skeleton": {"joints": [[0, 0, 0], [0, H, 0]], "radii": [R, R], "parents": [-1, 0]}}}],
           "camera": CAM, "lights": [{"direction": [0.3, 0.9, 0.5]}], "render": {"bounces": 1}}
    exp = validate(copy.deepcopy(raw))
    return render(exp, progress=False)


def _camera_rays():
    """Pixel-centre unit rays, row-major (the pinhole camera written out)."""
    eye, f = np.asarray(EYE), _unit(np.subtract(CAM["target"], EYE))
    right = _unit(np.cross(f, [0, 1, 0]))
    up = np.cross(right, f)
    w, h = CAM["width"], CAM["height"]
    th = np.tan(np.radians(CAM["fov_deg"]) / 2)
    px, py = np.meshgrid(((np.arange(w) + 0.5) / w * 2 - 1) * th * w / h, (1 - (np.arange(h) + 0.5) / h * 2) * th)
    return eye, _unit(f + px.reshape(-1, 1) * right + py.reshape(-1, 1) * up)


def test_the_integrator_flags_exactly_the_pixels_whose_ray_is_totally_reflected():
    """From inside the glass every camera ray leaves through the side wall, at an angle whose
    sine is the ray's horizontal distance from the axis over R: Snell's law predicts total
    internal reflection where 1.5 sin(theta) > 1. The pixels carrying the ``tir`` bit are
    those (away from the caps and 1e-3 from the critical angle)."""
    eye, d = _camera_rays()
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = eye[0] * d[:, 0] + eye[2] * d[:, 2]
    t = (-b + np.sqrt(b * b - a * (eye[0] ** 2 + eye[2] ** 2 - R * R))) / a  # the far root: leaving
    p = eye + t[:, None] * d
    normal = np.stack([p[:, 0], np.zeros(len(p)), p[:, 2]], 1) / R
    sin_i = np.linalg.norm(np.cross(d, normal), axis=1)
    side = (p[:, 1] > 0.05) & (p[:, 1] < H - 0.05)
    clear = side & (np.abs(IOR * sin_i - 1) > 1e-3)
    want = IOR * sin_i > 1
    res = _inside_glass()
    got = (np.asarray(res.hits.flags) & FLAG_TIR) != 0
    assert FLAG_NAMES[FLAG_TIR] == "tir" and res.run["flags"]["tir"] == int(got.sum())
    assert clear.sum() > 200 and want[clear].sum() > 30 and (~want[clear]).sum() > 30
    np.testing.assert_array_equal(got[clear], want[clear])
