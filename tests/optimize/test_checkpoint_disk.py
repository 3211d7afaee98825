"""A full disk while the optimizer writes its checkpoint says so and names the folder (torch's own
message is "[enforce fail at inline_container.cc] unexpected pos"), and leaves no partial file
(issue 21 item 7). On a real, tiny tmpfs where the machine lets the test mount one."""

from __future__ import annotations

import errno
import subprocess

import pytest
import torch

from recon.optimize import checkpoint as ckpt


@pytest.fixture
def tiny_disk(tmp_path):
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    mounted = r.returncode == 0
    yield mnt, mounted
    if mounted:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)  # lazy: torch may still hold the file


def test_full_disk_names_the_folder(tiny_disk, monkeypatch):
    folder, mounted = tiny_disk
    if not mounted:  # no mount permission: the same failure, simulated as torch reports it
        def full(*a, **k):
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534")
        monkeypatch.setattr(torch, "save", full)
        monkeypatch.setattr(ckpt, "_disk_full", lambda folder, margin=0: True)
    ckpt_dir = folder / "checkpoints"
    with pytest.raises(OSError, match=r"checkpoints: no space left on device") as info:
        ckpt.save(ckpt_dir, {"geom": torch.zeros(1_000_000)})
    assert info.value.errno == errno.ENOSPC
    assert not any(p.name != "checkpoints" for p in folder.rglob("*") if p.is_file())  # no partial file


def test_other_write_errors_pass_through(tmp_path, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("something else")
    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(RuntimeError, match="something else"):
        ckpt.save(tmp_path / "c", {"x": 1})
