"""Fixtures: one set of report inputs (report_scene.py) and the report made from it."""

from __future__ import annotations

import json

import pytest
import report_scene


@pytest.fixture(scope="session")
def scene(tmp_path_factory) -> report_scene.Scene:
    return report_scene.build(tmp_path_factory.mktemp("report-inputs"))


@pytest.fixture(scope="session")
def fast_settings():
    from recon.report import ReportSettings

    return ReportSettings(spp=report_scene.SPP, chamfer_samples=20_000, texture_samples=20_000)


@pytest.fixture(scope="session")
def report(scene, fast_settings):
    """The report of ``scene`` (with ground truth and benchmarks): (folder, returned metrics, metrics.json as read back)."""
    from recon.report import make_report

    out = scene.results / "report"
    returned = make_report(**scene.report_args(out), settings=fast_settings)
    return out, returned, json.loads((out / "metrics.json").read_text())
