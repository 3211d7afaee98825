"""Checkpoints: everything a killed run needs to continue as if it had never stopped.

A checkpoint holds the stage index and the next iteration, the stage's mesh (connectivity,
UVs, the positions at the start of the stage, which the surface guard measures new defects
against), the raw parameters, the optimizer state, the iteration log so far, phase timings and
the fingerprint of the inputs and settings. View sampling and render seeds are functions of
(seed, stage, iteration) (:func:`iteration_rng`, :func:`render_seed`), so the random state is
the iteration counter itself. Files are written atomically (tmp + rename); a checkpoint whose
fingerprint differs from the current run's is ignored.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import torch

from recon.io.atomic import atomic_path

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "last.pt"
FORMAT_VERSION = 1


def iteration_rng(seed: int, stage: int, iteration: int) -> np.random.Generator:
    """The generator of one iteration's random choices (views), independent of history."""
    return np.random.default_rng([int(seed), int(stage), int(iteration)])


def render_seed(seed: int, stage: int, iteration: int) -> int:
    """A 31-bit seed for the renderer's sampler, distinct per (seed, stage, iteration)."""
    h = hashlib.blake2b(f"{seed}/{stage}/{iteration}".encode(), digest_size=4).digest()
    return int.from_bytes(h, "little") & 0x7FFFFFFF


def file_digest(path: str | os.PathLike) -> str:
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def fingerprint(settings_dict: dict, files: list) -> str:
    """Hash of the settings that shape the result and the contents of the input files."""
    s = {k: v for k, v in settings_dict.items() if k not in ("checkpoint_every",)}
    h = hashlib.blake2b(digest_size=16)
    h.update(json.dumps(s, sort_keys=True, default=str).encode())
    for f in files:
        if f is None:
            h.update(b"<none>")
            continue
        h.update(str(Path(f).name).encode())
        h.update(file_digest(f).encode() if Path(f).is_file() else b"-")
    return h.hexdigest()


def save(ckpt_dir: str | os.PathLike, state: dict) -> Path:
    """Write ``state`` as ``ckpt_dir/last.pt`` atomically; returns the path."""
    path = Path(ckpt_dir) / CHECKPOINT_NAME
    state = dict(state, format_version=FORMAT_VERSION)
    try:
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
    except (OSError, RuntimeError) as e:
        # torch's writer reports a full disk as "RuntimeError: [enforce fail at
        # inline_container.cc:...] unexpected pos ...": say what it is and where
        if getattr(e, "errno", None) == errno.ENOSPC or _disk_full(path.parent):
            raise OSError(errno.ENOSPC, f"{path.parent}: no space left on device while writing the optimizer's "
                                        "checkpoint; free some space there (or pass results= on another disk) "
                                        "and rerun: the run resumes from its last checkpoint") from e
        raise
    return path


def _disk_full(folder: Path, margin: int = 1 << 20) -> bool:
    """True when ``folder``'s file system has less than ``margin`` bytes free."""
    try:
        return shutil.disk_usage(folder).free < margin
    except OSError:
        return False


def load(ckpt_dir: str | os.PathLike, expected_fingerprint: str) -> dict | None:
    """The last checkpoint when it belongs to this run (same fingerprint), else None."""
    path = Path(ckpt_dir) / CHECKPOINT_NAME
    if not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # a truncated file cannot happen (atomic writes) but a foreign one can
        log.warning("%s: unreadable checkpoint (%s); starting from scratch", path, e)
        return None
    if state.get("format_version") != FORMAT_VERSION or state.get("fingerprint") != expected_fingerprint:
        log.warning("%s: checkpoint of other inputs or settings; starting from scratch", path)
        return None
    return state
