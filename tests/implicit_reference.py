"""Independent float64 NumPy root finding for skeletal implicit surfaces (tests only).

F(x) = sum_i (1 - r_i^2 / R_i^2)^2 over primitives within R_i (Rouiller 2011, Sec. 3), r_i the
distance to a point or to a segment with R interpolated along it. The first root of F = T along a
ray is found by dense uniform sampling of the ray's interval inside the union of influence
spheres, then 60 bisections of the first bracket.
"""

from __future__ import annotations

import numpy as np


def field(x, a, b, ra, rb):
    """x (..., 3) -> F (...). Written per coordinate: (..., P) arrays, the sums over the three
    coordinates in the order ``np.sum`` takes them (x + y, then + z)."""
    ab = b - a
    ax = [x[..., None, k] - a[:, k] for k in range(3)]
    den = ab[:, 0] * ab[:, 0] + ab[:, 1] * ab[:, 1] + ab[:, 2] * ab[:, 2]
    dot = ax[0] * ab[:, 0] + ax[1] * ab[:, 1] + ax[2] * ab[:, 2]
    s = np.clip(np.where(den > 0, dot / np.where(den > 0, den, 1.0), 0.0), 0.0, 1.0)
    d = [ax[k] - s * ab[:, k] for k in range(3)]
    r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    R = ra + (rb - ra) * s
    q = np.where(R > 0, r2 / np.where(R > 0, R * R, 1.0), 1.0)
    return np.sum(np.where(q < 1, (1 - q) ** 2, 0.0), -1)


def interval(O, D, a, b, ra, rb):
    c = 0.5 * (a + b)
    rad = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(ra, rb)
    oc = c[None] - O[:, None]
    tc = np.sum(oc * D[:, None], -1)
    d2 = np.sum(oc * oc, -1) - tc * tc
    half = np.sqrt(np.maximum(rad**2 - d2, 0))
    hit = d2 < rad**2
    lo = np.where(hit, np.maximum(tc - half, 0.0), np.inf).min(1)
    hi = np.where(hit, tc + half, -np.inf).max(1)
    return lo, hi


def first_root(O, D, a, b, ra, rb, T, n=512, batch=1000):
    """(t, margin, slope): first root t (inf if none); margin = T - max F sampled before the root
    (or along the whole ray on a miss); slope = |dF/dt| at the root (finite differences)."""
    N = O.shape[0]
    # rays per pass: at most ``batch``, and at most about 128k samples, so a pass's (rays,
    # samples, primitives) temporaries stay in cache (2,000 rays of 257 samples ran twice as
    # slow as 500); every ray's arithmetic is the same whatever the pass holds
    batch = max(1, min(batch, (1 << 17) // (n + 1)))
    t_out = np.full(N, np.inf)
    margin = np.full(N, np.inf)
    slope = np.zeros(N)
    lo, hi = interval(O, D, a, b, ra, rb)
    u = np.linspace(0, 1, n + 1)
    for i in range(0, N, batch):
        sl = slice(i, i + batch)
        ok = hi[sl] > lo[sl]
        l, h = np.where(ok, lo[sl], 0), np.where(ok, hi[sl], 1)
        ts = l[:, None] + (h - l)[:, None] * u[None]
        F = field(O[sl, None] + ts[..., None] * D[sl, None], a, b, ra, rb)
        inside = (F > T) & ok[:, None]
        found = inside.any(1)
        k = np.argmax(inside, 1)
        # leave out the approach to the root itself (0.05 long) so margin measures grazing
        m = np.ceil(0.05 / np.maximum((h - l) / n, 1e-12)).astype(int)
        before = np.where(np.arange(n + 1)[None] < np.where(found, k - m, n + 1)[:, None], F, -np.inf)
        margin[sl] = T - before.max(1)
        rows = np.arange(ts.shape[0])
        tl, th = ts[rows, np.maximum(k - 1, 0)], ts[rows, k]
        for _ in range(60):
            m = 0.5 * (tl + th)
            fin = field(O[sl] + m[:, None] * D[sl], a, b, ra, rb) > T
            th = np.where(fin, m, th)
            tl = np.where(fin, tl, m)
        t = 0.5 * (tl + th)
        eps = 1e-6
        g = (field(O[sl] + (t + eps)[:, None] * D[sl], a, b, ra, rb) - field(O[sl] + (t - eps)[:, None] * D[sl], a, b, ra, rb)) / (2 * eps)
        t_out[sl] = np.where(found & (k > 0), t, np.where(found, l, np.inf))
        slope[sl] = np.abs(g)
    return t_out, margin, slope


def first_root_near(O, D, a, b, ra, rb, T, h):
    """:func:`first_root` for models of many primitives: each ray sums only the primitives
    whose sphere of influence its line crosses (a kernel is 0 outside it, so F is the same),
    sampled every ``h`` at most along its interval (so that a chord or a bump between two
    samples is shorter than h wherever the ray is long). Returns (t, margin, slope) as
    :func:`first_root`."""
    N = O.shape[0]
    c = 0.5 * (a + b)
    rad = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(ra, rb)
    t_out, margin, slope = np.full(N, np.inf), np.full(N, np.inf), np.zeros(N)
    step = 256
    for i in range(0, N, step):
        sl = slice(i, min(i + step, N))
        oc = c[None] - O[sl, None]
        tc = np.sum(oc * D[sl, None], -1)
        d2 = np.sum(oc * oc, -1) - tc * tc
        near = d2 < rad[None] ** 2 * 1.0001
        for j, row in zip(range(sl.start, sl.stop), near):
            idx = np.nonzero(row)[0]
            if idx.size == 0:
                continue
            lo, hi = interval(O[j:j + 1], D[j:j + 1], a[idx], b[idx], ra[idx], rb[idx])
            n = int(np.clip(np.ceil((hi[0] - lo[0]) / h), 64, 1 << 16)) if hi[0] > lo[0] else 64
            t, m, s = first_root(O[j:j + 1], D[j:j + 1], a[idx], b[idx], ra[idx], rb[idx], T, n=n)
            t_out[j], margin[j], slope[j] = t[0], m[0], s[0]
    return t_out, margin, slope
