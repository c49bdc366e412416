"""A contact sheet of a render's AOVs: ``jskel render EXP --out DIR --aov-sheet`` -> DIR/aov_sheet.png.

Six panels in two rows, read back from the files the render wrote (so the sheet shows exactly
what is on disk): the image; depth, nearest bright (255) to farthest dark (55), misses black;
normals as (n + 1) / 2 in RGB; uv as the fractional parts of u and v in red and green; ids, a
colour per primitive (misses black); flags, a colour per flag value (0 dark grey). Panels are
placed pixel for pixel (nearest-neighbour enlarged by an integer factor so labels fit), the
labels in strips between them (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

PANELS = ("image", "depth", "normals", "uv", "ids", "flags")
LABELS = {"image": "image", "depth": "depth (near bright)", "normals": "normals (n+1)/2", "uv": "uv (fractional)",
          "ids": "ids (prim)", "flags": "flags"}
MIN_PANEL = 160  # pixels: panels narrower than this are enlarged by an integer factor
PAD, LABEL = 4, 18  # pixels between panels, label strip height
NO_FLAGS = 40  # grey of a pixel without flags


class Layout(NamedTuple):
    """Where each panel lies on the sheet: ``scale`` (integer enlargement), the panel size
    (h, w) after it, the sheet's (height, width) and each panel's top-left (row, col) pixel."""

    scale: int
    panel: tuple[int, int]
    size: tuple[int, int]
    origin: dict


def layout(height: int, width: int) -> Layout:
    """The sheet's layout for AOVs of ``height`` x ``width`` pixels: three panels a row."""
    k = max(1, -(-MIN_PANEL // width))
    h, w = height * k, width * k
    origin = {name: (LABEL + (i // 3) * (LABEL + h + PAD), PAD + (i % 3) * (w + PAD)) for i, name in enumerate(PANELS)}
    return Layout(k, (h, w), (2 * (LABEL + h + PAD) + PAD, 3 * w + 4 * PAD), origin)


def hash_colors(values: np.ndarray) -> np.ndarray:
    """A colour (uint8 RGB, each channel 64..255) per integer value, the same value always the same colour."""
    x = (values.astype(np.uint64) * np.uint64(2654435761)) % np.uint64(1 << 32)
    ch = np.stack([(x >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)], axis=-1).astype(np.float64)
    return (64 + np.round(ch * 191 / 255)).astype(np.uint8)


def depth_panel(depth: np.ndarray) -> np.ndarray:
    """Grey from 255 (nearest hit) to 55 (farthest), misses (non-finite) black."""
    hit = np.isfinite(depth)
    out = np.zeros(depth.shape + (3,), np.uint8)
    if hit.any():
        d = depth[hit].astype(np.float64)
        span = d.max() - d.min()
        v = (d - d.min()) / span if span > 0 else np.zeros_like(d)
        out[hit] = np.round(255 - 200 * v)[:, None].astype(np.uint8)
    return out


def panels_of(image, depth, normal, uv, prim, flags=None) -> dict:
    """The six panels (H, W, 3) uint8 of one render's outputs: ``image`` (H, W, 3) uint8,
    ``depth`` (H, W) (+inf on a miss), ``normal`` (H, W, 3), ``uv`` (H, W, 2), ``prim`` (H, W)
    (-1 on a miss), ``flags`` (H, W) or None (none recorded: every pixel grey)."""
    depth = np.asarray(depth)
    hit = np.isfinite(depth)[..., None]
    normal = np.asarray(normal, np.float64)
    uv = np.asarray(uv, np.float64)
    prim = np.asarray(prim)
    flags = np.zeros(depth.shape, np.int32) if flags is None else np.asarray(flags)
    uv_rgb = np.concatenate([uv - np.floor(uv), np.zeros(uv.shape[:-1] + (1,))], axis=-1)
    return {
        "image": np.asarray(image)[..., :3],
        "depth": depth_panel(depth),
        "normals": np.where(hit, np.round(np.clip(normal * 0.5 + 0.5, 0, 1) * 255), 0).astype(np.uint8),
        "uv": np.where(hit, np.round(np.clip(uv_rgb, 0, 1) * 255), 0).astype(np.uint8),
        "ids": np.where((prim >= 0)[..., None], hash_colors(np.maximum(prim, 0)), 0).astype(np.uint8),
        "flags": np.where((flags != 0)[..., None], hash_colors(flags), NO_FLAGS).astype(np.uint8),
    }


def panels(folder) -> dict:
    """The six panels (H, W, 3) uint8 of the AOV files in ``folder``."""
    import imageio.v3 as iio

    f = Path(folder)
    flags = np.load(f / "flags.npy") if (f / "flags.npy").exists() else None
    return panels_of(iio.imread(f / "image.png"), np.load(f / "depth.npy"), np.load(f / "normal.npy"), np.load(f / "uv.npy"),
                     np.load(f / "prim.npy"), flags)


def aov_sheet(folder, name: str = "aov_sheet.png") -> Path:
    """Write the contact sheet of the AOVs in ``folder`` (as ``write_aovs`` left them) to
    ``folder/name``; returns its path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    p = panels(folder)
    lay = layout(*p["image"].shape[:2])
    dpi = 100
    fig = Figure(figsize=(lay.size[1] / dpi, lay.size[0] / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    for key, (r, c) in lay.origin.items():
        big = np.repeat(np.repeat(p[key], lay.scale, axis=0), lay.scale, axis=1)
        # figimage's offsets run from the sheet's bottom-left corner to the panel's
        fig.figimage(big, xo=c, yo=lay.size[0] - r - lay.panel[0], origin="upper")
        label = LABELS[key] if key != "flags" or (Path(folder) / "flags.npy").exists() else "flags (none recorded)"
        fig.text(c / lay.size[1], 1 - (r - 4) / lay.size[0], label, fontsize=9, va="bottom", ha="left")
    out = Path(folder) / name
    fig.savefig(out, dpi=dpi, facecolor="white")
    return out
