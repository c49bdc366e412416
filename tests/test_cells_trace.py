"""Ray tracing cell objects (Nürnberg 2011, Sec. 3.2) against a fine-step float64 NumPy march
written here; tile skipping; the laws of reflection and refraction; modes; bad input."""

from __future__ import annotations

import stat

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import reference as ref
from jskel import cells, cli, executor
from jskel.render import render
from jskel.cells._membership import INSIDE, unpack
from jskel.cells._search import first_hit
from jskel.optics import reflect, refract
from jskel.rays import FLAG_FLOAT_SPACING, FLAG_GRAZE, make_rays
from jskel.executor import map_chunks

N_RAYS = 1000


def cell_cfg(tmp, **kw):
    base = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
            "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 6,
            "search": "linear", "steps_per_tile": 256, "bisection": 10, "cache": str(tmp / "cache")}
    base.update(kw)
    return cells.CellsConfig.model_validate(base)


@pytest.fixture(scope="module")
def obj(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cells")
    built = cells.build(cell_cfg(tmp))
    rng = np.random.default_rng(2)
    lo, hi = built.bounds
    O, D = ref.random_rays(rng, lo, hi, N_RAYS, spread=0.8)
    return tmp, built, O, D


_FN = {}


def trace(built, O, D):
    key = built.static
    if key not in _FN:
        def f(p, r, st=key):
            def one(o, d, a, b):
                m = first_hit(p, o, d, a, b, st.options)
                return cells.intersect_one(p, st, o, d, a, b), m.steps
            return jax.vmap(one)(*r)
        _FN[key] = f
    out = map_chunks(_FN[key], built.params, make_rays(O - built.anchor, D), chunk=N_RAYS, progress=False).out
    return out


def reference_first_cell(built, O, D, sub=4096, want=None):
    """Float64 NumPy march at 1/sub of a tile from the box entry (or the origin, inside the
    box): the first sample in an INSIDE split cell (``want`` True, the default) or, per ray
    where ``want`` is False, the first sample inside the box that is not in one; returns (t,
    whole-cell id of that sample) with the documented key (tile - offset, cell)."""
    want = np.ones(len(O), bool) if want is None else np.asarray(want, bool)
    p = built.params
    n = int(p.tiles)
    r = int(p.res)
    split = np.asarray(p.split)
    codes = unpack(np.asarray(p.words), split.max())
    off = np.asarray(p.owner_off)
    cell_of = np.asarray(p.split_cell)
    lo = np.asarray(built.bounds[0], np.float64)
    size = float((built.bounds[1][0] - built.bounds[0][0]) / n)
    hi = lo + n * size
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - O) / D, (hi - O) / D
    t0 = np.max(np.minimum(ta, tb), 1).clip(0)
    t1 = np.min(np.maximum(ta, tb), 1)
    h = size / sub
    t_hit = np.full(len(O), np.inf)
    cid = np.full(len(O), -1, np.int64)
    todo = np.nonzero(t0 < t1)[0]
    k0 = 0
    block = 2048
    while todo.size:
        ks = k0 + np.arange(block)
        t = t0[todo, None] + ks[None, :] * h
        x = O[todo, None, :] + t[..., None] * D[todo, None, :]
        u = (x - lo) / size
        tile = np.floor(u).astype(np.int64)
        ok = np.all((tile >= 0) & (tile < n), -1) & (t <= t1[todo, None])
        tile = np.clip(tile, 0, n - 1)
        vox = np.clip(np.floor((u - np.floor(u)) * r).astype(np.int64), 0, r - 1)
        s = split[vox[..., 0], vox[..., 1], vox[..., 2]]
        code = codes[tile[..., 0], tile[..., 1], tile[..., 2], np.maximum(s - 1, 0)]
        inside = ok & (s > 0) & (code == INSIDE)
        target = ok & (inside == want[todo, None])
        first = np.argmax(target, 1)
        found = target[np.arange(len(todo)), first]
        rows = todo[found]
        t_hit[rows] = t[found, first[found]]
        tt = tile[found, first[found]]
        ss = s[found, first[found]]
        owner = tt - off[ss] + 2
        m = n + 4
        cid[rows] = ((owner[:, 0] * m + owner[:, 1]) * m + owner[:, 2]) * (int(p.slots) // 8 + 1) + cell_of[ss]
        alive = ~found & (t0[todo] + (k0 + block) * h <= t1[todo])
        todo = todo[alive]
        k0 += block
    return t_hit, cid


def test_first_hit_cell_agrees_with_a_fine_float64_march(obj):
    tmp, built, O, D = obj
    hit, steps = trace(built, O, D)
    t_ref, id_ref = reference_first_cell(built, O, D)
    assert np.isfinite(t_ref).mean() > 0.3  # the rays do hit the torus's cells
    got = np.where(np.isfinite(hit.t), np.asarray(hit.prim), -1)
    agree = np.mean(got == id_ref)
    assert agree >= 0.995, agree
    both = np.isfinite(hit.t) & np.isfinite(t_ref) & (got == id_ref)
    size = float((built.bounds[1][0] - built.bounds[0][0]) / 6)
    err = np.abs(hit.t[both] - t_ref[both])
    # within one coarse step but where the coarse march stepped over a sliver of the same cell
    assert np.quantile(err, 0.99) < size / 256 + 1e-4, np.quantile(err, 0.99)
    assert np.median(err) < size / 256 / 2**8 + 1e-4  # bisection: step / 2^10, plus float32 at t ~ 8


def test_tile_skipping_changes_no_pixel_and_saves_steps(obj):
    tmp, built, O, D = obj
    plain = cells.build(cell_cfg(tmp, skip=False))
    a, steps_a = trace(built, O, D)
    b, steps_b = trace(plain, O, D)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.prim, b.prim)
    np.testing.assert_array_equal(a.normal, b.normal)
    assert np.sum(steps_a) < 0.8 * np.sum(steps_b), (np.sum(steps_a), np.sum(steps_b))


