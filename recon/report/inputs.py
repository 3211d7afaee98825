"""What the report reads: the optimized model, the optimizer's log and summary, benchmarks.

Every reader raises :class:`ReportError` naming the file and the fix when a required input is
missing or unusable. The optimizer's log (``optimize/log.jsonl``, one JSON object per line) is
read defensively: unreadable lines are skipped with a warning, and only what is there is shown.

Per-phase seconds (render, loss, backward, geometry processing) are recognized in a log record
or in ``summary.json`` in any of these spellings (``<phase>`` is any lower-case name):

- a nested mapping under ``timings``, ``timing``, ``phases``, ``phase_seconds``, ``seconds``,
  ``times`` or ``optimize_phases``: ``{"timings": {"render": 0.12, "backward": 0.3}}``;
- flat keys with a time prefix or suffix: ``t_<phase>``, ``time_<phase>``,
  ``seconds_<phase>``, ``<phase>_s``, ``<phase>_sec``, ``<phase>_seconds``, ``<phase>_time``.

Log records hold the seconds of one iteration (they are summed); ``summary.json`` holds totals
(used as they are, in preference to the log's sums).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.io.images import ImageError, read_texture_map
from recon.io.mesh import Mesh, MeshError, read_mesh
from recon.stages import NAMES as STAGE_NAMES

log = logging.getLogger(__name__)

MODEL_FILES = {
    "mesh": "mesh.obj",
    "diffuse": "diffuse.exr",
    "specular": "specular.exr",
    "roughness": "roughness.exr",
}
"""The optimize stage's model files (DESIGN section 2), by role."""

LOG_FILE = "log.jsonl"
SUMMARY_FILE = "summary.json"

TIMING_GROUPS = ("timings", "timing", "phases", "phase_seconds", "seconds", "times", "optimize_phases")
NOT_PHASES = ("wall", "total", "elapsed")
ITERATION_KEYS = ("iter", "iteration")
_PREFIX = re.compile(r"^(?:t|time|seconds|sec)_([a-z][a-z0-9_]*)$")
_SUFFIX = re.compile(r"^([a-z][a-z0-9_]*?)_(?:s|sec|secs|seconds|time)$")


class ReportError(ValueError):
    """An input the report cannot use; the message names the file and the fix."""


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


# ---- The optimized model ----
@dataclass
class Model:
    """The optimize stage's result.

    Attributes
    ----------
    mesh : Mesh with UVs (OBJ convention)
    diffuse : (H, W, 3) float32 linear a_d in [0, 1]
    specular : (H', W', 1 or 3) float32 a_s in [0, 1]
    roughness : (H'', W'', 1) float32 perceptual roughness in [0, 1]
    """

    mesh: Mesh
    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray

    def textures(self) -> dict[str, np.ndarray]:
        return {"diffuse": self.diffuse, "specular": self.specular, "roughness": self.roughness}


def _require(path: Path, what: str, producer: str) -> Path:
    if not path.is_file():
        raise ReportError(f"{path}: not found; the report needs {what} ({producer})")
    return path


def read_map(path: str | os.PathLike, what: str, channels: tuple[int, ...], producer: str) -> np.ndarray:
    """Read one texture map EXR (:func:`recon.io.images.read_texture_map`: channels, finiteness, [0, 1])."""
    path = _require(Path(path), f"the {what} map", producer)
    try:
        return read_texture_map(path, what, channels)
    except ImageError as e:
        raise ReportError(f"{e} ({producer})") from e


def read_surface_mesh(path: str | os.PathLike, producer: str) -> Mesh:
    """Read an OBJ/PLY mesh with faces and finite vertices (UVs optional)."""
    path = _require(Path(path), "the mesh", producer)
    try:
        mesh = read_mesh(path)
    except MeshError as e:
        raise ReportError(f"{e} ({producer})") from e
    if len(mesh.t_pos_idx) == 0:
        raise ReportError(f"{path}: the mesh has no faces ({producer})")
    if not np.all(np.isfinite(mesh.v_pos)) or (mesh.has_uv and not np.all(np.isfinite(mesh.v_tex))):
        raise ReportError(f"{path}: vertex positions or UVs contain NaN or Inf ({producer})")
    return mesh


