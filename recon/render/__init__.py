"""Differentiable rendering under a collocated point light (DESIGN section 3).

Public API: :class:`RenderSettings`, :class:`CollocatedRenderer` (``render``, ``render_batch``,
``render_torch``).
"""

from recon.render.collocated import CollocatedRenderer, RenderError, RenderSettings

__all__ = ["CollocatedRenderer", "RenderError", "RenderSettings"]
