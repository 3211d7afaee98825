"""The glb writer: UV flip, seam splits, the material's glTF encoding."""

from __future__ import annotations

import numpy as np
import pygltflib
import pytest

from recon.export.gltf import split_seams, uv_obj_to_gltf
from recon.io.mesh import Mesh


def test_uv_flip_known_values():
    uv = np.array([[0.0, 0.0], [0.25, 1.0], [0.5, 0.75]])
    assert np.array_equal(uv_obj_to_gltf(uv), [[0.0, 1.0], [0.25, 0.0], [0.5, 0.25]])
    assert np.array_equal(uv_obj_to_gltf(uv_obj_to_gltf(uv)), uv)


def test_uv_flip_texel_centres():
    """DESIGN 2: texel (i, j) of an H x W map sits at OBJ v = 1 - (i + 0.5)/H, i.e. glTF's
    v = (i + 0.5)/H (glTF's origin is the image's top-left)."""
    H, W = 4, 8
    i, j = np.mgrid[0:H, 0:W]
    uv_obj = np.stack([(j + 0.5) / W, 1 - (i + 0.5) / H], -1).reshape(-1, 2)
    uv = uv_obj_to_gltf(uv_obj)
    assert np.allclose(uv[:, 1] * H - 0.5, i.ravel()) and np.allclose(uv[:, 0] * W - 0.5, j.ravel())


def test_split_seams(model):
    m = model.mesh
    pos, nrm, uv, faces = split_seams(m)
    pairs = {(p, t) for p, t in zip(m.t_pos_idx.ravel(), m.t_tex_idx.ravel(), strict=True)}
    assert len(pos) == len(pairs) > len(m.v_pos)  # the atlas has seams
    assert np.array_equal(pos[faces], m.v_pos[m.t_pos_idx])
    assert np.array_equal(uv[faces], m.v_tex[m.t_tex_idx])
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0)
    assert np.array_equal(nrm[faces], m.vertex_normals()[m.t_pos_idx])  # smooth across seams


def test_split_seams_degenerate_vertex_gets_a_unit_normal():
    m = Mesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3]],
             [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 1, 3]])
    _, nrm, _, _ = split_seams(m)
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0) and np.all(np.isfinite(nrm))


@pytest.fixture(scope="module")
def gltf(exported):
    return pygltflib.GLTF2().load(str(exported["glb"]))


def test_material_encoding(gltf):
    """DESIGN 4: metallic 0, roughness in G, a_s through KHR_materials_specular with
    specularColorFactor 1/0.04, specular 1 (F90 = 1, Schlick's)."""
    assert gltf.extensionsUsed == ["KHR_materials_specular"]
    assert not gltf.extensionsRequired
    (mat,) = gltf.materials
    pbr = mat.pbrMetallicRoughness
    assert pbr.metallicFactor == 0.0 and pbr.roughnessFactor == 1.0
    assert pbr.baseColorFactor == [1, 1, 1, 1]
    spec = mat.extensions["KHR_materials_specular"]
    assert spec["specularFactor"] == 1.0
    assert np.allclose(spec["specularColorFactor"], 25.0)
    assert {gltf.images[gltf.textures[i].source].name for i in
            (pbr.baseColorTexture.index, pbr.metallicRoughnessTexture.index,
             spec["specularColorTexture"]["index"])} == {"diffuse", "metallic_roughness", "specular"}
    assert all(img.mimeType == "image/png" and img.bufferView is not None for img in gltf.images)
    assert mat.doubleSided is False and mat.alphaMode == "OPAQUE"


def test_textures_are_the_exported_pngs(gltf, exported):
    """glb and usdz carry byte-identical textures (the PNGs beside asset.usda)."""
    blob = gltf.binary_blob()
    for img in gltf.images:
        v = gltf.bufferViews[img.bufferView]
        assert blob[v.byteOffset: v.byteOffset + v.byteLength] == exported[img.name].read_bytes()


def test_recon_extras(gltf):
    extras = gltf.asset.extras["recon"]
    T = np.asarray(extras["object_to_world"]).reshape(4, 4)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and extras["up"] == "cameras"
    assert gltf.asset.version == "2.0"
