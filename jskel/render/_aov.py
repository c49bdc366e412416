"""Image and AOV writers: image.png, depth.npy, normal.npy, uv.npy, prim.npy, run.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def write_aovs(out: str | Path, hits, image_u8: np.ndarray, width: int, height: int, run: dict, extra: dict | None = None) -> dict:
    """Write every output of a render into ``out``; returns {name: path}.

    extra: more per-pixel arrays (leading axis width*height) written as ``<name>.npy`` with
    shape (H, W, ...), e.g. a scene's ``obj``, ``visibility``, ``reflect_obj``.
    hits: NumPy ``Hit`` with a leading axis of width*height (row-major).
    depth.npy (H,W) float32, +inf on a miss; normal.npy (H,W,3) float32; uv.npy (H,W,2)
    float32; prim.npy (H,W) int32, -1 on a miss; image.png (H,W,3) uint8.
    """
    import imageio.v3 as iio

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    h, w = int(height), int(width)
    files = {
        "depth": (np.asarray(hits.t, np.float32).reshape(h, w)),
        "normal": (np.asarray(hits.normal, np.float32).reshape(h, w, 3)),
        "uv": (np.asarray(hits.uv, np.float32).reshape(h, w, 2)),
        "prim": (np.asarray(hits.prim, np.int32).reshape(h, w)),
    }
    if getattr(hits, "flags", None) is not None:
        files["flags"] = np.asarray(hits.flags, np.int32).reshape(h, w)
    for name, arr in (extra or {}).items():
        a = np.asarray(arr)
        files[name] = a.reshape((h, w) + a.shape[1:])
    paths = {}
    for name, arr in files.items():
        p = out / f"{name}.npy"
        np.save(p, arr)
        paths[name] = str(p)
    p = out / "image.png"
    iio.imwrite(p, image_u8.reshape(h, w, 3))
    paths["image"] = str(p)
    p = out / "run.json"
    p.write_text(json.dumps(run, indent=2, default=str) + "\n")
    paths["run"] = str(p)
    return paths
