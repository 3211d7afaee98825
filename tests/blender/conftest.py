"""Fixtures: the exported assets (``case``) and what Blender made of them (``blender``).
Helpers and the list of assets: blender_case.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from blender_case import DEMO_GT, BlenderResult, Case, asset_views, run_blender
from export_readers import read_glb, read_usdz  # on sys.path through blender_case

from recon.io.cameras import load_cameras


def _cases() -> list[str]:
    return ["gt"] + (["results"] if os.environ.get("RECON_BLENDER_RESULTS") else [])


@pytest.fixture(scope="session", params=_cases())
def case(request, tmp_path_factory) -> Case:
    if request.param == "gt":
        from recon.export import ExportSettings, export_asset

        out = tmp_path_factory.mktemp("gt") / "export"
        export_asset(DEMO_GT / "mesh.obj", DEMO_GT / "diffuse.exr", DEMO_GT / "specular.exr",
                     DEMO_GT / "roughness.exr", out, ExportSettings(),
                     cameras_json=DEMO_GT / "cameras.json")
        return Case("gt", out, load_cameras(DEMO_GT / "cameras.json"))
    results = Path(os.environ["RECON_BLENDER_RESULTS"])
    for p in (results / "export" / "asset.glb", results / "export" / "asset.usdz",
              results / "poses" / "cameras.json"):
        if not p.is_file():
            pytest.fail(f"RECON_BLENDER_RESULTS={results}: {p} not found (run the pipeline first)")
    return Case(f"results:{results.name}", results / "export",
                load_cameras(results / "poses" / "cameras.json"))


_RESULTS: dict = {}


@pytest.fixture(scope="session")
def blender(case, tmp_path_factory):
    """``blender(fmt, fix=False)``: the asset opened (and rendered) in Blender, cached."""

    def get(fmt: str, fix: bool = False) -> BlenderResult:
        key = (case.name, fmt, fix)
        if key not in _RESULTS:
            path = case.export / f"asset.{fmt}"
            asset = (read_glb if fmt == "glb" else read_usdz)(path)
            views, intensity = asset_views(case.cameras, asset.object_to_world)
            out = tmp_path_factory.mktemp(f"blender_{fmt}{'_fix' if fix else ''}")
            scene, loops = run_blender(path, out, views, intensity,
                                       ("--fix-usd-specular",) if fix else ())
            _RESULTS[key] = BlenderResult(scene, loops, out, views, intensity, asset)
        return _RESULTS[key]

    return get