def test_cache_returns_the_same_object_without_recomputing(obj):
    tmp, built, O, D = obj
    again = cells.build(cell_cfg(tmp))
    assert built.info["cache"] == "miss" and again.info["cache"] == "hit"
    for x, y in zip(jax.tree_util.tree_leaves(built.params), jax.tree_util.tree_leaves(again.params)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_reflection_and_snell_laws_hold_with_no_nan():
    rng = np.random.default_rng(4)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where((np.sum(d * n, 1) > 0)[:, None], -n, n)  # facing against d
    d[:5] = np.cross(n[:5], [0.3, 0.5, 0.81])  # grazing: d . n = 0
    d[:5] /= np.linalg.norm(d[:5], axis=1, keepdims=True)
    r = np.asarray(jax.vmap(reflect)(jnp.float32(d), jnp.float32(n)), np.float64)
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(np.sum(r * n, 1), -np.sum(d * n, 1), atol=1e-5)  # equal angles
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.einsum("ij,ij->i", np.cross(d, n), r), 0.0, atol=1e-5)  # coplanar
    for eta in (1 / 1.5, 1.5):
        t, tir = jax.vmap(lambda a, b: refract(a, b, eta))(jnp.float32(d), jnp.float32(n))
        t, tir = np.asarray(t, np.float64), np.asarray(tir)
        assert np.all(np.isfinite(t))
        cos_i = -np.sum(d * n, 1)
        sin_i = np.sqrt(np.maximum(0, 1 - cos_i**2))
        want_tir = eta * sin_i > 1
        ok = ~want_tir & (np.abs(eta * sin_i - 1) > 1e-4)
        np.testing.assert_array_equal(tir[ok], want_tir[ok])
        sin_t = np.linalg.norm(np.cross(t, n), axis=1)
        np.testing.assert_allclose(sin_t[ok], eta * sin_i[ok], atol=1e-5)  # Snell: sin t = eta sin i
        np.testing.assert_allclose(np.einsum("ij,ij->i", np.cross(d, n), t)[ok], 0.0, atol=1e-5)
        assert np.all(np.sum(t[ok] * n[ok], 1) < 1e-6)  # goes through the surface
        if want_tir.any():  # total internal reflection returns the mirror direction
            np.testing.assert_allclose(t[want_tir & (eta * sin_i > 1 + 1e-4)], r[want_tir & (eta * sin_i > 1 + 1e-4)], atol=1e-5)
    assert (1.5 * np.sqrt(np.maximum(0, 1 - np.sum(d * n, 1) ** 2)) > 1).any()  # TIR was exercised


