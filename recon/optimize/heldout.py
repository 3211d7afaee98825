"""The held-out views and the paired held-out test every selection shares.

Which views are held out (:func:`split_holdout`), and how two models are compared on them
(:func:`compare`): per-tile errors of the same tiles under both, the richer model kept only
when its gain beats the noise of the paired differences. The material selection
(:mod:`recon.optimize.material_select`), the imaging selection (:mod:`recon.optimize.imaging_select`),
the camera refinement's selection (:mod:`recon.optimize.cameras`) and the plateau test
(:mod:`recon.optimize.schedule`) all decide with it.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from recon.optimize.material import SelectionSettings
    from recon.optimize.settings import OptimizeSettings
    from recon.optimize.views import Views

__all__ = ["compare", "split_holdout"]

log = logging.getLogger(__name__)


def split_holdout(views: Views, settings: OptimizeSettings, force: bool = False):
    """(training views, held-out views or None, info dict) for ``settings.holds_out`` (or
    ``force``: the camera refinement's selection needs them).

    Every ``holdout_every``-th view (starting at the middle of the first block) is held out,
    at least 2; none when fewer than 4 views would remain to optimize on.
    """
    n = len(views)
    if not (settings.holds_out or force):
        return views, None, None
    k = int(settings.select.holdout_every)
    held = list(range(k // 2, n, k))
    if len(held) < 2 and n >= 2:
        held = sorted({n // 4, (3 * n) // 4})
    train = [i for i in range(n) if i not in set(held)]
    if len(held) < 2 or len(train) < 4:
        log.warning("only %d views: none held out, so no material selection or plateau test "
                    "(need at least 6)", n)
        return views, None, {"held_out": [], "reason": f"only {n} views (need at least 6)"}
    return views.subset(train), views.subset(held), {"held_out": [views.stems[i] for i in held],
                                                     "train_views": len(train)}


def compare(richer: np.ndarray, current: np.ndarray, s: SelectionSettings) -> dict:
    """Paired comparison of per-tile held-out errors: gain = mean of (current - richer).

    Accepted when gain > z * SE and gain > min_gain * (the current model's mean error). With
    ``s.trim`` > 0 the gain is Yuen's trimmed mean (that fraction of tiles dropped at each end,
    SE from the winsorized variance); the default 0 keeps every tile, because the gain of a
    specular or roughness model sits in the few highlight tiles and a trim removes exactly those
    (``bench/selection.py``, glossy blob, seed 0: the top 2 % of tiles carry 156 % of the
    textured-roughness gain; a 2 % trim cuts that gain from 0.0058 to 0.0010).
    """
    ok = np.isfinite(richer) & np.isfinite(current)
    d = np.sort(current[ok] - richer[ok])
    n = int(d.size)
    if n < 3:
        return {"gain": 0.0, "se": float("inf"), "relative_gain": 0.0, "tiles": n, "accepted": False}
    g = int(np.floor(float(s.trim) * n))
    kept = d[g:n - g]
    gain = float(kept.mean())
    w = np.clip(d, kept[0], kept[-1])  # winsorized
    se = float(w.std(ddof=1) / ((1 - 2 * g / n) * np.sqrt(n)))
    e = np.sort(current[ok])
    err = float(e[g:n - g].mean())
    accept = bool(gain > s.z * se and gain > s.min_gain * err)
    return {"gain": gain, "se": se, "relative_gain": gain / err if err > 0 else 0.0, "tiles": n,
            "trimmed": 2 * g, "accepted": accept}
