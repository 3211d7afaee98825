"""Fixtures: a small optimize-stage output (export_model.py) and its export."""

from __future__ import annotations

from pathlib import Path

import pytest
from export_model import Model, write_model


@pytest.fixture(scope="session")
def model(tmp_path_factory) -> Model:
    return write_model(tmp_path_factory.mktemp("capture"))


@pytest.fixture(scope="session")
def exported(model, tmp_path_factory) -> dict[str, Path]:
    """The model exported with the default settings (up from the cameras)."""
    from recon.export import ExportSettings, export_asset

    out = tmp_path_factory.mktemp("results") / "export"
    return export_asset(*model.inputs(), out, ExportSettings(), cameras_json=model.cameras_json)
