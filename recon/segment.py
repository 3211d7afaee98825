"""Former home of the tabletop masks, now in the package :mod:`recon.masks`: the method in
:mod:`recon.masks.tabletop`, the stage function in :mod:`recon.masks.views`, points triangulated
with known cameras in :mod:`recon.masks.points`; PLY points are read by
:func:`recon.io.mesh.read_points`. The names below stay importable from here for callers that
have not moved yet."""

from recon.io.mesh import read_points as read_points_ply
from recon.masks.points import triangulate_points
from recon.masks.tabletop import SegmentError, SegmentSettings, segment_tabletop
from recon.masks.views import run_tabletop_masks

__all__ = ["SegmentError", "SegmentSettings", "read_points_ply", "run_tabletop_masks", "segment_tabletop",
           "triangulate_points"]
