"""Validators: the export passes the Khronos glTF validator and every UsdValidation validator;
negative controls show both catch broken files."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pygltflib
import pytest

from recon.export import ValidatorUnavailable, gltf_errors, validate_gltf, validate_usdz
from recon.export.validate import TOOL_DIR


@pytest.fixture(scope="module")
def gltf_validator():
    if shutil.which("node") is None or not (TOOL_DIR / "node_modules" / "gltf-validator").is_dir():
        (pytest.fail if os.environ.get("CI") else pytest.skip)("glTF validator not installed: apt-get install -y nodejs npm && "
                    "npm ci --prefix tools/gltf-validator (scripts/setup.sh does it)")
    return validate_gltf


def test_glb_is_valid(gltf_validator, exported):
    report = gltf_validator(exported["glb"])
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    assert report["info"]["extensionsUsed"] == ["KHR_materials_specular"]
    assert report["info"]["totalTriangleCount"] > 1000
    assert report["info"]["hasTextures"]
    assert gltf_errors(report) == []


def _corrupt(exported, tmp_path, edit) -> str:
    g = pygltflib.GLTF2().load(str(exported["glb"]))
    blob = bytearray(g.binary_blob())
    edit(g, blob)
    g.set_binary_blob(bytes(blob))
    path = tmp_path / "broken.glb"
    g.save_binary(str(path))
    return path


def test_glb_with_out_of_range_index_fails(gltf_validator, exported, tmp_path):
    def edit(g, blob):
        view = g.bufferViews[g.accessors[g.meshes[0].primitives[0].indices].bufferView]
        blob[view.byteOffset + 20: view.byteOffset + 24] = np.uint32(10**6).tobytes()

    errors = gltf_errors(gltf_validator(_corrupt(exported, tmp_path, edit)))
    assert any(e.startswith("ACCESSOR_INDEX_OOB") for e in errors), errors


def test_glb_with_wrong_position_bounds_fails(gltf_validator, exported, tmp_path):
    def edit(g, blob):
        g.accessors[0].max = [0.1, 0.1, 0.1]

    errors = gltf_errors(gltf_validator(_corrupt(exported, tmp_path, edit)))
    assert any(e.startswith("ACCESSOR_MAX_MISMATCH") for e in errors), errors


def test_glb_with_nan_normal_fails(gltf_validator, exported, tmp_path):
    def edit(g, blob):
        view = g.bufferViews[g.accessors[1].bufferView]
        blob[view.byteOffset: view.byteOffset + 4] = np.float32(np.nan).tobytes()

    errors = gltf_errors(gltf_validator(_corrupt(exported, tmp_path, edit)))
    assert any(e.startswith("ACCESSOR_INVALID_FLOAT") for e in errors), errors


def test_validate_gltf_errors(tmp_path, monkeypatch, exported):
    with pytest.raises(FileNotFoundError, match="nothing.glb"):
        validate_gltf(tmp_path / "nothing.glb")
    monkeypatch.setenv("RECON_GLTF_VALIDATOR", str(tmp_path))
    with pytest.raises(ValidatorUnavailable, match="npm ci --prefix"):
        validate_gltf(exported["glb"])


def test_usdz_is_valid(exported):
    assert validate_usdz(exported["usdz"], include_warnings=True) == []


def _repackage(exported, tmp_path, edit) -> str:
    """A copy of the export with asset.usda edited, packaged again."""
    from pxr import Sdf, UsdUtils

    folder = tmp_path / "copy"
    shutil.copytree(exported["usda"].parent, folder)
    usda = folder / "asset.usda"
    usda.write_text(edit(usda.read_text()))
    usdz = folder / "broken.usdz"
    UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(usda)), str(usdz))
    assert usdz.is_file()
    return usdz


def test_usdz_with_broken_texture_reference_fails(exported, tmp_path):
    usdz = _repackage(exported, tmp_path, lambda t: t.replace("./specular.png", "./missing.png"))
    errors = validate_usdz(usdz)
    assert any("UnresolvableDependency" in e and "missing.png" in e for e in errors), errors


def test_usdz_without_stage_metadata_fails(exported, tmp_path):
    usdz = _repackage(exported, tmp_path,
                      lambda t: t.replace('upAxis = "Y"', "").replace("metersPerUnit = 1", ""))
    errors = validate_usdz(usdz)
    assert any("MissingUpAxisMetadata" in e for e in errors), errors
    assert any("MissingMetersPerUnitMetadata" in e for e in errors), errors


def test_usdz_with_wrong_shader_input_type_fails(exported, tmp_path):
    usdz = _repackage(exported, tmp_path, lambda t: t.replace(
        "int inputs:useSpecularWorkflow = 1", 'string inputs:useSpecularWorkflow = "1"'))
    errors = validate_usdz(usdz)
    assert any("ShaderSdrCompliance" in e for e in errors), errors


def test_validate_usdz_unreadable(tmp_path):
    bad = tmp_path / "bad.usdz"
    bad.write_bytes(b"not a zip")
    assert validate_usdz(bad)
    with pytest.raises(FileNotFoundError):
        validate_usdz(tmp_path / "nothing.usdz")
