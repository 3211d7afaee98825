"""Independent readers of the exported files, written from the format specifications.

They share nothing with the writers in ``recon.export``: pygltflib + PIL for the .glb, pxr +
zipfile + PIL for the .usdz, sRGB decoding from IEC 61966-2-1 written out here. Each returns
the asset in the frame its file defines (+Y up, the root transforms applied) as a
:class:`recon.io.mesh.Mesh` with OBJ-convention UVs (what the project's renderer takes),
the DESIGN section 3 maps, the stored vertex normals and the root transform.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass

import numpy as np
from PIL import Image

from recon.io.mesh import Mesh


@dataclass
class Asset:
    mesh: Mesh  # world frame, OBJ UVs; positions welded so the renderer's normals match
    normals: np.ndarray  # (V, 3) stored normals (world frame), per welded vertex
    a_d: np.ndarray  # (H, W, 3) linear
    a_s: np.ndarray  # (H, W, 1 or 3) linear
    r: np.ndarray  # (H, W, 1)
    object_to_world: np.ndarray  # (4, 4), column vectors


def srgb_decode(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB EOTF, values in [0, 1]."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def srgb_encode(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0, 1)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def decode_png(data: bytes) -> np.ndarray:
    """(H, W, C) float64 in [0, 1], still encoded."""
    img = Image.open(io.BytesIO(data))
    a = np.asarray(img)
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    a = a.astype(np.float64) / scale
    return a[:, :, None] if a.ndim == 2 else a


def _weld(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray):
    """Merge vertices with identical positions: (V', 3), (F, 3), (V', 3) normals."""
    uniq, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    return uniq, inverse.ravel()[faces], normals[first]


def _world(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


# ---- glTF ----
_COMPONENTS = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _accessor(g, blob: bytes, index: int) -> np.ndarray:
    acc = g.accessors[index]
    view = g.bufferViews[acc.bufferView]
    dtype = np.dtype(_COMPONENTS[acc.componentType])
    width = _WIDTH[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    a = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return a.reshape(acc.count, width) if width > 1 else a


def _node_matrix(node) -> np.ndarray:
    """The node's local matrix (glTF: T * R * S, quaternion (x, y, z, w))."""
    if node.matrix:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major
    x, y, z, w = node.rotation or (0.0, 0.0, 0.0, 1.0)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    M = np.eye(4)
    M[:3, :3] = R @ np.diag(node.scale or (1.0, 1.0, 1.0))
    M[:3, 3] = node.translation or (0.0, 0.0, 0.0)
    return M


def read_glb(path) -> Asset:
    import pygltflib

    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    scene = g.scenes[g.scene or 0]
    (node_index,) = scene.nodes
    node = g.nodes[node_index]
    T = _node_matrix(node)
    (prim,) = g.meshes[node.mesh].primitives
    assert prim.mode in (None, 4)
    pos = _accessor(g, blob, prim.attributes.POSITION).astype(np.float64)
    nrm = _accessor(g, blob, prim.attributes.NORMAL).astype(np.float64)
    uv_gltf = _accessor(g, blob, prim.attributes.TEXCOORD_0).astype(np.float64)
    faces = _accessor(g, blob, prim.indices).astype(np.int64).reshape(-1, 3)

    def image(tex_info) -> np.ndarray:
        img = g.images[g.textures[tex_info["index"] if isinstance(tex_info, dict) else tex_info.index].source]
        view = g.bufferViews[img.bufferView]
        return decode_png(blob[view.byteOffset: view.byteOffset + view.byteLength])

    mat = g.materials[prim.material]
    pbr = mat.pbrMetallicRoughness
    assert (pbr.metallicFactor or 0.0) == 0.0
    a_d = srgb_decode(image(pbr.baseColorTexture)[:, :, :3]) * np.asarray(pbr.baseColorFactor[:3])
    r = image(pbr.metallicRoughnessTexture)[:, :, 1:2] * pbr.roughnessFactor
    spec = mat.extensions["KHR_materials_specular"]
    s = spec.get("specularFactor", 1.0)
    assert "specularTexture" not in spec
    color = srgb_decode(image(spec["specularColorTexture"])[:, :, :3])
    color = color * np.asarray(spec.get("specularColorFactor", [1.0, 1.0, 1.0]))
    ior = (mat.extensions.get("KHR_materials_ior") or {}).get("ior", 1.5)
    a_s = np.minimum(((ior - 1) / (ior + 1)) ** 2 * color, 1.0) * s

    uv_obj = np.stack([uv_gltf[:, 0], 1.0 - uv_gltf[:, 1]], axis=1)  # glTF origin top-left
    world = _world(pos, T)
    nrm_world = nrm @ np.linalg.inv(T[:3, :3])  # normals: inverse transpose
    nrm_world /= np.linalg.norm(nrm_world, axis=1, keepdims=True)
    v_pos, t_pos_idx, n_welded = _weld(world, faces, nrm_world)
    return Asset(Mesh(v_pos, t_pos_idx, uv_obj, faces), n_welded, a_d, a_s, r, T)


