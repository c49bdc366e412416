"""Cell precomputation (Nürnberg 2011, Ch. 4) against brute force written here: split cells by
connected components of each cell in the tile, memberships by explicit periodic tiling of the
whole object space and per-cell min / max of the inside flag; packing; Table 5.1."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from jskel.cells._membership import INSIDE, INTERSECTED, OUTSIDE, UNSET, memory_table, membership, pack, unpack
from jskel.cells._tiles import part_links, part_offsets, sphere_tile, split_cells, voronoi_tile

FULL = np.ones((3, 3, 3))


def torus_inside(p, R=1.0, r=0.45):
    q = np.hypot(p[:, 0], p[:, 2]) - R
    return q * q + p[:, 1] ** 2 < r * r


def brute_membership(tile, split, slots, n, inside, lo, size):
    """(N,N,N,S) codes: tile the map over the whole object space, label each cell index's
    connected regions (26-neighbourhood), min / max of the inside flag per region (Table 4.2)."""
    res = tile.shape[0]
    big = np.tile(tile, (n, n, n))
    bsplit = np.tile(split, (n, n, n)).astype(np.int64)
    g = (np.arange(n * res) + 0.5) / res
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * size + lo
    flag = inside(pts).reshape(big.shape).astype(np.int64)
    want = np.full((n, n, n, slots), UNSET, np.uint8)
    for c in range(1, int(tile.max()) + 1):
        lab, count = ndimage.label(big == c, structure=FULL)
        idx = np.arange(1, count + 1)
        mn = np.asarray(ndimage.minimum(flag, lab, idx), np.int64)
        mx = np.asarray(ndimage.maximum(flag, lab, idx), np.int64)
        code = np.where(mn == mx, mn, INTERSECTED)
        vox = np.argwhere(big == c)
        t = vox // res
        want[t[:, 0], t[:, 1], t[:, 2], bsplit[tuple(vox.T)] - 1] = code[lab[tuple(vox.T)] - 1]
    return want


CASES = [  # tile resolution, cells, tiles per axis, seed, coarse samples per tile edge, map kind
    (8, 8, 4, 0, 8, "voronoi"),
    (12, 8, 5, 1, 2, "voronoi"),
    (10, 12, 6, 2, 2, "voronoi"),
    (16, 6, 5, 3, 3, "spheres"),
]


@pytest.mark.parametrize("res,cells,n,seed,coarse,kind", CASES)
def test_membership_equals_brute_force_tiling(res, cells, n, seed, coarse, kind):
    tile = voronoi_tile(res, cells, seed) if kind == "voronoi" else sphere_tile(res, cells, 0.3, seed)
    sc = split_cells(tile)
    off = part_offsets(sc, part_links(sc))
    lo, size = np.full(3, -1.6), 3.2 / n
    mem = membership(sc, off, torus_inside, lo, size, n, coarse=coarse)
    got = unpack(mem.words, len(sc.split_cell) - 1)
    want = brute_membership(sc.tile, sc.split, 8 * cells, n, torus_inside, lo, size)
    assert np.array_equal(got, want)
    assert {OUTSIDE, INSIDE, INTERSECTED} <= set(np.unique(got).tolist())  # a case with all three


@pytest.mark.parametrize("res,cells,seed", [(16, 8, 0), (20, 8, 5)])
def test_split_cells_are_the_parts_of_each_cell_in_the_tile(res, cells, seed):
    tile = voronoi_tile(res, cells, seed)
    sc = split_cells(tile)
    i = np.arange(res)
    faces = np.zeros_like(tile, np.int64)  # Fig. 4.3 bits, written independently
    for a in range(3):
        sh = [1, 1, 1]
        sh[a] = res
        faces |= ((i == 0).reshape(sh) << (2 * a)) | ((i == res - 1).reshape(sh) << (2 * a + 1))
    seen = {}
    for c in range(1, cells + 1):
        lab, count = ndimage.label(tile == c, structure=FULL)
        codes = []
        for k in range(1, count + 1):
            part = lab == k
            code = int(np.bitwise_or.reduce(faces[part]))
            s = np.unique(sc.split[part])
            assert len(s) == 1 and s[0] > 0  # one split index per part
            assert sc.split_face[s[0]] == code and sc.split_cell[s[0]] == c
            seen.setdefault((c, code), set()).add(int(s[0]))
            codes.append(code)
        ranks = sorted(set(codes))  # Sec. 4.3: ascending face codes get ascending indices 8(c-1)+1..
        for r, code in enumerate(ranks):
            assert seen[(c, code)] == {8 * (c - 1) + r + 1}
    assert np.all((sc.split == 0) == (tile == 0))


def test_pack_unpack_round_trip_for_every_code_and_slot():
    rng = np.random.default_rng(0)
    codes = rng.integers(0, 4, size=(50, 64)).astype(np.uint8)
    codes[0] = np.arange(64) % 4  # every code at every residue
    for c in range(4):
        codes[1 + c] = c
    words = pack(codes)
    assert words.shape == (50, 4) and words.dtype == np.uint32  # 64 split cells in 128 bits (Fig. 4.9)
    assert np.array_equal(unpack(words, 64), codes)
    # Alg. 4.5 read by hand: slot s sits in word s >> 4 at bit 2 (s & 15)
    for s in (0, 15, 16, 37, 63):
        assert (int(words[0, s >> 4]) >> (2 * (s & 15))) & 3 == s % 4
    assert np.array_equal(unpack(pack(codes[:, :10]), 10), codes[:, :10])  # fewer slots: padded UNSET


def test_memory_table_reproduces_table_5_1():
    mb, kb = 1024 * 1024, 1024
    rows = [  # cell map res, tiles, then Table 5.1: cell, colour, normal, membership, total
        (256, 32, 16 * mb, 8 * mb, 256 * mb, 512 * kb, 280),
        (128, 64, 2 * mb, 8 * mb, 32 * mb, 4 * mb, 46),
        (64, 128, 256 * kb, 8 * mb, 4 * mb, 32 * mb, 44),
        (32, 256, 32 * kb, 8 * mb, 512 * kb, 256 * mb, 264),
    ]
    for res, tiles, cell, color, normal, member, total_mb in rows:
        m = memory_table(res, tiles, color_res=128)
        assert (m["cell_map"], m["color_map"], m["normal_map"], m["membership_map"]) == (cell, color, normal, member)
        assert int(m["total"] / mb) == total_mb  # the table rounds 280.5 MB to 280, 44.25 to 44


def _codes(base, tiles=8, seed=1):
    """Memberships of a base shape through ``cells.precompute``, and those of ``truth(points)``
    on the same tile map and object box through ``membership``."""
    from jskel import cells

    cfg = cells.CellsConfig.model_validate({"type": "cells", "base": base, "tiles": tiles, "cache": None, "margin": 0.1,
                                            "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": seed}})
    obj = cells.precompute(cfg)
    return unpack(obj.words, len(obj.split_cell) - 1), obj


RHO = float(np.sqrt(1 - np.sqrt(0.5)))  # a lone metaball of R = 1 at T = 0.5


@pytest.mark.parametrize("kind", ["mesh", "implicit", "frusta"])
def test_mesh_implicit_and_frusta_base_shapes_match_their_closed_forms(tmp_path, kind):
    """An icosphere mesh (trimesh) of radius 1, a lone metaball (surface: the sphere of radius
    R sqrt(1 - sqrt(T))) and a one-segment frusta cylinder (radius 0.6, flat caps) give the
    memberships of their closed forms except next to the surface (where the polygon or the
    float32 inside test decides a boundary voxel), never inside for outside. The mesh is
    voxelized at 256 a side (``base.voxels``), the default 512 fills a grid eight times larger."""
    import trimesh

    if kind == "mesh":
        path = tmp_path / "sphere.stl"
        trimesh.creation.icosphere(subdivisions=5, radius=1.0).export(path)
        base = {"type": "voxel_mesh", "path": str(path), "voxels": 256}

        def truth(p):
            return np.sum(p * p, 1) < 1.0
    elif kind == "implicit":
        base = {"type": "object", "object": {"type": "implicit", "threshold": 0.5, "balls": [{"center": [0, 0, 0], "radius": 1.0}]}}

        def truth(p):
            return np.sum(p * p, 1) < RHO * RHO
    else:
        base = {"type": "object", "object": {"type": "frusta", "skeleton": {"joints": [[0, -1, 0], [0, 1, 0]], "radii": [0.6, 0.6], "parents": [-1, 0]}}}

        def truth(p):
            return (p[:, 0] ** 2 + p[:, 2] ** 2 < 0.36) & (np.abs(p[:, 1]) < 1.0)
    got, obj = _codes(base)
    sc = split_cells(voronoi_tile(16, 8, 1))
    want = unpack(membership(sc, part_offsets(sc, part_links(sc)), truth, obj.lo, obj.size, 8, coarse=2).words, 64)
    present = got != UNSET
    assert np.array_equal(present, want != UNSET)
    same = np.mean(got[present] == want[present])
    assert same > 0.98, same
    diff = present & (got != want)
    assert np.all((got[diff] == INTERSECTED) | (want[diff] == INTERSECTED))  # never inside vs outside
    assert np.sum(want == INSIDE) > 50


@pytest.mark.parametrize("base", [{"type": "torus", "major": 1.0, "minor": 0.45, "center": [0.3, -0.2, 0.1]},
                                  {"type": "sphere", "radius": 0.8, "center": [0.0, 0.5, -0.25]}], ids=["torus", "sphere"])
def test_analytic_base_shapes_give_the_memberships_of_their_point_tests(base):
    """The torus and the sphere test their voxels as three broadcast axes (``AxisInside``, no
    (B, r^3, 3) points): the memberships equal, code for code, those of this file's own point
    tests of the same shapes through ``membership``, on the object's own box."""
    got, obj = _codes(base, tiles=6)
    c = np.asarray(base["center"])
    if base["type"] == "torus":
        def truth(p):
            return torus_inside(p - c, base["major"], base["minor"])
    else:
        def truth(p):
            return np.sum((p - c) ** 2, 1) < base["radius"] ** 2
    sc = split_cells(voronoi_tile(16, 8, 1))
    want = unpack(membership(sc, part_offsets(sc, part_links(sc)), truth, obj.lo, obj.size, 6, coarse=2).words, 64)
    assert np.sum(want == INSIDE) > 20 and np.sum(want == INTERSECTED) > 20
    np.testing.assert_array_equal(got, want)


