"""``jskel.view`` (issue 28), headless: the widget's controls are set from the test, as moving
them does, and each displayed image is compared with a direct ``render`` of the changed
experiment, written out here (radii scaled, a joint moved, the eye turned about the up axis with
a rotation matrix, raised in spherical coordinates, moved towards the target). A traced change
hands no program to XLA (``jskel.compile.cache.program_counts``); the AOVs are drawn from the last render
with the colour maps written out in float64. The render itself is checked against the float64
reference in tests/test_rerender.py on the same skeleton and image size."""

from __future__ import annotations

import base64
import copy

import imageio.v3 as iio
import numpy as np
import pytest

from jskel import config
from jskel.render import render

pytest.importorskip("ipywidgets", reason="jskel.view needs ipywidgets (the [notebook] and [dev] extras install it)")

import jskel  # noqa: E402
from jskel.view import Control, State, aov_image, apply, base_of, default_controls, default_knobs, full_of  # noqa: E402

# test_rerender's branching skeleton and image size (64x48 in chunks of 256, 16 per call)
JOINTS = np.array([[0, 0, 0], [0, 1.5, 0], [0.2, 3.0, 0.1], [1.0, 2.4, 0.0], [-0.8, 2.3, -0.5]], float)
RADII = np.array([0.5, 0.4, 0.2, 0.15, 0.15])
PARENTS = [-1, 0, 1, 1, 1]
EYE, TARGET = np.array([4.0, 2.5, 6.0]), np.array([0.1, 1.6, -0.1])


def _raw(joints=JOINTS, radii=RADII, eye=EYE):
    return {
        "name": "view",
        "object": {"type": "frusta", "accel": "bvh",
                   "skeleton": {"joints": np.asarray(joints).tolist(), "radii": np.asarray(radii).tolist(), "parents": PARENTS}},
        "camera": {"eye": np.asarray(eye).tolist(), "target": TARGET.tolist(), "up": [0, 1, 0], "fov_deg": 40, "width": 64, "height": 48},
        "render": {"chunk": 256, "chunks_per_call": 16, "progress": False},
    }


def _direct(raw):
    return render(config.validate(raw), progress=False)


@pytest.fixture(scope="module")
def v():
    return jskel.view(_raw())


