"""Error metrics between two renders of the same camera (host side, NumPy float64).

Each takes NumPy ``Hit`` records with a leading pixel axis. Pixels are compared where both
renders hit (depth, normals) or where either hits (hit/miss disagreement).
"""

from __future__ import annotations

import numpy as np


def compare(hits, ref, rgb=None, ref_rgb=None) -> dict:
    """Hit/miss disagreement (% of pixels), the % of pixels whose hit primitive (segment,
    primitive, cell id) differs (a miss counts as -1), depth RMSE and max over pixels hit in
    both, the mean and max angle between normals (degrees) over those pixels; with colours,
    the image RMSE and PSNR (dB, peak 1) of the linear RGB clipped to [0, 1]."""
    a = np.isfinite(np.asarray(hits.t, np.float64))
    b = np.isfinite(np.asarray(ref.t, np.float64))
    both = a & b
    out = {"hit_miss_pct": float(100.0 * np.mean(a != b)), "pixels_hit_both": int(both.sum())}
    if getattr(hits, "prim", None) is not None and getattr(ref, "prim", None) is not None:
        pa = np.where(a, np.asarray(hits.prim), -1)
        pb = np.where(b, np.asarray(ref.prim), -1)
        out["prim_mismatch_pct"] = float(100.0 * np.mean(pa != pb))
    if rgb is not None and ref_rgb is not None:
        d = np.clip(np.asarray(rgb, np.float64), 0, 1) - np.clip(np.asarray(ref_rgb, np.float64), 0, 1)
        mse = float(np.mean(d * d))
        out["image_rmse"] = float(np.sqrt(mse))
        out["psnr_db"] = float(10 * np.log10(1.0 / mse)) if mse > 0 else None
    if both.any():
        dt = np.asarray(hits.t, np.float64)[both] - np.asarray(ref.t, np.float64)[both]
        out["depth_rmse"] = float(np.sqrt(np.mean(dt * dt)))
        out["depth_max"] = float(np.max(np.abs(dt)))
        if getattr(hits, "normal", None) is None:
            return out
        na = np.asarray(hits.normal, np.float64)[both]
        nb = np.asarray(ref.normal, np.float64)[both]
        cos = np.clip(np.sum(na * nb, -1) / np.maximum(np.linalg.norm(na, axis=-1) * np.linalg.norm(nb, axis=-1), 1e-300), -1, 1)
        ang = np.degrees(np.arccos(cos))
        out["normal_deg_mean"] = float(ang.mean())
        out["normal_deg_max"] = float(ang.max())
    else:
        out.update(depth_rmse=None, depth_max=None, normal_deg_mean=None, normal_deg_max=None)
    return out


def pareto_front(times, errors) -> np.ndarray:
    """Boolean mask of the settings no other setting beats in both time and error."""
    t = np.asarray(times, float)
    e = np.asarray(errors, float)
    keep = np.ones(t.shape[0], bool)
    for i in range(t.shape[0]):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep
