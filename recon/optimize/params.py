"""Parameterizations of the texture maps: unconstrained tensors <-> values in their valid ranges.

Diffuse and specular albedo live in [0, 1], roughness in [r_min, 1]. Two choices:

- ``sigmoid``: value = lo + (hi - lo) * sigmoid(x). Always in range; the gradient is finite
  everywhere (it vanishes smoothly at the ends). Values at exactly lo/hi are stored as the
  logits of lo + eps / hi - eps (eps = 1e-4 of the range).
- ``clamp``: value = x, projected back into [lo, hi] after each optimizer step
  (:meth:`Parameterization.project_`). Identity gradient; the ends are reachable exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

EPS = 1e-4


@dataclass(frozen=True)
class Parameterization:
    """Maps a raw tensor to values in ``[lo, hi]``; ``kind`` is "sigmoid" or "clamp"."""

    lo: float = 0.0
    hi: float = 1.0
    kind: str = "sigmoid"

    def __post_init__(self):
        if not self.hi > self.lo:
            raise ValueError(f"need hi > lo, got [{self.lo}, {self.hi}]")
        if self.kind not in ("sigmoid", "clamp"):
            raise ValueError(f"kind must be 'sigmoid' or 'clamp', got {self.kind!r}")

    def value(self, raw: torch.Tensor) -> torch.Tensor:
        """Values in ``[lo, hi]`` (differentiable), same shape as ``raw``."""
        if self.kind == "sigmoid":
            return self.lo + (self.hi - self.lo) * torch.sigmoid(raw)
        return raw.clamp(self.lo, self.hi)

    def raw(self, value) -> torch.Tensor:
        """Inverse of :meth:`value` (values outside the range are clipped into it first)."""
        if isinstance(value, torch.Tensor):
            v = value.detach().to(torch.float32)
        else:  # a copy: maps may be read-only numpy views (np.broadcast_to of a uniform value)
            v = torch.from_numpy(np.array(value, dtype=np.float32))
        if self.kind == "sigmoid":
            t = ((v - self.lo) / (self.hi - self.lo)).clamp(EPS, 1 - EPS)
            return torch.log(t) - torch.log1p(-t)
        return v.clamp(self.lo, self.hi).clone()

    @torch.no_grad()
    def project_(self, raw: torch.Tensor) -> None:
        """Keep ``raw`` in range in place after a step (only "clamp" needs it)."""
        if self.kind == "clamp":
            raw.clamp_(self.lo, self.hi)


def albedo_param(kind: str = "sigmoid") -> Parameterization:
    return Parameterization(0.0, 1.0, kind)


def roughness_param(r_min: float, kind: str = "sigmoid") -> Parameterization:
    return Parameterization(float(r_min), 1.0, kind)


def constant_map(size: int, channels: int, value) -> np.ndarray:
    """A ``(size, size, channels)`` float32 map filled with ``value`` (the paper's initial maps):
    a number, or one value per channel."""
    v = np.broadcast_to(np.asarray(value, dtype=np.float32).reshape(-1), (int(channels),))
    return np.broadcast_to(v, (int(size), int(size), int(channels))).copy()


class TexturePyramid:
    """A texture map as a sum of bilinearly upsampled levels (full size, 1/2, 1/4, ...).

    ``raw = P_0 + sum_l up(P_l)``: the map can still take any value per texel (P_0), but the
    coarse levels receive the summed gradient of every texel they cover, so low-frequency
    content (a specular level seen only in a few highlights, say) is learned from the whole
    neighbourhood instead of texel by texel. ``levels = 1`` is a plain texel map.

    Parameters
    ----------
    raw : (T, T, C) tensor, the initial raw (parameterized) map; coarse levels start at zero.
    levels : number of levels; sizes T, T/2, ... stop above 4 texels.
    """

    def __init__(self, raw: torch.Tensor, levels: int = 1):
        if raw.ndim != 3:
            raise ValueError(f"raw must be (T, T, C), got {tuple(raw.shape)}")
        T, _, C = raw.shape
        self.size = int(T)
        self.levels = [raw.detach().to(torch.float32).clone().requires_grad_(True)]
        s = T // 2
        while len(self.levels) < int(levels) and s >= 4:
            self.levels.append(torch.zeros((s, s, C), dtype=torch.float32, requires_grad=True))
            s //= 2

    def full(self) -> torch.Tensor:
        """(T, T, C) raw map, differentiable w.r.t. every level."""
        out = self.levels[0]
        for lv in self.levels[1:]:
            up = torch.nn.functional.interpolate(lv.permute(2, 0, 1)[None], size=(self.size, self.size),
                                                 mode="bilinear", align_corners=False)
            out = out + up[0].permute(1, 2, 0)
        return out

    def parameters(self) -> list[torch.Tensor]:
        return list(self.levels)

    @torch.no_grad()
    def project_(self, param: Parameterization) -> None:
        """Keep the summed raw map in range ("clamp" parameterization) by adjusting the finest level."""
        if param.kind != "clamp":
            return
        full = self.full()
        self.levels[0].add_(full.clamp(param.lo, param.hi) - full)

    def state(self) -> list[torch.Tensor]:
        return [lv.detach().clone() for lv in self.levels]

    @staticmethod
    def from_state(levels: list[torch.Tensor]) -> "TexturePyramid":
        p = TexturePyramid(levels[0], 1)
        p.levels += [lv.detach().to(torch.float32).clone().requires_grad_(True) for lv in levels[1:]]
        return p
