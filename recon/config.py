"""Settings: presets, per-capture overrides and frozen settings dataclasses.

A stage's settings are the ``<stage>:`` section of ``config/presets/<preset>.yaml``, updated
by the same section of the capture's ``capture.yaml``. The capture may also pick its own
``preset`` and ``light_intensity``. Every stage turns the merged dict into its frozen settings
dataclass with :func:`build_settings`, which rejects unknown keys with a message naming the
file they came from.

``light_intensity`` (the flash's I_e) has one route: it becomes the poses stage's
``light_intensity`` setting, and that stage writes it into ``poses/cameras.json`` whether it
runs SfM or passes the capture's own ``cameras.json`` through (a capture whose cameras.json
states another intensity is an error naming both files); every later stage reads it there.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import typing
from pathlib import Path

import yaml

STAGES = ("linearize", "masks", "poses", "init_mesh", "uv", "optimize", "export", "report")
PRESETS = ("draft", "balanced", "accurate")
CAPTURE_KEYS = ("preset", "light_intensity") + STAGES
DEFAULT_PRESETS_DIR = Path(__file__).resolve().parents[1] / "config" / "presets"


class ConfigError(ValueError):
    """A setting that cannot be used; the message names the file and the key."""


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values at the top level")
    return data


def read_capture_yaml(capture_dir: str | os.PathLike) -> dict:
    """The capture's ``capture.yaml`` (empty when absent), with its keys checked."""
    path = Path(capture_dir) / "capture.yaml"
    if not path.is_file():
        return {}
    data = _read_yaml(path)
    unknown = sorted(set(data) - set(CAPTURE_KEYS))
    if unknown:
        raise ConfigError(
            f"{path}: unknown key(s) {unknown}; allowed: {', '.join(CAPTURE_KEYS)}"
        )
    if "preset" in data and data["preset"] not in PRESETS:
        raise ConfigError(f"{path}: preset must be one of {PRESETS}, got {data['preset']!r}")
    for stage in STAGES:
        if stage in data and not isinstance(data[stage], dict):
            raise ConfigError(f"{path}: '{stage}' must be a mapping of setting names to values")
    if "light_intensity" in data:
        value = data["light_intensity"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{path}: light_intensity must be a positive number, got {value!r}")
        section = data.get("poses", {})
        if "light_intensity" in section and section["light_intensity"] != value:
            raise ConfigError(
                f"{path}: light_intensity {value!r} and poses.light_intensity {section['light_intensity']!r} "
                "differ; give the light intensity once (the top-level light_intensity)"
            )
    return data


def capture_preset(capture_dir: str | os.PathLike, default: str) -> str:
    """The preset a capture runs with: its capture.yaml's ``preset``, else ``default``."""
    return read_capture_yaml(capture_dir).get("preset", default)


def load_preset(preset: str, presets_dir: str | os.PathLike | None = None) -> dict:
    presets_dir = Path(presets_dir or DEFAULT_PRESETS_DIR)
    path = presets_dir / f"{preset}.yaml"
    if not path.is_file():
        raise ConfigError(f"preset '{preset}' not found: {path} does not exist (presets: {PRESETS})")
    data = _read_yaml(path)
    unknown = sorted(set(data) - set(STAGES))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; stages are {', '.join(STAGES)}")
    return data


def stage_settings(
    stage: str,
    preset: str,
    capture_dir: str | os.PathLike | None = None,
    presets_dir: str | os.PathLike | None = None,
) -> dict:
    """Merged settings dict of ``stage``: preset section updated by capture.yaml's section.

    The capture's own ``preset`` key, when present, replaces ``preset``. The result carries
    ``_sources`` (the files it came from) for error messages; :func:`build_settings` drops it.
    """
    if stage not in STAGES:
        raise ConfigError(f"unknown stage '{stage}'; stages are {', '.join(STAGES)}")
    cap = read_capture_yaml(capture_dir) if capture_dir is not None else {}
    preset = cap.get("preset", preset)
    merged = copy.deepcopy(load_preset(preset, presets_dir).get(stage) or {})
    sources = [str(Path(presets_dir or DEFAULT_PRESETS_DIR) / f"{preset}.yaml")]
    if stage in cap:
        merged.update(cap[stage])
        sources.append(str(Path(capture_dir) / "capture.yaml"))
    if stage == "poses" and "light_intensity" in cap:  # the one route of the light (module docstring)
        merged["light_intensity"] = cap["light_intensity"]
        if str(Path(capture_dir) / "capture.yaml") not in sources:
            sources.append(str(Path(capture_dir) / "capture.yaml"))
    merged["_sources"] = sources
    merged["_preset"] = preset
    return merged


def effective_settings(
    stage: str,
    preset: str,
    capture_dir: str | os.PathLike | None = None,
    presets_dir: str | os.PathLike | None = None,
) -> dict:
    """:func:`stage_settings` without its bookkeeping keys: the values the stage uses.

    This is what a Snakemake rule tracks as ``params``: switching to a preset whose section of
    this stage is equal, or moving the captures folder, changes nothing here and so reruns
    nothing (the preset's name and the source paths are not part of it).
    """
    return {k: v for k, v in stage_settings(stage, preset, capture_dir, presets_dir).items()
            if not k.startswith("_")}


def job_settings(stage: str, job, presets_dir: str | os.PathLike | None = None) -> dict:
    """Inside a Snakemake job: the stage's settings with ``_sources`` and ``_preset`` again.

    ``job`` is the ``snakemake`` object Snakemake injects into a rule's script (duck-typed: its
    ``config["captures"]``, ``config["preset"]`` and ``wildcards.capture``; ``recon`` never
    imports Snakemake). The values equal the rule's tracked ``params.settings``; the sources
    name the files in error messages. One addition: a job of a :data:`GPU_STAGES` stage whose
    resources request a GPU (:func:`job_variant`) renders with ``cuda_ad_rgb`` unless its
    settings name a variant (not tracked: the device is where a job runs, not a setting).
    """
    capture_dir = Path(job.config["captures"]) / job.wildcards.capture
    settings = stage_settings(stage, job.config["preset"], capture_dir, presets_dir)
    variant = job_variant(getattr(job, "resources", None))
    if stage in GPU_STAGES and variant and not settings.get("variant"):
        settings["variant"] = variant
    return settings


GPU_STAGES = ("optimize",)
"""Stages that render on a GPU when their job was given one (profiles/slurm: ``gpu``/``gres``)."""


def job_variant(resources) -> str | None:
    """The Mitsuba variant a job's resources ask for: ``"cuda_ad_rgb"`` when they request a GPU
    (``gpu`` > 0, or a ``gres`` naming ``gpu`` such as ``"gpu:1"`` / ``"gpu:a100:1"``), else None
    (then :func:`recon.mi.default_variant` decides: ``RECON_VARIANT``, else the CPU).

    ``resources`` is a mapping with ``get`` (Snakemake's ``snakemake.resources``) or None. A
    variant named in the settings (``optimize: {variant: ...}``) wins over this choice.
    """
    if resources is None:
        return None
    gpu = resources.get("gpu") or 0
    gres = str(resources.get("gres") or "")
    try:
        gpu = int(gpu)
    except (TypeError, ValueError):
        raise ConfigError(f"resource gpu={gpu!r}: expected a number of GPUs (e.g. gpu=1)") from None
    wants_gpu = gpu > 0 or any(part.split(":")[0] == "gpu" for part in gres.split(",") if part)
    return "cuda_ad_rgb" if wants_gpu else None


T = typing.TypeVar("T")


def build_settings(cls: type[T], values: dict | None, source: str = "settings") -> T:
    """Build the frozen dataclass ``cls`` from ``values``, rejecting unknown keys.

    Lists become tuples where the field is a tuple; ``_``-prefixed bookkeeping keys are ignored.
    """
    values = dict(values or {})
    sources = values.pop("_sources", None)
    values.pop("_preset", None)
    where = " / ".join(sources) if sources else source
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown {cls.__name__} key(s) {unknown}; valid keys: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in values.items():
        hint = hints.get(name)
        origin = typing.get_origin(hint)
        if (hint is tuple or origin is tuple) and isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        elif hint is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: invalid {cls.__name__} ({e})") from e


def check_results_location(results: str | os.PathLike, captures_root: str | os.PathLike) -> None:
    """Refuse a results folder that is, contains, or lies inside the captures folder.

    Stages replace their result folders whole; a results folder that overlaps the captures
    would let them overwrite or delete a user's own files (a capture's ``masks/``, say). Checked
    before anything runs; the message names both paths.
    """
    res = Path(results).resolve()
    root = Path(captures_root).resolve()
    if res == root or root in res.parents or res in root.parents:
        how = ("is" if res == root else "lies inside" if root in res.parents else "contains")
        raise ConfigError(
            f"results folder '{res}' {how} the captures folder '{root}': stages replace their "
            "result folders and would overwrite or delete your own files there; pass "
            "--config results=DIR with a folder outside the captures"
        )


def discover_captures(captures_root: str | os.PathLike) -> list[str]:
    """Names of the capture folders under ``captures_root`` (those with an ``images/`` folder)."""
    root = Path(captures_root)
    if not root.is_dir():
        raise ConfigError(
            f"captures folder '{root}' does not exist; set `captures` in config/config.yaml "
            "or pass --config captures=DIR"
        )
    names = sorted(p.name for p in root.iterdir() if (p / "images").is_dir())
    if not names:
        raise ConfigError(
            f"no capture folders in '{root}': each capture is a folder with an images/ folder "
            "(DESIGN section 1)"
        )
    return names
