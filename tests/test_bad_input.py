"""Degenerate input rejected at construction (issue 29, class 4): a table of bad inputs, one row
per class of problem per representation and section, each with the exact lines it gives, and
rows with several problems that come in one error. Each experiment row runs the CLI
(``jskel render``) with compilation made to fail, so every problem is found before anything is
traced: exit code 2, one ``jskel: error:`` line per problem, each naming the field path, the
index and the value. The array entry points (``make_rays``, ``load_points``, ``fit_points``)
raise one ValueError the same way. Hypothesis draws corrupted skeletons (any set of joints
not finite, any set of radii negative) whose every problem must be named at once."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from jskel import cli, executor
from jskel.config import ConfigError
from jskel.fit import fit_points, load_points
from jskel.fit._config import PointsConfig, SolverConfig
from jskel.rays import make_rays

FRUSTA = "{type: frusta, skeleton: {joints: [[0,0,0],[0,1,0],[0,2,0]], radii: [0.3, 0.2, 0.1], parents: [-1, 0, 1]}}"
CAMERA = "{eye: [0, 1, 5], target: [0, 1, 0], width: 16, height: 16}"


def _body(obj: str = FRUSTA, camera: str = CAMERA, extra: str = "") -> str:
    return f"object: {obj}\ncamera: {camera}\n{extra}"


def _skeleton(joints: str, radii: str, parents: str) -> str:
    return f"{{type: frusta, skeleton: {{joints: {joints}, radii: {radii}, parents: {parents}}}}}"


def _implicit(balls: str = "[]", tubes: str = "[]", more: str = "") -> str:
    return f"{{type: implicit, balls: {balls}, tubes: {tubes}{more}}}"


def _zigzag(n: int, bend_deg: float = 179.5) -> str:
    """n segments of length 2 in the x-y plane, each turning by ``bend_deg`` from the one
    before (the k-th along (sin k*bend, cos k*bend)): n - 1 fold-backs of exactly that angle."""
    a = np.radians(bend_deg) * np.arange(n)
    steps = 2.0 * np.stack([np.sin(a), np.cos(a), np.zeros(n)], 1)
    return str(np.concatenate([np.zeros((1, 3)), np.cumsum(steps, 0)]).tolist())


JOINTS6 = "[[0,0,0],[0,1,0],[0,2,0],[0,3,0],[0,4,0],[0,5,0]]"
BALL = "[{center: [0, 0, 0], radius: 1}]"
BAD_OBJ = "v 0 0 0\nv nan 0 0\nv 0 1 0\nv 1 0 0\nf 1 2 3\nf 1 3 4\n"

# (id, experiment body, the exact error lines); MESH in a body is the path of an OBJ holding BAD_OBJ,
# TEX of a float TIFF holding a NaN and an infinity (written in the test)
TABLE = [
    ("frusta_texture_nan", _body(FRUSTA[:-1] + ", texture: TEX}"),
     ["object.texture ('TEX'): 2 texels: not finite (indices (1, 2): [nan, 0.5, 0.5], (3, 0): [0.5, inf, 0.5])"]),
    ("relief_map_nan", _body(FRUSTA[:-1] + ", relief: {map: TEX}}"),
     ["object.relief.map ('TEX'): 2 texels: not finite (indices (1, 2): [nan, 0.5, 0.5], (3, 0): [0.5, inf, 0.5])"]),
    ("frusta_joint_nan", _body(_skeleton("[[0,0,0],[.nan,1,0],[0,2,0]]", "[0.3, 0.2, 0.1]", "[-1, 0, 1]")),
     ["object.skeleton.joints[1][0]: Input should be a finite number (got nan)"]),
    ("frusta_radius_negative", _body(_skeleton("[[0,0,0],[0,1,0],[0,2,0]]", "[0.3, -0.2, 0.1]", "[-1, 0, 1]")),
     ["object.skeleton.radii[1]: Input should be greater than or equal to 0 (got -0.2)"]),
    ("frusta_joints_coincide", _body(_skeleton("[[0,0,0],[0,1,0],[0,1,0]]", "[0.3, 0.2, 0.1]", "[-1, 0, 1]")),
     ["object.skeleton.joints[2]: zero-length segment (got 1 -> 2 at [0, 1, 0])"]),
    ("frusta_radii_zero_both_ends", _body(_skeleton("[[0,0,0],[0,1,0],[0,2,0]]", "[0.3, 0, 0]", "[-1, 0, 1]")),
     ["object.skeleton.radii[2]: segment of radius 0 at both ends (got 1 -> 2 at [0, 2, 0])"]),
    ("frusta_count_mismatch", _body(_skeleton("[[0,0,0],[0,1,0],[0,2,0]]", "[0.3, 0.2]", "[-1, 0, 1]")),
     ["object.skeleton.radii: has 2 entries for 3 joints"]),
    ("implicit_tube_ends_coincide", _body(_implicit(tubes="[{a: [1, 2, 3], b: [1, 2, 3], radius_a: 0.5, radius_b: 0.3}]")),
     ["object.tubes[0].b: coincides with a; a tube needs a length (got [1, 2, 3])"]),
    ("implicit_ball_radius_zero", _body(_implicit(balls="[{center: [0, 0, 0], radius: 0}]")),
     ["object.balls[0].radius: Input should be greater than 0 (got 0)"]),
    ("implicit_threshold_negative", _body(_implicit(BALL, more=", threshold: -0.5")),
     ["object.threshold: Input should be greater than 0 (got -0.5)"]),
    ("implicit_centre_inf", _body(_implicit("[{center: [.inf, 0, 0], radius: 1}]")),
     ["object.balls[0].center[0]: Input should be a finite number (got inf)"]),
    ("implicit_bone_no_length", _body(_implicit(more=", bones: [{name: arm, head: [0, 1, 0], tail: [0, 1, 0], tube: [0.2, 0.1]}]")),
     ["object.bones[0].tail: equals its head; a bone needs a length (got [0, 1, 0])"]),
    ("implicit_bones_every_unknown_parent_and_cycle", _body(_implicit(BALL, more=", bones: [" + ", ".join(
        f"{{name: {n}, parent: {p}, head: [0, {k}, 0], tail: [0, {k + 1}, 0]}}"
        for k, (n, p) in enumerate((("a", "b"), ("b", "a"), ("c", "ghost"), ("d", "e"), ("e", "f"), ("f", "d")))) + "]")),
     ["object.bones[2].parent: unknown bone 'ghost'",
      "object.bones[0].parent: bone parents make a cycle (a -> b -> a)",
      "object.bones[3].parent: bone parents make a cycle (d -> e -> f -> d)"]),
    ("implicit_projector_axis_zero", _body(_implicit(BALL, more=", texture: brick, projector: {axis: [0, 0, 0]}")),
     ["object.projector.axis: is the zero vector (got [0, 0, 0])"]),
    ("cells_base_radius_negative", _body("{type: cells, base: {type: sphere, radius: -1}}"),
     ["object.base.radius: Input should be greater than 0 (got -1)"]),
    ("mesh_vertex_nan", _body("{type: mesh, path: MESH}"),
     ["object.path ('MESH') vertices[1]: not finite (got [nan, 0, 0])"]),
    ("camera_fov_zero", _body(camera="{fov_deg: 0, width: 16, height: 16}"),
     ["camera.fov_deg: Input should be greater than 0 (got 0)"]),
    ("camera_eye_is_target", _body(camera="{eye: [0, 1, 0], target: [0, 1, 0], width: 16, height: 16}"),
     ["camera.target: target equals eye (got [0, 1, 0])"]),
    ("camera_up_nan", _body(camera="{up: [0, .nan, 0], width: 16, height: 16}"),
     ["camera.up[1]: Input should be a finite number (got nan)"]),
    ("light_direction_zero", _body(extra="lights: [{direction: [0, 0, 0]}]\n"),
     ["lights[0].direction: direction is the zero vector (got [0, 0, 0])"]),
    ("frusta_parents_every_bad_index", _body(_skeleton(JOINTS6, "[0.1, 0.1, 0.1, 0.1, 0.1, 0.1]", "[-1, 9, 1, -5, 4, 4]")),
     ["object.skeleton.parents: 2 joints: index out of range [-1, 5] (indices 1: 9, 3: -5)",
      "object.skeleton.parents[4]: is the joint itself (got 4)"]),
    ("frusta_parents_every_cycle", _body(_skeleton(JOINTS6, "[0.1, 0.1, 0.1, 0.1, 0.1, 0.1]", "[2, 0, 1, 4, 5, 3]")),
     ["object.skeleton.parents: 2 cycles: parents make a cycle (indices 0: 0 -> 2 -> 1 -> 0, 3: 3 -> 4 -> 5 -> 3)"]),
    ("frusta_parents_one_cycle_beside_a_tree", _body(_skeleton(JOINTS6, "[0.1, 0.1, 0.1, 0.1, 0.1, 0.1]", "[-1, 0, 1, 5, 3, 4]")),
     ["object.skeleton.parents[3]: parents make a cycle (got 3 -> 5 -> 4 -> 3)"]),
    ("frusta_fold_back", _body(_skeleton(_zigzag(2), "[0.2, 0.2, 0.2]", "[-1, 0, 1]")),
     ["object.skeleton.joints[1]: folds back by more than 179 degrees (got 179.5 degrees from segment 0 to segment 1)"]),
    # several problems, all in one error: field errors and the checks between fields together
    ("several_fold_backs", _body(_skeleton(_zigzag(3), "[0.2, -0.2, 0.2, 0.2]", "[-1, 0, 1, 2]"), camera="{fov_deg: 0, width: 16, height: 16}"),
     ["camera.fov_deg: Input should be greater than 0 (got 0)",
      "object.skeleton.radii[1]: Input should be greater than or equal to 0 (got -0.2)",
      "object.skeleton.joints: 2 joints: folds back by more than 179 degrees "
      "(indices 1: 179.5 degrees from segment 0 to segment 1, 2: 179.5 degrees from segment 1 to segment 2)"]),
    ("several_frusta", _body(_skeleton("[[0,0,0],[0,1,0],[0,1,0],[.nan,3,0]]", "[0.3, -0.2, 0.1, 0.1]", "[-1, 0, 1, 2]"),
                             camera="{fov_deg: 0, width: 16, height: 16}", extra="lights: [{direction: [0, 0, 0]}]\n"),
     ["camera.fov_deg: Input should be greater than 0 (got 0)",
      "lights[0].direction: direction is the zero vector (got [0, 0, 0])",
      "object.skeleton.joints[3][0]: Input should be a finite number (got nan)",
      "object.skeleton.radii[1]: Input should be greater than or equal to 0 (got -0.2)",
      "object.skeleton.joints[2]: zero-length segment (got 1 -> 2 at [0, 1, 0])"]),
    ("several_implicit", _body(_implicit("[{center: [0, 0, 0], radius: 0}]",
                                         "[{a: [0, 0, 0], b: [0, 0, 0], radius_a: -1, radius_b: 0.3}, {a: [0, 0, 0], b: [0, 1, 0], radius_a: 0, radius_b: 0}]",
                                         ", threshold: 0")),
     ["object.threshold: Input should be greater than 0 (got 0)",
      "object.balls[0].radius: Input should be greater than 0 (got 0)",
      "object.tubes[0].radius_a: Input should be greater than or equal to 0 (got -1)",
      "object.tubes[0].b: coincides with a; a tube needs a length (got [0, 0, 0])",
      "object.tubes[1]: both radii are 0; a tube needs a positive radius at one end at least (got [0, 0])"]),
    ("several_segments_counted", _body(_skeleton("[[0,0,0],[0,1,0],[0,1,0],[0,1,0],[0,1,0],[0,1,0],[0,1,0],[0,1,0]]",
                                                 "[0.3, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2]", "[-1, 0, 1, 2, 3, 4, 5, 6]")),
     ["object.skeleton.joints: 6 joints: zero-length segment (indices 2: 1 -> 2 at [0, 1, 0], 3: 2 -> 3 at [0, 1, 0], "
      "4: 3 -> 4 at [0, 1, 0], 5: 4 -> 5 at [0, 1, 0], 6: 5 -> 6 at [0, 1, 0], ...)"]),
    # a scene: each object's placement, motion and material, every bad value by object index
    ("scene_placements_and_materials",
     "objects:\n"
     f"  - {{name: a, shape: {FRUSTA}, transform: {{scale: 0, translate: [.nan, 0, 0], rotate_deg: [0, .inf, 0]}},\n"
     "     material: {reflectivity: -0.5, color: [.nan, 1, 1], transparency: 2}}\n"
     f"  - {{name: b, shape: {_implicit(BALL)}, motion: {{translate: [.nan, 0, 0]}}, material: {{ior: 0}}}}\n"
     f"camera: {CAMERA}\n",
     ["objects[0].transform.translate[0]: Input should be a finite number (got nan)",
      "objects[0].transform.rotate_deg[1]: Input should be a finite number (got inf)",
      "objects[0].transform.scale: Input should be greater than 0 (got 0)",
      "objects[0].material.color[0]: Input should be a finite number (got nan)",
      "objects[0].material.reflectivity: Input should be greater than or equal to 0 (got -0.5)",
      "objects[0].material.transparency: Input should be less than or equal to 1 (got 2)",
      "objects[1].material.ior: Input should be greater than 0 (got 0)",
      "objects[1].motion.translate[0]: Input should be a finite number (got nan)"]),
]


@pytest.fixture
def no_compile(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("compiled despite bad input")

    monkeypatch.setattr(executor, "compile_batch_fn", boom)


@pytest.mark.parametrize("body, lines", [row[1:] for row in TABLE], ids=[row[0] for row in TABLE])
def test_bad_experiment_is_every_problem_in_one_error_before_any_compile(tmp_path, capsys, no_compile, body, lines):
    mesh = tmp_path / "bad.obj"
    mesh.write_text(BAD_OBJ)
    tex = tmp_path / "bad.tif"
    texels = np.full((4, 5, 3), 0.5, np.float32)
    texels[1, 2, 0], texels[3, 0, 1] = np.nan, np.inf
    import imageio.v3 as iio

    iio.imwrite(tex, texels)
    exp = tmp_path / "exp.yaml"
    exp.write_text(body.replace("MESH", str(mesh)).replace("TEX", str(tex)))
    rc = cli.main(["render", str(exp), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err == ["jskel: error: " + line.replace("MESH", str(mesh)).replace("TEX", str(tex)) for line in lines]


def test_rays_every_bad_ray_by_index_and_value():
    o = np.zeros((9, 3))
    d = np.tile([0.0, 0.0, 1.0], (9, 1))
    d[1] = 0.0
    with pytest.raises(ConfigError) as e:
        make_rays(o, d)
    assert e.value.lines == ["rays.directions[1]: is the zero vector (got [0, 0, 0])"]
    o[[0, 2, 3, 5, 6, 8], 0] = [np.nan, np.inf, np.nan, -np.inf, np.nan, np.nan]
    d[4, 2] = np.nan
    with pytest.raises(ConfigError) as e:
        make_rays(o, d, t_min=np.r_[0.0, np.nan, np.zeros(7)])
    assert e.value.lines == [
        "rays.origins: 6 rays: not finite (indices 0: [nan, 0, 0], 2: [inf, 0, 0], 3: [nan, 0, 0], 5: [-inf, 0, 0], 6: [nan, 0, 0], ...)",
        "rays.directions[4]: not finite (got [0, 0, nan])",
        "rays.directions[1]: is the zero vector (got [0, 0, 0])",
        "rays.t_min[1]: is not a number (got nan)",
    ]


def test_a_cloud_with_one_bad_point_names_the_point(tmp_path):
    pts = np.random.default_rng(0).normal(size=(50, 3))
    pts[31, 1] = np.nan
    f = tmp_path / "cloud.npy"
    np.save(f, pts)
    with pytest.raises(ValueError) as e:
        load_points(PointsConfig(file=str(f)))
    assert str(e.value) == f"points.file[31]: not finite (got [{pts[31, 0]:.6g}, nan, {pts[31, 2]:.6g}]); set points.nonfinite: drop to drop them"
    pts[[3, 7], 2] = np.inf
    np.save(f, pts)
    with pytest.raises(ValueError) as e:
        load_points(PointsConfig(file=str(f)))
    v = [f"[{x:.6g}, {y:.6g}, {z:.6g}]" for x, y, z in pts[[3, 7, 31]]]
    assert str(e.value) == f"points.file: 3 of 50 points: not finite (indices 3: {v[0]}, 7: {v[1]}, 31: {v[2]}); set points.nonfinite: drop to drop them"


def test_fit_points_names_the_bad_point_before_compiling(no_compile):
    pts = np.random.default_rng(1).normal(size=(40, 3))
    pts[5] = [np.nan, 0.0, 1.0]
    with pytest.raises(ValueError) as e:
        fit_points(pts, [[0, 0, 0], [0, 1, 0]], [0.2, 0.2], [-1, 0], SolverConfig())
    assert str(e.value) == "points[5]: not finite (got [nan, 0, 1])"


def test_fit_many_names_every_bad_cloud_point_and_start_before_compiling(monkeypatch):
    """``fit_many`` (B clouds, B starts): a non-finite point of cloud 1, a non-finite joint of
    start 0 and a negative radius of start 2, in one error before its solver is compiled; a
    batch whose fits diverge names each cloud that did (non-finite, or above its start's loss)."""
    from jskel.fit import _fit, fit_many

    monkeypatch.setattr(_fit, "_solve_clouds", None)  # (reaching the compile fails on None)
    clouds = np.random.default_rng(1).normal(size=(3, 40, 3))
    clouds[1, 7] = [0, np.inf, 1]
    j = np.array([[[0, 0, 0], [0, 1, 0], [0, 2, 0]]] * 3, float)
    r = np.full((3, 3), 0.2)
    j[0, 2] = [np.nan, 2, 0]
    r[2, 1] = -0.1
    with pytest.raises(ValueError) as e:
        fit_many(clouds, j, r, [-1, 0, 1], SolverConfig())
    assert e.value.lines == ["clouds[1][7]: not finite (got [0, inf, 1])", "init.skeleton[0].joints[2]: not finite (got [nan, 2, 0])",
                             "init.skeleton[2].radii[1]: negative radius (got -0.1)"]
    with pytest.raises(ValueError) as e:
        _fit._raise_diverged(SolverConfig(name="gauss_newton"), np.array([1.0, 2.0, 3.0, 1.0]), np.array([0.5, np.nan, 4.0, 0.2]),
                             np.array([True, True, True, False]))
    assert str(e.value) == ("solver.name: gauss_newton diverged on 3 of 4 clouds: clouds[1] (loss 2 -> nan), clouds[2] (loss 3 -> 4), "
                            "clouds[3] (loss 1 -> 0.2) (try lm, a smaller learning_rate or more points)")
    _fit._raise_diverged(SolverConfig(), np.array([1.0, 2.0]), np.array([0.5, 2.0]), np.array([True, True]))  # none diverged


def test_skeleton_arrays_every_problem_at_once(no_compile):
    from jskel import frusta

    joints = [[0, 0, 0], [np.nan, 1, 0], [0, 2, 0], [0, 2, 0]]
    with pytest.raises(ConfigError) as e:
        frusta.frusta_from_skeleton(joints, [0.3, 0.2, -0.1, 0.1], [-1, 0, 1, 2])
    assert e.value.lines == [
        "object.skeleton.joints[1]: not finite (got [nan, 1, 0])",
        "object.skeleton.radii[2]: negative radius (got -0.1)",
        "object.skeleton.joints[3]: zero-length segment (got 2 -> 3 at [0, 2, 0])",
    ]


def _named(field, what, idx, arr, noun):
    """The documented lines for entries ``idx`` of ``arr`` with one problem (written here, in the
    form docs/numerics.md gives: one entry by its index and value; more, their count and the
    first five)."""
    def v(x):
        a = np.ravel(np.asarray(x, np.float64))
        return f"{a[0]:.6g}" if a.size == 1 else "[" + ", ".join(f"{y:.6g}" for y in a) + "]"

    if not idx:
        return []
    if len(idx) == 1:
        return [f"{field}[{idx[0]}]: {what} (got {v(arr[idx[0]])})"]
    shown = ", ".join(f"{i}: {v(arr[i])}" for i in idx[:5])
    return [f"{field}: {len(idx)} {noun}: {what} (indices {shown}{', ...' if len(idx) > 5 else ''})"]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(n=st.integers(3, 14), data=st.data())
def test_every_corrupted_joint_and_radius_is_named_at_once(n, data):
    """Class 4 by hypothesis: a straight chain of ``n`` joints, then a drawn set of joints given
    a NaN or an infinity in a drawn coordinate and a drawn set of radii made negative: one
    ConfigError before anything compiles, naming every one of them (the index and the value;
    past five, the count and the first five), joints first."""
    from jskel import frusta

    joints = np.stack([np.zeros(n), np.arange(n, dtype=np.float64), np.zeros(n)], 1)
    radii = np.full(n, 0.2)
    bad_j = sorted(data.draw(st.sets(st.integers(0, n - 1), max_size=n), "joints"))
    bad_r = sorted(data.draw(st.sets(st.integers(0, n - 1), max_size=n), "radii"))
    assume(bad_j or bad_r)
    for i in bad_j:
        joints[i, data.draw(st.integers(0, 2))] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    for i in bad_r:
        radii[i] = -data.draw(st.floats(1e-6, 1e6))
    want = (_named("object.skeleton.joints", "not finite", bad_j, joints, "joints")
            + _named("object.skeleton.radii", "negative radius", bad_r, radii, "joints"))
    with pytest.raises(ConfigError) as e:
        frusta.frusta_from_skeleton(joints, radii, list(range(-1, n - 1)))
    assert e.value.lines == want


BAD_FLOATS = st.sampled_from([np.nan, np.inf, -np.inf])


@settings(max_examples=30, deadline=None, derandomize=True)
@given(nb=st.integers(1, 6), nt=st.integers(1, 4), data=st.data())
def test_every_corrupted_implicit_primitive_is_named_at_once(nb, nt, data):
    """Class 4 by hypothesis, implicit surfaces: ``nb`` balls and ``nt`` tubes, then a drawn set of
    centre coordinates made NaN or infinite, a drawn set of ball radii made 0 or negative and a
    drawn set of tubes given coinciding ends: one ConfigError naming every one (the field's
    index and the value as given), the balls' in order, then the tubes'."""
    from jskel.config import validate

    balls = [{"center": [float(i), 0.0, 0.0], "radius": 0.5} for i in range(nb)]
    tubes = [{"a": [float(i), 2.0, 0.0], "b": [float(i), 3.0, 0.5], "radius_a": 0.3, "radius_b": 0.2} for i in range(nt)]
    bad_c = sorted(data.draw(st.sets(st.tuples(st.integers(0, nb - 1), st.integers(0, 2)), max_size=4), "centres"))
    bad_r = sorted(data.draw(st.sets(st.integers(0, nb - 1), max_size=nb), "radii"))
    bad_t = sorted(data.draw(st.sets(st.integers(0, nt - 1), max_size=nt), "tubes"))
    assume(bad_c or bad_r or bad_t)
    for i, k in bad_c:
        balls[i]["center"][k] = data.draw(BAD_FLOATS)
    for i in bad_r:
        balls[i]["radius"] = data.draw(st.sampled_from([0.0, -0.5, -1.0, -2.5, -1e-06]))
    for i in bad_t:
        tubes[i]["b"] = list(tubes[i]["a"])
    want = []
    for i in range(nb):  # per field, as validated: a ball's centre coordinates, then its radius
        want += [f"object.balls[{i}].center[{k}]: Input should be a finite number (got {balls[i]['center'][k]!r})" for j, k in bad_c if j == i]
        want += [f"object.balls[{i}].radius: Input should be greater than 0 (got {balls[i]['radius']!r})"] if i in bad_r else []
    want += [f"object.tubes[{i}].b: coincides with a; a tube needs a length (got [{i}, 2, 0])" for i in bad_t]
    raw = {"object": {"type": "implicit", "balls": balls, "tubes": tubes}, "camera": {"eye": [0, 1, 5], "target": [0, 1, 0], "width": 16, "height": 16}}
    with pytest.raises(ConfigError) as e:
        validate(raw)
    assert e.value.lines == want


@settings(max_examples=30, deadline=None, derandomize=True)
@given(kind=st.sampled_from(["sphere", "torus"]), data=st.data())
def test_every_corrupted_cell_base_value_is_named_at_once(kind, data):
    """Class 4 by hypothesis, cell objects: a sphere or torus base shape with a drawn set of centre
    coordinates made NaN or infinite and a drawn set of its sizes (radius; major and minor)
    made 0 or negative: one ConfigError naming every one (the field and the value as given), in
    the section's field order (centre, major, minor, radius)."""
    from jskel.config import validate

    base = {"type": kind, "center": [0.0, 0.0, 0.0], **({"radius": 1.0} if kind == "sphere" else {"major": 1.0, "minor": 0.4})}
    sizes = ["radius"] if kind == "sphere" else ["major", "minor"]
    bad_c = sorted(data.draw(st.sets(st.integers(0, 2), max_size=3), "centre"))
    bad_s = [k for k in sizes if data.draw(st.booleans(), k)]
    assume(bad_c or bad_s)
    for k in bad_c:
        base["center"][k] = data.draw(BAD_FLOATS)
    for k in bad_s:
        base[k] = data.draw(st.sampled_from([0.0, -0.4, -1.0, -3.5]))
    want = [f"object.base.center[{k}]: Input should be a finite number (got {base['center'][k]!r})" for k in bad_c]
    want += [f"object.base.{k}: Input should be greater than 0 (got {base[k]!r})" for k in ("major", "minor", "radius") if k in bad_s]
    raw = {"object": {"type": "cells", "base": base}, "camera": {"eye": [0, 1, 5], "target": [0, 1, 0], "width": 16, "height": 16}}
    with pytest.raises(ConfigError) as e:
        validate(raw)
    assert e.value.lines == want


@settings(max_examples=20, deadline=None, derandomize=True)
@given(n=st.integers(4, 12), data=st.data())
def test_every_corrupted_mesh_vertex_is_named_at_once(n, data, tmp_path_factory):
    """Class 4 by hypothesis, meshes: a fan of ``n`` vertices written as OBJ with a drawn set of
    them given a NaN or an infinity in a drawn coordinate: one error naming the file and every
    bad vertex (its index and value; past five, the count and the first five)."""
    from jskel import registry

    v = np.stack([np.cos(np.arange(n)), np.sin(np.arange(n)), np.zeros(n)], 1).round(3)
    v[0] = 0.0
    bad = sorted(data.draw(st.sets(st.integers(0, n - 1), min_size=1, max_size=n), "vertices"))
    for i in bad:
        v[i, data.draw(st.integers(0, 2))] = data.draw(BAD_FLOATS)
    path = tmp_path_factory.mktemp("mesh") / "fan.obj"
    path.write_text("".join(f"v {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in v) + "".join(f"f 1 {i + 1} {i + 2}\n" for i in range(1, n - 1)))
    rep = registry.get("mesh")
    with pytest.raises(ValueError) as e:
        rep.build(rep.Config.model_validate({"type": "mesh", "path": str(path)}))
    assert getattr(e.value, "lines", [str(e.value)]) == _named(f"object.path ({str(path)!r}) vertices", "not finite", bad, v, "vertices")


@settings(max_examples=30, deadline=None, derandomize=True)
@given(n=st.integers(2, 40), data=st.data())
def test_every_corrupted_ray_and_cloud_point_is_named_at_once(n, data):
    """Class 4 by hypothesis, rays and point clouds: ``n`` rays with a drawn set of origins given
    a NaN or an infinity, a drawn set of directions given one and another set made zero, and a
    cloud of ``n`` points with a drawn set corrupted the same way: ``make_rays`` and ``fit_points``
    name every one (origins, directions not finite, directions zero; the cloud's points), before
    anything compiles."""
    rng = np.random.default_rng(n)
    o, d = rng.normal(size=(n, 3)).round(3), np.tile([0.0, 0.0, 1.0], (n, 1))
    bad_o = sorted(data.draw(st.sets(st.integers(0, n - 1), max_size=n), "origins"))
    bad_d = sorted(data.draw(st.sets(st.integers(0, n - 1), max_size=n), "directions"))
    zero = sorted(set(data.draw(st.sets(st.integers(0, n - 1), max_size=n), "zero")) - set(bad_d))
    assume(bad_o or bad_d or zero)
    for i in bad_o:
        o[i, data.draw(st.integers(0, 2))] = data.draw(BAD_FLOATS)
    for i in bad_d:
        d[i, data.draw(st.integers(0, 2))] = data.draw(BAD_FLOATS)
    d[zero] = 0.0
    with pytest.raises(ConfigError) as e:
        make_rays(o, d)
    assert e.value.lines == (_named("rays.origins", "not finite", bad_o, o, "rays") + _named("rays.directions", "not finite", bad_d, d, "rays")
                             + _named("rays.directions", "is the zero vector", zero, d, "rays"))
    if bad_o:  # the same corruption as a cloud of points to fit
        pts = np.concatenate([o, rng.normal(size=(40, 3)).round(3)])
        with pytest.raises(ValueError) as e:
            fit_points(pts, [[0, 0, 0], [0, 1, 0]], [0.2, 0.2], [-1, 0], SolverConfig())
        assert str(e.value) == "\n".join(_named("points", "not finite", bad_o, pts, f"of {len(pts)} points"))


def test_a_cell_colour_map_names_every_bad_texel(tmp_path):
    from jskel import cells

    colors = np.full((4, 4, 4, 3), 0.5)
    colors[0, 0, 0, 0] = np.nan
    colors[1, 2, 3, 1] = np.inf
    np.save(tmp_path / "colors.npy", colors)
    cfg = cells.CellsConfig.model_validate({"type": "cells", "tiles": 2, "cache": None, "color_map": str(tmp_path / "colors.npy"),
                                            "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 1}})
    with pytest.raises(ConfigError) as e:
        cells.precompute(cfg)
    assert e.value.lines == ["object.color_map: 2 texels: not finite (indices (0, 0, 0): [nan, 0.5, 0.5], (1, 2, 3): [0.5, inf, 0.5])"]


def test_validate_skeleton_every_value_parent_and_cycle_at_once():
    from jskel import frusta

    joints = [[0, 0, 0], [np.nan, 1, 0], [0, 2, 0], [0, 3, 0], [0, 4, 0], [0, 5, 0]]
    with pytest.raises(ConfigError) as e:
        frusta.validate_skeleton(joints, [0.1, 0.1, -0.1, 0.1, 0.1, 0.1], [-1, 0, 7, 4, 3, 5])
    assert e.value.lines == [
        "object.skeleton.joints[1]: not finite (got [nan, 1, 0])",
        "object.skeleton.radii[2]: negative radius (got -0.1)",
        "object.skeleton.parents[2]: index out of range [-1, 5] (got 7)",
        "object.skeleton.parents[5]: is the joint itself (got 5)",
    ]
    with pytest.raises(ConfigError) as e:  # the indices fine: every cycle, the NaN joint still named
        frusta.validate_skeleton(joints, [0.1] * 6, [-1, 0, 1, 4, 3, 0])
    assert e.value.lines == [
        "object.skeleton.joints[1]: not finite (got [nan, 1, 0])",
        "object.skeleton.parents[3]: parents make a cycle (got 3 -> 4 -> 3)",
    ]
