"""Exploring without recompiling (issue 27): after a first render, a change of a radius, of the
camera pose, of the image size within a bucket, of the skeleton's segment count within a
bucket, of the samples per pixel, of the light or of the material renders with no program handed to XLA (none compiled, none loaded from the persistent
cache: ``jskel.compile.cache.program_counts``), and every re-render casts the changed experiment, checked
against the independent float64 reference (``tests/reference.py``, Bhagvat et al. 2009 Sec. 2).

The executor's buckets themselves are checked on a batch function of a few operations (nothing
of a render compiles there): batches smaller than one chunk padded to a few sizes, grouped
calls of a power of two chunks whose padding chunks are skipped, against NumPy.

A mesh of 72 and of 76 triangles and an implicit model of 5 and of 6 balls each share one
size bucket (``executor.size_bucket``): the second renders with no program, its hits checked
against a float64 reference written here (ray-triangle and ray-sphere).
"""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from triangles import moller_trumbore
from jskel import config
from jskel.compile.cache import count_programs, program_counts
from jskel.executor import batch_bucket, calls_grouping, map_chunks, size_bucket
from jskel.rays import make_rays
from jskel.render import camera_of, render

# a branching skeleton of 4 segments, and the same grown by two (both pad to 8 segment rows)
JOINTS = np.array([[0, 0, 0], [0, 1.5, 0], [0.2, 3.0, 0.1], [1.0, 2.4, 0.0], [-0.8, 2.3, -0.5]], float)
RADII = np.array([0.5, 0.4, 0.2, 0.15, 0.15])
PARENTS = np.array([-1, 0, 1, 1, 1])
GROWN = (np.vstack([JOINTS, [[0.4, 3.9, 0.3], [1.7, 2.9, 0.2]]]), np.append(RADII, [0.12, 0.1]), np.append(PARENTS, [2, 3]))
# 64x48 and 80x60 rays in chunks of 256, at most 16 per call: 12 and 19 chunks, one call of 16
# (4 padding chunks) and two (13 padding chunks), one program
SMALL, LARGER = (64, 48), (80, 60)


def _experiment(joints=JOINTS, radii=RADII, parents=PARENTS, eye=(4.0, 2.5, 6.0), size=SMALL, spp=1, extra=None):
    raw = {
        "name": "rerender",
        "object": {"type": "frusta", "accel": "bvh",
                   "skeleton": {"joints": joints.tolist(), "radii": radii.tolist(), "parents": parents.tolist()}},
        "camera": {"eye": list(eye), "target": [0.1, 1.6, -0.1], "up": [0, 1, 0], "fov_deg": 40, "width": size[0], "height": size[1]},
        "render": {"chunk": 256, "chunks_per_call": 16, "progress": False, "spp": spp},
    }
    for key, value in (extra or {}).items():  # "object.color": ... sets a key of a section
        section, _, name = key.rpartition(".")
        (raw.setdefault(section, {}) if section else raw)[name] = value
    return config.validate(raw)


def _programs(exp, names=None):
    """(render result, programs handed to XLA by the render: compiled + loaded); ``names``, a
    dict, gets each program's name and how many of it were handed over (for a failure's message)."""
    count_programs()
    before = program_counts()
    res = render(exp)
    after = program_counts()
    if names is not None:
        names.update({k: v[0] - before["by_name"].get(k, [0])[0] for k, v in after["by_name"].items()
                      if v[0] != before["by_name"].get(k, [0])[0]})
    return res, (after["compiled"] - before["compiled"]) + (after["loaded"] - before["loaded"])


def _assert_casts(res, exp, joints, radii, parents):
    """The render's first hits are the reference's for the experiment's camera rays: the same
    hit or miss and t within 1e-4 of the skeleton's size wherever a ray is away from a
    silhouette and a seam."""
    O, D = camera_of(exp).ray_arrays()
    segs = ref.segments(joints, radii, parents)
    lo, hi = joints.min(0) - radii.max(), joints.max(0) + radii.max()
    scale = float(np.linalg.norm(hi - lo))
    t_ref, _ = ref.intersect(segs, O, D)
    far = ref.far_from_silhouette(segs, O, D, delta=1e-3 * scale, jump=2e-2 * scale)
    t = np.asarray(res.hits.t, np.float64)
    assert t.shape == (exp.camera.width * exp.camera.height,) and res.image.shape == (exp.camera.height, exp.camera.width, 3)
    assert 0.05 < np.isfinite(t_ref).mean() < 0.95 and far.mean() > 0.8
    np.testing.assert_array_equal(np.isfinite(t)[far], np.isfinite(t_ref)[far])
    both = far & np.isfinite(t_ref)
    assert np.max(np.abs(t[both] - t_ref[both])) <= 1e-4 * scale


