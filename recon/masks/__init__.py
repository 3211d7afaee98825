"""Object masks, one per view (DESIGN section 2): three kinds, one module each.

- :mod:`recon.masks.given`: a capture's own ``masks/<stem>.png``, used as they are.
- :mod:`recon.masks.falloff`: flash-falloff masks of one photo, without cameras (the flash
  lights the object far more than a background farther away).
- :mod:`recon.masks.tabletop`: an object standing on a table, apart from the table, with
  cameras and the support plane (:mod:`recon.support`).

The stage functions: :func:`run_masks` (:mod:`recon.masks.stage`, the masks stage: given or
flash-falloff masks, before any camera is known) and :func:`run_view_masks`
(:mod:`recon.masks.views`: with cameras, the support plane and the masks made again).
"""

from recon.masks.common import LUMA, MaskError
from recon.masks.falloff import NO_LIGHT, WHITE_LEVEL_KINDS, MaskSettings, derive_mask, otsu_threshold
from recon.masks.given import fit_given_mask
from recon.masks.stage import list_linear_stems, run_masks
from recon.masks.views import run_tabletop_masks, run_view_masks

__all__ = ["LUMA", "NO_LIGHT", "WHITE_LEVEL_KINDS", "MaskError", "MaskSettings", "derive_mask", "fit_given_mask",
           "list_linear_stems", "otsu_threshold", "run_masks", "run_tabletop_masks", "run_view_masks"]
