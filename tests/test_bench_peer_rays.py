"""A bench's peer casts the rays jskel rendered, also where the camera is framed on the object's
bounds (``camera.frame: auto``, as the neuron benchmark's is): the study gets the experiment with
the camera the render used. The rays the study would cast are checked against a float64 NumPy
ray-cylinder intersection written here. Also: the neuron benchmark files validate and expand
to the settings their section of docs/performance.md describes. No peer is needed (the study is replaced)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jskel.measure.bench import BenchFile, groups_of, run_bench
from jskel.measure.files import read_model
from jskel.probe.study import Peers
from jskel.render import camera_of

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
R, H = 1.0, 10.0  # one segment: a cylinder of radius R along y from 0 to H


def _cylinder_t(o, d):
    """Nearest t > 0 of each ray (float64) on the infinite cylinder x^2 + z^2 = R^2 (inf on a
    miss), and the y of that hit."""
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2])
    c = o[:, 0] ** 2 + o[:, 2] ** 2 - R * R
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    t = np.where(t > 0, t, np.inf)
    y = o[:, 1] + np.where(np.isfinite(t), t, 0) * d[:, 1]
    return t, y


def test_the_peer_study_gets_the_rays_of_an_auto_framed_render(tmp_path):
    exp = tmp_path / "cyl.yaml"
    exp.write_text(f"""
object:
  type: frusta
  skeleton: {{joints: [[0, 0, 0], [0, {H}, 0]], radii: [{R}, {R}], parents: [-1, 0]}}
camera: {{frame: auto, view: [0, 0, 1], fov_deg: 40}}
render: {{progress: false}}
""")
    file = tmp_path / "b.yaml"
    file.write_text(f"""
width: 32
height: 24
runs: 1
warmup: 1
scenes: [{exp}]
sweep:
  - {{object.accel: bvh}}
reference: [object.accel=bvh]
peer: skeleton
""")
    seen = {}

    def study(exp, ref_hits, runs, rows, options):
        seen["rays"] = camera_of(exp).ray_arrays()  # raises while frame: auto is unresolved
        seen["t"] = np.asarray(ref_hits.t, np.float64)
        return [{"peer": "stand-in", "rows_seen": len(rows)}]

    rows = run_bench(file, [], out=tmp_path / "rows.jsonl", peers=Peers(studies={"skeleton": study}))
    assert rows[-1] == {"peer": "stand-in", "rows_seen": 1}
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2  # the row and the study's, kept (and plotted beside)
    o, d = (np.asarray(a, np.float64) for a in seen["rays"])
    assert o.shape == (32 * 24, 3)
    t_ref, y = _cylinder_t(o, d)
    t = seen["t"]
    body = np.isfinite(t_ref) & (y > 0.05 * H) & (y < 0.95 * H)  # the side, away from either end's cap
    far = ~np.isfinite(t_ref)
    assert body.mean() > 0.05  # framed: the cylinder covers a good part of the image
    # the same rays: jskel hit where the cylinder's side is, at the same depth, and nothing
    # where the ray misses the infinite cylinder (a few silhouette pixels may differ)
    agree = np.isfinite(t[body])
    assert agree.mean() > 0.97
    np.testing.assert_allclose(t[body][agree], t_ref[body][agree], rtol=2e-4)
    assert np.mean(np.isfinite(t[far])) < 0.02


def test_the_neuron_benchmarks_expand_to_their_documented_settings():
    """bench_neuron.yaml: one BVH row with the peers on the reference's rays; ``--set
    set=[...]`` carries the copies to every scene. bench_neuron_size.yaml: 1, 2 and 4 copies a
    side (4,177 x k^2 nodes), jskel alone."""
    file = EXPERIMENTS / "bench_neuron.yaml"
    b = read_model(BenchFile, file, ["set=[object.skeleton.replicate=4]"])
    (g,) = groups_of(b, file, [])
    assert b.peer == "skeleton" and b.cast and g.reference is not None
    assert [j.setting for j in g.jobs] == [{"object.accel": "bvh"}]
    assert g.reference.objects[0].shape.skeleton.replicate == 4 and g.jobs[0].exp.objects[0].shape.skeleton.replicate == 4
    assert (g.reference.camera.width, g.reference.camera.height) == (1024, 768)
    file = EXPERIMENTS / "bench_neuron_size.yaml"
    s = read_model(BenchFile, file, [])
    (g,) = groups_of(s, file, [])
    assert s.peer is None and s.cast and s.stats and g.reference is None
    assert [j.exp.objects[0].shape.skeleton.replicate for j in g.jobs] == [1, 2, 4]
    assert s.labels == [f"{4177 * k * k} nodes" for k in (1, 2, 4)]
