"""The frusta exported as a triangle mesh (``jskel.frusta.export_mesh``, ``jskel export``): the
file's vertices on the analytic cones, and the mesh read back as a ``type: mesh`` object hitting
the same rays as the frusta within the tessellation's sagitta. Cones, normals and bounds are
computed here in float64 NumPy from the skeleton alone."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from jskel import frusta, mesh
from jskel.cli import main
from jskel.executor import map_chunks
from jskel.interface import Object, intersect
from jskel.rays import make_rays

from conftest import build_skeleton, cast

# a chain with a 17-degree and a 25-degree bend, tapering 0.3 -> 0.1, and a side branch
JOINTS = np.array([[0, 0, 0], [0, 1, 0], [0.3, 2, 0], [0.8, 2.6, 0.2], [-0.5, 1.6, 0.1]], np.float64)
RADII = np.array([0.3, 0.25, 0.18, 0.1, 0.12])
PARENTS = np.array([-1, 0, 1, 2, 1])
LEVEL = 2
NU = 8 * 2**LEVEL  # generators around each segment


def _cfg():
    return frusta.FrustaConfig.model_validate({"type": "frusta", "skeleton": {
        "joints": JOINTS.tolist(), "radii": RADII.tolist(), "parents": PARENTS.tolist()}})


def _cones(p):
    """For points p (N, 3) and every segment (parent a -> child b) of the skeleton: axial
    coordinate y (N, S) from a, radial distance rho, the cone's radius at y, the segment length
    and the taper k = (r_b - r_a) / h; the cone is the one through both joints' circles."""
    b = np.nonzero(PARENTS >= 0)[0]
    a = PARENTS[b]
    axis = JOINTS[b] - JOINTS[a]
    h = np.linalg.norm(axis, axis=1)
    m = axis / h[:, None]
    q = p[:, None, :] - JOINTS[a][None]
    y = np.einsum("nsk,sk->ns", q, m)
    radial = q - y[..., None] * m[None]
    rho = np.linalg.norm(radial, axis=-1)
    k = (RADII[b] - RADII[a]) / h
    return y, rho, RADII[a][None] + k[None] * y, h, k, m, radial


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    path = tmp_path_factory.mktemp("export") / "frusta.ply"
    info = frusta.export_mesh(path, _cfg(), LEVEL)
    return path, info


def test_every_vertex_lies_on_its_cone(exported):
    path, info = exported
    v = np.asarray(trimesh.load(path, process=False).vertices)  # in the file's order (read_mesh merges)
    assert v.dtype == np.float64
    assert info["segments"] == 4 and info["faces"] == 4 * 16 * 4**LEVEL + NU * 4  # fans: the root, two tips, the side branch's base
    lateral = 4 * (2**LEVEL + 1) * NU
    y, rho, r, h, k, m, _ = _cones(v[:lateral])
    # distance to the nearest segment's cone surface, among segments whose span holds the vertex
    # (the pieces reach past their joints up to the cutting planes, at most 0.5 of a length here)
    near = (y > -0.5 * h) & (y < 1.5 * h)
    dist = np.where(near, np.abs(rho - r) / np.sqrt(1 + k * k), np.inf).min(1)
    assert np.max(dist) < 1e-9 * np.max(RADII), np.max(dist)
    # cap centres lie on their segment's axis
    y, rho, *_ = _cones(v[lateral:])
    assert v.shape[0] == lateral + 4 and np.min(rho, axis=1).max() < 1e-12


def view_rays(w: int = 32, hgt: int = 24):
    """(O, D) float64: a pinhole's rays over the skeleton."""
    eye = np.array([0.4, 1.3, 4.0])
    xs, ys = np.meshgrid(np.linspace(-0.7, 1.1, w), np.linspace(-0.4, 2.9, hgt))
    target = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    D = target - eye
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return np.broadcast_to(eye, D.shape).copy(), D


def frusta_t(O, D):
    return np.asarray(cast(build_skeleton(JOINTS, RADII, PARENTS), O, D).t, np.float64)


def test_mesh_hits_the_frusta_rays_within_the_sagitta(exported):
    path, _ = exported
    O, D = view_rays()
    built = mesh.build(mesh.MeshConfig.model_validate({"type": "mesh", "path": str(path)}))
    hm = map_chunks(intersect, Object(built.params, built.static, "mesh"), make_rays(O - built.anchor, D), chunk=4096, progress=False).out
    check_mesh_hits(frusta_t(O, D), np.asarray(hm.t, np.float64), O, D, path)


