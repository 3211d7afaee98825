"""DNG opcode lists in the linearize stage (DNG specification 1.6, chapter 7).

Phones store their lens-shading (vignetting and colour-shading) correction in the DNG instead
of applying it: GainMap opcodes (ID 9) in OpcodeList2, one map per Bayer colour (row and column
pitch 2), applied to the linear reference values (after the LinearizationTable, the black level
and the scaling to [0, 1] of the white level; before demosaicing), or in OpcodeList3 on the
demosaiced camera RGB. The stage applies every GainMap of OpcodeList2 and OpcodeList3 in list
order, clipping at 1 after each as the DNG SDK does (``dng_opcode_GainMap::ProcessArea``).
Other opcodes (lens distortion warps, bad-pixel fixes, ...) and everything in OpcodeList1 (on
the stored data, before linearization) are not applied and are named in a warning and in
``linear.json``. LibRaw applies none of them (checked: a GainMap of 2 leaves its output as is).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from recon.io.dng import OPCODE_GAIN_MAP, OPCODE_LIST_TAGS, GainMap, read_opcode_list
from recon.linearize.settings import LinearizeError

log = logging.getLogger(__name__)


@dataclasses.dataclass
class Opcodes:
    """The opcode lists of one DNG: the GainMaps applied after linearization (``stage2``) and
    after demosaicing (``stage3``), and the opcodes left out, as "OpcodeListN: Name" strings."""

    stage2: list[GainMap] = dataclasses.field(default_factory=list)
    stage3: list[GainMap] = dataclasses.field(default_factory=list)
    ignored: list[str] = dataclasses.field(default_factory=list)

    @property
    def applied(self) -> list[str]:
        return [f"OpcodeList{k}: GainMap" for k, maps in ((2, self.stage2), (3, self.stage3)) for _ in maps]


def read_opcodes(path: Path, tag) -> Opcodes:
    """The opcode lists of the DNG ``path`` (``tag(name)`` returns a tag's value or None);
    LinearizeError for a list that cannot be parsed."""
    out = Opcodes()
    for number, name in enumerate(OPCODE_LIST_TAGS, start=1):
        value = tag(name)
        if value is None:
            continue
        try:
            ops = read_opcode_list(value)
            for op in ops:
                if op.id == OPCODE_GAIN_MAP and number in (2, 3):
                    (out.stage2 if number == 2 else out.stage3).append(GainMap.from_opcode(op))
                else:
                    out.ignored.append(f"{name}: {op.name}{' (optional)' if op.optional else ''}")
        except ValueError as e:
            raise LinearizeError(
                f"{path}: its DNG {name} cannot be parsed ({e}); the file is corrupt: copy it from "
                "the camera again or remove it from images/"
            ) from e
    if out.ignored:
        log.warning("%s: DNG opcodes not applied: %s (only GainMap in OpcodeList2/3 is)", path,
                    ", ".join(out.ignored))
    return out


def apply_gain_maps(image: np.ndarray, maps: list[GainMap]) -> np.ndarray:
    """Multiply ``image`` in place by the GainMaps ``maps``, in order, clipping at 1 after each.

    Parameters
    ----------
    image : (H, W) or (H, W, C) float32
        Linear values with 1 = the white level: the CFA image (one plane) after linearization,
        or the demosaiced camera RGB (plane k = channel k).
    maps : list of GainMap
        Their rectangles, pitches and relative map positions refer to this image's H x W.

    Returns
    -------
    ``image``.
    """
    planes = 1 if image.ndim == 2 else image.shape[2]
    height, width = image.shape[:2]
    for gm in maps:
        rows, cols = gm.area(height, width)
        r = np.arange(height)[rows]
        c = np.arange(width)[cols]
        if not len(r) or not len(c):
            continue
        for p in range(gm.plane, min(gm.plane + gm.planes, planes)):
            view = image[rows, cols] if image.ndim == 2 else image[rows, cols, p]
            view *= gm.gains_at(r, c, height, width, p)
            np.minimum(view, 1.0, out=view)
    return image
