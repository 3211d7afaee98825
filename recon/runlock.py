"""One run at a time per results folder, with a lock that a crash cannot leave behind.

Snakemake's own lock is a set of files under ``.snakemake/locks`` that only a clean exit
removes: after ``kill -9`` or a power loss every later run stopped with ``LockException`` until
``--unlock`` (which also clears the locks of other runs that are still going). recon's workflow
profile turns it off (``nolock``) and takes this lock instead, when the run starts
(``onstart``, so dry runs never wait for it): an exclusive ``flock`` on
``<results>/.recon-run.lock``. The kernel releases a ``flock`` when its holder exits however it
exits, so a crashed run never blocks the next one, and a second run started on the same results
while the first is working is refused with a message that names the first one.
"""

from __future__ import annotations

import datetime
import errno
import fcntl
import json
import os
import socket
import sys
from pathlib import Path

LOCK_NAME = ".recon-run.lock"


class RunLockError(RuntimeError):
    """Another run is working on the same results folder."""


class RunLock:
    """An exclusive lock on a results folder, held until :meth:`release` or the process exits."""

    def __init__(self, results: str | os.PathLike):
        self.results = Path(results).resolve()
        self.path = self.results / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        """Take the lock or raise :class:`RunLockError` naming the run that holds it."""
        self.results.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            raise RunLockError(
                f"another run is working on the results folder '{self.results}' ({self._holder()}); "
                "two runs at once would write the same files: wait for it to finish (or stop it), then run "
                "the same command again"
            ) from None
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                "command": " ".join(sys.argv)}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
        self._fd = fd
        return self

    def _holder(self) -> str:
        try:
            info = json.loads(self.path.read_text() or "{}")
        except (OSError, ValueError):
            info = {}
        if not info:
            return "it is starting"
        return f"pid {info.get('pid')} on {info.get('host')}, started {info.get('started')}: {info.get('command')}"

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


_HELD: dict[Path, RunLock] = {}


def lock_results(results: str | os.PathLike) -> RunLock:
    """Take (once per process) the lock of ``results`` and keep it until the process exits."""
    key = Path(results).resolve()
    if key not in _HELD:
        _HELD[key] = RunLock(key).acquire()
    return _HELD[key]
