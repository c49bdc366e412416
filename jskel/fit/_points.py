"""The points a skeleton is fitted to (issue 10): a cloud read from a file, or sampled uniformly
from a known skeleton's surface (:func:`sample_surface`) with noise and outliers
(``points.synthetic``), with the facts that ``fit.json`` reports about them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import checks, frusta
from ..config import ConfigError
from ._config import PointsConfig
from ._distance import segments_of


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
        if cfg.nonfinite == "reject":  # each bad point by its index in the cloud and its value (jskel.checks)
            field = "points.file" if cfg.synthetic is None else "points.synthetic"
            raise ConfigError([line + "; set points.nonfinite: drop to drop them" for line in checks.nonfinite(field, pts, f"of {len(pts)} points")])
        pts = pts[~bad]
        info["dropped_nonfinite"] = int(bad.sum())
    info["points"] = int(len(pts))
    return pts, info, truth


def sample_surface(joints, radii, parents, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points spread uniformly over the skeleton's surface (host, float64), for
    synthetic studies: lateral surfaces by area and caps by area, rejected where a sample lies
    outside its segment's planes or inside another segment (the host build's geometry)."""
    a, _, _ = frusta.frusta_from_skeleton(joints, radii, parents, path="points.synthetic.skeleton")
    bands = _lateral_bands(a)
    caps_b = np.where(a.cap_b, np.pi * a.r1**2, 0.0)
    caps_t = np.where(a.cap_t, np.pi * a.r2**2, 0.0)
    areas = np.concatenate([bands[-1], caps_b, caps_t])
    out = []
    need = count
    while need > 0:
        m = max(4 * need, 256)
        p, i = _proposals(a, bands, areas, m, rng)
        q = p - a.c1[i]
        tol = 1e-9 * (1 + np.abs(a.h[i]))
        ok = (np.sum(a.nb[i] * q, -1) >= a.db[i] - tol) & (np.sum(a.nt[i] * q, -1) <= a.dt[i] + tol)
        ok &= ~_inside_another(a, bands[0], p, i)
        got = p[ok][:need]
        out.append(got)
        need -= got.shape[0]
    return np.concatenate(out)


def _lateral_bands(a):
    """Per segment of the host frusta ``a``: (slope k, axial range y_lo, y_hi of the proposal,
    radii there, lateral area of that cone band).

    The lateral surface between tilted planes reaches past y in [0, h] on the outer side of a
    bend (an earlier version sampled y in [0, h] only and left that sliver bare): propose y
    over the cuts' whole axial extent, uniformly by area, and reject what lies outside the
    planes (rejection from a uniform proposal keeps the accepted points uniform)."""
    k = (a.r2 - a.r1) / a.h

    def extent(n, d):
        nm = np.sum(n * a.m, -1)
        ns = np.sqrt(np.maximum(1.0 - nm * nm, 0.0))
        y1 = (d - a.r1 * ns) / np.maximum(nm + k * ns, 1e-9)
        y2 = (d + a.r1 * ns) / np.maximum(nm - k * ns, 1e-9)
        return np.minimum(y1, y2), np.maximum(y1, y2)

    y_lo = np.minimum(extent(a.nb, a.db)[0], 0.0)
    y_hi = np.maximum(extent(a.nt, a.dt)[1], a.h)
    # keep the proposal on the cone's nappe (r >= 0)
    y_lo = np.where(k > 0, np.maximum(y_lo, -a.r1 / np.where(k > 0, k, 1.0)), y_lo)
    y_hi = np.where(k < 0, np.minimum(y_hi, -a.r1 / np.where(k < 0, k, -1.0)), y_hi)
    r_lo, r_hi = a.r1 + k * y_lo, a.r1 + k * y_hi
    slant = np.sqrt(1.0 + k * k) * (y_hi - y_lo)
    return k, y_lo, y_hi, r_lo, r_hi, np.pi * (r_lo + r_hi) * slant


def _proposals(a, bands, areas, m: int, rng: np.random.Generator):
    """``m`` proposals (m,3) uniform by area over the lateral bands and the caps (``areas``: the
    S bands, then the S bottom and S top caps), and each one's segment (m,)."""
    s = a.h.shape[0]
    _, y_lo, y_hi, r_lo, r_hi, _ = bands
    pick = rng.choice(areas.size, size=m, p=areas / areas.sum())
    i = pick % s
    kind = pick // s
    phi = rng.uniform(0, 2 * np.pi, m)
    e = np.cos(phi)[:, None] * a.u[i] + np.sin(phi)[:, None] * a.w[i]
    # lateral: y with density proportional to the local radius (area of a cone band)
    u = rng.uniform(0, 1, m)
    ra, rb, ya, yb = r_lo[i], r_hi[i], y_lo[i], y_hi[i]
    sloped = np.abs(rb - ra) > 1e-12
    rr = np.sqrt(ra**2 + u * (rb**2 - ra**2))
    y = ya + np.where(sloped, (rr - ra) / np.where(sloped, rb - ra, 1.0), u) * (yb - ya)
    rad = np.where(sloped, rr, ra)
    r1, r2 = a.r1[i], a.r2[i]
    p_lat = a.c1[i] + y[:, None] * a.m[i] + rad[:, None] * e
    rc = np.sqrt(rng.uniform(0, 1, m))
    p_bot = a.c1[i] + (rc * r1)[:, None] * e
    p_top = a.c1[i] + a.h[i][:, None] * a.m[i] + (rc * r2)[:, None] * e
    return np.where((kind == 0)[:, None], p_lat, np.where((kind == 1)[:, None], p_bot, p_top)), i


def _inside_another(a, k, p, i) -> np.ndarray:
    """(m,) whether each point ``p`` lies strictly inside a segment other than its own ``i``
    (proposals x segments, in blocks: at 500 segments and 400,000 proposals one float64 block
    of (proposals, segments, 3) is 4.8 GB)."""
    s = a.h.shape[0]
    out = np.zeros(p.shape[0], bool)
    block = max(1, (1 << 21) // s)
    for b0 in range(0, p.shape[0], block):  # host loop over proposal blocks (bounded memory)
        sl = slice(b0, b0 + block)
        qa = p[sl, None, :] - a.c1[None]
        ya = np.sum(qa * a.m[None], -1)
        rho = np.linalg.norm(qa - ya[..., None] * a.m[None], axis=-1)
        inside = (rho < (a.r1 + k * ya) - 1e-9) & (np.sum(a.nb[None] * qa, -1) > a.db + 1e-9) & (np.sum(a.nt[None] * qa, -1) < a.dt - 1e-9)
        inside[np.arange(inside.shape[0]), i[sl]] = False
        out[sl] = inside.any(axis=1)
    return out
