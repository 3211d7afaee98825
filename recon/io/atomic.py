"""Atomic outputs: a stage either leaves complete files or nothing at all.

Every writer in ``recon`` goes through :func:`atomic_path` (one file) or
:func:`atomic_dir` (a whole stage folder): data is written next to the destination under a
temporary name and renamed into place only on success, so an error or a kill never leaves a
half-written file that a later stage (or Snakemake) would mistake for a result.

Before the rename the data are flushed to the disk (``fsync`` of every file written, then of the
folder holding the new name), so that after a power loss the destination holds the previous
result or the complete new one, never an empty or truncated file (a rename alone may reach the
disk before the data it names).

Temporary names carry the writing process's id (``.<name>.tmp-<pid>-<random>``). A process
killed inside a block (kill -9, power loss) leaves its temporary behind; the next writer of the
same destination removes every such leftover whose process no longer runs, so kills do not
accumulate hidden folders, and a writer that is still running is never disturbed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _running(pid: int) -> bool:
    """Whether process ``pid`` may still write: it exists and is not a zombie. A writer killed
    together with its parent (kill -9 of the run's process group) stays a zombie until init
    reaps it, which can be after the next run has started; it never writes again."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # no procfs (not Linux), or gone meanwhile
        return True
    return stat[stat.rindex(")") + 2 :][:1] not in ("Z", "X")  # state after "pid (comm) "


def _fsync(path: Path, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a folder's entries) to the disk; a file system that cannot
    (some network or virtual ones refuse fsync on folders) is left as it is."""
    try:
        fd = os.open(path, (os.O_RDONLY | os.O_DIRECTORY) if directory else os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_IN_TEMPORARY = re.compile(r"^\.(.+)\.tmp-(\d+)-")


def _inside_temporary_folder(path: Path) -> bool:
    """Whether ``path`` lies in an :func:`atomic_dir` temporary of this process, whose files are
    flushed all together before that folder is renamed."""
    pid = str(os.getpid())
    return any((m := _IN_TEMPORARY.match(p.name)) and m.group(2) == pid for p in path.parents)


def _fsync_tree(root: Path) -> None:
    for folder, _dirs, files in os.walk(root):
        for name in files:
            _fsync(Path(folder) / name)
        _fsync(Path(folder), directory=True)


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries that killed writers of ``path`` left beside it.

    Matches ``.<name>.tmp-<pid>-*`` and ``.<name>.old-<pid>`` (and, for files,
    ``.<stem>.tmp-<pid>-*<suffix>``) whose process is gone; returns what was removed.
    """
    path = Path(path)
    if not path.parent.is_dir():
        return []
    names = {re.escape(path.name), re.escape(path.stem)}
    pattern = re.compile(r"^\.(?:%s)\.(?:tmp|old)-(\d+)(?:-.*)?$" % "|".join(sorted(names)))
    removed = []
    for p in path.parent.iterdir():
        m = pattern.match(p.name)
        if m is None or int(m.group(1)) == os.getpid() or _running(int(m.group(1))):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
        removed.append(p)
    if removed:
        log.info("removed %d temporaries of interrupted runs beside %s: %s", len(removed), path,
                 ", ".join(p.name for p in removed))
    return removed



@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` when the block succeeds.

    ``suffix`` defaults to the destination's, so format-sniffing writers (OpenEXR, OpenCV)
    still see the right extension.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.stem}.tmp-{os.getpid()}-", suffix=suffix if suffix is not None else path.suffix,
        dir=path.parent,
    )
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; results are meant to be shared
    try:
        yield Path(tmp)
        durable = not _inside_temporary_folder(path)
        if durable:
            _fsync(Path(tmp))
        os.replace(tmp, path)
        if durable:
            _fsync(path.parent, directory=True)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike):
    """Yield a fresh temporary folder beside ``path``; it replaces ``path`` on success.

    On failure the temporary folder is removed and ``path`` is left as it was (absent, or the
    previous complete result). An existing ``path`` is swapped with the new folder in one system
    call where Linux allows it (``renameat2`` with ``RENAME_EXCHANGE``), so no instant, and no
    signal or kill, finds the destination missing; elsewhere two renames do it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-{os.getpid()}-", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
    try:
        yield tmp
        _fsync_tree(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.is_dir() and not path.is_symlink() and _exchange(tmp, path):
        # one system call swapped the folders: ``path`` is the new result, ``tmp`` the old one
        _fsync(path.parent, directory=True)
        shutil.rmtree(tmp, ignore_errors=True)
        return
    # no atomic exchange here (a file system without it, or nothing to replace): set the
    # previous result aside, and put it back if the new one cannot take its place
    old = None
    try:
        if path.exists():
            old = path.parent / f".{path.name}.old-{os.getpid()}"
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException:
        if old is not None and not path.exists():
            os.replace(old, path)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _fsync(path.parent, directory=True)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` atomically (Linux renameat2 RENAME_EXCHANGE); False where
    the system or the file system cannot."""
    import ctypes
    import errno

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(b))
