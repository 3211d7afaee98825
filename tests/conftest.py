"""Shared fixtures: paths to the repository, the shared real data, and a CPU Mitsuba variant."""

from __future__ import annotations

import os
from pathlib import Path

# before any plugin imports torch: see recon/__init__.py (OpenMP threads must not spin)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository; tests that need it skip when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (it sits beside the repository in CI)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the CPU variant (tests never depend on a GPU)."""
    from recon.mi import load_variant

    return load_variant("llvm_ad_rgb")
