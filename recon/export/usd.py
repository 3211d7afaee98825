"""USD writer: ``asset.usda`` (root layer) and ``asset.usdz`` (it packaged with its textures).

Layout (material mapping and frames: :mod:`recon.export.conventions`)::

    /asset                    Xform, defaultPrim, kind = component (no transform of its own,
                              so a referencing prim may set one without losing ours)
    /asset/geom               Xform, xformOp:transform = object_to_world (+Y up, metres)
    /asset/geom/mesh          Mesh: points (cameras.json frame), vertex normals
                              (area-weighted), primvars:st faceVarying indexed (OBJ/USD
                              convention: origin bottom-left), subdivisionScheme none
    /asset/Looks/material     Material: UsdPreviewSurface (useSpecularWorkflow 1) fed by
                              three UsdUVTexture nodes and one UsdPrimvarReader_float2

Stage metadata: upAxis Y, metersPerUnit 1. The usdz is made from the root layer file
(``UsdUtils.CreateNewUsdzPackage``), never from ``stage.Export()``, which writes absolute
texture paths that break packaging.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from recon.io.mesh import Mesh

log = logging.getLogger(__name__)

__all__ = ["write_usd"]


def _texture(stage, material_path, name: str, file: str, color_space: str, st_output):
    from pxr import Sdf, UsdShade

    tex = UsdShade.Shader.Define(stage, material_path.AppendChild(name))
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{file}"))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_output)
    return tex


def write_usd(
    usda_path: str | os.PathLike,
    usdz_path: str | os.PathLike,
    mesh: Mesh,
    textures: dict[str, Path],
    object_to_world: np.ndarray,
    extras: dict | None = None,
) -> None:
    """Write the root layer ``usda_path`` and the package ``usdz_path``.

    Not atomic on its own: :func:`recon.export.asset.export_asset` calls it inside a
    temporary folder. The texture files must already sit beside ``usda_path``.

    Parameters
    ----------
    mesh : Mesh with UVs (OBJ convention), vertex data in the cameras.json frame.
    textures : dict
        PNG paths under ``diffuse``, ``specular``, ``metallic_roughness``, in the folder of
        ``usda_path``.
    object_to_world : (4, 4) float
        Column-vector convention (p_world = T @ p); written transposed, as USD multiplies
        row vectors.
    extras : dict, optional
        Stored in the layer's ``customLayerData["recon"]``.
    """
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

    usda_path, usdz_path = Path(usda_path), Path(usdz_path)
    for key, p in textures.items():
        if Path(p).parent.resolve() != usda_path.parent.resolve():
            raise ValueError(f"texture {key} ({p}) must be beside {usda_path}")

    stage = Usd.Stage.CreateNew(str(usda_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    root = UsdGeom.Xform.Define(stage, "/asset")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    if extras:
        stage.GetRootLayer().customLayerData = {"recon": {
            k: (Vt.DoubleArray(v) if isinstance(v, list) else v) for k, v in extras.items()
        }}

    geom = UsdGeom.Xform.Define(stage, "/asset/geom")
    T = np.asarray(object_to_world, dtype=np.float64)
    geom.AddTransformOp().Set(Gf.Matrix4d(T.T.tolist()))

    # ---- Mesh ----
    m = UsdGeom.Mesh.Define(stage, "/asset/geom/mesh")
    points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.v_pos, dtype=np.float32))
    m.CreatePointsAttr(points)
    m.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.t_pos_idx), 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.t_pos_idx.ravel(), dtype=np.int32)))
    vn = mesh.vertex_normals()
    bad = np.linalg.norm(vn, axis=1) < 0.5
    vn[bad] = (0.0, 0.0, 1.0)
    m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vn, dtype=np.float32)))
    m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    m.CreateDoubleSidedAttr(False)
    st = UsdGeom.PrimvarsAPI(m.GetPrim()).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(mesh.v_tex, dtype=np.float32)))
    st.SetIndices(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.t_tex_idx.ravel(), dtype=np.int32)))

    # ---- Material ----
    UsdGeom.Scope.Define(stage, "/asset/Looks")
    material = UsdShade.Material.Define(stage, "/asset/Looks/material")
    mp = material.GetPath()
    surface = UsdShade.Shader.Define(stage, mp.AppendChild("PreviewSurface"))
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")

    reader = UsdShade.Shader.Define(stage, mp.AppendChild("stReader"))
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    names = {k: Path(p).name for k, p in textures.items()}
    diffuse = _texture(stage, mp, "diffuseTexture", names["diffuse"], "sRGB", st_out)
    specular = _texture(stage, mp, "specularTexture", names["specular"], "sRGB", st_out)
    rough = _texture(stage, mp, "roughnessTexture", names["metallic_roughness"], "raw", st_out)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        diffuse.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    surface.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        specular.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(
        rough.CreateOutput("g", Sdf.ValueTypeNames.Float))

    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    del stage

    _package(usda_path, [Path(p) for p in textures.values()], usdz_path)
    log.info("wrote %s and %s", usda_path, usdz_path)


# The modification time given to every file in the usdz: midnight of 2000-01-01 in local time,
# so that the zip's DOS date and time fields (local time) read the same on every machine.
_PACKAGE_MTIME = (2000, 1, 1, 0, 0, 0, 0, 0, -1)


def _package(usda_path: Path, textures: list[Path], usdz_path: Path) -> None:
    """``UsdUtils.CreateNewUsdzPackage`` of the root layer and its textures, byte for byte the
    same for the same files: the package's zip headers carry each file's modification time, so
    it is made from copies stamped with one fixed time (the deliverables beside it keep theirs,
    which Snakemake reads). Without this, two exports of the same inputs differed in the usdz
    alone (tests/workflow/test_faults.py's re-export compares the folder byte for byte)."""
    import shutil
    import tempfile
    import time

    from pxr import Sdf, UsdUtils

    stamp = time.mktime(_PACKAGE_MTIME)
    with tempfile.TemporaryDirectory(prefix=".usdz-", dir=usdz_path.parent) as scratch:
        for src in [usda_path, *textures]:
            dst = Path(scratch) / src.name
            shutil.copyfile(src, dst)
            os.utime(dst, (stamp, stamp))
        root = Path(scratch) / usda_path.name
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(root)), str(usdz_path)):
            raise OSError(f"{usdz_path}: UsdUtils.CreateNewUsdzPackage failed for {usda_path}")
