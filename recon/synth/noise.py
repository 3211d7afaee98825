"""Deterministic 3D value noise (numpy), the source of procedural detail in synthetic objects.

All functions are pure: the same points and seed give the same values on every machine
(integer hashing, float64 arithmetic, no threads).
"""

from __future__ import annotations

import numpy as np

_TABLE = 256


def _tables(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
    perm = rng.permutation(_TABLE).astype(np.int64)
    values = rng.uniform(-1.0, 1.0, _TABLE)
    return perm, values


def value_noise(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth lattice value noise at ``points (N, 3)`` (unit lattice spacing): ``(N,)`` in [-1, 1].

    Values at integer lattice points are pseudo-random; between them a quintic fade makes the
    field C2-continuous. The pattern repeats every 256 units.
    """
    p = np.asarray(points, dtype=np.float64)
    perm, values = _tables(seed)
    base = np.floor(p)
    f = p - base
    i = base.astype(np.int64)
    w = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)  # quintic fade
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        hx = perm[(i[:, 0] + dx) & 255]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            hy = perm[(hx + i[:, 1] + dy) & 255]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                h = perm[(hy + i[:, 2] + dz) & 255]
                out += wx * wy * wz * values[h]
    return out


def fbm(points: np.ndarray, frequency: float, octaves: int = 4, seed: int = 0,
        gain: float = 0.5, lacunarity: float = 2.0) -> np.ndarray:
    """Fractal sum of :func:`value_noise`, normalized to [-1, 1]: ``(N,)`` from ``(N, 3)``."""
    p = np.asarray(points, dtype=np.float64)
    total = np.zeros(len(p))
    norm = 0.0
    amp, freq = 1.0, float(frequency)
    for k in range(int(octaves)):
        # a per-octave offset keeps lattice points of different octaves apart
        total += amp * value_noise(p * freq + 17.31 * (k + 1), seed + 101 * k)
        norm += amp
        amp *= gain
        freq *= lacunarity
    return total / norm


def cell_hash(cells: np.ndarray, seed: int, k: int) -> np.ndarray:
    """Deterministic uniform numbers in [0, 1) per integer cell ``(N, 3)`` (channel ``k``)."""
    c = np.asarray(cells, dtype=np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        h = (c[:, 0] * np.uint64(73856093)) ^ (c[:, 1] * np.uint64(19349663)) \
            ^ (c[:, 2] * np.uint64(83492791))
        h ^= np.uint64((int(seed) * 2654435761 + int(k) * 40503 + 12345) % 2**64)
        for _ in range(2):  # splitmix-style finalizer
            h ^= h >> np.uint64(31)
            h *= np.uint64(0xBF58476D1CE4E5B9)
            h ^= h >> np.uint64(29)
    return (h >> np.uint64(40)).astype(np.float64) / float(1 << 24)


def dots(points: np.ndarray, cell: float, seed: int = 0, radius=(0.35, 0.7)):
    """Random balls on a jittered 3D grid (one per cell of size ``cell``), seen on a surface.

    Returns
    -------
    inside : (N,) bool
        The point lies in some ball.
    level : (N,) float
        Uniform [0, 1) number of the nearest-center ball containing the point (0 outside).
    """
    p = np.asarray(points, dtype=np.float64)
    base = np.floor(p / cell).astype(np.int64)
    best = np.full(len(p), np.inf)
    level = np.zeros(len(p))
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                c = base + np.array([dx, dy, dz])
                center = (c + np.stack([cell_hash(c, seed, k) for k in range(3)], 1)) * cell
                rad = (radius[0] + (radius[1] - radius[0]) * cell_hash(c, seed, 3)) * cell
                d = np.linalg.norm(p - center, axis=1) / rad
                take = (d < 1.0) & (d < best)
                best = np.where(take, d, best)
                level = np.where(take, cell_hash(c, seed, 4), level)
    return np.isfinite(best), level
