"""Bones, forward kinematics and rest-pose texture skinning (Rouiller 2011, Sec. 5-6.1)."""

from __future__ import annotations

import numpy as np
import pytest

from jskel import implicit
from test_implicit import cast

T = 0.5
R = 0.5


def rot_xyz(deg):
    """R = Rz Ry Rx (the documented Euler convention), written here independently."""
    x, y, z = np.radians(deg)
    rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx


def cfg_at(frame, projector="cylindrical", **extra):
    return implicit.ImplicitConfig.model_validate({**extra,
        "type": "implicit", "threshold": T, "method": "lipschitz", "eps": 1e-3, "frame": frame,
        "bones": [
            {"name": "upper", "head": [0, 0, 0], "tail": [0, 2, 0], "tube": [R, R], "influence": 0.9,
             "keys": [{"frame": 0, "rotate": [0, 0, 0]}, {"frame": 10, "rotate": [0, 0, 30]}]},
            {"name": "lower", "parent": "upper", "head": [0, 2, 0], "tail": [0, 4, 0], "tube": [R, R], "influence": 0.9,
             "keys": [{"frame": 0, "rotate": [0, 0, 0]}, {"frame": 10, "rotate": [40, 0, 0]}]},
        ],
        "projector": {"type": projector, "origin": [0, 0, 0], "axis": [0, 1, 0], "up": [0, 0, 1], "scale": [1, 0.25]},
    })


def posed(p_rest, frame):
    """Material point of bone 'lower' at `frame`: FK written in the test (linear keys)."""
    f = np.clip(frame / 10, 0, 1)
    r_up = rot_xyz([0, 0, 30 * f])
    r_lo = rot_xyz([40 * f, 0, 0])
    world_lower_rot = r_up @ r_lo
    world_lower_head = r_up @ np.array([0, 2.0, 0])
    return world_lower_head + world_lower_rot @ (p_rest - [0, 2.0, 0]), world_lower_rot


def test_skinned_uv_is_constant_on_material_points():
    rho = R * np.sqrt(1 - np.sqrt(T))  # surface radius of a lone tube: (1 - rho^2/R^2)^2 = T
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    heights = np.array([2.9, 3.2])
    A, H = np.meshgrid(ang, heights)
    radial = np.stack([np.sin(A.ravel()), np.zeros(A.size), np.cos(A.ravel())], 1)
    p_rest = radial * rho + np.stack([np.zeros(A.size), H.ravel(), np.zeros(A.size)], 1)
    uvs = []
    for frame in (0.0, 5.0, 10.0):
        P = np.array([posed(p, frame)[0] for p in p_rest])
        rot = posed(p_rest[0], frame)[1]
        n = radial @ rot.T
        hit = cast(implicit.build(cfg_at(frame)), P + 2.0 * n, -n)
        assert np.all(np.isfinite(hit.t)) and np.all(hit.flags == 0)
        np.testing.assert_allclose(hit.position, P, atol=2e-4)  # FK agrees with the test's own
        uvs.append(hit.uv)
    du = np.abs(uvs[1] - uvs[0])
    du[:, 0] = np.minimum(du[:, 0], 1 - du[:, 0])
    assert du.max() < 1e-3
    du = np.abs(uvs[2] - uvs[0])
    du[:, 0] = np.minimum(du[:, 0], 1 - du[:, 0])
    assert du.max() < 1e-3
    # and the uv is the projector's: u = angle / 2 pi + 0.5 about +y from +z, v = 0.25 * height
    u_want = np.mod(np.arctan2(p_rest[:, 0], p_rest[:, 2]) / (2 * np.pi) + 0.5, 1.0)
    du = np.abs(np.mod(uvs[0][:, 0], 1.0) - u_want)
    assert np.minimum(du, 1 - du).max() < 1e-3
    np.testing.assert_allclose(uvs[0][:, 1], 0.25 * p_rest[:, 1], atol=1e-3)


def test_bad_rig_input_names_the_key():
    base = cfg_at(0).model_dump()
    bad = dict(base, balls=[{"center": [0, 0, 0], "radius": 1.0, "bone": "nope"}])
    with pytest.raises(ValueError, match=r"object\.balls\[0\]\.bone: unknown bone 'nope'"):
        implicit.build(implicit.ImplicitConfig.model_validate(bad))
    bones = [dict(b) for b in base["bones"]]
    bones[0]["parent"] = "lower"
    with pytest.raises(ValueError, match=r"object\.bones.*cycle"):
        implicit.build(implicit.ImplicitConfig.model_validate(dict(base, bones=bones)))
    bones = [dict(b) for b in base["bones"]]
    bones[1]["parent"] = "ghost"
    with pytest.raises(ValueError, match=r"object\.bones\[1\]\.parent: unknown bone 'ghost'"):
        implicit.build(implicit.ImplicitConfig.model_validate(dict(base, bones=bones)))
    local = {"type": "planar", "region": {"center": [0, 0, 0], "radius": 1.0}}
    with pytest.raises(ValueError, match=r"projectors\[0\]: has no texture and the model has none"):
        implicit.ImplicitConfig.model_validate(dict(base, projectors=[local]))
    with pytest.raises(ValueError, match=r"object\.projectors\[0\]\.texture: cannot read image 'nope\.png'"):
        implicit.build(implicit.ImplicitConfig.model_validate(dict(base, projectors=[dict(local, texture="nope.png")])))