@pytest.mark.parametrize(
    "obj_yaml, needle",
    [
        ("tiles: 0", ["object.tiles", "0"]),
        ("steps_per_tile: 0", ["object.steps_per_tile", "0"]),
        ("ior: 0", ["object.ior", "0"]),
        ("ior: -1.5", ["object.ior", "-1.5"]),
        ("tile_map: {type: file, path: TMP/flat.npy}", ["object.tile_map.path", "3D"]),
        ("tile_map: {type: file, path: TMP/float.npy}", ["object.tile_map.path", "integers"]),
        ("base: {type: voxel_mesh, path: TMP/open.stl}", ["object.base.path", "not watertight"]),
    ],
    ids=["tiles", "step", "ior0", "ior_neg", "not_3d", "not_int", "open_mesh"],
)
def test_bad_input_one_line_exit_2(tmp_path, capsys, monkeypatch, obj_yaml, needle):
    import trimesh

    np.save(tmp_path / "flat.npy", np.ones((8, 8), np.int32))
    np.save(tmp_path / "float.npy", np.ones((8, 8, 8), np.float32))
    box = trimesh.creation.box()
    trimesh.Trimesh(box.vertices, box.faces[:-1]).export(tmp_path / "open.stl")

    def boom(*a, **k):
        raise AssertionError("compiled despite bad input")

    monkeypatch.setattr(executor, "compile_batch_fn", boom)
    body = f"object: {{type: cells, cache: null, {obj_yaml.replace('TMP', str(tmp_path))}}}\ncamera: {{width: 8, height: 8}}\n"
    p = tmp_path / "exp.yaml"
    p.write_text(body)
    rc = cli.main(["render", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    for n in needle:
        assert n in err[0], (n, err[0])


def test_cli_render_writes_the_cell_aov_from_the_cache(obj, tmp_path):
    import json

    tmp, built, O, D = obj
    body = f"""object: {{type: cells, base: {{type: torus, major: 1.0, minor: 0.45}}, tiles: 6, search: linear, steps_per_tile: 256, bisection: 10,
  tile_map: {{type: voronoi, resolution: 16, cells: 8, seed: 0}}, cache: {tmp / 'cache'}}}
camera: {{eye: [0, 2, 2.5], target: [0, 0, 0], width: 32, height: 24}}
render: {{progress: false}}
"""
    p = tmp_path / "exp.yaml"
    p.write_text(body)
    assert cli.main(["render", str(p), "--out", str(tmp_path / "o")]) == 0
    cell = np.load(tmp_path / "o" / "cell.npy")
    prim = np.load(tmp_path / "o" / "prim.npy")
    depth = np.load(tmp_path / "o" / "depth.npy")
    np.testing.assert_array_equal(cell, prim)
    assert cell.shape == (24, 32) and np.all((cell >= 0) == np.isfinite(depth)) and np.isfinite(depth).mean() > 0.2
    run = json.loads((tmp_path / "o" / "run.json").read_text())
    assert run["info"]["cache"] == "hit" and run["info"]["precompute_s"] > 0


def sky(d):
    """The procedural ``sky`` environment of a cell object, float64: horizon (0.85, 0.9, 1) to
    zenith (0.25, 0.45, 0.85) upwards, (0.3, 0.27, 0.24) to (0.12, 0.1, 0.08) towards the nadir."""
    up = np.clip(d[:, 1] / np.linalg.norm(d, axis=1), -1, 1)[:, None]
    return np.where(up >= 0, (1 - up) * [0.85, 0.9, 1.0] + up * [0.25, 0.45, 0.85], (1 + up) * [0.3, 0.27, 0.24] - up * [0.12, 0.1, 0.08])


def test_a_single_cell_object_renders_through_the_integrator_with_its_own_sky(obj):
    """A first-hit cell object is a scene of one: escaping rays see the object's environment
    (not the experiment's background), and jittered samples blend its silhouette."""
    from jskel.config import validate
    from jskel.render import camera_of, render

    tmp, built, O, D = obj
    raw = {"object": cell_cfg(tmp).model_dump(mode="json"), "camera": {"eye": [0, 2, 2.5], "target": [0, 0, 0], "width": 32, "height": 24},
           "render": {"progress": False}}
    exp = validate(raw)
    res = render(exp)
    miss = ~np.isfinite(res.hits.t)
    assert 0.2 < miss.mean() < 0.8
    _, d = camera_of(exp).ray_arrays()
    np.testing.assert_allclose(res.rgb[miss], sky(d[miss]), atol=2e-6)
    assert "effects" not in res.run  # first hit: no secondary-ray level was compiled
    raw["render"]["spp"] = 4
    four = render(validate(raw))
    np.testing.assert_array_equal(four.hits.prim, res.hits.prim)  # AOVs from the pixel centres
    assert four.run["rays"] == 4 * res.run["rays"] and np.any(four.rgb != res.rgb)


def _cell_lookup(built, x):
    """Float64 NumPy of Alg. 4.8's normal and the colour map at world points x (M,3), by the
    voxel / texel holding each point (the tile map wraps): (normal or 0, colour)."""
    p = built.params
    n = int(p.tiles)
    lo = np.asarray(built.bounds[0], np.float64)
    size = float((built.bounds[1][0] - built.bounds[0][0]) / n)
    u = (x - lo) / size
    local = u - np.floor(u)
    normals, colors = np.asarray(p.normals, np.float64), np.asarray(p.colors, np.float64)
    r, c = int(p.res), int(p.cres)
    v = np.clip(np.floor(local * r), 0, r - 1).astype(np.int64)
    i = np.clip(np.floor(local * c), 0, c - 1).astype(np.int64)
    return normals[v[:, 0], v[:, 1], v[:, 2]], colors[i[:, 0], i[:, 1], i[:, 2]]


def _local_f64(exp, base, n, d):
    """Ambient + Lambert + Blinn-Phong of directional lights (float64), the normal turned to face
    the viewer; the experiment's shading section."""
    sh = exp.shading
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = np.where(np.sum(n * d, 1, keepdims=True) > 0, -n, n)
    col = sh.ambient * base
    for light in exp.lights:
        l = np.asarray(light.direction, np.float64) / np.linalg.norm(light.direction)
        rad = light.intensity * np.asarray(light.color, np.float64)
        h = l - d
        h = h / np.linalg.norm(h, axis=1, keepdims=True)
        ndl = np.maximum(n @ l, 0.0)
        spec = np.where(ndl > 0, np.maximum(np.sum(h * n, 1), 0.0) ** sh.shininess, 0.0)
        col = col + rad * (base * ndl[:, None] + sh.specular * spec[:, None])
    return col


def test_reflection_mode_is_the_integrators_mirror_material_against_a_float64_bounce(obj):
    """Reflection mode (Sec. 3.2.3, Alg. 3.2) with one bounce, rendered by the shared
    integrator, against float64 NumPy written here: the fine march finds the first hit, Alg.
    4.8's normal and the colour map shade it, the mirror ray starts one voxel out along the
    normal and is marched again; c = (1 - k) local + k (local of the bounce's hit, whole, or the
    sky where it escapes). Pixels may differ where the two marches straddle a voxel boundary."""
    from jskel.config import validate
    from jskel.render import camera_of, render

    tmp, built, _, _ = obj
    k = 0.6
    raw = {"object": cell_cfg(tmp, mode="reflection", bounces=1, reflectivity=k).model_dump(mode="json"),
           "camera": {"eye": [0, 2, 2.5], "target": [0, 0, 0], "width": 32, "height": 24},
           "lights": [{"direction": [0.4, 0.9, 0.5], "color": [1.0, 0.95, 0.9], "intensity": 1.0}], "render": {"progress": False}}
    exp = validate(raw)
    res = render(exp)
    assert res.run["effects"]["reflection"] and res.run["effects"]["bounces"] == 1
    O, D = camera_of(exp).ray_arrays()
    t0, _ = reference_first_cell(built, O, D)
    hit = np.isfinite(t0)
    x = O[hit] + t0[hit, None] * D[hit]
    nrm, base = _cell_lookup(built, x)
    d = D[hit] / np.linalg.norm(D[hit], axis=1, keepdims=True)
    nrm = np.where(np.sum(nrm * nrm, 1, keepdims=True) > 0, nrm, -d)
    nf = np.where(np.sum(nrm * d, 1, keepdims=True) > 0, -nrm, nrm)
    r = d - 2 * np.sum(d * nf, 1, keepdims=True) * nf
    voxel = float(built.bounds[1][0] - built.bounds[0][0]) / int(built.params.tiles) / int(built.params.res)
    t1, _ = reference_first_cell(built, x + voxel * nf, r)
    hit1 = np.isfinite(t1)
    n1, b1 = _cell_lookup(built, x + voxel * nf + np.where(hit1, t1, 0)[:, None] * r)
    n1 = np.where(np.sum(n1 * n1, 1, keepdims=True) > 0, n1, -r)
    second = np.where(hit1[:, None], _local_f64(exp, b1, n1, r), sky(r))
    want = sky(D)
    want[hit] = (1 - k) * _local_f64(exp, base, nrm, d) + k * second
    assert 0.2 < hit.mean() < 0.8 and 0.05 < hit1.mean() < 0.95  # both kinds of bounce are checked
    same = np.isfinite(res.hits.t) == hit  # the fine march may catch a sliver the 1/256 step skips
    assert same.mean() > 0.99
    err = np.abs(res.rgb - want).max(axis=1)[same]
    assert np.all(np.isfinite(res.rgb)) and np.mean(err) < 5e-3 and np.mean(err > 2e-2) < 0.03, (np.mean(err), np.mean(err > 2e-2))
    np.testing.assert_allclose(res.rgb[~hit & same], want[~hit & same], atol=2e-6)  # escaping camera rays see the object's sky


def _in_cell(built, x):
    """Float64: is each point x (M,3) in an INSIDE split cell of the object?"""
    p = built.params
    n, r = int(p.tiles), int(p.res)
    split = np.asarray(p.split)
    codes = unpack(np.asarray(p.words), split.max())
    lo = np.asarray(built.bounds[0], np.float64)
    size = float((built.bounds[1][0] - built.bounds[0][0]) / n)
    u = (x - lo) / size
    tile = np.floor(u).astype(np.int64)
    ok = np.all((tile >= 0) & (tile < n), -1)
    tile = np.clip(tile, 0, n - 1)
    vox = np.clip(np.floor((u - np.floor(u)) * r).astype(np.int64), 0, r - 1)
    s = split[vox[:, 0], vox[:, 1], vox[:, 2]]
    return ok & (s > 0) & (codes[tile[:, 0], tile[:, 1], tile[:, 2], np.maximum(s - 1, 0)] == INSIDE)


def _snell(d, n_out, ior):
    """Float64 Snell's law at a surface of outward unit normal n_out for unit d: (direction,
    entering, total internal reflection); under total internal reflection the mirror direction."""
    entering = np.sum(d * n_out, 1) < 0
    nf = np.where(entering[:, None], n_out, -n_out)
    eta = np.where(entering, 1.0 / ior, ior)
    cos_i = -np.sum(d * nf, 1)
    k = 1 - eta**2 * (1 - cos_i**2)
    tir = k < 0
    t = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * nf
    m = d - 2 * np.sum(d * nf, 1, keepdims=True) * nf
    out = np.where(tir[:, None], m, t)
    return out / np.linalg.norm(out, axis=1, keepdims=True), entering, tir


def test_refraction_mode_is_the_integrators_glass_material_against_a_float64_alg_3_3(obj):
    """Refraction mode (Sec. 3.2.4, Alg. 3.3) with two boundary events after the first hit,
    rendered by the shared integrator, against float64 NumPy written here: the fine march finds
    the first hit; the ray refracts in (eta = 1/ior) with the weight 0.85 x (0.5 + 0.5 x the
    cell colour); each next ray starts one linear step through the surface, where the sample
    there decides whether it searches for the exit of an inside cell or the entry of the next
    (Alg. 3.3 row 3), refracts at the boundary it finds (Alg. 4.8's normal turned outward;
    total internal reflection keeps it inside), entering cells tint it again; after the last
    event, or where it escapes, it sees the sky: c = 0.15 local + 0.85 tint x sky. The fine and
    the 1/256 march may straddle a voxel where a path grazes a cell, so a few pixels differ."""
    from jskel.config import validate
    from jskel.render import camera_of, render

    tmp, built, _, _ = obj
    ior, bounces = 1.5, 2
    raw = {"object": cell_cfg(tmp, mode="refraction", bounces=bounces, ior=ior).model_dump(mode="json"),
           "camera": {"eye": [0, 2, 2.5], "target": [0, 0, 0], "width": 32, "height": 24},
           "lights": [{"direction": [0.4, 0.9, 0.5], "color": [1.0, 0.95, 0.9], "intensity": 1.0}], "render": {"progress": False}}
    exp = validate(raw)
    res = render(exp)
    assert res.run["effects"]["refraction"] and res.run["effects"]["bounces"] == bounces
    O, D = camera_of(exp).ray_arrays()
    size = float((built.bounds[1][0] - built.bounds[0][0]) / int(built.params.tiles))
    step = size / 256  # the object's linear step (steps_per_tile 256)

    def outward(x_cell, d, leaving):
        nrm, col = _cell_lookup(built, x_cell)
        nrm = np.where(np.sum(nrm * nrm, 1, keepdims=True) > 0, nrm, -d)
        wrong = (np.sum(nrm * d, 1) > 0) != leaving
        return np.where(wrong[:, None], -nrm, nrm), col

    t0, _ = reference_first_cell(built, O, D)
    hit = np.isfinite(t0)
    d = D[hit] / np.linalg.norm(D[hit], axis=1, keepdims=True)
    x = O[hit] + t0[hit, None] * D[hit]
    n0, base = outward(x, d, np.zeros(len(d), bool))
    local = _local_f64(exp, base, n0, d)
    d, _, _ = _snell(d, n0, ior)
    tint = 0.5 + 0.5 * base
    org = x - step * n0
    alive = np.ones(len(d), bool)
    events = np.zeros(2, int)  # (exits, entries) seen, to show both branches are checked
    for _ in range(bounces):
        want = ~_in_cell(built, org)
        t, _ = reference_first_cell(built, org, d, want=want)
        got = alive & np.isfinite(t)
        xt = org + np.where(got, t, 0)[:, None] * d
        x_cell = np.where(want[:, None], xt, xt - (size / 4096) * d)  # the sample in the cell
        nrm, col = outward(x_cell, d, ~want)
        nd, entering, tir = _snell(d, nrm, ior)
        events += [np.sum(got & ~want), np.sum(got & want)]
        tint = np.where((got & entering & ~tir)[:, None], tint * (0.5 + 0.5 * col), tint)
        side = np.where(tir[:, None], nrm * np.where(entering, 1, -1)[:, None], -nrm * np.where(entering, 1, -1)[:, None])
        org = np.where(got[:, None], xt + step * side, org)
        d = np.where(got[:, None], nd, d)
        alive = got
    want_rgb = sky(D)
    want_rgb[hit] = 0.15 * local + 0.85 * tint * sky(d)
    assert 0.2 < hit.mean() < 0.8 and events.min() > 20, events  # exits and re-entries both checked
    same = np.isfinite(res.hits.t) == hit
    assert same.mean() > 0.99
    err = np.abs(res.rgb - want_rgb).max(axis=1)[same]
    assert np.all(np.isfinite(res.rgb)) and np.mean(err) < 5e-3 and np.mean(err > 5e-2) < 0.03, (np.mean(err), np.mean(err > 5e-2))
    np.testing.assert_allclose(res.rgb[~hit & same], want_rgb[~hit & same], atol=2e-6)  # escaping camera rays see the sky


def test_the_default_cache_lives_in_jskels_cache_directory_and_follows_its_switch(tmp_path, monkeypatch, capsys):
    """``cache: auto`` (the default) keeps precomputed objects in the ``cells`` folder of
    ``JSKEL_CACHE_DIR``, not under the working directory, made private (0700); a folder others
    may write is refused with one warning line, as the compiled programs' is; ``JSKEL_CACHE=off``
    keeps none."""
    precompute = cells.precompute
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JSKEL_CACHE_DIR", str(tmp_path / "jc"))
    cfg = cells.CellsConfig.model_validate({"type": "cells", "base": {"type": "sphere", "radius": 1.0}, "tiles": 2,
                                            "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}})
    assert cfg.cache == "auto"
    assert precompute(cfg).info["cache"] == "miss" and precompute(cfg).info["cache"] == "hit"
    assert len(list((tmp_path / "jc" / "cells").glob("*.npz"))) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jc"]  # nothing written where the process runs
    assert stat.S_IMODE((tmp_path / "jc" / "cells").stat().st_mode) == 0o700
    (tmp_path / "jc" / "cells").chmod(0o777)
    capsys.readouterr()
    assert precompute(cfg).info["cache"] == "off"
    err = capsys.readouterr().err
    assert "writable by group or others" in err and str(tmp_path / "jc" / "cells") in err
    monkeypatch.setenv("JSKEL_CACHE", "off")
    assert precompute(cfg).info["cache"] == "off"


def test_another_sample_cap_or_bisection_count_casts_without_a_program(obj):
    """The sample cap and the bisection count are values (``CellParams``): the fixture's object
    with 2 halvings, 12 halvings and a cap of 8 samples casts through the program its first cast
    compiled (nothing handed to XLA), and each runs its own count. A hit's t is the inside end of
    the last bracket, so the same linear steps give the same hits, and 12 halvings land at or
    before 2 halvings' t, within that bracket (h / 4, h the linear step), and nearer on most
    rays; a cap of 8 samples stops rays that need more (STEP_CAP), which the default cap does not."""
    from jskel.compile.cache import count_programs, program_counts
    from jskel.rays import FLAG_STEP_CAP

    tmp, built, O, D = obj
    variants = [cells.build(cell_cfg(tmp, **kw)) for kw in ({"bisection": 2}, {"bisection": 12}, {"max_steps": 8})]
    base, _ = trace(built, O, D)
    count_programs()
    before = program_counts()
    (h2, _), (h12, _), (hc, _) = (trace(b, O, D) for b in variants)
    after = program_counts()
    assert after["compiled"] + after["loaded"] == before["compiled"] + before["loaded"]
    np.testing.assert_array_equal(np.isfinite(h2.t), np.isfinite(h12.t))
    both = np.isfinite(h2.t)
    assert both.mean() > 0.2
    h = float(built.params.step) * float(built.params.size)  # |D| = 1
    gap = h2.t[both].astype(np.float64) - h12.t[both]
    assert np.all(gap >= -1e-6 * h) and np.all(gap <= h / 4 * (1 + 1e-3)) and np.mean(gap > 1e-3 * h) > 0.5
    capped = (np.asarray(hc.flags) & FLAG_STEP_CAP) != 0
    assert capped.sum() > 20 and not np.any((np.asarray(base.flags) & FLAG_STEP_CAP) != 0)
    assert np.all(~np.isfinite(hc.t[capped]))


def cast_without_a_program(built, other, O, D):
    """``other``'s cast after ``built``'s hands XLA no program, and its first cells and t agree
    with the float64 march written here (t to the linear step, a 256th of a tile); its Hit."""
    from jskel.compile.cache import count_programs, program_counts

    trace(built, O, D)
    count_programs()
    before = program_counts()
    hit, _ = trace(other, O, D)
    after = program_counts()
    assert after["compiled"] + after["loaded"] == before["compiled"] + before["loaded"]
    t_ref, id_ref = reference_first_cell(other, O, D)
    assert np.isfinite(t_ref).mean() > 0.3
    got = np.where(np.isfinite(hit.t), np.asarray(hit.prim), -1)
    assert np.mean(got == id_ref) >= 0.995
    both = np.isfinite(hit.t) & np.isfinite(t_ref) & (got == id_ref)
    size = float((other.bounds[1][0] - other.bounds[0][0]) / int(other.params.tiles))
    assert np.quantile(np.abs(hit.t[both] - t_ref[both]), 0.99) < size / 256 + 1e-4
    return hit


def test_another_cell_count_filling_the_same_words_casts_without_a_program(obj):
    """7 cells a tile (56 split cells) instead of the fixture's 8 (64): both fit 4 membership
    words (16 slots each), so the split-index tables have the same 65 rows and the count is a
    value (``CellParams.slots``); the cast compiles nothing, and its first cells and t agree with
    the float64 march written here, as the fixture's do (the whole-cell key counts 7 cells)."""
    tmp, built, O, D = obj
    seven = cells.build(cell_cfg(tmp, tile_map={"type": "voronoi", "resolution": 16, "cells": 7, "seed": 0}))
    assert int(seven.params.slots) == 56 and int(built.params.slots) == 64
    assert seven.params.split_cell.shape == built.params.split_cell.shape == (65,)
    cast_without_a_program(built, seven, O, D)
    cell_of = np.asarray(seven.params.split_cell)
    assert np.all(cell_of[57:] == 0) and cell_of[1:57].max() == 7  # cells 1..7 (0: an empty part), then inert rows


def test_another_tile_count_in_the_same_bucket_casts_without_a_program(obj):
    """5 tiles along each axis instead of the fixture's 6: the tile tables are padded to the
    count's size bucket (8) and the count is a value (``CellParams.tiles``), so the cast
    compiles nothing; its first cells and t agree with the float64 march written here, whose
    box is 5 tiles wide (a ray that crosses the padding tiles' region finds nothing there)."""
    tmp, built, O, D = obj
    five = cells.build(cell_cfg(tmp, tiles=5))
    assert int(five.params.tiles) == 5 and int(built.params.tiles) == 6
    assert five.params.words.shape == built.params.words.shape and five.params.words.shape[0] == 8
    hit = cast_without_a_program(built, five, O, D)
    size = float((five.bounds[1][0] - five.bounds[0][0]) / 5)
    lo, hi = (np.asarray(b, np.float64) for b in five.bounds)
    x = O + np.where(np.isfinite(hit.t), hit.t, 0)[:, None] * D
    assert np.all(np.all((x >= lo - size / 256) & (x <= hi + size / 256), 1)[np.isfinite(hit.t)])  # no hit in the padding


def test_another_tile_map_resolution_in_the_same_bucket_casts_without_a_program(obj):
    """Tile maps of 24 and 32 voxels a side: the map (split indices, normals) and the Worley
    colour map drawn at its resolution are padded to the size bucket (32), and the resolutions
    are values (``CellParams.res``, ``cres``), so the
    second cast compiles nothing; its first cells and t agree with the float64 march written
    here, which reads the map at 24 voxels a side."""
    tmp, _, O, D = obj
    maps = [cells.build(cell_cfg(tmp, tile_map={"type": "voronoi", "resolution": r, "cells": 8, "seed": 0})) for r in (32, 24)]
    assert [int(m.params.res) for m in maps] == [32, 24]
    assert maps[0].params.split.shape == maps[1].params.split.shape == (32, 32, 32)
    assert maps[0].params.normals.shape == maps[1].params.normals.shape
    assert maps[0].params.colors.shape == maps[1].params.colors.shape and int(maps[1].params.cres) == 24
    split = np.asarray(maps[1].params.split)
    assert np.all(split[24:] == 0) and split[:24, :24, :24].min() > 0  # padding past r, never read
    cast_without_a_program(*maps, O, D)


def test_the_voxel_walk_finds_the_float64_marchs_first_cell_with_nothing_stepped_over(obj):
    """``search: voxels`` visits every tile-map voxel the ray crosses, in order: its first cells
    equal the float64 march's at 1/4096 of a tile (written here) on every ray, its t lies within
    that march's resolution of the reference and at most 2^-12 voxel past the crossed face (no
    bracket), no ray is flagged as having stepped over a part, skipping tiles changes no hit,
    and it looks up far fewer voxels than the linear search takes samples."""
    tmp, built, O, D = obj
    walk = cells.build(cell_cfg(tmp, search="voxels"))
    flat = cells.build(cell_cfg(tmp, search="voxels", skip=False))
    hit, steps = trace(walk, O, D)
    hit_flat, steps_flat = trace(flat, O, D)
    _, steps_linear = trace(built, O, D)
    t_ref, id_ref = reference_first_cell(walk, O, D)
    got = np.where(np.isfinite(hit.t), np.asarray(hit.prim), -1)
    assert np.isfinite(t_ref).mean() > 0.3 and np.all(got == id_ref)
    ok = np.isfinite(hit.t)
    size = float((walk.bounds[1][0] - walk.bounds[0][0]) / 6)
    voxel = size / int(walk.params.res)
    dn = np.linalg.norm(D[ok], axis=1)
    assert np.all(np.abs(hit.t[ok] - t_ref[ok]) * dn <= size / 4096 + 1e-5)
    x = (O - walk.anchor)[ok] + np.asarray(hit.t, np.float64)[ok, None] * D[ok]
    v = (x - np.asarray(walk.params.lo, np.float64)) / voxel
    assert np.all(np.min(np.abs(v - np.round(v)), 1) <= 2.0**-12 + 1e-4)  # on a face (float32 positions)
    assert not np.any(np.asarray(hit.flags) & FLAG_GRAZE)
    np.testing.assert_array_equal(np.asarray(hit.t), np.asarray(hit_flat.t))
    np.testing.assert_array_equal(np.asarray(hit.prim), np.asarray(hit_flat.prim))
    assert np.mean(steps) * 4 < np.mean(steps_linear) and np.mean(steps) < np.mean(steps_flat)
    # leaving (the refraction mode's two-sided search, Alg. 3.3): from half a voxel into the cells
    # found, the first voxel outside them, against the float64 march looking for one
    org = (O + (np.asarray(hit.t, np.float64)[:, None] + 0.5 * voxel / np.linalg.norm(D, axis=1)[:, None]) * D)[ok]
    start = _in_cell(walk, org)
    org, dd = org[start], D[ok][start]
    exit_t = jax.jit(jax.vmap(lambda o, d: first_hit(walk.params, o, d, 0.0, jnp.inf, walk.static.options, True).t))
    t_out = np.asarray(exit_t(jnp.asarray(org - walk.anchor, jnp.float32), jnp.asarray(dd, jnp.float32)), np.float64)
    t_out_ref, _ = reference_first_cell(walk, org, dd, want=np.zeros(len(org), bool))
    assert start.mean() > 0.9 and np.all(np.isfinite(t_out_ref))
    np.testing.assert_array_equal(np.isfinite(t_out), True)
    assert np.all(np.abs(t_out - t_out_ref) * np.linalg.norm(dd, axis=1) <= size / 4096 + 1e-5)
    # the same rays from 1,000 units back (about 330 object sizes): the same cells, no flag; from
    # 10,000, where float32 positions are spaced above a 32nd of a voxel: every ray flagged
    dn = D / np.linalg.norm(D, axis=1, keepdims=True)
    near, _ = trace(walk, O, dn)
    far3, _ = trace(walk, O - 1e3 * dn, dn)
    np.testing.assert_array_equal(np.asarray(far3.prim), np.asarray(near.prim))
    assert not np.any(np.asarray(far3.flags) & FLAG_FLOAT_SPACING)
    far4, _ = trace(walk, O - 1e4 * dn, dn)
    assert np.all(np.asarray(far4.flags) & FLAG_FLOAT_SPACING)
    # along the axes (direction components exactly 0, whose exits are inf), a fifth of them in
    # the planes of voxel faces: the float64 march's first cells on every ray
    rng = np.random.default_rng(5)
    lo, hi = (np.asarray(b, np.float64) for b in walk.bounds)
    axis, sign = rng.integers(0, 3, len(O)), rng.choice([-1.0, 1.0], len(O))
    da = np.zeros_like(D)
    da[np.arange(len(O)), axis] = sign
    oa = lo + rng.uniform(0, 1, D.shape) * (hi - lo)
    oa[: len(O) // 5] = lo + np.round((oa[: len(O) // 5] - lo) / voxel) * voxel
    oa[np.arange(len(O)), axis] = np.where(sign > 0, lo[axis] - 1.0, hi[axis] + 1.0)
    ha, _ = trace(walk, oa, da)
    ta_ref, ida_ref = reference_first_cell(walk, oa, da)
    assert np.isfinite(ta_ref).mean() > 0.2
    np.testing.assert_array_equal(np.where(np.isfinite(ha.t), np.asarray(ha.prim), -1), ida_ref)


def test_a_hits_normal_is_that_of_the_voxel_it_entered(obj):
    """Alg. 4.8's normal at a hit is the normal map's value at the voxel the ray entered: the
    voxel on the ray's side of the face it crossed, found here in float64 from the float32 t (the
    axis whose voxel coordinate is nearest an integer), up to the orientation the cast chooses,
    or the ray's reverse where that voxel has none. The march's t lies within about an ulp of
    the face, so the hit point in float32 may round back across it, where the normal map holds a
    neighbouring cell's normal."""
    tmp, built, O, D = obj
    hit, _ = trace(built, O, D)
    p = built.params
    r = int(p.res)
    t = np.asarray(hit.t, np.float64)
    ok = np.isfinite(t)
    x = (O - built.anchor)[ok] + t[ok, None] * D[ok]
    v = (x - np.asarray(p.lo, np.float64)) / float(p.size) * r
    frac = np.abs(v - np.round(v))
    axis = np.argmin(frac, 1)
    rows = np.arange(len(v))
    v_in = v.copy()
    v_in[rows, axis] = np.round(v[rows, axis]) + 0.25 * np.sign(D[ok][rows, axis])
    local = np.floor(v_in).astype(np.int64) % r
    nm = np.asarray(p.normals, np.float64)[local[:, 0], local[:, 1], local[:, 2]]
    dn = -D[ok] / np.linalg.norm(D[ok], axis=1, keepdims=True)
    want = np.where(np.sum(nm * nm, 1, keepdims=True) > 0, nm, dn)
    got = np.asarray(hit.normal, np.float64)[ok]
    clear = np.sort(frac, 1)[:, 1] > 1e-3  # not within rounding of a voxel edge, where either voxel is right
    agree = np.abs(np.sum(got * want, 1)) > 0.999
    assert ok.sum() > 300 and clear.mean() > 0.99
    assert agree[clear].all(), (np.sum(~agree[clear]), clear.sum())


def reference_dda(built, O, D, want=None):
    """Float64 Amanatides-Woo walk (written here) through the object's voxels, tiles times the
    tile map's resolution per axis, from the box entry (or the origin, inside the box): the
    entry t of the first voxel in an INSIDE split cell (``want`` True, the default) or, per ray
    where ``want`` is False, of the first voxel that is not, and that voxel's whole-cell id
    (:func:`reference_first_cell`'s key). Each crossing's t is computed from the voxel's integer
    index, not accumulated. Also returns each hit's distance to the nearest voxel edge, in
    voxels (the float32 walk may round a ray through an edge or corner either way), and the
    voxels each ray looked at (the hit's included)."""
    want = np.ones(len(O), bool) if want is None else np.asarray(want, bool)
    p = built.params
    n, r = int(p.tiles), int(p.res)
    split = np.asarray(p.split)
    codes = unpack(np.asarray(p.words), split.max())
    off, cell_of = np.asarray(p.owner_off), np.asarray(p.split_cell)
    lo = np.asarray(built.bounds[0], np.float64)
    size = float((built.bounds[1][0] - built.bounds[0][0]) / n)
    g, vs = n * r, size / r
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - O) / D, (lo + n * size - O) / D
    t0 = np.max(np.minimum(ta, tb), 1).clip(0)
    t1 = np.min(np.maximum(ta, tb), 1)
    step = np.where(D > 0, 1, -1)
    v = np.clip(np.floor((O + t0[:, None] * D - lo) / vs).astype(np.int64), 0, g - 1)
    t_cur = t0.copy()
    t_hit, cid, edge = np.full(len(O), np.inf), np.full(len(O), -1, np.int64), np.full(len(O), np.inf)
    alive = t0 < t1
    visited = np.zeros(len(O), np.int64)
    for _ in range(3 * g + 3):
        idx = np.nonzero(alive)[0]
        if not idx.size:
            break
        visited[idx] += 1
        vv = v[idx]
        tile, loc = vv // r, vv % r
        s = split[loc[:, 0], loc[:, 1], loc[:, 2]]
        inside = (s > 0) & (codes[tile[:, 0], tile[:, 1], tile[:, 2], np.maximum(s - 1, 0)] == INSIDE)
        hit = inside == want[idx]
        rows = idx[hit]
        t_hit[rows] = t_cur[rows]
        owner = tile[hit] - off[s[hit]] + 2
        m = n + 4
        cid[rows] = ((owner[:, 0] * m + owner[:, 1]) * m + owner[:, 2]) * (int(p.slots) // 8 + 1) + cell_of[s[hit]]
        x = (O[rows] + t_cur[rows, None] * D[rows] - lo) / vs
        frac = np.sort(np.abs(x - np.round(x)), 1)
        edge[rows] = frac[:, 1]  # the second-nearest face: near 0 on an edge or a corner
        alive[rows] = False
        go = idx[~hit]
        with np.errstate(divide="ignore", invalid="ignore"):
            nxt = np.where(D[go] != 0, (lo + (v[go] + (step[go] > 0)) * vs - O[go]) / D[go], np.inf)
        axis = np.argmin(nxt, 1)
        t_cur[go] = nxt[np.arange(go.size), axis]
        v[go, axis] += step[go, axis]
        inb = np.all((v[go] >= 0) & (v[go] < g), 1) & (t_cur[go] < t1[go])
        alive[go[~inb]] = False
    return t_hit, cid, edge, visited


def _walk_from(built, O, D, want):
    """The walk's t from origins O inside or outside the box along D, looking for an inside
    voxel (``want``) or for the first one outside (the refraction mode's exit search)."""
    f = jax.jit(jax.vmap(lambda o, d: first_hit(built.params, o, d, 0.0, jnp.inf, built.static.options, not want).t))
    return np.asarray(f(jnp.asarray(O - built.anchor, jnp.float32), jnp.asarray(D, jnp.float32)), np.float64)


@pytest.mark.parametrize("seed,tiles", [(11, 6), (12, 6), (13, 16)])
def test_the_voxel_walk_equals_a_float64_dda_on_random_tile_maps(tmp_path, seed, tiles):
    """The default search (``voxels``, with the occupancy pyramid) on tile maps of random cell
    sites, against :func:`reference_dda` (an exact float64 walk, not a march), for the searches
    of all three modes: every ray's first cell (first hit), and t on that voxel's entry face
    (2^-12 of a voxel past it); from just outside each cell found, along the ray mirrored in
    the face it crossed, the next inside voxel (the reflection mode's secondary search); from
    half a voxel into each cell found, the first voxel outside (the refraction mode's exit
    search, Alg. 3.3). Rays whose reference hit lies within 1e-4 voxel of a voxel edge are left
    out (float32 may round the ray through either neighbour). 16 tiles a side: blocks of up to
    4 tiles are crossed in one step, empty and full ones (the levels asserted present)."""
    from jskel.cells._trace import EMPTY_SHIFT, FULL_SHIFT, LEVEL_MASK

    base = {"type": "torus", "major": 1.0, "minor": 0.45 if tiles == 6 else 0.7}  # a thick tube: full blocks
    built = cells.build(cell_cfg(tmp_path, search="voxels", tiles=tiles, base=base, tile_map={"type": "voronoi", "resolution": 16, "cells": 8, "seed": seed}))
    assert built.static.options.voxels and built.static.options.pyramid
    if tiles == 16:
        fl = np.asarray(built.params.tile_flags)
        assert ((fl >> EMPTY_SHIFT) & LEVEL_MASK).max() >= 2 and ((fl >> FULL_SHIFT) & LEVEL_MASK).max() >= 1
    rng = np.random.default_rng(seed)
    lo, hi = built.bounds
    O, D = ref.random_rays(rng, lo, hi, N_RAYS, spread=0.8)
    hit, _ = trace(built, O, D)
    t_ref, id_ref, edge, _ = reference_dda(built, O, D)
    got = np.where(np.isfinite(hit.t), np.asarray(hit.prim), -1)
    clear = edge > 1e-4
    assert np.isfinite(t_ref).mean() > 0.3 and clear.mean() > 0.99
    np.testing.assert_array_equal(got[clear], id_ref[clear])
    ok = np.isfinite(t_ref) & clear
    voxel = float((built.bounds[1][0] - built.bounds[0][0]) / tiles) / int(built.params.res)
    tol = voxel * 2.0**-12 + 2e-5
    dn = np.linalg.norm(D, axis=1)
    assert np.all(np.abs(hit.t[ok] - t_ref[ok]) * dn[ok] <= tol)
    # the reflection mode's search: from a quarter voxel before the face, mirrored in it
    x_hit = O[ok] + t_ref[ok, None] * D[ok]
    u = (x_hit - np.asarray(lo, np.float64)) / voxel
    axis = np.argmin(np.abs(u - np.round(u)), 1)  # the face crossed: the coordinate on a voxel plane
    org = x_hit - 0.25 * voxel * D[ok] / dn[ok, None]
    mirrored = D[ok].copy()
    mirrored[np.arange(len(axis)), axis] *= -1
    t_m = _walk_from(built, org, mirrored, True)
    t_m_ref, _, edge_m, _ = reference_dda(built, org, mirrored)
    clear_m = edge_m > 1e-4
    assert clear_m.mean() > 0.99 and np.isfinite(t_m_ref).mean() > 0.3
    np.testing.assert_array_equal(np.isfinite(t_m[clear_m]), np.isfinite(t_m_ref[clear_m]))
    both = clear_m & np.isfinite(t_m_ref)
    assert np.all(np.abs(t_m - t_m_ref)[both] * np.linalg.norm(mirrored[both], axis=1) <= tol)
    # the exit search, from half a voxel inside the cells found
    org = (O + (t_ref[:, None] + 0.5 * voxel / dn[:, None]) * D)[ok]
    inside = _in_cell(built, org)
    org, dd = org[inside], D[ok][inside]
    t_out = _walk_from(built, org, dd, False)
    t_out_ref, _, edge_out, _ = reference_dda(built, org, dd, want=np.zeros(len(org), bool))
    clear_out = edge_out > 1e-4
    assert inside.mean() > 0.9 and clear_out.mean() > 0.99 and np.all(np.isfinite(t_out_ref))
    err = np.abs(t_out - t_out_ref)[clear_out] * np.linalg.norm(dd[clear_out], axis=1)
    assert np.all(err <= tol), err.max()


def test_render_steps_writes_each_pixels_voxels_as_the_dda_counts_them(obj, tmp_path, capsys):
    """``render.steps: true`` writes steps.npy (H, W): with tile skipping off, each pixel's count
    is the voxels :func:`reference_dda` visits along that pixel's camera ray; with skipping
    and the pyramid (the defaults), no pixel more. A representation that counts no steps, and
    a scene, are refused with exit code 2, naming the key."""
    from jskel import config
    from jskel.render import camera_of

    tmp, _, _, _ = obj
    body = f"""object: {{type: cells, base: {{type: torus, major: 1.0, minor: 0.45}}, tiles: 6, skip: SKIP,
  tile_map: {{type: voronoi, resolution: 16, cells: 8, seed: 0}}, cache: {tmp / 'cache'}}}
camera: {{eye: [0, 2, 2.5], target: [0, 0, 0], width: 32, height: 24}}
render: {{progress: false, steps: true}}
"""
    steps = {}
    for skip in ("false", "true"):
        p = tmp_path / f"exp_{skip}.yaml"
        p.write_text(body.replace("SKIP", skip))
        assert cli.main(["render", str(p), "--out", str(tmp_path / skip)]) == 0
        steps[skip] = np.load(tmp_path / skip / "steps.npy")
    exp = config.load(str(tmp_path / "exp_false.yaml"))
    O, D = camera_of(exp).ray_arrays()
    built = cells.build(cell_cfg(tmp, search="voxels", skip=False))
    visited = reference_dda(built, O, D)[3].reshape(24, 32)
    assert steps["false"].shape == (24, 32) and visited.max() > 20
    np.testing.assert_array_equal(steps["false"], visited)
    assert np.all(steps["true"] <= steps["false"]) and steps["true"].sum() < steps["false"].sum()
    frusta = tmp_path / "frusta.yaml"
    frusta.write_text("object: {type: frusta, skeleton: {joints: [[0,0,0],[0,1,0]], radii: [0.3, 0.2], parents: [-1, 0]}}\nrender: {steps: true}\n")
    capsys.readouterr()
    assert cli.main(["render", str(frusta), "--out", str(tmp_path / "f")]) == 2
    assert "render.steps" in capsys.readouterr().err
    scene = tmp_path / "scene.yaml"
    scene.write_text("objects:\n  - {name: a, shape: {type: frusta, skeleton: {joints: [[0,0,0],[0,1,0]], radii: [0.3, 0.2], parents: [-1, 0]}}}\n"
                     "render: {steps: true}\n")
    assert cli.main(["render", str(scene), "--out", str(tmp_path / "s")]) == 2
    assert "render.steps" in capsys.readouterr().err


def test_render_steps_of_a_placed_object_are_those_of_the_object_where_it_stands(obj):
    """A scene of one cell object moved by ``transform.translate``, seen by a camera moved the
    same way, counts the steps of the object written where it stands (the camera rays are placed
    in the object's frame before they are counted): the same steps on (nearly) every pixel; and
    so does one turned 90 degrees about y and scaled by 1.5, seen by the camera turned and
    scaled with it (R_y(90) written here: x -> -z, z -> x)."""
    from jskel.config import validate

    tmp, _, _, _ = obj
    shape = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45}, "tiles": 6,
             "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "cache": str(tmp / "cache")}
    move = np.array([0.75, -0.5, 0.25])
    cam = {"eye": [0, 2, 2.5], "target": [0, 0, 0], "width": 32, "height": 24}
    moved = {**cam, "eye": list(np.add(cam["eye"], move)), "target": list(move)}
    render_opts = {"progress": False, "steps": True}
    here = render(validate({"object": shape, "camera": cam, "render": render_opts})).aovs["steps"]
    there = render(validate({"objects": [{"shape": shape, "transform": {"translate": move.tolist()}}], "camera": moved,
                             "render": render_opts})).aovs["steps"]
    assert here.max() > 20 and np.mean(here == there) > 0.995, np.mean(here == there)
    turn = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    turned = {**cam, "eye": list(1.5 * turn @ cam["eye"]), "target": [0.0, 0.0, 0.0], "up": list(turn @ [0.0, 1.0, 0.0])}
    there = render(validate({"objects": [{"shape": shape, "transform": {"rotate_deg": [0, 90, 0], "scale": 1.5}}], "camera": turned,
                             "render": render_opts})).aovs["steps"]
    assert np.mean(here == there) > 0.99, np.mean(here == there)


def test_tile_levels_are_the_largest_uniform_blocks(rng):
    """``tile_levels``: per tile, the largest l such that the aligned block of 2^l tiles a side
    holding it has no INSIDE part (empty level) or only INSIDE-only tiles (full level), the
    tiles past the 6 given (padding to 8) counting as empty and not full; checked tile by tile
    against blocks cut here."""
    from jskel.cells._trace import EMPTY_SHIFT, FULL_SHIFT, LEVEL_MASK, TILE_ALL_INSIDE, TILE_HAS_INSIDE, tile_levels

    full = TILE_HAS_INSIDE | TILE_ALL_INSIDE
    flags = rng.choice([0, TILE_HAS_INSIDE, full], size=(6, 6, 6), p=[0.3, 0.3, 0.4]).astype(np.int32)
    flags[:4, :4, :4] = full  # a full block of 4
    flags[4:, 4:, :2] = 0  # an empty block of 2
    flags[4:6, 0:2, 4:6] = full  # a full block of 2 whose block of 4 reaches the padding
    out = tile_levels(flags)
    np.testing.assert_array_equal(out & 3, flags)
    padded = np.zeros((8, 8, 8), np.int32)
    padded[:6, :6, :6] = flags
    for i, j, k in np.ndindex(6, 6, 6):
        want = []
        for bit, uniform in ((EMPTY_SHIFT, lambda b: not np.any(b & TILE_HAS_INSIDE)), (FULL_SHIFT, lambda b: bool(np.all(b & TILE_ALL_INSIDE)))):
            lvl = 0
            for l in (1, 2, 3):
                w = 1 << l
                blk = padded[i // w * w:(i // w + 1) * w, j // w * w:(j // w + 1) * w, k // w * w:(k // w + 1) * w]
                if uniform(blk):
                    lvl = l
                else:
                    break
            want.append(lvl)
        assert ((out[i, j, k] >> EMPTY_SHIFT) & LEVEL_MASK, (out[i, j, k] >> FULL_SHIFT) & LEVEL_MASK) == tuple(want), (i, j, k)
    assert (out[0, 0, 0] >> FULL_SHIFT) & LEVEL_MASK == 2 and (out[4, 0, 4] >> FULL_SHIFT) & LEVEL_MASK == 1
    assert (out[5, 5, 0] >> EMPTY_SHIFT) & LEVEL_MASK >= 1


def test_traversal_stats_count_the_voxels_the_walk_looks_at(obj):
    """``traversal_stats`` (what ``bench`` reports with ``stats: true``): the voxel walk without
    tile skipping looks at exactly the voxels the float64 DDA of :func:`reference_dda` does,
    ray by ray, so its mean, 99th percentile and max are the reference's; tile skipping only
    lowers the count."""
    tmp, _, O, D = obj
    flat = cells.build(cell_cfg(tmp, search="voxels", skip=False))
    _, steps = trace(flat, O, D)
    visited = reference_dda(flat, O, D)[3]
    np.testing.assert_array_equal(np.asarray(steps), visited)
    rays = make_rays(O - flat.anchor, D)
    stats = cells.traversal_stats(flat, rays)
    assert stats["steps_per_ray_mean"] == pytest.approx(visited.mean()) and stats["steps_per_ray_max"] == visited.max()
    assert stats["steps_per_ray_p99"] == pytest.approx(np.percentile(visited, 99))
    skipping = cells.traversal_stats(cells.build(cell_cfg(tmp, search="voxels")), rays)
    assert skipping["steps_per_ray_mean"] < stats["steps_per_ray_mean"]
