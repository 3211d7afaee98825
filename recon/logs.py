"""Logging set-up for stage runs: everything the library logs goes to the stage's log file."""

from __future__ import annotations

import logging
import os
import sys


def configure(log_path: str | os.PathLike | None = None, level: int = logging.INFO) -> None:
    """Send ``recon``'s log records to ``log_path`` (and stderr), one line each."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if log_path:
        os.makedirs(os.path.dirname(os.path.abspath(log_path)), exist_ok=True)
        handlers.append(logging.FileHandler(log_path, mode="w"))
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    for h in handlers:
        h.setFormatter(fmt)
        root.addHandler(h)
    root.setLevel(level)
