"""Invariance (issue 9): moving, turning and uniformly scaling a scene together with its camera
changes depth only by the scale, for every representation (cells: translation and scale, since
their tile grid is fixed to the world axes). Float32, a translation of 1.2e3 and a scale of 7.3."""

from __future__ import annotations

import numpy as np
import pytest

from jskel.config import validate
from jskel.render import render

S = 7.3
C = np.array([1200.0, -340.0, 55.0])


def _rot(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


R = _rot([1, 2, 3], 0.7)


def _pt(x, rotate=True):
    return (S * (R if rotate else np.eye(3)) @ np.asarray(x, float) + C).tolist()


def _camera(eye, target, rotate=True):
    up = (R if rotate else np.eye(3)) @ np.array([0.0, 1.0, 0.0])
    return {"eye": _pt(eye, rotate), "target": _pt(target, rotate), "up": up.tolist(), "fov_deg": 40, "width": 40, "height": 30}


def _compare(a, b, size, tol, cells=False):
    ta, tb = np.asarray(a.hits.t, np.float64), np.asarray(b.hits.t, np.float64)
    ha, hb = np.isfinite(ta), np.isfinite(tb)
    assert 0.05 < ha.mean() < 0.95
    assert np.mean(ha != hb) <= 0.01  # silhouette pixels may flip
    both = ha & hb
    err = np.abs(tb[both] - S * ta[both]) / (S * size)
    assert np.quantile(err, 0.99) <= tol, float(np.quantile(err, 0.99))
    if cells:
        assert np.mean(np.asarray(a.hits.prim)[both] == np.asarray(b.hits.prim)[both]) >= 0.99


def test_frusta_depth_follows_the_transform():
    j = np.array([[0, 0, 0], [0, 1, 0], [0.4, 1.9, 0.1], [-0.5, 1.6, 0.2]], float)
    r = [0.35, 0.3, 0.12, 0.1]
    p = [-1, 0, 1, 1]
    cam = ([0.5, 1.0, 5.0], [0.0, 1.0, 0.0])
    base = {"object": {"type": "frusta", "skeleton": {"joints": j.tolist(), "radii": r, "parents": p}},
            "camera": {**_camera(*cam), **{"eye": cam[0], "target": cam[1], "up": [0, 1, 0]}}}
    moved = {"object": {"type": "frusta", "skeleton": {"joints": [_pt(x) for x in j], "radii": [S * x for x in r], "parents": p}},
             "camera": _camera(*cam)}
    _compare(render(validate(base)), render(validate(moved)), 2.5, 1e-5)


@pytest.mark.parametrize("method", ["lipschitz", "bisection"])
def test_implicit_depth_follows_the_transform(method):
    balls = [([0, 0, 0], 1.0), ([0.9, 0.4, 0.1], 0.7)]
    tube = ([-0.8, -0.6, 0.2], [0.4, 0.9, -0.1], 0.5, 0.3)
    obj = {"type": "implicit", "threshold": 0.5, "method": method, "eps": 1e-3, "bisection": 16,
           "balls": [{"center": c, "radius": rr} for c, rr in balls],
           "tubes": [{"a": tube[0], "b": tube[1], "radius_a": tube[2], "radius_b": tube[3]}]}
    moved_obj = dict(obj, eps=S * 1e-3, balls=[{"center": _pt(c), "radius": S * rr} for c, rr in balls],
                     tubes=[{"a": _pt(tube[0]), "b": _pt(tube[1]), "radius_a": S * tube[2], "radius_b": S * tube[3]}])
    cam = ([0.3, 0.5, 4.5], [0.0, 0.1, 0.0])
    base = {"object": obj, "camera": {**_camera(*cam), **{"eye": cam[0], "target": cam[1], "up": [0, 1, 0]}}}
    moved = {"object": moved_obj, "camera": _camera(*cam)}
    _compare(render(validate(base)), render(validate(moved)), 3.0, 1e-4)


@pytest.mark.parametrize("mode", ["first_hit", "reflection", "refraction"])
def test_cells_depth_follows_translation_and_scale(tmp_path, mode):
    """Secondary rays start off the surface by the object's own start distance (a voxel; a
    linear step when refracting) scaled with the object, plus a rounding bound that grows with
    the hit's magnitude (no fixed epsilon that a translation or scale could break): the
    colours, which depend on where the reflected and refracted rays go, stay the same too."""
    obj = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
           "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 6, "mode": mode,
           "search": "linear", "steps_per_tile": 64, "bisection": 12, "cache": str(tmp_path / "c")}
    moved_obj = dict(obj, base={"type": "torus", "major": S, "minor": S * 0.45, "center": C.tolist()})
    cam = ([0.0, 2.2, 2.6], [0.0, 0.0, 0.0])
    base = {"object": obj, "camera": {**_camera(*cam, rotate=False), **{"eye": cam[0], "target": cam[1]}}}
    moved = {"object": moved_obj, "camera": _camera(*cam, rotate=False)}
    a, b = render(validate(base)), render(validate(moved))
    _compare(a, b, 3.0, 1e-4, cells=True)
    diff = np.abs(np.asarray(a.rgb, np.float64) - np.asarray(b.rgb, np.float64)).max(-1)
    assert np.mean(diff <= 2e-3) >= 0.98, float(np.mean(diff <= 2e-3))
