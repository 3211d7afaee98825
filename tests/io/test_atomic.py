import os
import stat
import time
from pathlib import Path

import pytest

from recon.io.atomic import atomic_dir, atomic_path


def test_atomic_path_replaces_only_on_success(tmp_path):
    dest = tmp_path / "a.txt"
    dest.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert dest.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with atomic_path(dest) as tmp:
        assert tmp.suffix == ".txt" and tmp.parent == tmp_path
        tmp.write_text("new")
    assert dest.read_text() == "new"
    mode = stat.S_IMODE(dest.stat().st_mode)
    assert mode == 0o666 & ~_umask()


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_atomic_dir_leaves_previous_result_on_failure(tmp_path):
    out = tmp_path / "stage"
    with atomic_dir(out) as d:
        (d / "x").write_text("1")
    assert (out / "x").read_text() == "1"
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~_umask()
    with pytest.raises(ValueError):
        with atomic_dir(out) as d:
            (d / "x").write_text("2")
            raise ValueError("bad input")
    assert (out / "x").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]
    with atomic_dir(out) as d:
        (d / "y").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == ["y"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]


_KILLED_WRITER = """
import os, signal, sys
from recon.io.atomic import atomic_dir, atomic_path
out = sys.argv[1]
with atomic_path(out + "/file.txt") as t:
    t.write_text("half")
    with atomic_dir(out + "/stage") as d:
        (d / "x").write_text("half")
        os.kill(os.getpid(), signal.SIGKILL)
"""


def test_temporaries_of_a_killed_writer_are_removed_by_the_next_one(tmp_path):
    """kill -9 inside atomic_dir/atomic_path leaves hidden temporaries; the next write of the same
    destination removes them (their process is gone) and leaves a live writer's alone."""
    import subprocess
    import sys

    with atomic_dir(tmp_path / "stage") as d:
        (d / "x").write_text("previous")
    r = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(tmp_path)], capture_output=True)
    assert r.returncode == -9
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert any(n.startswith(".stage.tmp-") for n in left) and any(n.startswith(".file.tmp-") for n in left), left
    assert (tmp_path / "stage" / "x").read_text() == "previous"  # the previous result survived
    alive = tmp_path / f".stage.tmp-{os.getppid()}-live"  # a running process's temporary
    alive.mkdir()
    with atomic_dir(tmp_path / "stage") as d:
        (d / "x").write_text("new")
    with atomic_path(tmp_path / "file.txt") as t:
        t.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == [alive.name, "file.txt", "stage"]
    assert (tmp_path / "stage" / "x").read_text() == "new"


def test_a_zombie_writers_temporaries_are_removed(tmp_path):
    """A writer killed with its parent stays a zombie until init reaps it, possibly after the
    next run has started: a zombie never writes again, so its temporaries go (seen in the kill
    tests: every killed stage's temporary was left while the rerun ran)."""
    import signal
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        child.send_signal(signal.SIGKILL)
        deadline = time.monotonic() + 120  # a hang guard: a SIGKILLed child is a zombie within milliseconds
        while Path(f"/proc/{child.pid}/stat").read_text().split(") ")[1][:1] != "Z":  # not reaped yet
            assert time.monotonic() < deadline
            time.sleep(0.01)
        (tmp_path / f".stage.tmp-{child.pid}-zombie").mkdir()
        with atomic_dir(tmp_path / "stage") as d:
            (d / "x").write_text("new")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]
    finally:
        child.wait()


def test_data_reach_the_disk_before_the_rename(tmp_path, monkeypatch):
    """fsync (the real one, counted) of every file and folder written, before the rename makes
    them the result: after a power loss a destination is the old or the complete new data. Files
    written inside an atomic_dir are flushed once, with their folder."""
    import recon.io.atomic as atomic

    synced, renamed = [], []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    def replace(src, dst):
        renamed.append((str(src), str(dst), len(synced)))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic.os, "replace", replace)
    with atomic_path(tmp_path / "one.txt") as tmp:
        tmp.write_text("data")
    assert synced[0] == str(tmp) and renamed[0][2] == 1  # the file, then the rename
    assert synced[1] == str(tmp_path)  # then the folder that holds the new name
    synced.clear()
    renamed.clear()
    with atomic_dir(tmp_path / "stage") as tmp:
        for k in range(3):
            with atomic_path(tmp / f"{k}.txt") as f:
                f.write_text(str(k))
        (tmp / "sub").mkdir()
        (tmp / "sub" / "x.txt").write_text("x")
    files = [s for s in synced if s.endswith(".txt")]
    assert sorted(os.path.basename(s) for s in files) == ["0.txt", "1.txt", "2.txt", "x.txt"]  # once each
    final = renamed[-1]
    assert final[1] == str(tmp_path / "stage") and final[2] == len(synced) - 1  # all before it
    assert synced[-1] == str(tmp_path)
    assert (tmp_path / "stage" / "sub" / "x.txt").read_text() == "x"


def test_existing_folder_is_swapped_in_one_step(tmp_path, monkeypatch):
    """Replacing a stage folder: one renameat2(RENAME_EXCHANGE) where Linux allows it (no
    os.replace, so no instant without the folder); else two renames, and the previous folder is
    put back when the second fails."""
    import recon.io.atomic as atomic

    dest = tmp_path / "export"
    dest.mkdir()
    (dest / "asset.glb").write_text("old")
    calls = []
    real_replace = os.replace
    monkeypatch.setattr(atomic.os, "replace", lambda a, b: (calls.append((a, b)), real_replace(a, b)))
    with atomic_dir(dest) as tmp:
        (tmp / "asset.glb").write_text("new")
    assert (dest / "asset.glb").read_text() == "new" and calls == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]

    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)

    def failing_replace(a, b):
        if Path(a).name.startswith(".export.tmp-"):
            raise OSError(28, "No space left on device", str(b))
        real_replace(a, b)

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space"):
        with atomic_dir(dest) as tmp:
            (tmp / "asset.glb").write_text("newer")
    assert (dest / "asset.glb").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]
