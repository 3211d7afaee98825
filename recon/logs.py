"""Logging for stage runs: the stage's log file holds everything, the terminal the essentials.

Every workflow script runs its stage inside :func:`stage`::

    with stage(snakemake.log[0]):
        run_uv(...)

Inside the block, ``recon``'s log records go to the rule's log file and to stderr, one line each.
When the block raises, the log file gets the traceback and then, as its last line, the error
message; the terminal gets the message and the log's path, and the process exits with status 1.
A user error (:func:`is_user_error`: bad input, a bad setting, a full disk) shows no Python
traceback on the terminal (``RECON_TRACEBACK=1`` shows it); any other exception is a bug in
recon and shows its traceback there too. Ctrl-C exits with status 130 and "interrupted" in the
log; SIGTERM (how Snakemake and batch systems stop a job) with status 143 and "terminated": both
unwind the stage, so its temporary folder is removed and the previous result left in place.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import traceback
from pathlib import Path

log = logging.getLogger("recon.stage")

#: Set to 1 to see the Python traceback of a user error on the terminal too.
TRACEBACK_ENV = "RECON_TRACEBACK"

_FILE_ONLY = "recon_file_only"  # attribute of records that only the log file gets


class _NotFileOnly(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not getattr(record, _FILE_ONLY, False)


def configure(log_path: str | os.PathLike | None = None, level: int = logging.INFO) -> None:
    """Send ``recon``'s log records to ``log_path`` (and stderr), one line each."""
    stderr = logging.StreamHandler(sys.stderr)
    stderr.addFilter(_NotFileOnly())
    handlers: list[logging.Handler] = [stderr]
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


def is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is an error in the user's input or environment rather than a bug.

    User errors are recon's own error classes (``CaptureError``, ``ConfigError``, ``MaskError``,
    ...: every class defined in a ``recon`` module; they name the file and the fix) and
    operating-system errors (``OSError``: no space left, permission denied, a missing file),
    whose message names the path.
    """
    if isinstance(exc, OSError):
        return True
    module = type(exc).__module__ or ""
    return isinstance(exc, Exception) and (module == "recon" or module.startswith("recon."))


def user_message(exc: BaseException) -> str:
    """The one-line (or few-line) message the terminal shows for ``exc``."""
    text = str(exc).strip()
    if is_user_error(exc) and not isinstance(exc, OSError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Terminated(BaseException):
    """SIGTERM received: raised inside the stage so that it unwinds like Ctrl-C."""


def _on_sigterm(signum, frame):
    raise Terminated()


def _show_traceback() -> bool:
    return os.environ.get(TRACEBACK_ENV, "").strip().lower() not in ("", "0", "false", "no")


def _flush() -> None:
    for h in logging.getLogger().handlers:
        with contextlib.suppress(Exception):
            h.flush()


def report_failure(exc: BaseException, stage_name: str, log_path: str | os.PathLike | None) -> None:
    """Log ``exc`` (traceback, then the message as the last line) and tell the terminal.

    The log file gets the traceback and the message; stderr gets the message, where the log is,
    and, for a bug or with ``RECON_TRACEBACK=1``, the traceback.
    """
    user = is_user_error(exc)
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)).rstrip()
    message = user_message(exc)
    log.error("traceback (for the developers):\n%s", tb, extra={_FILE_ONLY: True})
    log.error("%s failed: %s", stage_name, message, extra={_FILE_ONLY: True})
    _flush()
    lines = []
    if not user or _show_traceback():
        lines.append(tb)
    lines.append(f"recon {stage_name}: error: {message}")
    if log_path:
        lines.append(f"  (log: {log_path})")
    if not user:
        lines.append("  This looks like a bug in recon: please report it with the log above.")
    sys.stderr.write("\n".join(lines) + "\n")
    sys.stderr.flush()


@contextlib.contextmanager
def stage(log_path: str | os.PathLike | None, name: str | None = None, level: int = logging.INFO):
    """Run a stage's block with its log set up; on an exception, report it and exit 1.

    ``name`` defaults to the log file's stem (``logs/export.log`` -> ``export``). See the module
    docstring for what goes where.
    """
    stage_name = name or (Path(log_path).stem if log_path else "stage")
    configure(log_path, level)
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    except (KeyboardInterrupt, Terminated) as exc:
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else "terminated"
        log.error("%s %s", stage_name, what)
        _flush()
        sys.stderr.write(f"recon {stage_name}: {what}\n")
        raise SystemExit(130 if what == "interrupted" else 143) from None
    except SystemExit:
        raise
    except BaseException as exc:  # noqa: BLE001 (reported, then the process exits 1)
        report_failure(exc, stage_name, log_path)
        raise SystemExit(1) from None
    finally:
        signal.signal(signal.SIGTERM, previous)
