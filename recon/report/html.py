"""The report page: one self-contained ``index.html`` that links only files inside report/.

Everything shown is passed in as plain data; this module only formats. Text from files (stems,
stage names, the material model) is HTML-escaped, file names are URL-quoted.
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass, field
from urllib.parse import quote

CSS = """
body { font-family: system-ui, sans-serif; margin: 0 auto; max-width: 1320px; padding: 0 18px 40px;
       color: #1d1d1f; background: #fafafa; }
h1 { font-size: 1.6em; margin: 18px 0 4px; } h2 { font-size: 1.2em; margin: 28px 0 10px;
     border-bottom: 1px solid #ddd; padding-bottom: 4px; }
.sub { color: #666; margin: 0 0 12px; }
.cards { display: flex; flex-wrap: wrap; gap: 10px; }
.card { background: #fff; border: 1px solid #e3e3e3; border-radius: 6px; padding: 8px 12px; min-width: 120px; }
.card .k { font-size: 0.78em; color: #666; } .card .v { font-size: 1.25em; font-weight: 600; }
model-viewer { width: 100%; height: 520px; background-color: #3a3a3a; border-radius: 6px; }
.views { display: grid; grid-template-columns: repeat(auto-fill, minmax(600px, 1fr)); gap: 14px; }
.view { background: #fff; border: 1px solid #e3e3e3; border-radius: 6px; padding: 8px; }
.view .row { display: grid; grid-template-columns: repeat(3, 1fr); gap: 4px; }
.view img, .maps img, .plots img { width: 100%; height: auto; display: block; image-rendering: auto; }
.view .cap { font-size: 0.85em; margin-top: 4px; display: flex; justify-content: space-between; }
.view .lbl { font-size: 0.72em; color: #777; text-align: center; }
.maps, .plots { display: grid; grid-template-columns: repeat(auto-fill, minmax(380px, 1fr)); gap: 14px; }
figure { margin: 0; } figcaption { font-size: 0.85em; color: #555; margin-top: 4px; }
table { border-collapse: collapse; font-size: 0.9em; } td, th { padding: 3px 10px; border-bottom: 1px solid #eee; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.note { font-size: 0.85em; color: #666; } pre { background: #fff; border: 1px solid #eee; padding: 8px; overflow-x: auto; }
"""


def fmt(x, digits: int = 4) -> str:
    """A number for display (``-`` for None/NaN)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return f"{x:.{digits}g}"
    return html.escape(str(x))


def src(name: str) -> str:
    return html.escape(quote(name))


@dataclass
class ViewEntry:
    stem: str
    rmse: float
    files: dict  # role -> file name: input, render, error
    labels: tuple = ("input", "re-render", "error")
    note: str = ""  # shown after the stem, e.g. "held out: never fitted"


@dataclass
class Page:
    capture: str
    preset: str | None
    material_model: object = None
    material_selection: dict | None = None  # summary.json's evidence of the held-out model choice
    camera_refinement: dict | None = None  # metrics.json's camera_refinement (issue 17)
    imaging_selection: dict | None = None  # the camera's imaging terms chosen the same way
    imaging_loop: dict | None = None  # the terms chosen on the coarse model, used in the shape's loop
    cards: list = field(default_factory=list)  # (label, value string)
    viewer_head: str = ""
    viewer_body: str = ""
    views: list = field(default_factory=list)  # ViewEntry
    views_note: str = ""
    error_colorbar: str = ""
    maps: list = field(default_factory=list)  # (file, caption)
    plots: list = field(default_factory=list)  # (file, caption)
    stage_times: dict = field(default_factory=dict)
    phase_times: dict = field(default_factory=dict)
    phase_source: str = ""
    optimize_stages: tuple = ((), ())  # (column names, rows) of the coarse-to-fine stages
    gt_metrics: dict = field(default_factory=dict)
    gt_views: list = field(default_factory=list)  # ViewEntry with gt labels
    gt_note: str = ""
    notes: list = field(default_factory=list)


def _table(rows, head=None) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head) if head else ""
    body = "".join(
        "<tr>" + "".join(f'<td class="num">{fmt(c)}</td>' if isinstance(c, (int, float)) and not isinstance(c, bool)
                         else f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>"
        for r in rows
    )
    return f"<table>{'<tr>' + h + '</tr>' if h else ''}{body}</table>"


def _view_block(v: ViewEntry, rmse_label: str = "RMSE") -> str:
    imgs = "".join(
        f'<a href="{src(v.files[k])}"><img loading="lazy" src="{src(v.files[k])}" alt="{html.escape(v.stem)} {lbl}"></a>'
        for k, lbl in zip(("input", "render", "error"), v.labels, strict=True)
    )
    labels = "".join(f'<div class="lbl">{html.escape(lbl)}</div>' for lbl in v.labels)
    return (f'<div class="view" id="view-{html.escape(v.stem)}"><div class="row">{imgs}</div>'
            f'<div class="row">{labels}</div>'
            f'<div class="cap"><b>{html.escape(v.stem)}</b>{f" ({html.escape(v.note)})" if v.note else ""}<span>{rmse_label} {fmt(v.rmse)}</span></div></div>')


def render_page(p: Page) -> str:
    """The whole ``index.html`` as a string."""
    parts = [
        "<!doctype html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>recon report: {html.escape(p.capture)}</title>",
        f"<style>{CSS}</style>", p.viewer_head, "</head><body>",
        f"<h1>{html.escape(p.capture)}</h1>",
        f'<p class="sub">preset <b>{html.escape(p.preset or "unknown")}</b>'
        + (f" &middot; material model <b>{_material_text(p.material_model)}</b>" if p.material_model is not None else "")
        + ' &middot; <a href="metrics.json">metrics.json</a></p>',
    ]
    if p.cards:
        parts.append('<div class="cards">' + "".join(
            f'<div class="card"><div class="k">{html.escape(k)}</div><div class="v">{html.escape(v)}</div></div>'
            for k, v in p.cards) + "</div>")
    parts += ["<h2>3D asset</h2>", p.viewer_body]

    parts.append("<h2>Views: input, re-render of the optimized model, error</h2>")
    if p.views_note:
        parts.append(f'<p class="note">{html.escape(p.views_note)}</p>')
    parts.append(p.error_colorbar)
    parts.append('<div class="views">' + "".join(_view_block(v) for v in p.views) + "</div>")

    if p.gt_metrics or p.gt_views:
        parts.append("<h2>Against the ground truth</h2>")
        if p.gt_note:
            parts.append(f'<p class="note">{html.escape(p.gt_note)}</p>')
        rows = [(k, v) for k, v in p.gt_metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
        for k, v in p.gt_metrics.items():
            if isinstance(v, dict) and k != "alignment":
                rows += [(f"{k}.{kk}", vv) for kk, vv in v.items()
                         if isinstance(vv, (int, float)) and not isinstance(vv, bool)]
        parts.append(_table(rows, ("metric", "value")))
        if "alignment" in p.gt_metrics:
            parts.append("<details><summary>alignment (estimated frame to ground truth)</summary><pre>"
                         + html.escape(json.dumps(p.gt_metrics["alignment"], indent=1)) + "</pre></details>")
        if p.gt_views:
            parts.append('<div class="views">' + "".join(_view_block(v) for v in p.gt_views) + "</div>")

    if p.maps:
        parts.append("<h2>Texture maps</h2>")
        parts.append('<div class="maps">' + "".join(
            f'<figure><a href="{src(f)}"><img src="{src(f)}" alt="{html.escape(c)}"></a>'
            f"<figcaption>{html.escape(c)}</figcaption></figure>" for f, c in p.maps) + "</div>")

    if isinstance(p.material_selection, dict) and p.material_selection.get("candidates"):
        parts.append(_selection_section(p.material_selection))
    if isinstance(p.camera_refinement, dict) and p.camera_refinement.get("mode"):
        parts.append(_camera_section(p.camera_refinement))
    if isinstance(p.imaging_loop, dict) and p.imaging_loop.get("candidates"):
        parts.append(_imaging_section(
            p.imaging_loop, f"Camera imaging in the shape's optimization: terms chosen on stage "
                            f"{p.imaging_loop.get('after_stage')}'s model"))
    if isinstance(p.imaging_selection, dict) and p.imaging_selection.get("candidates"):
        parts.append(_imaging_section(p.imaging_selection))

    parts.append("<h2>Optimization and timings</h2>")
    if p.plots:
        parts.append('<div class="plots">' + "".join(
            f'<figure><img src="{src(f)}" alt="{html.escape(c)}"><figcaption>{html.escape(c)}</figcaption></figure>'
            for f, c in p.plots) + "</div>")
    if p.optimize_stages and p.optimize_stages[1]:
        parts.append("<h3>Coarse-to-fine stages of the optimization (summary.json)</h3>")
        parts.append(_table(p.optimize_stages[1], p.optimize_stages[0]))
    if p.stage_times:
        parts.append("<h3>Wall time per stage (Snakemake benchmarks)</h3>")
        parts.append(_table([(k, v) for k, v in p.stage_times.items()], ("stage", "seconds")))
    if p.phase_times:
        parts.append(f"<h3>Optimization phases (from {html.escape(p.phase_source)})</h3>")
        parts.append(_table([(k, v) for k, v in p.phase_times.items()], ("phase", "seconds")))
    for n in p.notes:
        parts.append(f'<p class="note">{html.escape(n)}</p>')
    parts.append("</body></html>")
    return "\n".join(x for x in parts if x)


def _selection_section(sel: dict) -> str:
    """The material models tried on held-out views, their errors and the decision."""
    rows = []
    for r in sel["candidates"]:
        gain, se = r.get("gain"), r.get("se")
        rows.append((r.get("step", ""), _model_words(r.get("model")),
                     r.get("heldout_error"), "" if gain is None else gain, "" if se is None else se,
                     "baseline" if gain is None else ("kept" if r.get("accepted") else "rejected")))
    head = ("step", "model", "held-out error", "gain", "SE", "decision")
    return ("<h2>Material model: chosen on held-out views</h2>"
            f'<p>Chosen: <b>{html.escape(_model_words(sel.get("chosen")))}</b> '
            f'({sel.get("heldout_views", "?")} held-out views, {sel.get("train_views", "?")} fitted on). '
            f'{html.escape(str(sel.get("criterion", "")))}; error = {html.escape(str(sel.get("metric", "")))}.</p>'
            + _table(rows, head))


def _camera_section(cam: dict) -> str:
    """The camera refinement: mode and decision, intrinsics before/after, corrections per view."""
    out = ["<h2>Cameras refined by the renderer</h2>"]
    used = "used" if cam.get("refined") else "not used"
    out.append(f'<p>Mode <b>{html.escape(str(cam.get("mode")))}</b> ({html.escape(str(cam.get("reason", "")))}); '
               f"the refined cameras were <b>{used}</b>"
               + (f"; refined from coarse-to-fine stage {int(cam['first_stage'])}"
                  if isinstance(cam.get("first_stage"), int) else "") + ".</p>")
    sel = cam.get("selection")
    if isinstance(sel, dict):
        out.append(f'<p class="note">{html.escape(str(sel.get("criterion", "")))}.</p>')
        out.append(_table([("held-out error without refinement", sel.get("control_heldout_error")),
                           ("held-out error with refinement", sel.get("refined_heldout_error")),
                           ("gain", sel.get("gain")), ("SE", sel.get("se")),
                           ("decision", "kept" if sel.get("accepted") else "rejected")], ("", "value")))
    cor = cam.get("corrections")
    if isinstance(cor, dict):
        before, after = cor.get("intrinsics_before") or {}, cor.get("intrinsics_after") or {}
        out.append("<h3>Intrinsics (shared, full-size pixels of the first view)</h3>")
        out.append(_table([(k, before.get(k), after.get(k)) for k in ("fx", "fy", "cx", "cy")],
                          ("", "before", "after")))
        views = cor.get("views") if isinstance(cor.get("views"), dict) else {}
        rows = [(stem, v.get("rotation_deg"), v.get("center_shift_object", v.get("center_shift")))
                for stem, v in views.items() if isinstance(v, dict)]
        out.append(f'<h3>Pose correction per view ({"applied" if cam.get("refined") else "proposed, not applied"})'
                   "</h3>")
        out.append('<p class="note">rotation in degrees; centre shift as a fraction of the object size '
                   "(the initial mesh's longest bounding-box side).</p>")
        out.append(_table(rows, ("view", "rotation (deg)", "centre shift")))
    return "".join(out)


def _imaging_section(sel: dict, title: str = "Camera imaging: terms chosen on held-out views") -> str:
    """The camera's imaging terms tried on held-out views (recon.optimize.imaging_select), the
    decision and the fitted values."""
    rows = []
    for r in sel["candidates"]:
        gain, se = r.get("gain"), r.get("se")
        backward = str(r.get("step", "")).startswith("without ")
        decision = ("baseline" if gain is None else ("dropped" if r.get("accepted") else "kept") if backward
                    else ("kept" if r.get("accepted") else "rejected"))
        rows.append((r.get("step", ""), ", ".join(r.get("terms") or []) or "ideal", r.get("heldout_error"),
                     "" if gain is None else gain, "" if se is None else se, decision))
    chosen = ", ".join(sel.get("chosen") or []) or "none (the ideal image formation)"
    values = {k: v for k, v in (sel.get("values") or {}).items() if k in ("flash_offset", "ambient", "falloff")}
    return (f"<h2>{html.escape(title)}</h2>"
            f"<p>Kept: <b>{html.escape(chosen)}</b>. {html.escape(str(sel.get('criterion', '')))}; "
            f"error = {html.escape(str(sel.get('metric', '')))}. "
            f"Fitted: {html.escape(json.dumps(values))}</p>"
            + _table(rows, ("step", "terms", "held-out error", "gain", "SE", "decision")))


def _model_words(model) -> str:
    if not isinstance(model, dict):
        return str(model)
    if model.get("specular") == "none":
        return "diffuse only"
    rgb = "RGB " if model.get("specular_color") == "rgb" else ""
    return f"{model.get('specular')} {rgb}specular, {model.get('roughness')} roughness"


def _material_text(model) -> str:
    if isinstance(model, str):
        return html.escape(model)
    if isinstance(model, dict) and "specular" in model:
        return html.escape(_model_words(model))
    return html.escape(json.dumps(model, sort_keys=True))
