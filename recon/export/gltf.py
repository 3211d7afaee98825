"""glTF 2.0 binary (.glb) writer: one mesh, one material with ``KHR_materials_specular``.

Material mapping and frames: see :mod:`recon.export.conventions`. glTF has one index per vertex,
so vertices are split where a position has several UVs (seams); each copy keeps the
area-weighted normal of its position (DESIGN section 3), computed on the unsplit mesh so the
shading stays smooth across seams.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from recon import __version__
from recon.export.conventions import SPECULAR_COLOR_FACTOR
from recon.io.atomic import atomic_path
from recon.io.mesh import Mesh

log = logging.getLogger(__name__)

__all__ = ["uv_obj_to_gltf", "split_seams", "write_glb"]

# glTF enums
_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071
_TRIANGLES = 4


def uv_obj_to_gltf(v_tex: np.ndarray) -> np.ndarray:
    """UVs from the OBJ convention (origin bottom-left, v up) to glTF's (origin top-left).

    The one place the v flip happens: ``(u, v) -> (u, 1 - v)``.

    Parameters
    ----------
    v_tex : (T, 2) float
    Returns
    -------
    (T, 2) float64
    """
    uv = np.array(v_tex, dtype=np.float64).reshape(-1, 2)
    uv[:, 1] = 1.0 - uv[:, 1]
    return uv


def split_seams(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One vertex per distinct (position, UV) pair.

    Parameters
    ----------
    mesh : Mesh with UVs

    Returns
    -------
    positions : (N, 3) float64
    normals : (N, 3) float64, unit length (area-weighted normals of the unsplit mesh)
    uv_obj : (N, 2) float64, OBJ convention
    faces : (F, 3) int64, indices into the N vertices
    """
    pairs = np.stack([mesh.t_pos_idx.ravel(), mesh.t_tex_idx.ravel()], axis=1)
    uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
    vn = mesh.vertex_normals()
    n = vn[uniq[:, 0]]
    length = np.linalg.norm(n, axis=1)
    bad = length < 0.5  # zero-area neighbourhoods have no normal
    if bad.any():
        log.warning("%d vertices touch only degenerate faces; their normal is set to +Z",
                    int(bad.sum()))
        n[bad] = (0.0, 0.0, 1.0)
    return (mesh.v_pos[uniq[:, 0]], n, mesh.v_tex[uniq[:, 1]],
            inverse.reshape(-1, 3).astype(np.int64))


def _pad4(b: bytes) -> bytes:
    return b + b"\x00" * (-len(b) % 4)


def write_glb(
    path: str | os.PathLike,
    mesh: Mesh,
    textures: dict[str, Path],
    object_to_world: np.ndarray,
    extras: dict | None = None,
) -> None:
    """Write ``path`` (.glb), atomically.

    Parameters
    ----------
    mesh : Mesh with UVs (OBJ convention), vertex data in the cameras.json frame.
    textures : dict
        PNG paths under the keys ``diffuse``, ``specular``, ``metallic_roughness``
        (:func:`recon.export.asset.write_textures`); embedded as they are.
    object_to_world : (4, 4) float
        Uniform scale times rotation, plus a translation; becomes the node's ``scale``,
        ``rotation`` and ``translation``.
    extras : dict, optional
        Stored as ``asset.extras["recon"]``.
    """
    import pygltflib as gl
    from scipy.spatial.transform import Rotation

    positions, normals, uv_obj, faces = split_seams(mesh)
    pos32 = positions.astype(np.float32)
    arrays = [
        (pos32, _ARRAY_BUFFER),
        (normals.astype(np.float32), _ARRAY_BUFFER),
        (uv_obj_to_gltf(uv_obj).astype(np.float32), _ARRAY_BUFFER),
        (faces.astype(np.uint32).ravel(), _ELEMENT_ARRAY_BUFFER),
    ]
    blob = b""
    views, accessors = [], []
    for a, target in arrays:
        data = np.ascontiguousarray(a).tobytes()
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob = _pad4(blob + data)
        is_index = target == _ELEMENT_ARRAY_BUFFER
        accessors.append(gl.Accessor(
            bufferView=len(views) - 1,
            componentType=_UINT if is_index else _FLOAT,
            count=int(a.shape[0]),
            type="SCALAR" if is_index else {2: "VEC2", 3: "VEC3"}[a.shape[1]],
        ))
    accessors[0].min = [float(x) for x in pos32.min(axis=0)]
    accessors[0].max = [float(x) for x in pos32.max(axis=0)]

    images = []
    for key in ("diffuse", "metallic_roughness", "specular"):
        data = Path(textures[key]).read_bytes()
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob = _pad4(blob + data)
        images.append(gl.Image(bufferView=len(views) - 1, mimeType="image/png", name=key))
    tex = {key: i for i, key in enumerate(("diffuse", "metallic_roughness", "specular"))}

    T = np.asarray(object_to_world, dtype=np.float64)
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    quat = Rotation.from_matrix(T[:3, :3] / scale).as_quat()  # (x, y, z, w), glTF's order
    quat /= np.linalg.norm(quat)
    node = gl.Node(mesh=0, name="asset")
    if not np.allclose(quat, (0, 0, 0, 1)):
        node.rotation = [float(x) for x in quat]
    if abs(scale - 1.0) > 1e-12:
        node.scale = [scale] * 3
    if np.any(T[:3, 3] != 0):
        node.translation = [float(x) for x in T[:3, 3]]

    material = gl.Material(
        name="material",
        pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorTexture=gl.TextureInfo(index=tex["diffuse"]),
            metallicFactor=0.0,
            roughnessFactor=1.0,
            metallicRoughnessTexture=gl.TextureInfo(index=tex["metallic_roughness"]),
        ),
        extensions={"KHR_materials_specular": {
            "specularFactor": 1.0,
            "specularColorFactor": [SPECULAR_COLOR_FACTOR] * 3,
            "specularColorTexture": {"index": tex["specular"]},
        }},
        doubleSided=False,
    )
    gltf = gl.GLTF2(
        asset=gl.Asset(generator=f"recon {__version__}", version="2.0",
                       extras={"recon": extras} if extras else {}),
        extensionsUsed=["KHR_materials_specular"],
        scene=0,
        scenes=[gl.Scene(nodes=[0])],
        nodes=[node],
        meshes=[gl.Mesh(name="asset", primitives=[gl.Primitive(
            attributes=gl.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
            indices=3, material=0, mode=_TRIANGLES,
        )])],
        materials=[material],
        samplers=[gl.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR,
                             wrapS=_CLAMP_TO_EDGE, wrapT=_CLAMP_TO_EDGE)],
        images=images,
        textures=[gl.Texture(sampler=0, source=i) for i in range(len(images))],
        accessors=accessors,
        bufferViews=views,
        buffers=[gl.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        if not gltf.save_binary(str(tmp)):
            raise OSError(f"{path}: pygltflib could not write the file")
    log.info("wrote %s (%d vertices after seam splits, %d faces)", path, len(positions), len(faces))
