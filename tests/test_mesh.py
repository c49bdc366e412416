"""Triangle meshes (``type: mesh``) against a float64 NumPy ray-triangle test written here, on
meshes trimesh generates and writes (PLY, OBJ, STL); closed meshes lose no ray through shared
edges and vertices; the winding-number ``inside``; bad files; a mesh as a cell object's base."""

from __future__ import annotations

import jax
import numpy as np
import pytest
import trimesh
from triangles import moller_trumbore

from conftest import whole_chunks
from jskel import cells, mesh
from jskel.rays import make_rays
from jskel.interface import Object, intersect

N = 4096


def _brute_f64(tri, O, D):
    """Nearest (t, face) of every ray over every triangle, float64 Möller-Trumbore written
    independently of ``jskel.mesh``; its edge tests are widened by 1e-9 (exact ones miss rays
    through a shared vertex on every triangle around it, even in float64)."""
    t_best = np.full(len(O), np.inf)
    f_best = np.full(len(O), -1)
    for lo in range(0, len(O), 256):
        t, u, v, det = moller_trumbore(tri, O[lo:lo + 256], D[lo:lo + 256])
        ok = (det != 0) & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
        t = np.where(ok, t, np.inf)
        t_best[lo:lo + 256] = t.min(1)
        f_best[lo:lo + 256] = np.where(np.isfinite(t.min(1)), t.argmin(1), -1)
    return t_best, f_best


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mesh")
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    out = {}
    for ext in ("ply", "obj", "stl"):
        p = tmp / f"sphere.{ext}"
        m.export(p)
        out[ext] = str(p)
    return m, out


def _cfg(path, **kw):
    return mesh.MeshConfig.model_validate({"type": "mesh", "path": path, **kw})


def _cast(built, O, D):
    return whole_chunks(intersect, Object(built.params, built.static, "mesh"), make_rays(O - built.anchor, D), N)


def test_every_format_reads_the_same_triangles(files):
    m, paths = files
    want = np.sort(m.vertices[m.faces].reshape(-1, 9), axis=0)
    for ext, p in paths.items():
        v, f, _ = mesh.read_mesh(p)
        got = np.sort(v[f].reshape(-1, 9), axis=0)
        np.testing.assert_allclose(got, want, atol=1e-6, err_msg=ext)


@pytest.mark.parametrize("traversal", ["packets", "bins"])
def test_hits_match_a_float64_brute_force_and_the_closed_mesh_loses_no_ray(files, traversal):
    """Each traversal (the BVH's packets, the packet candidate lists) against float64 brute
    force, on rays from all around aimed at every vertex, every edge's midpoint and random points:
    a ray through a shared vertex or edge is never lost."""
    m, paths = files
    built = mesh.build(_cfg(paths["ply"], offset=(3.0, -2.0, 5.0), scale=1.5, traversal=traversal))
    tri = (m.vertices * 1.5 + [3.0, -2.0, 5.0])[m.faces]
    rng = np.random.default_rng(0)
    c = np.array([3.0, -2.0, 5.0])
    u = rng.normal(size=(N, 3))
    O = c + 6.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    # aims: random points in the box, every vertex and every edge's midpoint (shared edges)
    v_world = m.vertices * 1.5 + [3.0, -2.0, 5.0]
    verts = v_world
    mids = 0.5 * (v_world[m.edges_unique[:, 0]] + v_world[m.edges_unique[:, 1]])
    aims = np.concatenate([verts, mids])
    aims = np.concatenate([aims, c + rng.uniform(-1.6, 1.6, (N - len(aims), 3))])[:N]
    D = aims - O
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    h = _cast(built, O, D)
    t_ref, f_ref = _brute_f64(tri, O, D)
    # rays through a vertex or an edge midpoint whose line passes inside the faceted sphere's
    # inscribed sphere must hit (the mesh is closed); grazing ones may round either way
    n_f = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inscribed = np.min(np.abs(np.sum(n_f / np.linalg.norm(n_f, axis=1, keepdims=True) * (tri[:, 0] - c), 1)))
    oc = c - O
    line = np.linalg.norm(oc - np.sum(oc * D, 1)[:, None] * D, axis=1)
    aimed = np.arange(N) < len(verts) + len(mids)
    through = aimed & (line < 0.999 * inscribed)
    graze = aimed & ~through  # aimed at a silhouette vertex or edge: float32 rounds them either way
    assert through.sum() > 1500
    got = np.isfinite(h.t)
    assert np.all(got[through]), f"{np.sum(~got[through])} rays through shared vertices or edges lost"
    ref = np.isfinite(t_ref)
    assert np.all(ref[through])
    assert np.mean((got != ref)[~graze]) < 1e-3  # elsewhere only chance grazes may differ
    both = got & ref
    np.testing.assert_allclose(h.t[both], t_ref[both], rtol=2e-6 * 8, atol=0)
    rand = both & ~aimed  # rays aimed at shared vertices and edges may take any face around them
    assert np.mean(h.prim[rand] == f_ref[rand]) > 0.99
    world = h.position[both] + built.anchor
    np.testing.assert_allclose(np.linalg.norm(world - c, axis=1), 1.5, rtol=2e-2)  # on the (faceted) sphere
    n_ref = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n_ref /= np.linalg.norm(n_ref, axis=1, keepdims=True)
    same = h.prim[both] == f_ref[both]
    np.testing.assert_allclose(h.normal[both][same], n_ref[f_ref[both][same]], atol=1e-5)
    assert np.all(np.sum(h.normal[both] * (world - c), 1) > 0)  # outward, as trimesh winds the faces


