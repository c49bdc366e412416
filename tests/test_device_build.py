"""Frusta rebuilt on the device from new joints (``frusta.rebuilder``, issue 6): the same surface
as the host's float64 build of the same frame, and derivatives of t with respect to the joints
through the cutting planes and frames."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_hits_agree, build_skeleton, cast, random_tree
from jskel import frusta
from jskel.frusta._device import params_from
from jskel.frusta._geometry import frusta_fields, padded_topology
from jskel.frusta._intersect import _segment_t, nearest_one


def test_a_device_rebuild_of_a_later_frame_casts_like_the_host_build_of_it():
    """The dancing cacti: the template is frame 0, the rebuild frame 7 (every cactus bent anew);
    against the host's build of frame 7 at 64 x 48, the same hits, segments and t within
    float32 rounding; the frames (u, w) within 1e-3 and the world bases within 1e-5."""
    from jskel.config import load
    from jskel.frusta import skeleton_arrays
    from jskel.render import camera_of

    exp = load("experiments/dancing_cacti.yaml", ["camera.width=64", "camera.height=48"])
    obj = exp.objects[0].shape
    rb = frusta.rebuilder(obj)
    later = obj.model_copy(update={"frame": 7.0})
    j, r, _, _ = skeleton_arrays(later.skeleton, 7.0)
    dev, host = rb(j, r), frusta.build(later)
    fd, fh = dev.params.plain.frusta, host.params.plain.frusta
    v = np.asarray(fh.valid)
    np.testing.assert_allclose(np.asarray(fd.c1)[v] + dev.anchor, np.asarray(fh.c1)[v] + host.anchor, atol=1e-5)
    for name in ("u", "w", "m"):
        np.testing.assert_allclose(np.asarray(getattr(fd, name))[v], np.asarray(getattr(fh, name))[v], atol=1e-3)
    np.testing.assert_array_equal(np.asarray(fd.cap_b), np.asarray(fh.cap_b))
    np.testing.assert_array_equal(np.asarray(fd.cap_t), np.asarray(fh.cap_t))
    O, D = camera_of(exp).ray_arrays()
    a, b = cast(host, O, D, culled=True), cast(dev, O, D, culled=True)
    assert np.isfinite(a.t).mean() > 0.2
    assert_hits_agree(a, b, 1e-5)


def test_device_rebuild_on_random_skeletons_and_bad_joints():
    """Random branching skeletons moved joint by joint: hits as the host build gives them (all
    but rays within float rounding of a silhouette, at most 0.1 %; t within 1e-4 but for rays
    next to a seam whose float32 plane differs from the float64 one, at most 0.5 % of them and
    within 5e-3); a zero-length segment in the new joints is a ValueError naming the joint, not a
    NaN surface."""
    import reference as ref

    rng = np.random.default_rng(21)
    for n in (64,):
        j, r, p = random_tree(rng, n)
        cfg = frusta.FrustaConfig.model_validate({"type": "frusta", "accel": "bvh", "skeleton": {
            "joints": j.tolist(), "radii": r.tolist(), "parents": p.tolist()}})
        rb = frusta.rebuilder(cfg)
        j2 = j + rng.normal(scale=0.05, size=j.shape)
        host = build_skeleton(j2, r, p, accel="bvh")
        dev = rb(j2, r)
        O, D = ref.random_rays(rng, j2.min(0) - 0.5, j2.max(0) + 0.5, 4096, spread=1.0)
        a, b = cast(host, O, D, culled=True), cast(dev, O, D, culled=True)
        ha, hb = np.isfinite(a.t), np.isfinite(b.t)
        assert 0.05 < ha.mean() and (ha != hb).mean() <= 1e-3
        both = ha & hb
        rel = np.abs(b.t[both] - a.t[both]) / a.t[both]
        # float32 planes at ill-conditioned joints (nearly collinear, a strong change of taper)
        # differ from the float64 host's: the seam moves and rays next to it change t slightly
        assert np.mean(rel > 1e-4) <= 0.005 and rel.max() < 5e-3, (np.mean(rel > 1e-4), rel.max())
        bad = j2.copy()
        bad[5] = bad[p[5]]
        with pytest.raises(ValueError, match=r"joints\[5\]"):
            rb(bad, r)
        # the device part for JAX values, checked under jit (checkify): the same fields as the
        # host-validated rebuild; a NaN radius and two joints that met, each named with its index
        got = rb.checked(jnp.asarray(j2, jnp.float32), jnp.asarray(r, jnp.float32)).plain.frusta
        v = np.asarray(dev.params.plain.frusta.valid)
        for name in ("c1", "h", "r1", "r2"):
            np.testing.assert_allclose(np.asarray(getattr(got, name))[v], np.asarray(getattr(dev.params.plain.frusta, name))[v], rtol=1e-5, atol=1e-6)
        r_nan = r.copy()
        r_nan[3] = np.nan
        with pytest.raises(ValueError) as e:
            rb.checked(jnp.asarray(j2, jnp.float32), jnp.asarray(r_nan, jnp.float32))
        assert e.value.lines == [f"object.skeleton.radii[3]: not finite (got nan); 1 of {n} entries"]
        with pytest.raises(ValueError) as e:
            rb.checked(jnp.asarray(bad, jnp.float32), jnp.asarray(r, jnp.float32))
        assert e.value.lines == [f"object.skeleton.segment_length[5]: not positive (got 0); 1 of {int(np.sum(p >= 0))} entries"]
        with pytest.raises(ValueError) as e:  # both at once (checkify alone names the first)
            rb.checked(jnp.asarray(bad, jnp.float32), jnp.asarray(r_nan, jnp.float32))
        assert e.value.lines == [f"object.skeleton.radii[3]: not finite (got nan); 1 of {n} entries",
                                 f"object.skeleton.segment_length[5]: not positive (got 0); 1 of {int(np.sum(p >= 0))} entries"]
        assert rb.checked.program._cache_size() == 1  # new values, the same program


def test_t_is_differentiable_in_the_joints_through_planes_and_frames():
    """A ray hitting a bent three-segment chain near its middle joint (where the cutting plane
    decides which frustum is hit): d t / d joints by jax.grad through ``frusta_fields`` and
    brute-force intersection equals central differences of the same function (float32,
    step 1e-3)."""
    joints = np.array([[0.0, 0.0, 0.0], [0.05, 1.0, 0.0], [0.3, 1.9, 0.1], [0.4, 2.8, 0.1]])
    radii = np.array([0.3, 0.25, 0.2, 0.1])
    parents = [-1, 0, 1, 2]
    built = build_skeleton(joints, radii, parents, accel="bvh")
    g = built.params.plain.frusta
    topo = frusta.topology(*frusta.validate_skeleton(joints, radii, parents)[::2])
    dtopo = padded_topology(topo, g.h.shape[0])
    o = jnp.asarray(np.array([0.1, 1.05, 3.0]) - built.anchor, jnp.float32)
    d = jnp.asarray([0.0, -0.02, -1.0], jnp.float32)

    def t_of(jnts):
        f = params_from(frusta_fields(jnts - jnp.asarray(built.anchor, jnp.float32), jnp.asarray(radii, jnp.float32), dtopo, 0.0, 3)[0], g)
        return nearest_one(f, _segment_t, o, d / jnp.linalg.norm(d), 0.0, jnp.inf, 8)[0]

    x = jnp.asarray(joints, jnp.float32)
    t_and_grad = jax.jit(jax.value_and_grad(t_of))  # one program: the differences read its value
    t0, grad = t_and_grad(x)
    assert np.isfinite(float(t0))
    grad = np.asarray(grad)
    assert np.all(np.isfinite(grad)) and np.abs(grad).max() > 0.1
    h = 1e-3
    fd = np.zeros_like(grad)
    for i in range(4):
        for k in range(3):
            e = np.zeros((4, 3), np.float32)
            e[i, k] = h
            fd[i, k] = (float(t_and_grad(x + e)[0]) - float(t_and_grad(x - e)[0])) / (2 * h)
    np.testing.assert_allclose(grad, fd, atol=2e-2)


def test_the_host_build_runs_the_shared_geometry_in_float64_against_the_paper_reference():
    """The host build is the device rebuild's geometry (``_geometry.frusta_fields``) jitted in
    float64 under a scoped x64 switch: on a random tree, a straight chain (collinear joints) and a
    joint with seven children, every plane, offset and cap equals the independent float64
    reference of Eq. 3-5 (tests/reference.py: A and B as 3D line meets) within 1e-9, which a
    float32 computation could not reach; frames are unit and orthogonal to the axis; and
    ``jax_enable_x64`` is left as it was (off)."""
    import reference as ref

    star = np.array([[0, 0, 0], [0, 1, 0]] + [[np.cos(a), 1.5, np.sin(a)] for a in np.linspace(0, 6, 7)], float)
    cases = [random_tree(np.random.default_rng(8), 40),
             (np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0], [0, 3.0, 0]]), np.array([0.3, 0.2, 0.2, 0.1]), np.array([-1, 0, 1, 2])),
             (star, np.full(9, 0.1), np.array([-1, 0] + [1] * 7))]
    for j, r, p in cases:
        with jax.enable_x64(False):  # whatever an earlier test left: the build's switch is its own
            arr, _, _ = frusta.frusta_from_skeleton(j, r, p, twist_deg=30.0)
            assert not jax.config.jax_enable_x64
        assert arr.nb.dtype == np.float64 and arr.u.dtype == np.float64
        for i, s in enumerate(ref.segments(j, r, p)):
            for (n, pt, cap), nn, dd, cc in ((s["bottom"], arr.nb[i], arr.db[i], arr.cap_b[i]),
                                             (s["top"], arr.nt[i], arr.dt[i], arr.cap_t[i])):
                assert cap == cc
                np.testing.assert_allclose(nn, n, atol=1e-9)
                np.testing.assert_allclose(dd, n @ (pt - s["c1"]), atol=1e-9)
            np.testing.assert_allclose(arr.c1[i], s["c1"], atol=1e-12)
            np.testing.assert_allclose(arr.m[i], s["m"], atol=1e-12)
        for f in (arr.u, arr.w):
            np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-12)
            np.testing.assert_allclose(np.sum(f * arr.m, 1), 0.0, atol=1e-12)
