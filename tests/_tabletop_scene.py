"""A small synthetic tabletop capture (recon.synth, ``scene="tabletop"``) shared by the tests of
the synthetic generator and of the tabletop masks: rendered once per test session."""

from __future__ import annotations

import hashlib
from pathlib import Path

# a mug (cavity + handle) on the wood table, 24 hand-held views of 192 x 144, linear EXR with
# noise, true cameras; ~25 s to render on 2 cores
TABLETOP_TEST = dict(scene="tabletop", object="mug", n_views=24, width=192, height=144, fov=50.0,
                     distance=5.0, format="exr", spp=8, seed=0, mesh_level=3, texture_size=256,
                     table_texture_size=512, write_cameras=True, write_masks=False,
                     write_gt_linear=False)


def tabletop_capture(base: Path, **overrides) -> Path:
    """The capture for these settings, rendered into ``base`` unless already there (pass pytest's
    ``tmp_path_factory.getbasetemp()`` to share one render between test modules)."""
    from recon import sections
    from recon.synth.capture import SynthSettings, make_capture

    from _shared import made_once

    settings = sections.replace(SynthSettings(), **{**TABLETOP_TEST, **overrides})
    name = f"tabletop-{hashlib.sha1(repr(settings).encode()).hexdigest()[:12]}"
    return made_once(base, name, lambda out: make_capture(out, settings))

# the ChArUco mat capture (recon.marker): 8 views of 320 x 240, the mat's squares 0.05 scene
# units (scale 0.1: the object ~0.19 units tall); ~20 s
MAT_TEST = dict(n_views=8, width=320, height=240, spp=4, texture_size=128, table_texture_size=1024,
                marker_square=0.5, scale=0.1, background=0.0)
MAT_TEST_SQUARE_UNITS = 0.05