def check_mesh_hits(tf, tm, O, D, path, t_tol=2e-5):
    """A mesh caster's t (``tm``) against the frusta's (``tf``) on rays (O, D): within the
    sagitta of the exported facets where both hit, and misses only where a ray grazes the cone or
    the rim of a cap (``tests/scripts/mesh_export_embree.py`` runs it on Embree's hits).
    ``t_tol``: the casters' rounding of t."""
    both = np.isfinite(tf) & np.isfinite(tm)
    assert both.sum() > 0.15 * tf.size  # the skeleton fills a good part of the view

    # the cone's normal at each frusta hit (its nearest segment), and the ray's incidence on it
    p = O + tf[:, None] * D
    y, rho, r, h, k, m, radial = _cones(np.where(np.isfinite(p), p, 0.0))
    near = (y > -0.5 * h) & (y < 1.5 * h)
    s = np.where(near, np.abs(rho - r), np.inf).argmin(1)
    i = np.arange(p.shape[0])
    e = radial[i, s] / np.maximum(rho[i, s], 1e-30)[:, None]
    n = (e - k[s, None] * m[s]) / np.sqrt(1 + k[s] ** 2)[:, None]
    cos = np.abs(np.sum(n * D, 1))
    lateral = np.abs(rho[i, s] - r[i, s]) < 1e-4  # else the hit is on a flat cap

    # sagitta of the facets: r_max (1 - cos(pi / nu)), r_max the largest radius the pieces reach
    # (their vertices', measured on the cones here)
    v, _, _ = mesh.read_mesh(str(path))
    r_max = np.max(_cones(v)[1].min(1))  # the largest vertex distance from the nearest axis
    sag = r_max * (1 - np.cos(np.pi / NU))
    # where both hit, the mesh lies behind the cone by at most the sagitta along the normal:
    # |t_frusta - t_mesh| <= sag / cos for the lateral surface (caps are the same plane), with
    # float32 rounding of t ~ 4 and rays no more grazing than 0.3
    ok = both & (~lateral | (cos > 0.3))
    dt = np.abs(np.subtract(tf, tm, out=np.zeros_like(tf), where=both))
    bound = np.where(lateral, sag / np.maximum(cos, 1e-6), 0.0) + t_tol
    assert np.all(dt[ok] <= bound[ok]), (np.max(dt[ok] - bound[ok]), sag)
    assert np.all(tm[both] >= tf[both] - t_tol)  # the inscribed mesh is never in front of the cone
    # hit masks agree except near silhouettes: the mesh is inscribed, so it hits no ray the
    # frusta miss; a ray only the frusta hit passes through the thin shell between the facets and
    # the cone, i.e. grazes the cone (|cos| <= sqrt(2 sag / r) for a ray through a sliver of a
    # circle, here < 0.15) or the rim band of a cap
    only_f = np.isfinite(tf) & ~np.isfinite(tm)
    assert not np.any(np.isfinite(tm) & ~np.isfinite(tf))
    rim = rho[i, s] >= r[i, s] * np.cos(np.pi / NU) - t_tol
    assert np.all(((lateral & (cos < 0.15)) | (~lateral & rim))[only_f]), (cos[only_f & lateral], rho[i, s][only_f & ~lateral])
    assert only_f.sum() <= 0.03 * np.isfinite(tf).sum()
    return {"rays": int(tf.size), "both_hit": int(both.sum()), "only_frusta": int(only_f.sum()),
            "dt_over_bound_max": float(np.max(dt[ok] / bound[ok])), "sagitta": float(sag)}


def test_export_command_and_its_errors(tmp_path, capsys):
    exp = tmp_path / "e.yaml"
    exp.write_text(f"name: e\nobject:\n  type: frusta\n  skeleton:\n    joints: {JOINTS.tolist()}\n"
                   f"    radii: {RADII.tolist()}\n    parents: {PARENTS.tolist()}\n")
    out = tmp_path / "m.obj"
    assert main(["export", str(exp), "--out", str(out), "--level", "1"]) == 0
    v, f, _ = mesh.read_mesh(str(out))
    assert f.shape[0] == 4 * 16 * 4 + 16 * 4
    want, _ = frusta.frusta_mesh(frusta.host_frusta(_cfg())[0], 1)
    np.testing.assert_allclose(np.sort(v, 0), np.sort(want, 0), rtol=0, atol=1e-15)  # 17 digits
    capsys.readouterr()
    assert main(["export", str(exp), "--out", str(tmp_path / "m.xyz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jskel: error: --out: cannot tell the mesh format from") and "m.xyz" in err[0]
    assert main(["export", str(exp), "--out", str(out), "--level", "9"]) == 2
    assert "level: expected an integer 0..8 (got 9)" in capsys.readouterr().err
