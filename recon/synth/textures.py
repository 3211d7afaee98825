"""Texture-map conventions of DESIGN section 2 in numpy: texel centers and bilinear lookups.

A map is ``(H, W, C)`` with the first row at the top. The texel in row i, column j sits at
OBJ coordinates u = (j + 0.5)/W, v = 1 - (i + 0.5)/H; lookups are bilinear between texel
centers and clamp to the edge texels outside them (Mitsuba's ``wrap_mode='clamp'``).
"""

from __future__ import annotations

import numpy as np


def texel_centers_uv(height: int, width: int) -> np.ndarray:
    """``(H, W, 2)`` OBJ (u, v) of every texel center."""
    j = (np.arange(width) + 0.5) / width
    i = (np.arange(height) + 0.5) / height
    u, v = np.meshgrid(j, 1.0 - i)
    return np.stack([u, v], axis=-1)


def uv_to_pixel(uv: np.ndarray, height: int, width: int) -> np.ndarray:
    """OBJ ``(..., 2)`` (u, v) -> continuous pixel coordinates ``(..., 2)`` (x = col, y = row),
    with texel (i, j) covering [j, j + 1] x [i, i + 1]."""
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([uv[..., 0] * width, (1.0 - uv[..., 1]) * height], axis=-1)


def bilinear_lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``texture (H, W, C)`` at OBJ ``uv (..., 2)``: ``(..., C)`` float64."""
    tex = np.asarray(texture, dtype=np.float64)
    if tex.ndim == 2:
        tex = tex[:, :, None]
    if tex.ndim != 3:
        raise ValueError(f"texture must be (H, W) or (H, W, C), got {tex.shape}")
    h, w = tex.shape[:2]
    p = uv_to_pixel(uv, h, w) - 0.5  # texel centers at integer coordinates
    x0 = np.floor(p[..., 0])
    y0 = np.floor(p[..., 1])
    fx = (p[..., 0] - x0)[..., None]
    fy = (p[..., 1] - y0)[..., None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa, xb = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    return ((1 - fy) * ((1 - fx) * tex[ya, xa] + fx * tex[ya, xb])
            + fy * ((1 - fx) * tex[yb, xa] + fx * tex[yb, xb]))
