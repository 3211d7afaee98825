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
