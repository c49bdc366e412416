"""Truths for the fit's radii, written for the tests in float64 NumPy (not from jskel)."""

from __future__ import annotations

import numpy as np


def noisy_cylinder(seed: int = 11, n: int = 3000, radius: float = 0.3, noise: float = 0.02):
    """(points (n, 3), their radial distances (n,)): a cylinder about the y axis from 0 to 2,
    sampled uniformly in y over [0.15, 1.85] and in angle, with Gaussian radial noise."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(0.15, 1.85, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    rho = radius + noise * rng.normal(size=n)
    return np.column_stack([rho * np.cos(phi), y, rho * np.sin(phi)]), rho


def expectile(rho: np.ndarray, w: float) -> float:
    """The r with w * sum (rho - r)+ = sum (r - rho)+ (the w / (1 + w) expectile), by bisection."""
    lo, hi = rho.min(), rho.max()
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if w * np.sum(np.maximum(rho - mid, 0)) > np.sum(np.maximum(mid - rho, 0)) else (lo, mid)
    return 0.5 * (lo + hi)