@pytest.fixture(scope="module")
def first():
    """The first render (it compiles, or loads from the persistent cache, what it needs)."""
    exp = _experiment()
    res, _ = _programs(exp)
    _assert_casts(res, exp, JOINTS, RADII, PARENTS)
    return res


CHANGES = {
    "radius": lambda: (dict(radii=RADII * np.array([1, 1.3, 1, 1, 1])), (JOINTS, RADII * np.array([1, 1.3, 1, 1, 1]), PARENTS)),
    "camera_pose": lambda: (dict(eye=(-3.0, 3.5, 6.5)), (JOINTS, RADII, PARENTS)),
    "image_size": lambda: (dict(size=LARGER), (JOINTS, RADII, PARENTS)),
    "segments": lambda: (dict(joints=GROWN[0], radii=GROWN[1], parents=GROWN[2]), GROWN),
    # twice the rays (24 chunks, two calls of 16): the first sample's hits are the pixel centres'
    "samples": lambda: (dict(spp=2), (JOINTS, RADII, PARENTS)),
    # the one default light's direction, colour and intensity (its kind and shadows kept)
    "light": lambda: (dict(extra={"lights": [{"direction": [-0.5, 0.7, 0.4], "color": [1.0, 0.9, 0.8], "intensity": 0.8}]}),
                      (JOINTS, RADII, PARENTS)),
    # the object's colour and the shading's terms
    "material": lambda: (dict(extra={"object.color": [0.6, 0.3, 0.2], "shading.ambient": 0.3, "shading.specular": 0.5,
                                     "shading.shininess": 16.0}), (JOINTS, RADII, PARENTS)),
}


@pytest.mark.parametrize("change", sorted(CHANGES))
def test_a_change_within_its_bucket_renders_without_a_program(first, change):
    kw, skeleton = CHANGES[change]()
    exp = _experiment(**kw)
    names = {}
    res, programs = _programs(exp, names)
    assert programs == 0, f"{change}: {programs} programs compiled or loaded: {names}"
    assert res.run["compile_s"] == 0.0
    _assert_casts(res, exp, *skeleton)
    assert res.image.shape != first.image.shape or np.any(res.image != first.image)  # not the first image again


def test_batch_buckets_are_few_and_waste_under_a_fifth():
    """Every batch size from 1 to 2^16 rays below a chunk pads to a bucket at least its size
    and under 1.25 times it (beyond 8 rays), with 4 buckets per doubling."""
    n = np.arange(1, 1 << 16)
    b = np.array([batch_bucket(int(k)) for k in n])
    assert np.all(b >= n) and np.all(np.diff(b) >= 0)
    assert np.all(b[n > 8] < 1.25 * n[n > 8])
    assert len(np.unique(b)) == 4 * 13 + 1  # 8, then 10, 12, 14, 16, ..., 2^16
    assert [calls_grouping(k, 64) for k in (1, 7, 8, 9, 16, 17, 32, 33, 64, 65, 1000)] == [1, 1, 8, 16, 16, 32, 32, 64, 64, 64, 64]


def _dot(params, rays):
    return {"v": params * (rays.origins * rays.directions).sum(-1) + rays.t_max, "i": rays.origins[:, 0].astype(np.int32)}


@pytest.mark.parametrize("chunk, group, sizes", [(4096, 1, (2640, 3000, 3072)), (256, 16, (12 * 256 - 5, 19 * 256 + 7, 40 * 256))])
def test_batch_sizes_in_a_bucket_share_one_program_and_every_ray_is_computed(chunk, group, sizes):
    """Batches of ``sizes`` rays, one program: below one chunk the batch is padded to its
    bucket; in grouped calls (16 chunks of 256 per call: 12, 19 and 40 chunks) the padding
    chunks are skipped and every real chunk is computed (the outputs equal NumPy's, float64)."""
    rng = np.random.default_rng(27)
    count_programs()
    compiled = []
    for n in sizes:
        o, d = rng.uniform(-100, 100, (n, 3)).round(), rng.normal(size=(n, 3))
        rays = make_rays(o, d / np.linalg.norm(d, axis=1, keepdims=True), 0.0, 2.0)
        before = program_counts()
        out = map_chunks(_dot, np.float32(0.5), rays, chunk=chunk, progress=False, group=group).out
        after = program_counts()
        compiled.append(after["compiled"] + after["loaded"] - before["compiled"] - before["loaded"])
        want = 0.5 * np.sum(np.asarray(rays.origins, np.float64) * np.asarray(rays.directions, np.float64), -1) + 2.0
        np.testing.assert_allclose(out["v"], want, rtol=1e-5, atol=1e-4)
        np.testing.assert_array_equal(out["i"], o[:, 0].astype(np.int32))
    assert compiled[1:] == [0] * (len(sizes) - 1), compiled


