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
        if getattr(hits, "uv", None) is not None and getattr(ref, "uv", None) is not None:
            out["uv_rmse"] = uv_rmse(np.asarray(hits.uv)[both], np.asarray(ref.uv)[both])
    else:
        out.update(depth_rmse=None, depth_max=None, normal_deg_mean=None, normal_deg_max=None)
    return out


def uv_rmse(uv, ref_uv) -> float:
    """RMS distance in (u, v) over pixels (N, 2), with u's difference taken around its wrap
    (u = 0.99 and 0.01 are 0.02 apart: u is an angle in turns, Eq. 6)."""
    d = np.asarray(uv, np.float64) - np.asarray(ref_uv, np.float64)
    du = d[:, 0] - np.round(d[:, 0])
    return float(np.sqrt(np.mean(du * du + d[:, 1] * d[:, 1])))


def ssim(rgb, ref_rgb, shape) -> float:
    """Mean structural similarity (Wang et al. 2004; scikit-image's implementation, 7x7 uniform
    window, data range 1) of two linear RGB images (H*W, 3) clipped to [0, 1], of ``shape``
    (H, W). Images smaller than the window are compared at the largest odd window that fits."""
    from skimage.metrics import structural_similarity

    a = np.clip(np.asarray(rgb, np.float64), 0, 1).reshape(*shape, 3)
    b = np.clip(np.asarray(ref_rgb, np.float64), 0, 1).reshape(*shape, 3)
    win = min(7, *shape)
    win -= 1 - win % 2
    if win < 3:
        raise ValueError(f"ssim: images of {shape[0]}x{shape[1]} pixels are smaller than a 3x3 window")
    return float(structural_similarity(a, b, data_range=1.0, channel_axis=-1, win_size=win))


def pareto_front(times, errors) -> np.ndarray:
    """Boolean mask of the settings no other setting beats in both time and error."""
    t = np.asarray(times, float)
    e = np.asarray(errors, float)
    keep = np.ones(t.shape[0], bool)
    for i in range(t.shape[0]):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep


def depth_in_pixels(t, ref_t, fov_y_deg: float, height: int) -> dict:
    """Depth error in units of the pixel footprint at the reference depth, over pixels hit in
    both: |t - t_ref| / (t_ref * 2 tan(fov/2) / H) (a pixel's height at distance t_ref on the
    optical axis). Below 1 the error is under a pixel's size, the criterion of Rouiller's
    Sec. 4.3 for "no visible artefacts". Returns its 99th percentile and maximum (None when no
    pixel is hit in both)."""
    t = np.asarray(t, np.float64)
    r = np.asarray(ref_t, np.float64)
    both = np.isfinite(t) & np.isfinite(r)
    if not both.any():
        return {"depth_px_p99": None, "depth_px_max": None}
    foot = r[both] * 2.0 * np.tan(np.radians(fov_y_deg) / 2.0) / height
    e = np.abs(t[both] - r[both]) / foot
    return {"depth_px_p99": float(np.quantile(e, 0.99)), "depth_px_max": float(e.max())}
