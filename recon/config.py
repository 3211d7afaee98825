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
import logging
import math
import os
import re
import types
import typing
from pathlib import Path

import yaml

from recon.io.images import IMAGE_EXTENSIONS
from recon.sections import move_flat, section_types
from recon.stages import GPU_STAGES, SETTINGS_STAGES

STAGES = SETTINGS_STAGES
"""The stages with a settings section, in pipeline order (:data:`recon.stages.STAGES`)."""
PRESETS = ("draft", "balanced", "accurate")
CAPTURE_KEYS = ("preset", "light_intensity") + STAGES
DEFAULT_PRESETS_DIR = Path(__file__).resolve().parents[1] / "config" / "presets"
_log = logging.getLogger(__name__)


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
    ``_sources`` (the files it came from) and ``_key_sources`` (the file each key of capture.yaml
    came from) for error messages; :func:`build_settings` drops them.
    """
    if stage not in STAGES:
        raise ConfigError(f"unknown stage '{stage}'; stages are {', '.join(STAGES)}")
    cap = read_capture_yaml(capture_dir) if capture_dir is not None else {}
    preset = cap.get("preset", preset)
    merged = copy.deepcopy(load_preset(preset, presets_dir).get(stage) or {})
    sources = [str(Path(presets_dir or DEFAULT_PRESETS_DIR) / f"{preset}.yaml")]
    key_sources = {}
    if stage in cap:
        _merge_section(merged, cap[stage], str(Path(capture_dir) / "capture.yaml"), key_sources)
        sources.append(str(Path(capture_dir) / "capture.yaml"))
    if stage == "poses" and "light_intensity" in cap:  # the one route of the light (module docstring)
        merged["light_intensity"] = cap["light_intensity"]
        key_sources["light_intensity"] = str(Path(capture_dir) / "capture.yaml")
        if str(Path(capture_dir) / "capture.yaml") not in sources:
            sources.append(str(Path(capture_dir) / "capture.yaml"))
    merged["_sources"] = sources
    merged["_key_sources"] = key_sources
    merged["_preset"] = preset
    return merged


def _merge_section(merged: dict, update: dict, source: str, key_sources: dict, prefix: str = "") -> None:
    """``merged`` updated by ``update`` (capture.yaml's section over the preset's), section by
    section: a section both give (a mapping in both) keeps the preset's keys the capture does not
    give. ``key_sources`` gets the dotted key of each value taken from ``source``."""
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = copy.deepcopy(merged[key])
            _merge_section(merged[key], value, source, key_sources, f"{prefix}{key}.")
        else:
            merged[key] = copy.deepcopy(value)
            key_sources[prefix + key] = source


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
    name the files in error messages. One addition: a job of a GPU stage (:data:`recon.stages.GPU_STAGES`) whose
    resources request a GPU (:func:`job_variant`) renders with ``cuda_ad_rgb`` unless its
    settings name a variant (not tracked: the device is where a job runs, not a setting).
    """
    capture_dir = Path(job.config["captures"]) / job.wildcards.capture
    settings = stage_settings(stage, job.config["preset"], capture_dir, presets_dir)
    variant = job_variant(getattr(job, "resources", None))
    if stage in GPU_STAGES and variant and not settings.get("variant"):
        settings["variant"] = variant
    return settings


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


def build_settings(cls: type[T], values: dict | None, source: str = "settings", _label: str | None = None) -> T:
    """Build the frozen dataclass ``cls`` from ``values``, rejecting unknown keys.

    Lists become tuples where the field is a tuple; ``_``-prefixed bookkeeping keys are ignored.
    A class with sections (:mod:`recon.sections`) takes each section as a mapping, built the same
    way; a flat key from before the sections (``poses: {sift_upsample: 2}``) is moved to its place
    (``features.sift_upsample``) with a one-line warning naming the file and the new place
    (:func:`recon.sections.move_flat`). Where the section gives the key too, the capture's value
    wins over the preset's; both in one file with different values is an error naming both.
    """
    values = dict(values or {})
    sources = values.pop("_sources", None)
    key_sources = dict(values.pop("_key_sources", None) or {})
    values.pop("_preset", None)
    where = " / ".join(sources) if sources else source
    label = _label or cls.__name__

    def where_is(*keys):  # the one file the keys came from, when that is known
        files = {key_sources.get(k, sources[0] if sources else source) for k in keys}
        return files.pop() if len(files) == 1 else where

    fields = {f.name: f for f in dataclasses.fields(cls)}
    sections = section_types(cls)
    if sections:
        values = _move_flat_keys(cls, values, key_sources, where_is, label)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where_is(*unknown)}: unknown {label} key(s) {unknown}; valid keys: {', '.join(sorted(fields))}"
            + (f" (in sections: {', '.join(sorted(sections))}; a flat key names its place in one)" if sections else "")
        )
    hints = typing.get_type_hints(cls)
    signed = set(getattr(cls, "SIGNED_SETTINGS", ()))
    kwargs = {}
    for name, value in values.items():
        if name in sections:
            kwargs[name] = _build_section(sections[name], name, value, sources, key_sources, where_is, source, label)
            continue
        hint = hints.get(name)
        problem = _type_problem(value, hint, name in signed)
        if problem:
            raise ConfigError(f"{where_is(name)}: {label} setting '{name}' {problem}, got {value!r}")
        origin = typing.get_origin(hint)
        if (hint is tuple or origin is tuple) and isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        elif float in _hint_types(hint) and int not in _hint_types(hint) and _is_number(value):
            value = float(value)
        elif int in _hint_types(hint) and float not in _hint_types(hint) and _is_number(value):
            value = int(value)  # a whole number written as 4.0
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:  # the dataclass's own checks: name the file of the keys it names
        named = [k for k in values if re.search(rf"\b{re.escape(k)}\b", str(e))]
        raise ConfigError(f"{where_is(*named) if named else where}: invalid {label} ({e})") from e