def _turned(azimuth_deg):
    """The eye turned about +y through the target (right-handed rotation matrix)."""
    a = np.deg2rad(azimuth_deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return TARGET + R @ (EYE - TARGET)


def _raised(elevation_deg, zoom):
    """The eye raised by ``elevation_deg`` towards +y (spherical coordinates about the target),
    its distance divided by ``zoom``."""
    d = EYE - TARGET
    r, horiz = np.linalg.norm(d), np.hypot(d[0], d[2])
    el = np.arctan2(d[1], horiz) + np.deg2rad(elevation_deg)
    flat = np.array([d[0], 0.0, d[2]]) / horiz
    return TARGET + (r / zoom) * (np.cos(el) * flat + np.array([0.0, np.sin(el), 0.0]))


def _reset(v):
    for k, val in (("azimuth", 0.0), ("elevation", 0.0), ("zoom", 1.0), ("aov", "image"),
                   ("radius scale", 1.0), ("last joint x", 0.0), ("last joint y", 0.0)):
        v.sliders[k].value = val


def test_the_first_image_is_the_experiments_render_and_shows_as_png(v):
    direct = _direct(_raw())
    assert v.image.shape == (48, 64, 3) and np.array_equal(v.image, direct.image)
    assert 0.05 < np.isfinite(direct.hits.t).mean() < 0.95
    bundle = v._repr_mimebundle_()
    assert "application/vnd.jupyter.widget-view+json" in bundle
    assert np.array_equal(iio.imread(base64.b64decode(bundle["image/png"]))[..., :3], v.image)
    assert set(v.sliders) >= {"azimuth", "elevation", "zoom", "aov", "radius scale", "last joint x", "last joint y"}


CHANGES = {
    "radius": ({"radius scale": 1.3}, lambda s: _raw(radii=RADII * s["radius scale"])),
    "joint": ({"last joint x": 0.3, "last joint y": -0.2},
              lambda s: _raw(joints=np.vstack([JOINTS[:-1], JOINTS[-1] + [s["last joint x"], s["last joint y"], 0.0]]))),
    "azimuth": ({"azimuth": 30.0}, lambda s: _raw(eye=_turned(s["azimuth"]))),
    "elevation_zoom": ({"elevation": 20.0, "zoom": 1.5}, lambda s: _raw(eye=_raised(s["elevation"], s["zoom"]))),
}


@pytest.mark.parametrize("change", sorted(CHANGES))
def test_a_traced_change_shows_the_changed_experiment_without_a_program(v, change):
    _reset(v)
    first = v.image.copy()
    sets, expected = CHANGES[change]
    for k, val in sets.items():
        v.sliders[k].value = val
        assert v.programs == 0, f"{change}: setting {k} handed {v.programs} programs to XLA"
    shown = {k: v.sliders[k].value for k in sets}  # as the slider holds it
    direct = _direct(expected(shown))
    assert np.array_equal(v.image, direct.image), f"{change}: {np.sum(np.any(v.image != direct.image, -1))} pixels differ"
    assert np.any(v.image != first), f"{change}: the image did not change"


def test_aovs_are_drawn_from_the_render_without_rendering(v):
    _reset(v)
    direct = _direct(_raw())
    t = np.asarray(direct.hits.t, np.float64).reshape(48, 64)
    hit = np.isfinite(t)
    result = v.result
    v.sliders["aov"].value = "depth"
    assert v.result is result, "choosing an AOV rendered again"
    g = v.image.astype(np.float64)
    d = t[hit]
    assert np.all(g[~hit] == 0) and np.all(g[..., 0] == g[..., 2])
    assert np.all(np.abs(g[..., 0][hit] - (255 - 200 * (d - d.min()) / (d.max() - d.min()))) <= 0.5 + 1e-9)
    v.sliders["aov"].value = "normals"
    n = np.asarray(direct.hits.normal, np.float64).reshape(48, 64, 3)
    assert np.all(np.abs(v.image[hit] - (n[hit] + 1) / 2 * 255) <= 0.5 + 1e-6) and np.all(v.image[~hit] == 0)
    v.sliders["aov"].value = "ids"
    prim = np.asarray(direct.hits.prim).reshape(48, 64)
    pairs = {(int(i), tuple(c)) for i, c in zip(prim[hit], v.image[hit])}
    assert len(pairs) == len(np.unique(prim[hit])) > 1 and np.all(v.image[~hit] == 0)
    v.sliders["aov"].value = "image"
    assert np.array_equal(v.image, direct.image)


def test_knobs_are_the_objects_quality_keys_and_set_its_config():
    raw = {"object": {"type": "implicit", "method": "bisection", "balls": [{"center": [0, 0, 0], "radius": 1.0}]},
           "camera": {"width": 8, "height": 6}}
    base = base_of(raw)
    assert "steps" not in base["object"], "the base keeps only the keys the experiment sets"
    full = full_of(base)
    knobs = default_knobs(full)
    assert set(knobs) == {"steps", "step", "eps", "bisection"}
    assert knobs["steps"].integer and knobs["steps"].value == 2048 and knobs["bisection"].lo == 0
    assert set(default_controls(full)) == {"scale", "threshold"}
    raw2 = apply(base, State(values={"steps": 300, "bisection": 3.0, "threshold": 0.6}), {**knobs, **default_controls(full)})
    obj = config.validate(raw2).objects[0].shape
    assert (obj.steps, obj.bisection, obj.threshold, obj.scale) == (300, 3, 0.6, 1.0)
    assert "steps" not in base["object"] and full["object"]["steps"] == 2048, "apply changed its base"
    # a section inside the object: a relief's steps and bisection
    fr = copy.deepcopy(_raw())
    fr["object"]["relief"] = {"map": "noise", "steps": 32, "bisection": 6}
    assert {k: (c.path, c.value) for k, c in default_knobs(fr).items()} == {
        "relief.steps": ("object.relief.steps", 32), "relief.bisection": ("object.relief.bisection", 6)}
    scaled = apply(_raw(), State(values={"k": 2.0}), {"k": Control("object.skeleton.radii", "scale", 0.5, 2.0, 1.0)})
    np.testing.assert_array_equal(scaled["object"]["skeleton"]["radii"], RADII * 2.0)


def test_a_value_the_experiment_rejects_is_shown_and_the_image_stays():
    w = jskel.view(_raw(), controls={"fov": Control("camera.fov_deg", "set", 10.0, 200.0, 40.0)}, knobs={})
    image, result = w.image.copy(), w.result
    w.sliders["fov"].value = 190.0
    assert w.result is result and np.array_equal(w.image, image)
    assert "camera.fov_deg" in w._status.value and "190" in w._status.value
    w.sliders["fov"].value = 30.0  # a value it accepts renders again, with the programs it has
    assert w.result is not result and w.programs == 0
    np.testing.assert_array_equal(w.image, _direct({**_raw(), "camera": {**_raw()["camera"], "fov_deg": 30.0}}).image)
    with pytest.raises(ValueError, match="aov: 'albedo' is not one of image, depth"):
        aov_image(result, "albedo", 64, 48)
