"""``jskel render EXP --out DIR --aov-sheet``: aov_sheet.png holds the image, depth, normals, uv,
ids and flags of the AOV files the same render wrote, panel for panel (checked here against
the files with the colour maps written out in float64, not the sheet code's own helpers)."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from jskel import cli
from jskel.render._sheet import layout

SMALL = ["camera.width=48", "camera.height=32", "render.chunk=4096", "render.progress=false"]


def _panels(sheet: np.ndarray, shape) -> dict:
    """Each panel cut from the sheet at the layout's place, its enlargement undone after
    checking that every enlarged pixel is a constant block."""
    lay = layout(*shape)
    out = {}
    for name, (r, c) in lay.origin.items():
        big = sheet[r : r + lay.panel[0], c : c + lay.panel[1]].astype(np.int64)
        small = big[:: lay.scale, :: lay.scale]
        assert np.array_equal(np.repeat(np.repeat(small, lay.scale, 0), lay.scale, 1), big), name
        out[name] = small
    return out


def test_render_writes_a_sheet_whose_panels_are_its_aov_files(tmp_path):
    out = tmp_path / "render"
    args = ["render", "--out", str(out), "--aov-sheet"] + [x for s in SMALL for x in ("--set", s)]
    assert cli.main(args) == 0
    depth = np.load(out / "depth.npy").astype(np.float64)
    hit = np.isfinite(depth)
    assert 0 < hit.sum() < hit.size, "the render should have hits and misses"
    p = _panels(np.asarray(iio.imread(out / "aov_sheet.png"))[..., :3], depth.shape)

    assert np.array_equal(p["image"], np.asarray(iio.imread(out / "image.png"))[..., :3])

    # depth: a grey ramp, 255 at the nearest hit to 55 at the farthest, monotone; misses black
    g = p["depth"]
    assert np.all(g[..., 0] == g[..., 1]) and np.all(g[..., 1] == g[..., 2]) and np.all(g[~hit] == 0)
    d, v = depth[hit], g[..., 0][hit]
    order = np.argsort(d, kind="stable")
    assert np.all(np.diff(v[order]) <= 0) and v.max() == 255 and v.min() == 55
    assert np.all(np.abs(v - (255 - 200 * (d - d.min()) / (d.max() - d.min()))) <= 0.5 + 1e-9)

    n = np.load(out / "normal.npy").astype(np.float64)
    assert np.all(np.abs(p["normals"][hit] - (n[hit] + 1) / 2 * 255) <= 0.5 + 1e-6) and np.all(p["normals"][~hit] == 0)

    uv = np.load(out / "uv.npy").astype(np.float64)[hit]
    frac = uv - np.floor(uv)
    assert np.all(np.abs(p["uv"][hit][:, :2] - frac * 255) <= 0.5 + 1e-6) and np.all(p["uv"][hit][:, 2] == 0)

    # ids: one colour per primitive, different primitives different colours, misses black
    prim = np.load(out / "prim.npy")
    ids = p["ids"]
    assert np.all(ids[prim < 0] == 0) and np.array_equal(prim >= 0, hit)
    pairs = {(int(i), tuple(c)) for i, c in zip(prim[hit], ids[hit])}
    assert len(pairs) == len(np.unique(prim[hit])) == len({c for _, c in pairs}) > 1

    flags = np.load(out / "flags.npy") if (out / "flags.npy").exists() else np.zeros(depth.shape, int)
    assert np.all(p["flags"][flags == 0] == 40) and not np.any(np.all(p["flags"][flags != 0] == 40, axis=-1))
