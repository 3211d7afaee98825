"""The USD writer: stage metadata, shading network, packaging."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest


@pytest.fixture(scope="module")
def stage(exported):
    from pxr import Usd

    return Usd.Stage.Open(str(exported["usdz"]))


def test_stage_metadata(stage):
    from pxr import Kind, Usd, UsdGeom

    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    root = stage.GetDefaultPrim()
    assert root.GetPath() == "/asset" and Usd.ModelAPI(root).GetKind() == Kind.Tokens.component
    # The up rotation is below the default prim, so referencing the asset keeps it.
    assert not UsdGeom.Xformable(root).GetOrderedXformOps()
    T = np.asarray(UsdGeom.Xformable(stage.GetPrimAtPath("/asset/geom"))
                   .GetLocalTransformation()).T
    recorded = np.asarray(stage.GetRootLayer().customLayerData["recon"]["object_to_world"])
    assert np.allclose(T, recorded.reshape(4, 4))


def test_shading_network(stage):
    from pxr import UsdGeom, UsdShade

    mesh = stage.GetPrimAtPath("/asset/geom/mesh")
    assert mesh.IsA(UsdGeom.Mesh) and mesh.HasAPI(UsdShade.MaterialBindingAPI)
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    assert surface.GetInput("useSpecularWorkflow").Get() == 1
    want = {"diffuseColor": ("./diffuse.png", "sRGB", "rgb"),
            "specularColor": ("./specular.png", "sRGB", "rgb"),
            "roughness": ("./metallic_roughness.png", "raw", "g")}
    for name, (file, space, output) in want.items():
        (src,), _ = surface.GetInput(name).GetConnectedSources()
        tex = UsdShade.Shader(src.source.GetPrim())
        assert tex.GetIdAttr().Get() == "UsdUVTexture"
        assert tex.GetInput("file").Get().path == file  # relative: packaging keeps it
        assert tex.GetInput("sourceColorSpace").Get() == space
        assert src.sourceName == output
        (st,), _ = tex.GetInput("st").GetConnectedSources()
        reader = UsdShade.Shader(st.source.GetPrim())
        assert reader.GetIdAttr().Get() == "UsdPrimvarReader_float2"
        assert reader.GetInput("varname").Get() == "st"


def test_usdz_package(exported):
    with zipfile.ZipFile(exported["usdz"]) as z:
        infos = z.infolist()
        assert infos[0].filename == "asset.usda"  # the root layer comes first
        assert {i.filename for i in infos} == {"asset.usda", "diffuse.png", "specular.png",
                                              "metallic_roughness.png"}
        assert all(i.compress_type == zipfile.ZIP_STORED for i in infos)
        for i in infos[1:]:
            assert z.read(i) == exported[i.filename.split(".")[0]].read_bytes()


def test_usda_has_no_absolute_paths(exported):
    text = exported["usda"].read_text()
    assert str(exported["usda"].parent) not in text and "@/" not in text


def test_usdz_is_the_same_for_the_same_files(exported, tmp_path):
    """The zip's headers carry file times: two packages of the same files, whose times differ
    (a re-export an hour later), are byte for byte the same, and every entry carries the one
    fixed stamp. The deliverables beside the usdz keep their own times."""
    import os
    import shutil

    from recon.export.usd import _package

    src = tmp_path / "src"
    src.mkdir()
    for name in ("asset.usda", "diffuse.png", "specular.png", "metallic_roughness.png"):
        shutil.copyfile(exported["usda"].parent / name, src / name)
    textures = [src / n for n in ("diffuse.png", "specular.png", "metallic_roughness.png")]
    packages = []
    for shift in (0, 3600):
        for p in [src / "asset.usda", *textures]:
            st = p.stat()
            os.utime(p, (st.st_atime - shift, st.st_mtime - shift))
        before = {p.name: p.stat().st_mtime for p in src.iterdir()}
        out = tmp_path / f"asset{shift}.usdz"
        _package(src / "asset.usda", textures, out)
        assert {p.name: p.stat().st_mtime for p in src.iterdir()} == before
        assert sorted(q.name for q in tmp_path.iterdir()) == sorted(
            ["src", *(f"asset{s}.usdz" for s in (0, 3600) if s <= shift)])  # no scratch left
        packages.append(out.read_bytes())
    assert packages[0] == packages[1]
    with zipfile.ZipFile(tmp_path / "asset0.usdz") as z:
        stamps = {i.date_time for i in z.infolist()}
        # one fixed stamp, midnight 2000-01-01 in local time (a reader in another time zone may see it shifted)
        assert len(stamps) == 1 and next(iter(stamps))[:2] in ((2000, 1), (1999, 12))
        assert z.read("diffuse.png") == (src / "diffuse.png").read_bytes()
