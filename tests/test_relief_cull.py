"""The relief shells' (ray, segment) pairs culled by the BVH leaves each ray meets
(``object.relief.cull``: ``tree`` walks per ray, ``packets`` lists for packets of 64 rays)
against every segment of each block a ray of the batch reaches (``blocks``, the pairs the
float64 references of ``test_relief.py`` check): the same hits, segments and undecided flags,
on a camera's rays in screen tiles, random rays, and rays along a chain of 160 segments that
meet more leaves than a ray keeps (cast by the blocks)."""

from __future__ import annotations

import numpy as np

import reference as ref
from conftest import assert_hits_agree, cast, random_tree
from jskel import frusta
from test_implicit_cull import camera_rays

CHAIN = 160  # segments of the straight chain along x: its axial rays meet >= 40 leaves of 4 (a ray keeps 32)
R, T = 0.1, 0.02  # the chain's radius and every shell's thickness


def relief_scene(tmp_path, cull: str):
    import imageio.v3 as iio

    rng = np.random.default_rng(7)
    height = rng.integers(0, 256, size=(64, 64))
    path = tmp_path / "h.png"
    if not path.exists():
        iio.imwrite(path, height.astype(np.uint8))
    j1, r1, p1 = random_tree(rng, 120, r_max=0.2)
    x = np.linspace(0.0, 8.0, CHAIN + 1)
    j2 = np.stack([x, np.full_like(x, -1.5), np.zeros_like(x)], 1)
    joints = np.concatenate([j1, j2])
    radii = np.concatenate([r1, np.full(CHAIN + 1, R)])
    parents = np.concatenate([p1, [-1], np.arange(CHAIN) + len(j1)])
    cfg = frusta.FrustaConfig.model_validate({
        "type": "frusta",
        "skeleton": {"joints": joints.tolist(), "radii": radii.tolist(), "parents": parents.tolist()},
        "relief": {"map": str(path), "thickness": T, "scale": [2.0, 1.0], "steps": 8, "bisection": 4, "cull": cull},
    })
    return frusta.build(cfg)


def test_leaves_cull_the_same_pairs_as_the_blocks(tmp_path):
    hits = {}
    for cull in ("blocks", "tree", "packets"):
        built = relief_scene(tmp_path, cull)
        assert built.info["relief_segments"] == 119 + CHAIN and built.static.relief_cull == cull
        if not hits:
            lo, hi = (np.asarray(b, float) for b in built.bounds)
            Oc, Dc = camera_rays(lo, hi)  # 4,096 rays in 8 x 8 tiles: the packets' lists
            Or, Dr = ref.random_rays(np.random.default_rng(3), lo, hi, 4032, spread=0.5)
            # along the chain from its far end, inside every shell (offset between R and R + T):
            # a packet's list in Morton order starts at the chain's near end, the wrong one
            ang = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
            off = (R + 0.5 * T) * np.stack([np.zeros_like(ang), np.cos(ang), np.sin(ang)], 1)
            Oa = np.array([9.0, -1.5, 0.0]) + off
            Da = np.tile([-1.0, 0.0, 0.0], (64, 1))
            O, D = np.concatenate([Oc, Or, Oa]), np.concatenate([Dc, Dr, Da])
        hits[cull] = cast(built, O, D, culled=True)
    base = hits["blocks"]
    h = np.isfinite(base.t)
    assert h[:4096].mean() > 0.1 and h[4096:8128].mean() > 0.05  # camera and random rays hit the tree
    assert np.all(h[8128:]) and np.all(base.position[8128:, 0] > 7.0)  # the axial rays hit the chain's far end first
    for cull in ("tree", "packets"):
        assert_hits_agree(base, hits[cull], rtol=1e-6)
        np.testing.assert_array_equal(base.flags, hits[cull].flags)