def test_a_mesh_of_large_triangles_voxelizes_to_its_closed_form():
    """``filled_voxels`` on a box of 12 triangles (each cut into a lattice of hundreds of
    points per edge, ``surface_points``) and on a 20-face icosahedron: every voxel whose centre
    lies more than a voxel's half diagonal inside the closed form is filled, every one as far
    outside is empty (a surface sampled too coarsely would leak and leave the inside empty; the
    check fails with samples 3 voxels apart), and each voxel sits where the grid's origin says."""
    import trimesh

    from jskel.cells._base import filled_voxels

    for mesh, inside in ((trimesh.creation.box(extents=(2.0, 1.0, 0.6)),
                          lambda p: np.max(np.abs(p) - [1.0, 0.5, 0.3], axis=1)),
                         (trimesh.creation.icosahedron(), None)):
        v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
        pitch = 1.0 / 32
        grid, origin = filled_voxels(v, f, pitch)
        centres = (np.argwhere(np.ones(grid.shape, bool)) + origin) * pitch
        if inside is None:  # the convex icosahedron: the largest signed plane distance of its faces
            n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            off = np.sum(n * v[f[:, 0]], 1)
            assert np.all(off > 0)  # outward normals

            def inside(p):
                return np.max(p @ n.T - off, axis=1)
        sd = inside(centres).reshape(grid.shape)
        half = 0.5 * np.sqrt(3) * pitch
        assert np.all(grid[sd < -half]) and not np.any(grid[sd > half])
        assert np.sum(sd < -half) > 1000  # (and the icosahedron's box holds over 1,000 voxels outside it)
        assert np.sum(sd > half) > (1000 if mesh.faces.shape[0] == 20 else -1)


