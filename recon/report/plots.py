"""Figures of the report, as PNG files (matplotlib, Agg) or inline SVG.

Each function writes one file atomically and returns nothing; figures are small (about
700 x 350 px) so the report stays light.
"""

from __future__ import annotations

import html
import os

import numpy as np

from recon.io.atomic import atomic_path
from recon.report.inputs import LossCurves

DPI = 100


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> None:
    plt = _pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI, bbox_inches="tight", format="png")
    plt.close(fig)


def loss_plot(curves: LossCurves, path: str | os.PathLike) -> None:
    """Loss against iteration, one colour band per coarse-to-fine stage.

    The y axis is logarithmic when the total ``loss`` is positive (terms that are zero somewhere
    are drawn where they are positive)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 3.5))
    x = curves.iteration
    stages = list(dict.fromkeys(curves.stage))
    if len(stages) > 1:
        starts = [x[np.array([st == s for st in curves.stage])].min() for s in stages]
        for k, s in enumerate(stages):
            end = starts[k + 1] if k + 1 < len(stages) else x.max()
            ax.axvspan(starts[k], end, color=f"C{k % 10}", alpha=0.08, lw=0)
            ax.text(starts[k], 1.0, f" stage {s}", transform=ax.get_xaxis_transform(),
                    va="top", fontsize=8)
    main = curves.series.get("loss")
    log_y = main is not None and np.isfinite(main).any() and bool(np.all(main[np.isfinite(main)] > 0))
    for name, y in curves.series.items():
        ok = np.isfinite(y) & ((y > 0) if log_y else True)
        if not ok.any():
            continue
        ax.plot(x[ok], y[ok], lw=1.6 if name == "loss" else 0.9,
                color="k" if name == "loss" else None, label=name)
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    if len(curves.series) > 1:
        ax.legend(fontsize=8, frameon=False, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.grid(alpha=0.3)
    _save(fig, path)


def bar_plot(values: dict[str, float], path: str | os.PathLike, xlabel: str = "seconds",
             title: str = "") -> None:
    """Horizontal bars of ``values`` (largest on top), each labelled with its value."""
    plt = _pyplot()
    items = sorted(values.items(), key=lambda kv: kv[1])
    n = len(items)
    fig, ax = plt.subplots(figsize=(7.0, 0.45 * n + 1.0 if n <= 12 else 0.2 * n + 4.0))
    names = [k for k, _ in items]
    v = np.array([x for _, x in items], dtype=float)
    ax.barh(names, v, color="C0")
    for i, x in enumerate(v):
        ax.text(x, i, f" {x:.3g}", va="center", fontsize=8 if n <= 30 else 6)
    ax.set_xlim(0, max(float(v.max()) * 1.15, 1e-9) if len(v) else 1)
    ax.set_xlabel(xlabel)
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    _save(fig, path)


def map_plot(texture: np.ndarray, path: str | os.PathLike, title: str, cmap: str = "viridis",
             vmin: float = 0.0, vmax: float = 1.0) -> None:
    """A one-channel map (H, W, 1) (or the channel mean of RGB) with a colorbar."""
    plt = _pyplot()
    t = np.asarray(texture, dtype=np.float32)
    if t.ndim == 3:
        if t.shape[2] > 1:
            title = f"{title} (mean of RGB)"
        t = t.mean(axis=2)
    fig, ax = plt.subplots(figsize=(4.2, 3.6))
    im = ax.imshow(t, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    _save(fig, path)


def colorbar_svg(vmax: float, cmap: str, label: str, width: int = 320, n_stops: int = 16) -> str:
    """An inline SVG colour bar from 0 to ``vmax`` for the colormap ``cmap``."""
    import matplotlib

    cm = matplotlib.colormaps[cmap]
    stops = "".join(
        f'<stop offset="{k / (n_stops - 1):.3f}" stop-color="#{"".join(f"{int(round(c * 255)):02x}" for c in cm(k / (n_stops - 1))[:3])}"/>'
        for k in range(n_stops)
    )
    ticks = "".join(
        f'<text x="{10 + f * (width - 20):.1f}" y="34" font-size="11" text-anchor="middle">{f * vmax:.3g}</text>'
        for f in (0.0, 0.25, 0.5, 0.75, 1.0)
    )
    return (
        f'<svg class="colorbar" xmlns="http://www.w3.org/2000/svg" width="{width}" height="52" '
        f'role="img" aria-label="{html.escape(label)}">'
        f'<defs><linearGradient id="cb-{cmap}">{stops}</linearGradient></defs>'
        f'<rect x="10" y="4" width="{width - 20}" height="16" fill="url(#cb-{cmap})"/>'
        f'{ticks}<text x="{width / 2:.0f}" y="49" font-size="11" text-anchor="middle">'
        f"{html.escape(label)}</text></svg>"
    )
