"""Test inputs made once per test session and shared between test modules, also between the
processes of ``pytest -n N`` (pytest-xdist; scripts/run_tests.sh runs the suite that way)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def made_once(base: Path, name: str, make: Callable[[Path], None], done: str = "gt/cameras.json") -> Path:
    """``<root>/<name>``, made by ``make(path)`` unless its file ``done`` is there.

    ``base`` is pytest's ``tmp_path_factory.getbasetemp()``. Under pytest-xdist each worker has
    its own (``<run>/popen-gwN``); the input then goes into the run's folder above them, and a
    file lock lets one worker make it while the others wait for it, so that no render is made
    twice and no worker reads one half written.
    """
    from filelock import FileLock

    root = Path(base)
    if root.name.startswith("popen-gw"):
        root = root.parent
    out = root / name
    with FileLock(str(out) + ".lock"):
        if not (out / done).is_file():
            make(out)
    return out