def test_grouped_calls_over_four_devices_skip_each_devices_padding_chunks():
    """Over four devices each grouped call's chunks are dealt out in turn and every device skips
    its own padding chunks (some run none): the outputs equal NumPy's (a subprocess: the device
    count is fixed at JAX's start)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    p = subprocess.run([sys.executable, str(root / "tests" / "scripts" / "grouped_sharded.py")], cwd=root, env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out["devices"] == 4 and len(out["cases"]) == 4
    assert all(c["equal"] for c in out["cases"]), out["cases"]


def test_size_buckets_double_to_64_then_grow_by_at_most_a_quarter():
    """Model tables pad to powers of two up to 64 (at least 8), then by under 1.25x, rounded
    up to a block size."""
    n = np.arange(1, 5000)
    b = np.array([size_bucket(int(k)) for k in n])
    assert np.all(b >= n) and np.all(np.diff(b) >= 0)
    assert sorted(set(b[n <= 64].tolist())) == [8, 16, 32, 64]
    assert np.all(b[n > 64] < 1.25 * n[n > 64])
    assert [size_bucket(k, 64) for k in (1, 65, 129, 513)] == [64, 128, 192, 640]


# a model in one bucket before and after a change of its size: 72 and 76 triangles (80 rows),
# 5 and 6 balls (16 rows, one block); small images in one call of the one-chunk program
MODEL_CAMERA = {"eye": [0.5, 3.0, 4.0], "target": [0.0, 0.0, 0.0], "up": [0, 1, 0], "fov_deg": 50, "width": 40, "height": 30}


def _model_experiment(obj):
    """The experiment of ``obj`` seen by :data:`MODEL_CAMERA`."""
    raw = {"name": "rerender_model", "object": obj, "camera": MODEL_CAMERA, "render": {"chunk": 2048, "progress": False}}
    return config.validate(raw)


def _terrain(extra: int) -> np.ndarray:
    """(F, 3, 3) triangles of a 6 x 6 height field over [-2, 2]^2 (72), and ``extra`` / 2 quads
    floating above it."""
    g = np.linspace(-2.0, 2.0, 7)
    x, z = np.meshgrid(g, g, indexing="ij")
    p = np.stack([x, 0.3 * np.sin(1.3 * x) * np.cos(0.9 * z), z], -1)
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3), np.stack([a, c, d], -2).reshape(-1, 3, 3)])
    for k in range(extra // 2):
        q = np.array([[-0.4, 1.0, -0.4], [0.4, 1.0, -0.4], [0.4, 1.1, 0.4], [-0.4, 1.1, 0.4]]) + [1.2 * k - 0.6, 0.2 * k, 0.0]
        tri = np.concatenate([tri, [q[[0, 1, 2]], q[[0, 2, 3]]]])
    return tri


def _mesh_object(tmp, tri):
    """The ``object`` section of triangles ``tri`` written to an OBJ file in ``tmp``."""
    path = tmp / f"terrain_{len(tri)}.obj"
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in tri.reshape(-1, 3)] + [f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}" for i in range(len(tri))]
    path.write_text("\n".join(lines) + "\n")
    return {"type": "mesh", "path": str(path), "leaf": 4}


def _triangles_f64(tri, O, D):
    """(t, ambiguous) of every ray against every triangle, float64 Moller-Trumbore: the nearest
    t > 0 (inf: none), and whether some triangle's barycentric margin is within 1e-4 of an edge."""
    t, u, v, det = moller_trumbore(tri, O, D)
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    t_hit = np.where((det != 0) & (margin >= 0) & (t > 0), t, np.inf)
    return t_hit.min(1), np.any((det != 0) & (np.abs(margin) < 1e-4) & (t > 0), axis=1)


BALL_T = 0.1  # the balls' threshold