# ---- USD ----
def _texture_for(shader_input):
    """The UsdUVTexture feeding a UsdPreviewSurface input, and the output name used."""
    from pxr import UsdShade

    (src,) = shader_input.GetConnectedSources()[0]
    tex = UsdShade.Shader(src.source.GetPrim())
    assert tex.GetIdAttr().Get() == "UsdUVTexture"
    return tex, src.sourceName


def _read_texture(tex, output: str, package: zipfile.ZipFile) -> np.ndarray:
    file = tex.GetInput("file").Get()
    resolved = file.resolvedPath  # "/path/asset.usdz[diffuse.png]"
    assert resolved.endswith("]"), f"texture {file} does not resolve inside the package"
    member = resolved[resolved.rindex("[") + 1: -1]
    a = decode_png(package.read(member))
    space = tex.GetInput("sourceColorSpace").Get() if tex.GetInput("sourceColorSpace") else "auto"
    # "auto" would depend on the reader's guess; the exporter must say which.
    assert space in ("sRGB", "raw"), f"{file}: sourceColorSpace {space!r}"
    if space == "sRGB":
        a = srgb_decode(a)
    channels = {"rgb": slice(0, 3), "r": slice(0, 1), "g": slice(1, 2), "b": slice(2, 3)}
    a = a[:, :, channels[output]]
    scale = tex.GetInput("scale").Get() if tex.GetInput("scale") else None
    bias = tex.GetInput("bias").Get() if tex.GetInput("bias") else None
    if scale is not None:
        a = a * np.asarray(scale)[channels[output]]
    if bias is not None:
        a = a + np.asarray(bias)[channels[output]]
    return a


def read_usdz(path) -> Asset:
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(path))
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    (prim,) = meshes
    m = UsdGeom.Mesh(prim)
    assert m.GetSubdivisionSchemeAttr().Get() == "none"
    counts = np.asarray(m.GetFaceVertexCountsAttr().Get())
    assert np.all(counts == 3)
    faces = np.asarray(m.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float64)
    assert m.GetNormalsInterpolation() == "vertex"
    nrm = np.asarray(m.GetNormalsAttr().Get(), dtype=np.float64)
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    assert st.GetInterpolation() == "faceVarying"
    values = np.asarray(st.Get(), dtype=np.float64)
    indices = np.asarray(st.GetIndices(), dtype=np.int64) if st.IsIndexed() \
        else np.arange(faces.size)
    # USD's st origin is the texture's bottom-left, like OBJ.
    t_tex_idx = indices.reshape(-1, 3)
    M = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    T = M.T  # USD multiplies row vectors

    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    assert surface.GetInput("useSpecularWorkflow").Get() == 1
    package = zipfile.ZipFile(str(path))
    maps = {}
    for name in ("diffuseColor", "specularColor", "roughness"):
        tex, output = _texture_for(surface.GetInput(name))
        maps[name] = _read_texture(tex, output, package)

    world = _world(pts, T)
    nrm_world = nrm @ np.linalg.inv(T[:3, :3])
    nrm_world /= np.linalg.norm(nrm_world, axis=1, keepdims=True)
    return Asset(Mesh(world, faces, values, t_tex_idx), nrm_world,
                 maps["diffuseColor"], maps["specularColor"], maps["roughness"], T)
