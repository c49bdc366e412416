"""Colour textures shared by the representations: loading and bilinear sampling."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import checks

BUILTIN = ("checker", "brick", "gravel", "grass")


def load_texture(name: str, path: str = "object.texture") -> np.ndarray:
    """(H, W, 3) linear RGB in [0, 1] from an image file, ``checker`` (8 x 8 squares) or one of
    scikit-image's texture photographs (``brick``, ``gravel``, ``grass``)."""
    if name == "checker":
        i = np.arange(64) // 8
        c = ((i[:, None] + i[None, :]) % 2).astype(np.float64)
        img = np.stack([0.9 * c + 0.1] * 3, -1) * np.array([1.0, 0.9, 0.75])
        return img**2.2
    if name in BUILTIN:
        import skimage.data

        img = np.asarray(getattr(skimage.data, name)(), np.float64)
    else:
        import imageio.v3 as iio

        try:
            img = np.asarray(iio.imread(name)).astype(np.float64)
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
            raise ValueError(f"{path}: cannot read image {name!r} (or name one of {', '.join(BUILTIN)}): {e}") from None
    if img.ndim == 2:
        img = np.stack([img] * 3, -1)
    img = finite_texels(img[..., :3], path, name)
    img = img / (255.0 if img.max() > 1.0 else 1.0)
    return img**2.2  # sRGB-ish to linear


def finite_texels(img: np.ndarray, path: str, name: str) -> np.ndarray:
    """``img`` (H, W, ...) if every texel is finite, else a ``ValueError`` naming the key, the
    file, and the bad texels by (row, column) with their values and count: a float image (TIFF,
    EXR, HDR) holding a NaN or an infinity would otherwise become a silent colour or height."""
    a = np.asarray(img, np.float64)
    bad = ~np.all(np.isfinite(a.reshape(a.shape[0], a.shape[1], -1)), axis=-1)
    if not bad.any():
        return img
    rc = np.argwhere(bad)
    vals = [a[r, c] for r, c in rc[:checks.SHOW]]
    raise ValueError("\n".join(checks.at(f"{path} ({name!r})", "not finite", rc, vals, "texels", count=len(rc))))


def bilinear_wrap(tex, uv, size=None):
    """Bilinear sample of (H, W, C) ``tex`` at ``uv`` (2,), both coordinates wrapping; ``size``
    (2,) int (h, w) samples only the top-left h x w texels (a texture padded into a stack)."""
    h, w = (tex.shape[0], tex.shape[1]) if size is None else (size[0], size[1])
    x = uv[0] * w - 0.5
    y = uv[1] * h - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx, fy = x - x0, y - y0
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)

    def at(yy, xx):
        return tex[jnp.mod(yy, h), jnp.mod(xx, w)]

    return (
        (1 - fx) * (1 - fy) * at(y0, x0)
        + fx * (1 - fy) * at(y0, x0 + 1)
        + (1 - fx) * fy * at(y0 + 1, x0)
        + fx * fy * at(y0 + 1, x0 + 1)
    )


RELIEF_TEXTURES = ("brick", "gravel", "grass")


def load_height_map(name: str, field: str = "object.relief.map") -> np.ndarray:
    """An 8-bit height map (a frusta relief's, an implicit displacement's): a scikit-image
    texture photograph by name, or an image file; a ValueError naming ``field`` otherwise."""
    if name in RELIEF_TEXTURES:
        import skimage.data

        img = np.asarray(getattr(skimage.data, name)())
    else:
        import imageio.v3 as iio

        try:
            img = np.asarray(iio.imread(name))
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
            raise ValueError(f"{field}: cannot read image {name!r} (or name one of {', '.join(RELIEF_TEXTURES)}): {e}") from None
    if img.ndim >= 2 and img.dtype.kind == "f":
        finite_texels(img, field, name)
    if img.ndim == 3:
        img = img[..., :3].mean(-1)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        hi = img.max()
        img = np.round(255.0 * img / (hi if hi > 1.0 else 1.0))
    if img.ndim != 2 or min(img.shape) < 2:
        raise ValueError(f"{field}: need a 2D image of at least 2x2 texels (got shape {img.shape})")
    return np.clip(img, 0, 255).astype(np.uint8)
