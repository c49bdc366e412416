"""The points a skeleton is fitted to (issue 10): a cloud read from a file, or sampled from a
known skeleton's surface with noise and outliers (``points.synthetic``), with the facts that
``fit.json`` reports about them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import frusta
from ._config import PointsConfig
from ._distance import sample_surface, segments_of


def read_points(path: str | Path) -> np.ndarray:
    """(N,3) float64 points from .npy, .xyz/.txt/.csv or .ply; ValueError naming ``points.file``."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"points.file: not found (got {str(p)!r})")
    ext = p.suffix.lower()
    try:
        if ext == ".npy":
            a = np.load(p, allow_pickle=False)
        elif ext in (".xyz", ".txt", ".csv"):
            a = np.loadtxt(p, delimiter="," if ext == ".csv" else None, ndmin=2) if p.stat().st_size else np.zeros((0, 3))
        elif ext == ".ply":
            import trimesh

            g = trimesh.load(p, process=False)
            a = np.asarray(g.vertices)
        else:
            raise ValueError(f"points.file: unknown format {ext!r} (got {str(p)!r}; .npy, .xyz, .txt, .csv, .ply)")
    except ValueError:
        raise
    except Exception as e:  # noqa: BLE001 - a corrupt file: say which and why, in one line
        raise ValueError(f"points.file: cannot read {str(p)!r}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    a = np.asarray(a, np.float64)
    if a.size == 0:
        raise ValueError(f"points.file: no points in {str(p)!r}")
    if a.ndim != 2 or a.shape[1] < 3:
        raise ValueError(f"points.file: expected (N, 3) points, got shape {a.shape} in {str(p)!r}")
    return a[:, :3]


def skeleton_arrays(sk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints, radii, parents) of a ``SkeletonConfig`` (explicit or procedural), float64."""
    j, r, p, _ = frusta.skeleton_arrays(sk)
    return np.asarray(j, np.float64), np.asarray(r, np.float64), np.asarray(p, np.int64)


def load_points(cfg: PointsConfig, base: Path | None = None) -> tuple[np.ndarray, dict, tuple | None]:
    """The cloud (N,3) float64, facts for fit.json, and the true skeleton of synthetic points."""
    info: dict = {}
    truth = None
    if cfg.synthetic is not None:
        s = cfg.synthetic
        j, r, p = skeleton_arrays(s.skeleton)
        segments_of(j, r, p, "points.synthetic.skeleton")
        rng = np.random.default_rng(s.seed)
        pts = sample_surface(j, r, p, s.count, rng)
        length = float(np.sum(np.linalg.norm(j[p[p >= 0]] - j[p >= 0], axis=1)))
        pts = pts + rng.normal(0.0, s.noise * length, pts.shape)
        n_out = int(round(s.outliers * s.count))
        if n_out:
            lo, hi = pts.min(0), pts.max(0)
            pad = 0.2 * (hi - lo)
            idx = rng.choice(s.count, n_out, replace=False)
            pts[idx] = rng.uniform(lo - pad, hi + pad, (n_out, 3))
        info.update({"source": "synthetic", "noise_sd": s.noise * length, "outliers": n_out, "skeleton_length": length})
        truth = (j, r, p)
    else:
        f = Path(cfg.file)
        pts = read_points(f if f.is_absolute() or base is None or f.exists() else base / f)
        info["source"] = str(cfg.file)
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        if cfg.nonfinite == "reject":
            raise ValueError(f"points: {int(bad.sum())} of {len(pts)} points are NaN or inf (first at index {first}: "
                             f"{pts[first].tolist()}); set points.nonfinite: drop to drop them")
        pts = pts[~bad]
        info["dropped_nonfinite"] = int(bad.sum())
    info["points"] = int(len(pts))
    return pts, info, truth
