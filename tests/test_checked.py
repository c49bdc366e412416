"""Values that turn bad under jit are reported (issue 29, class 4): ``interface.checked_intersect``
for every representation, ``checked_occluded``, ``checked_cast`` and ``checked_surface`` (one
representation: the same checks), the integrator's ``checked_scene_call`` and the frusta device
rebuild's ``checked`` (tests/test_device_build.py), all through ``jskel.checks.checked``. Each
bad value is set in the traced arrays themselves (a NaN ray origin, a NaN radius, a negative
radius, an infinite vertex, a zero step), so no host validation could have seen it; the line
each gives is written out here from the values set and their indices, every failing field
at once. The unchecked entry points hold none of it (their jaxpr is the representation's own
batch)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import test_conformance as conformance
from jskel import make_rays, registry
from jskel.config import ConfigError
from jskel.interface import Object, checked_cast, checked_intersect, checked_occluded, checked_surface, intersect

N = conformance.N


@pytest.fixture(scope="module")
def examples(tmp_path_factory):
    return conformance._examples(tmp_path_factory.mktemp("checked"))


@pytest.fixture(params=registry.names())
def case(request, examples):
    """The conformance suite's build of each representation (shared when both files run)."""
    if request.param not in conformance._CASES:
        conformance._CASES[request.param] = conformance.Case(request.param, examples[request.param])
    return conformance._CASES[request.param]


def _g(v) -> str:
    return f"{float(v):.6g}"


def _bad_params(name, params):
    """(params with one traced entry made bad, the line it gives), per representation, the
    entry chosen by the user's index (skeleton segment id, config primitive index)."""
    if name == "frusta":  # segment 3's base radius NaN
        f = params.plain.frusta
        row = int(np.nonzero(np.asarray(f.sid) == 3)[0][0])
        bad = params._replace(plain=params.plain._replace(frusta=f._replace(r1=f.r1.at[row].set(jnp.nan))))
        return bad, f"segments.r1[3]: not finite (got nan); 1 of {f.r1.shape[0]} entries"
    if name == "implicit":  # the config's primitive 1 (the second ball) of radius -0.5
        p = params.prims
        row = int(np.nonzero(np.asarray(params.prim_id) == 1)[0][0])
        bad = params._replace(prims=p._replace(ra=p.ra.at[row].set(-0.5)))
        return bad, f"primitives.ra[1]: negative (got -0.5); 1 of {p.ra.shape[0]} entries"
    if name == "mesh":  # triangle 7's second vertex at infinity in x
        v = np.asarray(params.v1[7])
        bad = params._replace(v1=params.v1.at[7, 0].set(jnp.inf))
        return bad, f"triangles.v1[7]: not finite (got [inf, {_g(v[1])}, {_g(v[2])}]); 1 of {params.v1.shape[0]} entries"
    assert name == "cells"  # a search step of 0
    return params._replace(step=jnp.zeros_like(params.step)), "step[0]: not positive (got 0); 1 of 1 entries"


def _bad_rays(rays):
    """(rays with two non-finite origins and a zero direction, their lines)."""
    o, d = np.asarray(rays.origins).copy(), np.asarray(rays.directions).copy()
    o[5, 1], o[9, 0], d[12] = np.nan, np.inf, 0.0
    lines = [f"rays.origins: 2 entries: not finite (indices 5: [{_g(o[5, 0])}, nan, {_g(o[5, 2])}], "
             f"9: [inf, {_g(o[9, 1])}, {_g(o[9, 2])}]); 2 of {N} entries",
             f"rays.directions[12]: is the zero vector (got [0, 0, 0]); 1 of {N} entries"]
    return rays._replace(origins=jnp.asarray(o), directions=jnp.asarray(d)), lines


def test_checked_intersect_names_the_bad_traced_value(case):
    obj = Object.of(case.rep, case.built)
    hit = checked_intersect(obj, case.rays)  # good values: the hits, nothing raised
    compiled = checked_intersect.program._cache_size()
    np.testing.assert_array_equal(np.isfinite(np.asarray(hit.t)), np.isfinite(case.batch.t))
    np.testing.assert_allclose(np.asarray(hit.t)[np.isfinite(case.batch.t)], case.batch.t[np.isfinite(case.batch.t)], rtol=1e-5)
    o = np.asarray(case.rays.origins).copy()
    o[5, 1] = np.nan
    with pytest.raises(ConfigError) as e:  # a ray (same shapes: no compile)
        checked_intersect(obj, case.rays._replace(origins=jnp.asarray(o)))
    assert e.value.lines == [f"rays.origins[5]: not finite (got [{_g(o[5, 0])}, nan, {_g(o[5, 2])}]); 1 of {N} entries"]
    params, line = _bad_params(case.name, case.built.params)
    with pytest.raises(ValueError) as e:
        checked_intersect(Object(params, case.built.static, case.name), case.rays)
    assert e.value.lines == [line]
    bad, lines = _bad_rays(case.rays)
    with pytest.raises(ValueError) as e:  # every failing field at once, in one error
        checked_intersect(Object(params, case.built.static, case.name), bad)
    assert e.value.lines == lines + [line]
    assert checked_intersect.program._cache_size() == compiled  # new values, the same program


