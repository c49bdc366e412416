"""Exploring without recompiling (issue 27): after a first render, a change of a radius, of the
camera pose, of the image size within a bucket, of the skeleton's segment count within a
bucket or of the samples per pixel renders with no program handed to XLA (none compiled, none loaded from the persistent
cache: ``jskel.cache.program_counts``), and every re-render casts the changed experiment, checked
against the independent float64 reference (``tests/reference.py``, Bhagvat et al. 2009 Sec. 2).

The executor's buckets themselves are checked on a batch function of a few operations (nothing
of a render compiles there): batches smaller than one chunk padded to a few sizes, grouped
calls of a power of two chunks whose padding chunks are skipped, against NumPy.
"""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from jskel import config
from jskel.cache import count_programs, program_counts
from jskel.executor import batch_bucket, calls_grouping, map_chunks
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


def _experiment(joints=JOINTS, radii=RADII, parents=PARENTS, eye=(4.0, 2.5, 6.0), size=SMALL, spp=1):
    raw = {
        "name": "rerender",
        "object": {"type": "frusta", "accel": "bvh",
                   "skeleton": {"joints": joints.tolist(), "radii": radii.tolist(), "parents": parents.tolist()}},
        "camera": {"eye": list(eye), "target": [0.1, 1.6, -0.1], "up": [0, 1, 0], "fov_deg": 40, "width": size[0], "height": size[1]},
        "render": {"chunk": 256, "chunks_per_call": 16, "progress": False, "spp": spp},
    }
    return config.validate(raw)


def _programs(exp, obj):
    """(render result, programs handed to XLA by the render: compiled + loaded)."""
    count_programs()
    before = program_counts()
    res = render(exp, obj)
    after = program_counts()
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
    exp, obj = _experiment()
    res, _ = _programs(exp, obj)
    _assert_casts(res, exp, JOINTS, RADII, PARENTS)
    return res


CHANGES = {
    "radius": lambda: (dict(radii=RADII * np.array([1, 1.3, 1, 1, 1])), (JOINTS, RADII * np.array([1, 1.3, 1, 1, 1]), PARENTS)),
    "camera_pose": lambda: (dict(eye=(-3.0, 3.5, 6.5)), (JOINTS, RADII, PARENTS)),
    "image_size": lambda: (dict(size=LARGER), (JOINTS, RADII, PARENTS)),
    "segments": lambda: (dict(joints=GROWN[0], radii=GROWN[1], parents=GROWN[2]), GROWN),
    # twice the rays (24 chunks, two calls of 16): the first sample's hits are the pixel centres'
    "samples": lambda: (dict(spp=2), (JOINTS, RADII, PARENTS)),
}


@pytest.mark.parametrize("change", sorted(CHANGES))
def test_a_change_within_its_bucket_renders_without_a_program(first, change):
    kw, skeleton = CHANGES[change]()
    exp, obj = _experiment(**kw)
    res, programs = _programs(exp, obj)
    assert programs == 0, f"{change}: {programs} programs compiled or loaded"
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
