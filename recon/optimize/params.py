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
        v = torch.as_tensor(np.asarray(value, dtype=np.float32))
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


def constant_map(size: int, channels: int, value: float) -> np.ndarray:
    """A ``(size, size, channels)`` float32 map filled with ``value`` (the paper's initial maps)."""
    return np.full((int(size), int(size), int(channels)), float(value), dtype=np.float32)