def test_every_checked_query_checks_the_same_fields(examples):
    """``checked_occluded`` gives the unchecked answer and raises the same lines as
    ``checked_intersect`` (run: the implicit balls, quickest to compile); ``checked_cast`` and
    ``checked_surface`` return the same checks' records, field for field (their programs traced,
    not compiled: each compile costs seconds of the suite's budget)."""
    name = "implicit"
    if name not in conformance._CASES:
        conformance._CASES[name] = conformance.Case(name, examples[name])
    case = conformance._CASES[name]
    obj = Object.of(case.rep, case.built)
    np.testing.assert_array_equal(np.asarray(checked_occluded(obj, case.rays)), case.occ)
    size = checked_occluded.program._cache_size()
    params, line = _bad_params(name, case.built.params)
    bad, lines = _bad_rays(case.rays)
    with pytest.raises(ValueError) as e:
        checked_occluded(Object(params, case.built.static, name), bad)
    assert e.value.lines == lines + [line]
    assert checked_occluded.program._cache_size() == size
    fields = lambda found: [(f.field, f.what) for f in found]  # noqa: E731
    want = fields(jax.eval_shape(checked_intersect.program, obj, case.rays)[1])
    assert len(want) == 1 + 2 + 1 + 1 + 2 + 2 + 2  # origins; directions (finite, zero); a; b; ra, rb, threshold (finite, sign)
    pre = jax.eval_shape(checked_cast.program, obj, case.rays)
    assert fields(pre[1]) == want
    assert fields(jax.eval_shape(checked_surface.program, obj, case.rays, pre[2])[1]) == want


def test_the_unchecked_intersect_is_the_representations_batch_alone(case):
    """``interface.intersect`` traces to exactly the jaxpr of the representation's own batch: the
    checks live in ``checked_intersect``'s program only."""
    obj = Object.of(case.rep, case.built)
    plain = jax.make_jaxpr(intersect)(obj, case.rays)
    own = jax.make_jaxpr(lambda p, r: case.rep.intersect_batch(p, case.built.static, r))(case.built.params, case.rays)
    assert str(plain) == str(own)


def test_checked_scene_call_names_bad_objects_placements_lights_and_rays():
    """The integrator's checked entry (``render._scene.checked_scene_call``): a scene of one
    implicit object (two balls, threshold 0.5) gives the closed-form sphere's t on good values
    (the first ball alone on the axis rays), and a bad primitive, a zero scale, a NaN light and
    bad rays, set in the traced scene, all come in one error, a line each, without a compile."""
    from jskel.config import validate
    from jskel.render._scene import Scene, build_scene, checked_scene_call

    # the two balls of radius 1 at y = 0 and y = 6, written at half size and placed by a scale of 2:
    # a scene of one at its anchor skips an identity placement (``SceneStatic.identity``), this
    # one is traced, so its ``xform`` is checked
    balls = [{"center": [0, 0, 0], "radius": 0.5}, {"center": [0, 3, 0], "radius": 0.5}]
    raw = {"objects": [{"shape": {"type": "implicit", "threshold": 0.5, "balls": balls}, "transform": {"scale": 2.0}}],
           "camera": {"eye": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 30, "width": 8, "height": 8},
           "lights": [{"direction": [0.4, 0.9, 0.5], "shadows": False}]}
    exp = validate(raw)
    params, static, origin, _, _ = build_scene(exp, np.float32)
    # rays from the camera's eye, relative to the scene's origin (a scene of one: its object's anchor)
    eye = np.asarray(exp.camera.eye, np.float64)
    d = np.random.default_rng(0).normal(scale=0.1, size=(N, 3)) + [0.0, 0.0, -1.0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = make_rays(np.tile(eye - origin, (N, 1)), d)
    out = checked_scene_call(Scene(params, static), rays)
    # the ball's surface: f = (1 - r^2)^2 = 0.5 at rho = sqrt(1 - sqrt(0.5)) (Wyvill's kernel, radius 1)
    rho, e = np.sqrt(1.0 - np.sqrt(0.5)), np.asarray(eye, np.float64)
    b = d @ e
    disc = b**2 - (e @ e - rho**2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    got = np.asarray(out["hit"].t, np.float64)
    assert 0.2 < np.isfinite(t).mean() < 0.9
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(t))
    np.testing.assert_allclose(got[np.isfinite(t)], t[np.isfinite(t)], atol=1e-3)
    compiled = checked_scene_call.program._cache_size()
    obj, line = _bad_params("implicit", params.objects[0])
    x = params.xforms[0]._replace(s=jnp.zeros_like(params.xforms[0].s))
    L = np.asarray(params.lights.direction[0])
    lights = params.lights._replace(direction=params.lights.direction.at[0, 2].set(jnp.nan))
    bad_rays, lines = _bad_rays(rays)
    bad = params._replace(objects=(obj,), xforms=(x,), lights=lights)
    with pytest.raises(ValueError) as e:
        checked_scene_call(Scene(bad, static), bad_rays)
    assert e.value.lines == lines + [f"objects[0].{line}", "objects[0].xform.s[0]: not positive (got 0); 1 of 1 entries",
                                     f"lights.direction[0]: not finite (got [{_g(L[0])}, {_g(L[1])}, nan]); 1 of 1 entries"]
    assert checked_scene_call.program._cache_size() == compiled
