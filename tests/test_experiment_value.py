"""The one experiment value (``config.Experiment``): a file's ``object:`` is a scene of one, and
whatever form a file takes, the same scene renders the same image."""

from __future__ import annotations

import numpy as np
import pytest

from jskel.config import ConfigError, Experiment, validate
from jskel.render import render

BALL = {"type": "implicit", "threshold": 0.5, "balls": [{"center": [0.2, 1.0, 0.0], "radius": 2.5}]}
CAM = {"eye": [0.0, 1.0, 5.0], "target": [0.0, 1.0, 0.0], "up": [0, 1, 0], "fov_deg": 40, "width": 16, "height": 12}
LIGHTS = [{"direction": [0.4, 0.9, 0.5]}]


def test_an_object_file_is_a_scene_of_one_whose_lights_cast_shadows_only_where_asked():
    """``object:`` becomes one object with no transform and the default material; a light that
    does not say ``shadows`` casts none there (a scene's does), one that says it keeps it; the
    shape is the representation's model, and the object remembers where the file wrote it."""
    one = validate({"object": BALL, "camera": CAM, "lights": LIGHTS + [{"direction": [0, 1, 0], "shadows": True}]})
    scene = validate({"objects": [{"shape": BALL}], "camera": CAM, "lights": LIGHTS})
    assert isinstance(one, Experiment) and len(one.objects) == 1
    o = one.objects[0]
    assert o.shape.type == "implicit" and type(o.shape).__name__ != "dict" and not o.is_placed
    assert o.at(0) == "object" and scene.objects[0].at(0) == "objects[0]"
    assert [l.shadows for l in one.lights] == [False, True] and [l.shadows for l in scene.lights] == [True]
    assert one.objects[0].shape == scene.objects[0].shape


def test_the_same_scene_renders_the_same_image_from_either_form_and_from_its_run_json():
    """An ``object:`` file, the scene of one written out (``objects:`` with the light's shadows
    off) and the run.json's resolved config loaded back give the very same image and depths."""
    a = render(validate({"object": BALL, "camera": CAM, "lights": LIGHTS}))
    b = render(validate({"objects": [{"shape": BALL}], "camera": CAM, "lights": [{**LIGHTS[0], "shadows": False}]}))
    c = render(validate(a.run["config"]))
    assert np.isfinite(a.hits.t).sum() > 40
    for r in (b, c):
        np.testing.assert_array_equal(a.image, r.image)
        np.testing.assert_array_equal(a.hits.t, r.hits.t)
    assert a.run["info"]["objects"] == 1 and a.aovs is None and "effects" not in a.run


def test_a_scene_of_one_moved_by_its_transform_matches_the_shape_written_there():
    """A ball placed by ``transform.translate`` is the ball written at the moved centre: depths
    agree to float32 rounding (the rays are relative to the moved anchor either way)."""
    moved = validate({"objects": [{"shape": BALL, "transform": {"translate": [0.3, -0.2, 0.1]}}], "camera": CAM, "lights": LIGHTS})
    there = {**BALL, "balls": [{"center": [0.5, 0.8, 0.1], "radius": 2.5}]}
    a, b = render(moved), render(validate({"objects": [{"shape": there}], "camera": CAM, "lights": LIGHTS}))
    hit = np.isfinite(b.hits.t)
    assert hit.sum() > 40 and np.array_equal(np.isfinite(a.hits.t), hit)
    np.testing.assert_allclose(a.hits.t[hit], b.hits.t[hit], rtol=1e-5)


def test_shapes_are_validated_by_their_representation_whoever_builds_the_value():
    """``Experiment`` built directly validates each shape through the registry; ``with_shapes``
    replaces them one per object; a wrong count or an unknown type is refused."""
    e = Experiment.model_validate({"objects": [{"shape": BALL}], "camera": CAM})
    assert type(e.objects[0].shape).__name__ == type(validate({"object": BALL}).objects[0].shape).__name__
    moved = e.with_shapes({**BALL, "threshold": 0.25})
    assert moved.objects[0].shape.threshold == 0.25 and e.objects[0].shape.threshold == 0.5
    with pytest.raises(ValueError, match="2 shapes given for 1 objects"):
        e.with_shapes(BALL, BALL)
    with pytest.raises(ValueError, match="unknown representation"):
        Experiment.model_validate({"objects": [{"shape": {"type": "nope"}}]})
    with pytest.raises(ConfigError) as err:
        validate({"objects": [{"shape": {**BALL, "threshold": -1}}, {"shape": {"type": "nope"}}], "camera": {"width": 0}})
    lines = err.value.lines
    assert lines[0].startswith("camera.width:") and any(l.startswith("objects[0].shape.threshold:") for l in lines)
    assert any(l.startswith("objects[1].shape.type: unknown representation") for l in lines) and len(lines) == 3, lines
