import os
import stat

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
