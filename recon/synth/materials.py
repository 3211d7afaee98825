"""Procedural spatially varying materials: 3D fields of diffuse albedo, specular albedo, roughness.

Each of the three quantities has its own partition of space into clearly different regions,
so that a reconstruction can be judged on each separately:

- diffuse: Voronoi cells of the direction from the center (4 colours), times a high-frequency
  pattern (mild fractal shading and random dark or light dots of radius 0.35-0.7 / frequency,
  one per 3D grid cell of size 1 / frequency) that gives SIFT features to register the views;
- specular: three bands along a tilted axis (a_s = 0.03, 0.25, 0.6, in a seeded order);
- roughness: three sectors around another axis (r = 0.18, 0.4, 0.75, in a seeded order).

Values are linear, inside [0, 1] and roughness inside [R_MIN, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.synth.noise import dots, fbm

DIFFUSE_PALETTE = np.array([
    [0.62, 0.26, 0.12],  # terracotta
    [0.10, 0.36, 0.42],  # teal
    [0.58, 0.47, 0.12],  # ochre
    [0.52, 0.52, 0.50],  # light grey
])
PALETTES = {
    "default": DIFFUSE_PALETTE,
    # the colours of the wooden table (recon.synth.tabletop.table_texture spans dark [0.20, 0.11,
    # 0.05] to light [0.56, 0.38, 0.21]): an object that a colour model cannot tell from the table
    "wood": np.array([[0.50, 0.33, 0.17], [0.30, 0.18, 0.08], [0.42, 0.27, 0.13], [0.56, 0.39, 0.22]]),
    # glazes of a ceramic: cream, blue, orange (close to the table's light wood) and a light cream
    "glaze": np.array([[0.72, 0.64, 0.48], [0.12, 0.20, 0.42], [0.62, 0.33, 0.11], [0.80, 0.74, 0.60]]),
    # a dark object: black and dark brown glazes (albedo 2-6 %)
    "dark": np.array([[0.035, 0.03, 0.028], [0.06, 0.04, 0.025], [0.03, 0.035, 0.04], [0.05, 0.05, 0.05]]),
}
"""Four diffuse colours each (the Voronoi cells of :class:`MaterialFields`); ``default`` is the
generator's palette, the others make objects whose colours a table or a backdrop shares."""
SPECULAR_LEVELS = np.array([0.03, 0.25, 0.6])
ROUGHNESS_LEVELS = np.array([0.18, 0.4, 0.75])


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class MaterialFields:
    """Seeded material fields; call :meth:`evaluate` at 3D points of the object.

    ``frequency`` sets the scale of the albedo pattern: about one dot per (1/frequency)^3 of
    space, dots 0.7-1.4 / frequency across (the object spans about 2 units). At 192 x 144 px,
    frequency 16 gave ~50 verified SIFT matches between views 28 degrees apart.

    ``palette``: a key of :data:`PALETTES` (the four cell colours).

    ``albedo``, ``specular``, ``roughness``: when set, that quantity is this constant everywhere
    instead of its field (``albedo`` scales nothing: a grey a_d = albedo, pattern and all gone);
    e.g. ``specular=0`` makes a purely diffuse object, ``roughness=1`` a fully rough one.
    """

    seed: int = 0
    frequency: float = 16.0
    pattern: bool = True
    albedo: float | None = None
    specular: float | None = None
    roughness: float | None = None
    palette: str = "default"

    def _rng(self) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([int(self.seed), 0x3A7]))

    def evaluate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fields at ``points (N, 3)``: ``a_d (N, 3)``, ``a_s (N, 1)``, ``r (N, 1)`` float64."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        rng = self._rng()
        d = _unit(p)
        # -- diffuse: Voronoi cells of directions, a permuted palette --
        seeds = _unit(rng.normal(size=(4, 3)))
        palette = PALETTES[self.palette][rng.permutation(4)]
        cell = np.argmax(d @ seeds.T, axis=1)
        a_d = palette[cell]
        if self.pattern:
            # mild fractal shading plus random dark and light dots (SIFT blobs)
            t = 0.5 + 0.5 * fbm(p, self.frequency / 3.0, octaves=2, seed=self.seed + 1)
            shade = 0.6 + 0.4 * np.clip((t - 0.25) / 0.5, 0.0, 1.0)
            inside, level = dots(p, 1.0 / self.frequency, seed=self.seed + 2)
            dot = np.where(level < 0.6, 0.12 + 0.2 * level, 1.5 + 0.5 * level)
            shade = shade * np.where(inside, dot, 1.0)
            a_d = a_d * shade[:, None]
        # -- specular: bands along a tilted axis --
        axis_s = _unit(np.array([rng.normal(0, 0.4), rng.normal(0, 0.4), 1.0]))
        h = p @ axis_s
        band = np.digitize(h, [-0.25, 0.3])
        a_s = SPECULAR_LEVELS[rng.permutation(3)][band][:, None]
        # -- roughness: sectors around another axis --
        axis_r = _unit(rng.normal(size=3))
        e1 = _unit(np.cross(axis_r, [0.0, 0.0, 1.0] if abs(axis_r[2]) < 0.9 else [1.0, 0, 0]))
        e2 = np.cross(axis_r, e1)
        ang = np.arctan2(p @ e2, p @ e1) + rng.uniform(0, 2 * np.pi)
        sector = (np.floor(np.mod(ang, 2 * np.pi) / (2 * np.pi / 3))).astype(int) % 3
        r = ROUGHNESS_LEVELS[rng.permutation(3)][sector][:, None]
        if self.albedo is not None:
            a_d = np.full_like(a_d, float(self.albedo))
        if self.specular is not None:
            a_s = np.full_like(a_s, float(self.specular))
        if self.roughness is not None:
            r = np.full_like(r, float(self.roughness))
        return np.clip(a_d, 0.0, 1.0), a_s, r