def read_textured_mesh(path: str | os.PathLike, producer: str) -> Mesh:
    """Read an OBJ/PLY mesh that must have UVs and finite vertices."""
    mesh = read_surface_mesh(path, producer)
    if not mesh.has_uv:
        raise ReportError(f"{path}: the mesh has no UVs (faces need v/vt indices); {producer}")
    return mesh


def read_model(optimize_dir: str | os.PathLike) -> Model:
    """The optimized mesh and maps in ``optimize_dir`` (mesh.obj, diffuse/specular/roughness.exr)."""
    d = Path(optimize_dir)
    producer = "written by the optimize stage: run it first"
    mesh = read_textured_mesh(d / MODEL_FILES["mesh"], producer)
    return Model(
        mesh=mesh,
        diffuse=read_map(d / MODEL_FILES["diffuse"], "diffuse", (3,), producer),
        specular=read_map(d / MODEL_FILES["specular"], "specular", (1, 3), producer),
        roughness=read_map(d / MODEL_FILES["roughness"], "roughness", (1,), producer),
    )


# ---- The optimizer's log and summary ----
def read_log(path: str | os.PathLike) -> list[dict]:
    """The records of ``log.jsonl`` (JSON objects, one per line); bad lines are skipped."""
    path = _require(Path(path), "the optimizer's log", "written by the optimize stage: run it first")
    records = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as e:
                log.warning("%s:%d: not JSON (%s); line skipped", path, n, e)
                continue
            if not isinstance(rec, dict):
                log.warning("%s:%d: not a JSON object; line skipped", path, n)
                continue
            records.append(rec)
    return records


