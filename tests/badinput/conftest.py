"""Fixtures of the bad-input corpus: the good sphere capture (built once) and fresh copies of it."""

from __future__ import annotations

import shutil

import pytest
from badinput_cases import sphere_capture


@pytest.fixture(scope="session")
def sphere_base(tmp_path_factory):
    """The good sphere captures (full, and photos alone), built once per session; copy before editing."""
    root = tmp_path_factory.mktemp("badinput_base")
    return {"full": sphere_capture(root / "full"),
            "photos": sphere_capture(root / "photos", cameras=False, masks=False, init_mesh=False)}


@pytest.fixture
def sphere(sphere_base, tmp_path):
    """A fresh copy of the full good sphere capture."""
    return shutil.copytree(sphere_base["full"], tmp_path / "sphere")
