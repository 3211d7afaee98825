"""Settings in sections: frozen dataclasses whose fields are settings or sections of settings.

A stage's settings class groups its keys into sections, frozen dataclasses themselves
(``PoseSettings.features.sift_upsample``), and the presets and ``capture.yaml`` are written in
the same sections (``poses: {features: {sift_upsample: 2}}``). A leaf name is unique within its
class, so a flat name from before the sections still names one place (:func:`leaf_paths`); a
class that also renamed keys lists them in ``MOVED = {"old_name": "section.new_name"}``.

Where a flat name is still met:

- a preset or ``capture.yaml``: :func:`recon.config.build_settings` moves the key to its place
  with a one-line warning naming the file, the key and its new place (:func:`move_flat`); a key
  that names no place is refused with the valid keys;
- Python: ``Settings(n_views=3)``, ``dataclasses.replace(s, n_views=3)`` and ``s.n_views`` work
  on a class decorated with :func:`sectioned`, each with a DeprecationWarning naming the new
  place; :func:`replace` is the way to change settings by leaf name (the synth command line).

Nothing here imports recon: every settings module may use it.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
import warnings


def _is_section_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


@functools.cache
def section_types(cls: type) -> dict[str, type]:
    """``{field: section class}`` of the fields of ``cls`` that are sections."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if _is_section_type(hints.get(f.name))}


@functools.cache
def leaf_paths(cls: type) -> dict[str, str]:
    """``{flat name: dotted path}`` of every setting inside a section of ``cls`` (and ``cls.MOVED``).

    The settings at the top level of ``cls`` are left out (their name is their place), and so is
    a name that two sections share (it names no one place).
    """
    paths: dict[str, str] = {}
    shared: set[str] = set()

    def walk(c: type, prefix: str) -> None:
        sections = section_types(c)
        for f in dataclasses.fields(c):
            if f.name in sections:
                walk(sections[f.name], f"{prefix}{f.name}.")
            elif prefix:
                if f.name in paths:
                    shared.add(f.name)
                paths[f.name] = prefix + f.name

    walk(cls, "")
    top = {f.name for f in dataclasses.fields(cls)}
    paths = {k: v for k, v in paths.items() if k not in shared and k not in top}
    paths.update(getattr(cls, "MOVED", {}))
    return paths


def get_path(settings, path: str):
    """The value at the dotted ``path`` of ``settings`` (``"features.sift_upsample"``)."""
    for part in path.split("."):
        settings = getattr(settings, part)
    return settings


def _default(cls: type, name: str):
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def _set_path(settings, path: str, value):
    """``settings`` with the value at the dotted ``path`` replaced (sections copied, never changed)."""
    head, _, rest = path.partition(".")
    if rest:
        value = _set_path(getattr(settings, head), rest, value)
    return dataclasses.replace(settings, **{head: value})


def replace(settings, **changes):
    """``settings`` with ``changes``: top-level fields, whole sections, or settings by leaf name.

    ``replace(s, n_views=8, fov=50.0)`` sets each leaf in its section (:func:`leaf_paths`), all
    changes at once (the class's checks see the final settings only); a name that is neither a
    field nor a leaf raises TypeError naming it.
    """
    cls = type(settings)
    fields = {f.name for f in dataclasses.fields(cls)}
    paths = leaf_paths(cls)
    unknown = sorted(k for k in changes if k not in fields and k not in paths)
    if unknown:
        raise TypeError(f"{cls.__name__} has no setting(s) {unknown}")
    return _replace_paths(settings, {k if k in fields else paths[k]: v for k, v in changes.items()})


def _replace_paths(settings, changes: dict):
    """``settings`` with the values of ``changes`` (dotted paths) in one replace per level."""
    direct, nested = {}, {}
    for path, value in changes.items():
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, sub in nested.items():
        direct[head] = _replace_paths(direct.get(head, getattr(settings, head)), sub)
    return dataclasses.replace(settings, **direct)


def flatten(settings) -> dict:
    """``{leaf name: value}`` of ``settings``, sections walked in place (declaration order)."""
    out = {}
    sections = section_types(type(settings))
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if f.name in sections:
            out.update(flatten(value))
        else:
            out[f.name] = value
    return out


def move_flat(cls: type, values: dict) -> tuple[dict, list[tuple[str, str]]]:
    """``values`` (a settings mapping, as from YAML) with flat keys moved into their sections.

    Returns ``(values, moved)``: a copy whose section mappings hold the flat keys under their
    names in the section, and ``[(flat key, dotted path)]`` of the keys moved. A key that is no
    field of ``cls`` and no leaf (:func:`leaf_paths`) is left where it is, for the caller to
    refuse. Where the section gives the key as well, the flat key replaces it: the caller decides
    before which of the two wins (:func:`recon.config.build_settings`).
    """
    fields = {f.name for f in dataclasses.fields(cls)}
    paths = leaf_paths(cls)
    out = dict(values)
    moved = []
    for key in list(out):
        if key in fields or key not in paths:
            continue
        value = out.pop(key)
        *heads, leaf = paths[key].split(".")
        node = out
        for head in heads:
            child = node.get(head)
            node[head] = dict(child) if isinstance(child, dict) else {}
            node = node[head]
        node[leaf] = value
        moved.append((key, paths[key]))
    return out, moved


def sectioned(cls: type) -> type:
    """Class decorator (after ``@dataclass(frozen=True)``) for a settings class with sections.

    The class's ``__init__`` also takes a section as a mapping (``matching={"matcher": "ordered"}``)
    and, deprecated, a flat leaf name (``n_views=8``, so ``dataclasses.replace(s, n_views=8)``
    works too); reading ``s.n_views`` gives ``s.<section>.n_views``. Both flat forms warn
    (DeprecationWarning) naming the new place.
    """
    init = cls.__init__
    names = {f.name for f in dataclasses.fields(cls)}

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        sections = section_types(cls)
        for name, value in kwargs.items():
            if name in sections and isinstance(value, dict):
                kwargs[name] = sections[name](**value)
        flat = {k: kwargs.pop(k) for k in [k for k in kwargs if k not in names]}
        if flat:
            paths = leaf_paths(cls)
            unknown = sorted(k for k in flat if k not in paths)
            if unknown:
                raise TypeError(f"{cls.__name__}: unknown setting(s) {unknown}")
            warnings.warn(f"{cls.__name__}: flat setting(s) given; their places are "
                          + ", ".join(f"{k} -> {paths[k]}" for k in flat)
                          + " (pass the sections, or use recon.sections.replace)",
                          DeprecationWarning, stacklevel=2)
            for key, value in flat.items():
                head, _, rest = paths[key].partition(".")
                base = kwargs[head] if head in kwargs else _default(cls, head)
                kwargs[head] = _set_path(base, rest, value)
        init(self, *args, **kwargs)

    def __getattr__(self, name):
        path = leaf_paths(cls).get(name)
        if path is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        warnings.warn(f"{cls.__name__}.{name} is now {cls.__name__}.{path}", DeprecationWarning, stacklevel=2)
        return get_path(self, path)

    cls.__init__ = __init__
    cls.__getattr__ = __getattr__
    return cls