def read_summary(path: str | os.PathLike) -> dict:
    """``summary.json`` as a dict, or ``{}`` when it is absent (a warning when unreadable)."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        log.warning("%s: not valid JSON (%s); ignored", path, e)
        return {}
    if not isinstance(data, dict):
        log.warning("%s: not a JSON object; ignored", path)
        return {}
    return data


def phase_seconds(record: dict) -> dict[str, float]:
    """Per-phase seconds found in one log record or summary (see the module docstring).

    A nested timing mapping, when there is one, is used alone; flat keys otherwise. Totals
    (``wall``, ``total``, ``elapsed``) are not phases and are left out.
    """
    out: dict[str, float] = {}
    for key, value in record.items():
        if key in TIMING_GROUPS and isinstance(value, dict):
            for name, sec in value.items():
                if _is_number(sec):
                    out[str(name)] = out.get(str(name), 0.0) + float(sec)
                elif isinstance(sec, dict) and _is_number(sec.get("total")):
                    out[str(name)] = out.get(str(name), 0.0) + float(sec["total"])
    if not out:
        for key, value in record.items():
            if not _is_number(value):
                continue
            m = _PREFIX.match(key) or _SUFFIX.match(key)
            if m:
                out[m.group(1)] = out.get(m.group(1), 0.0) + float(value)
    return {k: v for k, v in out.items() if k not in NOT_PHASES}


def optimize_phases(records: list[dict], summary: dict) -> tuple[dict[str, float], str]:
    """Total seconds per optimization phase and where they came from.

    Returns
    -------
    (phases, source): ``summary.json``'s totals when it has any, else the sums over the log's
    records; ``source`` is ``"summary.json"``, ``"log.jsonl"`` or ``""`` (none found).
    """
    phases = phase_seconds(summary)
    if phases:
        return phases, SUMMARY_FILE
    total: dict[str, float] = {}
    for rec in records:
        for name, sec in phase_seconds(rec).items():
            total[name] = total.get(name, 0.0) + sec
    return total, (LOG_FILE if total else "")


@dataclass
class LossCurves:
    """Loss values against the iteration, from the log's records.

    Attributes
    ----------
    iteration : (n,) float, the record's ``iter`` or ``iteration`` counted over the whole run
        (its index where missing)
    stage : list of n labels (the record's ``stage``, as a string; "" where missing)
    series : name -> (n,) float with NaN where a record lacks it; ``loss`` and every numeric
        key named ``loss_*`` or ``*_loss`` that is not a timing (``t_loss``, ``loss_s``)
    """

    iteration: np.ndarray
    stage: list[str]
    series: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.iteration)


def _is_loss_key(key: str) -> bool:
    if _PREFIX.match(key) or _SUFFIX.match(key):  # t_loss, loss_s: seconds of the loss phase
        return False
    return key == "loss" or key.startswith("loss_") or key.endswith("_loss")


def _iteration(record: dict):
    for key in ITERATION_KEYS:
        if _is_number(record.get(key)):
            return float(record[key])
    return None


def loss_curves(records: list[dict]) -> LossCurves:
    """The loss series of the log (records without any loss are left out).

    The x axis counts iterations over the whole run: where the logged iteration number starts
    again (per coarse-to-fine stage), the next stage continues after the previous one.
    """
    rows = [r for r in records if any(_is_loss_key(k) and _is_number(v) for k, v in r.items())]
    names = sorted({k for r in rows for k, v in r.items() if _is_loss_key(k) and _is_number(v)},
                   key=lambda k: (k != "loss", k))
    x, offset, prev = [], 0.0, None
    for i, r in enumerate(rows):
        it = _iteration(r)
        if it is None:
            x.append(float(i))
            continue
        if prev is not None and it + offset < prev:
            offset = prev + 1.0 - it
        x.append(it + offset)
        prev = it + offset
    stage = [str(r.get("stage", "")) for r in rows]
    series = {n: np.array([float(r[n]) if _is_number(r.get(n)) else np.nan for r in rows]) for n in names}
    return LossCurves(np.array(x, dtype=float), stage, series)


MATERIAL_SETTINGS = ("specular_channels", "r_min", "parameterization", "use_material_priors")
"""Optimizer settings that describe the material model, when no ``material_model`` is logged."""


def material_model(summary: dict, records: list[dict]):
    """The material model the optimizer reports: ``material_model`` in the summary, else in the
    last log record that has one, else the material settings in the summary's ``settings``
    (:data:`MATERIAL_SETTINGS`); None when there is nothing."""
    if summary.get("material_model") is not None:
        return summary["material_model"]
    for rec in reversed(records):
        if rec.get("material_model") is not None:
            return rec["material_model"]
    settings = summary.get("settings")
    if isinstance(settings, dict):
        found = {k: settings[k] for k in MATERIAL_SETTINGS if k in settings}
        if found:
            return found
    return None


def summary_r_min(summary: dict) -> float | None:
    """The optimizer's r_min (``r_min`` or ``settings.r_min`` of the summary), if valid."""
    for v in (summary.get("r_min"), (summary.get("settings") or {}).get("r_min")
              if isinstance(summary.get("settings"), dict) else None):
        if _is_number(v) and 0 < v <= 1:
            return float(v)
    return None


# ---- Snakemake benchmarks ----
def read_benchmarks(folder: str | os.PathLike | None) -> dict[str, float]:
    """Wall seconds per stage from Snakemake benchmark files ``<folder>/<stage>.tsv``.

    A benchmark TSV has a header with an ``s`` column and one row per repeat; the mean over
    repeats is returned, the stages in pipeline order (:data:`recon.stages.STAGES`; files of
    other names after them, by name). Unreadable files are skipped with a warning.
    """
    if folder is None or not Path(folder).is_dir():
        return {}
    out = {}
    order = {name: k for k, name in enumerate(STAGE_NAMES)}
    for path in sorted(Path(folder).glob("*.tsv"), key=lambda p: (order.get(p.stem, len(order)), p.name)):
        try:
            with open(path, newline="") as f:
                rows = list(csv.DictReader(f, delimiter="\t"))
            values = [float(r["s"]) for r in rows if r.get("s") not in (None, "", "NA")]
        except (OSError, KeyError, ValueError, csv.Error) as e:
            log.warning("%s: not a Snakemake benchmark file (%s); skipped", path, e)
            continue
        values = [v for v in values if math.isfinite(v)]
        if values:
            out[path.stem] = float(np.mean(values))
        else:
            log.warning("%s: no 's' values; skipped", path)
    return out