def _build_section(section_cls, name, value, sources, key_sources, where_is, source, label):
    """The section ``name`` of a settings class, built by :func:`build_settings` from its mapping."""
    if isinstance(value, section_cls):
        return value
    if not isinstance(value, dict):
        raise ConfigError(f"{where_is(name)}: {label} section '{name}' must be a mapping of setting names "
                          f"to values, got {value!r}")
    inner = {k[len(name) + 1:]: f for k, f in key_sources.items() if k.startswith(f"{name}.")}
    if name in key_sources:  # the whole section came from one file
        inner = {**dict.fromkeys(value, key_sources[name]), **inner}
    return build_settings(section_cls, {**value, "_sources": sources, "_key_sources": inner}, source,
                          _label=f"{label}.{name}")


def _move_flat_keys(cls, values: dict, key_sources: dict, where_is, label: str) -> dict:
    """``values`` with the flat keys of a class with sections moved to their places, each with a
    one-line warning; a flat key that its section gives too: the capture's value wins over the
    preset's, and one file giving both with different values is an error naming both.
    ``key_sources`` gets each moved key's file under its new place."""
    moved_values, moved = move_flat(cls, values)
    for key, path in moved:
        in_section = _lookup(values, path)
        file = where_is(key)
        _log.warning("%s: '%s' is deprecated here: its place is now '%s' (%s sections); move it there",
                     file, key, path, label)
        if in_section is not _MISSING and in_section != values[key]:
            if key_sources.get(path) == key_sources.get(key):
                raise ConfigError(f"{file}: {label} gives '{key}' ({values[key]!r}) and '{path}' "
                                  f"({in_section!r}); keep '{path}' only")
            if key_sources.get(path) is not None:  # the section's value is the capture's: it wins
                moved_values = _with_path(moved_values, path, in_section)
                continue
        if key in key_sources:
            key_sources[path] = key_sources[key]
    return moved_values


_MISSING = object()


def _lookup(values: dict, path: str):
    for part in path.split("."):
        if not isinstance(values, dict) or part not in values:
            return _MISSING
        values = values[part]
    return values


def _with_path(values: dict, path: str, value) -> dict:
    head, _, rest = path.partition(".")
    out = dict(values)
    out[head] = _with_path(out.get(head) or {}, rest, value) if rest else value
    return out


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _hint_types(hint) -> tuple:
    """The classes a field's type hint allows (``X | None`` -> (X, NoneType)); () when unknown."""
    if hint is None:
        return ()
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return tuple(typing.get_origin(h) or h for h in typing.get_args(hint))
    return (typing.get_origin(hint) or hint,)


def _type_problem(value, hint, signed: bool = False) -> str | None:
    """What is wrong with ``value`` for a field typed ``hint`` (None: nothing).

    A YAML file can give any type: a string for a number, a number for a switch. Numbers
    (int, float) must be finite and, unless the field is in the dataclass's
    ``SIGNED_SETTINGS``, not negative (counts, sizes, rates and weights); an ``int`` field
    takes whole numbers only, a ``bool`` field true/false only. Fields of other types are left
    to the dataclass's own checks.
    """
    allowed = _hint_types(hint)
    if not allowed or value is None and type(None) in allowed:
        return None
    numeric = [t for t in allowed if t in (int, float)]
    if _is_number(value) and numeric:
        if not math.isfinite(value):
            return "must be a finite number"
        if int in numeric and float not in numeric and value != int(value):
            return "must be a whole number"
        if value < 0 and not signed:
            return "must not be negative"
        return None
    if isinstance(value, bool) and bool in allowed:
        return None
    if isinstance(value, str) and str in allowed:
        return None
    if isinstance(value, (list, tuple)) and (tuple in allowed or list in allowed):
        return None
    if not set(allowed) <= {int, float, bool, str, tuple, list, type(None)}:
        return None  # a type this check does not know: the dataclass decides
    names = {int: "a whole number", float: "a number", bool: "true or false", str: "a string",
             tuple: "a list", list: "a list", type(None): "null"}
    want = " or ".join(dict.fromkeys(names[t] for t in allowed))
    return f"must be {want}"


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
    for p in sorted(root.iterdir()):
        if p.is_dir() and not p.name.startswith(".") and not (p / "images").is_dir():
            photos = [q.name for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTENSIONS]
            shown = ", ".join(sorted(photos)[:3]) + (", ..." if len(photos) > 3 else "")
            hint = (f"; it holds {len(photos)} photo(s) ({shown}): move them into {p / 'images'}/ "
                    "to make it a capture") if photos else ""
            _log.warning("%s: no images/ folder, so it is not a capture and is skipped%s", p, hint)
    if not names:
        raise ConfigError(
            f"no capture folders in '{root}': each capture is a folder with an images/ folder "
            "(DESIGN section 1)"
        )
    return names