def test_smooth_normals_interpolate_the_vertex_normals(files):
    m, paths = files
    built = mesh.build(_cfg(paths["ply"], normals="smooth"))
    rng = np.random.default_rng(1)
    O = rng.normal(size=(N, 3))
    O = 5.0 * O / np.linalg.norm(O, axis=1, keepdims=True)
    D = rng.uniform(-0.5, 0.5, (N, 3)) - O
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    h = _cast(built, O, D)
    hit = np.isfinite(h.t)
    p = h.position[hit] + built.anchor
    # an icosphere's vertex normals are its radial directions: the interpolated normal is the
    # hit's radial direction to within the facet's curvature
    radial = p / np.linalg.norm(p, axis=1, keepdims=True)
    assert np.max(np.linalg.norm(h.normal[hit] - radial, axis=1)) < 0.05
    np.testing.assert_allclose(np.linalg.norm(h.normal[hit], axis=1), 1.0, atol=1e-5)


def test_inside_is_the_winding_number_exact_when_closed_fractional_when_open(files, tmp_path):
    m, paths = files
    built = mesh.build(_cfg(paths["obj"]))
    rng = np.random.default_rng(2)
    x = rng.normal(size=(2000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    r = rng.uniform(0.0, 2.0, (2000, 1))
    keep = np.abs(r[:, 0] - 1.0) > 0.06  # away from the faceted surface
    pts = (x * r)[keep]
    w = np.asarray(jax.jit(jax.vmap(lambda q: mesh.winding_number(built.params, q)))(pts - built.anchor))
    inside = np.linalg.norm(pts, axis=1) < 1.0
    np.testing.assert_allclose(w[inside], 1.0, atol=1e-3)
    np.testing.assert_allclose(w[~inside], 0.0, atol=1e-3)
    got = np.asarray(jax.jit(jax.vmap(lambda q: mesh.inside(built.params, built.static, q)))(pts - built.anchor))
    np.testing.assert_array_equal(got, inside)
    # the upper half alone: at the centre the open hemisphere subtends half the sphere's solid angle
    half = m.copy()
    half.update_faces(half.triangles_center[:, 1] > 0)
    p = tmp_path / "half.ply"
    half.export(p)
    hb = mesh.build(_cfg(str(p)))
    assert hb.info["watertight"] is False and built.info["watertight"] is True
    w0 = float(mesh.winding_number(hb.params, np.zeros(3, np.float32) - hb.anchor.astype(np.float32)))
    assert abs(w0 - 0.5) < 0.02


def test_a_bad_mesh_file_is_one_value_error_listing_every_problem(tmp_path):
    with pytest.raises(ValueError, match=r"object\.path: no file '.*nothing\.obj'"):
        mesh.build(_cfg(str(tmp_path / "nothing.obj")))
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 1\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(ValueError) as e:
        mesh.build(_cfg(str(bad)))
    lines = str(e.value).splitlines()
    assert lines == [f"object.path ({str(bad)!r}) vertices[3]: not finite (got [nan, 0, 1])"], lines
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match="holds no triangles"):
        mesh.build(_cfg(str(empty)))


def test_a_mesh_is_a_cell_objects_base_shape(files, tmp_path):
    """The icosphere through its winding number, and the analytic sphere, as the cells' base
    shape: the same memberships but where the facets cut a cell differently."""
    _, paths = files
    common = {"type": "cells", "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 4,
              "cache": str(tmp_path / "cache")}
    a = cells.precompute(cells.CellsConfig.model_validate({**common, "base": {"type": "object", "object": {"type": "mesh", "path": paths["ply"]}}}))
    b = cells.precompute(cells.CellsConfig.model_validate({**common, "base": {"type": "sphere", "radius": 1.0}}))
    assert a.split.shape == b.split.shape
    ma, mb = a.info, b.info
    assert abs(ma["inside_split_cells"] - mb["inside_split_cells"]) <= 0.05 * mb["inside_split_cells"]


def _ray_segment_distance(o, d, a, b, samples=481):
    """Float64 lower bound on the distance from each ray ``o + t d`` (t >= 0, unit d; (N, 3))
    to the segment [a, b]: the distance from a point to a ray is convex along the segment, so
    its minimum over ``samples`` points is within half a spacing of the true one, subtracted."""
    s = np.linspace(0.0, 1.0, samples)
    q = a + s[:, None] * (b - a)  # (S, 3)
    w = q[None] - o[:, None]  # (N, S, 3)
    t = np.maximum(np.sum(w * d[:, None], -1), 0.0)
    dist = np.linalg.norm(w - t[..., None] * d[:, None], axis=-1).min(1)
    return dist - 0.5 * np.linalg.norm(b - a) / (samples - 1)


def _line_distance(o, d, a, u):
    """Float64 distance from each ray's line to the line a + s u (unit u), and s there."""
    n = np.cross(d, u)
    nn = np.linalg.norm(n, axis=-1)
    w = a - o
    dist = np.abs(np.sum(w * n, -1)) / np.maximum(nn, 1e-300)
    s = np.sum(np.cross(w, d) * n, -1) / np.maximum(nn * nn, 1e-300)
    return dist, s


def test_a_mesh_mirror_in_a_scene_reflects_and_shadows_frusta_implicit_and_cell_objects(tmp_path):
    """A mirror box mesh (trimesh) with a metaball, a frusta cylinder and a cell object above
    it, a directional light casting shadows: four representations in one scene. Truth in closed
    form (float64, written here): the box's depth by the slab test; for each object, a ray that
    clearly meets it (the sphere's chord, the cylinder's axis well inside the radius at its middle,
    the cell object's ball well inside the base sphere) or clearly misses it (a bounding sphere or
    capsule with a margin). Each mirrored and each shadow ray is decided only where every object
    is clearly met or clearly missed, and where exactly one is met."""
    import copy

    from jskel.config import validate
    from jskel.render import render

    box = trimesh.creation.box(extents=(2.0, 2.0, 0.4))  # centred at the origin: the mirror's face is z = 0.2
    p = tmp_path / "box.stl"
    box.export(p)
    T, R, C = 0.5, 0.8, np.array([-0.9, 0.0, 1.0])
    rs = R * np.sqrt(1.0 - np.sqrt(T))  # the lone metaball's surface: a sphere
    F0, F1, RF = np.array([0.5, -0.6, 1.0]), np.array([0.5, 0.6, 1.0]), 0.2  # the frusta cylinder
    CC, SC = np.array([-0.4, 0.65, 1.5]), 0.45  # the cell object: a unit base sphere scaled by 0.45
    L = np.array([0.0, 0.0, 1.0])  # light from +z: the objects shadow the mirror's face
    cam = {"eye": [3.0, 0.5, 5.0], "target": [0.0, 0.0, 0.0], "up": [0, 1, 0], "fov_deg": 40.0, "width": 96, "height": 72}
    cell_shape = {"type": "cells", "base": {"type": "sphere", "radius": 1.0}, "tiles": 4,
                  "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "cache": str(tmp_path / "cache")}
    raw = {"objects": [{"shape": {"type": "mesh", "path": str(p)}, "material": {"reflectivity": 0.9}},
                       {"shape": {"type": "implicit", "threshold": T, "balls": [{"center": C.tolist(), "radius": R}]}},
                       {"shape": {"type": "frusta", "skeleton": {"joints": [[0, -0.6, 0], [0, 0.6, 0]], "radii": [RF, RF], "parents": [-1, 0]}},
                        "transform": {"translate": [0.5, 0.0, 1.0]}},
                       {"shape": cell_shape, "transform": {"scale": SC, "translate": CC.tolist()}}],
           "camera": cam, "lights": [{"direction": L.tolist(), "shadows": True}], "render": {"bounces": 1}}
    exp = validate(copy.deepcopy(raw))
    res = render(exp, progress=False)
    # the camera's pixel-centre rays, written out
    eye = np.array(cam["eye"])
    f = -eye / np.linalg.norm(eye)
    right = np.cross(f, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    th = np.tan(np.radians(20.0))
    xs = ((np.arange(96) + 0.5) / 96 * 2 - 1) * th * 96 / 72
    ys = (1 - (np.arange(72) + 0.5) / 72 * 2) * th
    px, py = np.meshgrid(xs, ys)
    d = f + px.reshape(-1, 1) * right + py.reshape(-1, 1) * up
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def ball(o, dd, c, r):
        """(clearly met, clearly missed) by rays o + t dd, t > 0, for the sphere (c, r)."""
        oc = o - c
        b = np.sum(oc * dd, -1)
        q = np.sqrt(np.maximum(np.sum(oc * oc, -1) - b * b, 0.0))
        ahead = b < 0  # the centre lies ahead of the ray's origin (every origin here is outside)
        return ahead & (q < r - 0.05), (q > r + 0.05) | ~ahead

    def objects(o, dd):
        """(K, N) clearly met and clearly missed, for the ball, the cylinder and the cell object."""
        met, missed = [], []
        a, b = ball(o, dd, C, rs)
        met.append(a), missed.append(b)
        near = _ray_segment_distance(o, dd, F0, F1)
        axis, s_line = _line_distance(o, dd, F0, (F1 - F0) / np.linalg.norm(F1 - F0))
        ahead = np.sum((F0 + (F1 - F0) / 2 - o) * dd, -1) > 0
        met.append(ahead & (axis < RF - 0.05) & (np.abs(s_line - 0.6) < 0.4))
        missed.append(near > RF + 0.05)
        a, _ = ball(o, dd, CC, 0.5 * SC)  # the inner half of the base sphere holds whole cells only
        _, b = ball(o, dd, CC, SC + 0.1)  # an intersected cell may reach past the base sphere
        met.append(a), missed.append(b)
        return np.array(met), np.array(missed)

    t_face = (0.2 - eye[2]) / d[:, 2]
    hit = eye + t_face[:, None] * d
    _, clear = objects(np.broadcast_to(eye, d.shape), d)
    on_face = (np.abs(hit[:, 0]) < 0.95) & (np.abs(hit[:, 1]) < 0.95) & clear.all(0)  # the face, no object in front
    assert on_face.sum() > 500
    np.testing.assert_allclose(res.hits.t[on_face], t_face[on_face], rtol=1e-5)
    assert np.all(res.aovs["obj"][on_face] == 0)
    # mirrored rays: the one object a reflected ray clearly meets, nothing where it misses them all
    met, missed = objects(hit, d * np.array([1.0, 1.0, -1.0]))
    decided = on_face & (met | missed).all(0)
    for k in range(3):
        sees = decided & met[k] & (met.sum(0) == 1)
        assert sees.sum() > 8, (k, sees.sum())
        assert np.all(res.aovs["reflect_obj"][sees] == k + 1), k
    none = on_face & missed.all(0)
    assert none.sum() > 100 and np.all(res.aovs["reflect_obj"][none] == -1)
    # shadows: the face point's ray to the light meets an object, or clearly misses them all
    met, missed = objects(hit, np.broadcast_to(L, hit.shape))
    for k in range(3):
        dark = on_face & met[k]
        assert dark.sum() > 8, (k, dark.sum())
        assert np.all(res.aovs["visibility"][dark, 0] == 0), k
    lit = on_face & missed.all(0)
    assert lit.sum() > 100 and np.all(res.aovs["visibility"][lit, 0] == 1)


def test_packets_and_per_ray_walks_give_the_brute_force_hits(files):
    """Every traversal (packets, walks, bins, and bins that hand long lists to walks) against ``intersect_one`` (every triangle for every ray) on incoherent
    rays: the same hits and misses, t within float rounding (the programs round the same test
    apart by an ulp), the same triangle but for ties."""
    _, paths = files
    rng = np.random.default_rng(5)
    O = rng.normal(size=(N, 3)) * 2.0
    D = rng.uniform(-1.5, 1.5, (N, 3)) - O  # towards random points about the sphere, from anywhere (inside too)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    kinds = ({"traversal": "packets"}, {"traversal": "walks"}, {"traversal": "bins"},
             {"traversal": "bins", "bin_walk_ratio": 0.1})  # lists past 0.1 triangles per ray: these rays walk
    hits = [_cast(mesh.build(_cfg(paths["ply"], **kind)), O, D) for kind in kinds]
    b = mesh.build(_cfg(paths["ply"]))
    one = jax.jit(jax.vmap(lambda o, d, a, c: mesh.intersect_one(b.params, b.static, o, d, a, c)))
    ref = one(*make_rays(O - b.anchor, D))
    assert 0.2 < np.mean(np.isfinite(ref.t)) < 0.9
    for h in hits:
        np.testing.assert_array_equal(np.isfinite(h.t), np.isfinite(np.asarray(ref.t)))
        hit = np.isfinite(h.t)
        np.testing.assert_allclose(h.t[hit], np.asarray(ref.t)[hit], rtol=1e-6, atol=0)
        assert np.mean(h.prim == np.asarray(ref.prim)) > 0.999


def test_axis_aligned_rays_at_a_cube_hit_every_face_exactly_through_every_traversal(tmp_path):
    """A cube (flat, axis-aligned faces: boxes of zero thickness but for their padding) cast by
    rays whose directions are exactly along an axis (two components exactly 0: the packets'
    direction intervals are single points, the slab tests' inverses infinite), aimed at a grid over
    each face that includes the faces' diagonals (the edge shared by a face's two triangles):
    every ray hits, at t = the distance to the face's plane (float64 closed form), finite, with
    the face's outward normal, for bins, packets and walks alike."""
    path = tmp_path / "cube.ply"
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(path)
    g = np.linspace(-0.95, 0.95, 16)  # includes points on both diagonals of every face
    u, v = (a.reshape(-1) for a in np.meshgrid(g, g))
    O, D, T, Nrm = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            o = np.zeros((u.size, 3))
            o[:, (axis + 1) % 3], o[:, (axis + 2) % 3] = u, v
            o[:, axis] = -sign * 4.0  # 4 from the centre, looking along sign * axis
            d = np.zeros((u.size, 3))
            d[:, axis] = sign
            n = np.zeros(3)
            n[axis] = -sign
            O.append(o), D.append(d), T.append(np.full(u.size, 3.0)), Nrm.append(np.broadcast_to(n, (u.size, 3)))
    O, D, T, Nrm = (np.concatenate(x) for x in (O, D, T, Nrm))
    for kind in ("bins", "packets", "walks"):
        h = _cast(mesh.build(_cfg(str(path), traversal=kind)), O, D)
        assert np.all(np.isfinite(h.t)), (kind, int(np.sum(~np.isfinite(h.t))))
        np.testing.assert_allclose(h.t, T, rtol=1e-6, err_msg=kind)
        np.testing.assert_allclose(h.normal, Nrm, atol=1e-6, err_msg=kind)