def _balls(count: int):
    """``count`` balls of radius 0.6 on a circle, 1.39 apart or more (influences of radius 0.6:
    no two blend), and their surface radius: (1 - rho^2 / R^2)^2 = T."""
    ang = 2 * np.pi * np.arange(count) / 7
    c = np.stack([1.6 * np.cos(ang), 0.2 * np.arange(count) - 0.5, 1.6 * np.sin(ang)], 1)
    return c, 0.6 * np.sqrt(1 - np.sqrt(BALL_T))


def _spheres_f64(c, rho, O, D):
    """(t, ambiguous) of unit rays against spheres (centres c, radius rho), float64 closed form;
    ambiguous: passing within 2 % of rho of a silhouette."""
    oc = c[None] - O[:, None]
    tc = np.sum(oc * D[:, None], -1)
    d2 = np.sum(oc * oc, -1) - tc * tc
    t = np.where(d2 < rho**2, tc - np.sqrt(np.maximum(rho**2 - d2, 0)), np.inf)
    return t.min(1), np.any(np.abs(np.sqrt(np.maximum(d2, 0)) - rho) < 0.02 * rho, axis=1)


def _assert_model_hits(res, exp, t_ref, ambiguous, tol):
    """The render's first hits are the reference's (``t_ref`` along unit rays): the same hit or
    miss and t within ``tol`` wherever the reference is not ``ambiguous``."""
    O, D = camera_of(exp).ray_arrays()
    n = np.linalg.norm(np.asarray(D, np.float64), axis=1)
    t = np.asarray(res.hits.t, np.float64) * n  # a distance along the unit ray, as the reference's
    ok = ~ambiguous
    assert 0.05 < np.isfinite(t_ref).mean() < 0.95 and ok.mean() > 0.8
    np.testing.assert_array_equal(np.isfinite(t)[ok], np.isfinite(t_ref)[ok])
    both = ok & np.isfinite(t_ref)
    assert np.max(np.abs(t[both] - t_ref[both])) <= tol


def _unit_rays(exp):
    """The experiment's camera rays in float64, directions of length 1."""
    O, D = (np.asarray(x, np.float64) for x in camera_of(exp).ray_arrays())
    return O, D / np.linalg.norm(D, axis=1, keepdims=True)


@pytest.mark.parametrize("kind, sizes", [("mesh", (0, 4)), ("implicit", (5, 6))])
def test_a_model_grown_within_its_bucket_renders_without_a_program(tmp_path, kind, sizes):
    """The terrain's 72 triangles, then 76 (two more quads: 80 rows both, where 84 triangles
    would take 96 and new programs); 5 balls, then 6 (16 rows, one block of the default size):
    the second renders with no program handed to XLA, and both casts agree with float64."""
    programs = []
    for size in sizes:
        if kind == "mesh":
            tri = _terrain(size)
            exp = _model_experiment(_mesh_object(tmp_path, tri))
            t_ref, amb = _triangles_f64(tri, *_unit_rays(exp))
            tol = 1e-4
        else:
            c, rho = _balls(size)
            exp = _model_experiment({"type": "implicit", "threshold": BALL_T, "method": "lipschitz", "eps": 1e-3,
                                     "balls": [{"center": x.tolist(), "radius": 0.6} for x in c]})
            t_ref, amb = _spheres_f64(c, rho, *_unit_rays(exp))
            tol = 2e-3
        res, got = _programs(exp)
        programs.append(got)
        _assert_model_hits(res, exp, t_ref, amb, tol)
    assert programs[1] == 0, f"{kind}: {programs[1]} programs compiled or loaded for the grown model"


def test_an_implicit_threshold_and_step_lengths_render_without_a_program():
    """The 6 balls at another threshold (0.1 -> 0.16: a smaller surface radius), march step and
    tolerance (lengths, traced): no program handed to XLA after the first render, and the hits
    are the new threshold's spheres (float64 closed form)."""
    c, _ = _balls(6)
    programs = []
    for T, step, eps in ((BALL_T, 0.02, 1e-3), (0.16, 0.035, 5e-4)):
        exp = _model_experiment({"type": "implicit", "threshold": T, "method": "lipschitz", "step": step, "eps": eps,
                                 "balls": [{"center": x.tolist(), "radius": 0.6} for x in c]})
        res, got = _programs(exp)
        programs.append(got)
        _assert_model_hits(res, exp, *_spheres_f64(c, 0.6 * np.sqrt(1 - np.sqrt(T)), *_unit_rays(exp)), 2e-3)
    assert programs[1] == 0, f"{programs[1]} programs compiled or loaded for a new threshold and step lengths"