def test_frames_cli_writes_numbered_outputs_and_a_gif(tmp_path):
    from pathlib import Path

    from jskel import cli

    exp = Path(__file__).resolve().parent.parent / "experiments" / "spider.yaml"
    rc = cli.main(["render", str(exp), "--frames", "0:2:2", "--out", str(tmp_path), "--set", "camera.width=32",
                   "--set", "camera.height=24", "--no-progress"])
    assert rc == 0
    assert (tmp_path / "frame_0000" / "depth.npy").exists() and (tmp_path / "frame_0002" / "image.png").exists()
    import imageio.v3 as iio

    gif = iio.imread(tmp_path / "animation.gif")
    assert gif.shape[0] == 2 and gif.shape[1:3] == (24, 32)
    d0 = np.load(tmp_path / "frame_0000" / "depth.npy")
    d2 = np.load(tmp_path / "frame_0002" / "depth.npy")
    assert np.isfinite(d0).any() and not np.array_equal(d0, d2)  # the legs moved


def test_local_projectors_pick_by_rest_pose_region_and_keep_their_textures(tmp_path):
    """Sec. 6.1's "arbitrary number of projectors": two local projectors (regions of the rest
    pose, each with its own texture of a different size) and the global one as fallback; the
    uv of each material point is its region's projector's, at every frame."""
    import imageio.v3 as iio
    import jax

    from jskel.rays import make_rays

    red, blue = tmp_path / "red.png", tmp_path / "blue.png"
    iio.imwrite(red, np.tile(np.uint8([255, 0, 0]), (4, 4, 1)))
    iio.imwrite(blue, np.tile(np.uint8([0, 0, 255]), (8, 2, 1)))
    locals_ = [
        {"type": "planar", "origin": [0, 0, 0], "axis": [0, 0, 1], "up": [0, 1, 0], "scale": [1, 1],
         "region": {"center": [0, 3.3, 0], "radius": 0.3}, "texture": str(red)},
        {"type": "spherical", "origin": [0, 3.6, 0], "axis": [0, 1, 0], "up": [0, 0, 1], "scale": [1, 1],
         "region": {"center": [0, 3.6, 0], "radius": 0.3}, "texture": str(blue)},
    ]
    rho = R * np.sqrt(1 - np.sqrt(T))
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    A, H = np.meshgrid(ang, np.array([3.0, 3.3, 3.6]))  # on bone 'lower', clear of the joint's blend
    radial = np.stack([np.sin(A.ravel()), np.zeros(A.size), np.cos(A.ravel())], 1)
    p = radial * rho + np.stack([np.zeros(A.size), H.ravel(), np.zeros(A.size)], 1)
    which = np.repeat([2, 0, 1], ang.size)  # height 3.0: global; 3.3: red planar; 3.6: blue spherical
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    want = np.where((which == 0)[:, None], np.stack([-x, y], 1), 0.0)  # planar: side = z x y = -x
    sph = np.stack([np.arctan2(x, z) / (2 * np.pi) + 0.5, np.arctan2(np.hypot(x, z), y - 3.6) / np.pi], 1)
    cyl = np.stack([np.arctan2(x, z) / (2 * np.pi) + 0.5, 0.25 * y], 1)
    want = np.where((which == 1)[:, None], sph, np.where((which == 2)[:, None], cyl, want))
    colour = np.array([0.2, 0.6, 0.3])
    for frame in (0.0, 10.0):
        built = implicit.build(cfg_at(frame, projectors=locals_, color=colour.tolist()))
        P = np.array([posed(q, frame)[0] for q in p])
        n = radial @ posed(p[0], frame)[1].T
        rays = make_rays(P + 2.0 * n - built.anchor, -n)
        st = built.static

        def one(o, d, a, b, scene=built.params, st=st):
            h = implicit.intersect_one(scene, st, o, d, a, b)
            return h, implicit.albedo(scene, st, h)

        hit, rgb = jax.jit(jax.vmap(one))(*rays)
        assert np.all(np.isfinite(hit.t))
        got = np.asarray(hit.uv, np.float64)
        du = np.abs(got[:, 0] - want[:, 0])
        du = np.where(which > 0, np.minimum(du, 1 - du), du)  # angles wrap
        assert du.max() < 2e-3 and np.abs(got[:, 1] - want[:, 1]).max() < 2e-3
        rgb = np.asarray(rgb)
        np.testing.assert_allclose(rgb[which == 0], np.tile([1.0, 0, 0], (ang.size, 1)), atol=1e-5)
        np.testing.assert_allclose(rgb[which == 1], np.tile([0, 0, 1.0], (ang.size, 1)), atol=1e-5)
        np.testing.assert_allclose(rgb[which == 2], np.tile(colour, (ang.size, 1)), atol=1e-6)