def test_surface_points_are_the_same_lattice_in_any_pieces():
    """A triangle whose lattice exceeds the budget comes in bands of rows: the same points as in
    one piece (sorted), each on its triangle (barycentric coordinates in [0, 1], float64)."""
    from jskel.cells._base import surface_points

    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.3]])
    f = np.array([[0, 1, 2], [0, 1, 3]])
    whole = np.concatenate(list(surface_points(v, f, 0.01)))
    parts = list(surface_points(v, f, 0.01, budget=500))
    assert len(parts) > 10 and max(len(p) for p in parts) <= 1000
    pieces = np.concatenate(parts)
    ks = [int(np.ceil(np.sqrt(2.0) / 0.01)), int(np.ceil(np.sqrt(1.09) / 0.01))]  # each one's longest edge
    assert len(whole) == len(pieces) == sum((k + 1) * (k + 2) // 2 for k in ks)
    k = ks[0]
    np.testing.assert_array_equal(np.unique(whole, axis=0), np.unique(pieces, axis=0))
    flat = pieces[np.abs(pieces[:, 2]) < 1e-15]  # the first triangle's points: x, y >= 0, x + y <= 1
    assert len(flat) >= (k + 1) * (k + 2) // 2 and np.all(flat[:, :2] >= -1e-15) and np.all(flat[:, :2].sum(1) <= 1 + 1e-12)
