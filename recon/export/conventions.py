"""The export's conventions, shared by the glTF and USD writers (DESIGN section 4).

Texture files (:data:`TEXTURE_FILES`), written by :func:`recon.export.asset.write_textures`
and used by both formats, so both carry the same quantized values::

    diffuse.png               sRGB-encoded a_d               (8 bit RGB)
    specular.png              sRGB-encoded a_s               (8 bit RGB)
    metallic_roughness.png    G = r linear, R = B = 0        (8 bit RGB)

Material conventions (DESIGN section 4)
---------------------------------------
glTF 2.0 (core + ``KHR_materials_specular``), with the default IOR 1.5::

    baseColor   = sRGB-decode(diffuse.png) * baseColorFactor (1)          = a_d
    metallic    = metallicFactor (0)
    roughness   = metallic_roughness.png G (linear) * roughnessFactor (1) = r
    F0          = min(0.04 * specularColorFactor * sRGB-decode(specular.png), 1) * specular
                = min(0.04 * 25 * a_s, 1) * 1                              = a_s
    F90         = specular = specularFactor (1)                            (Schlick's F(1) = 1)

``specularColorTexture`` is sRGB-encoded by the extension's definition and its factor may
exceed 1, so ``a_s`` in [0, 1] is stored as sRGB-encode(a_s) with ``specularColorFactor`` =
1 / 0.04 = 25. ``specular`` (the scalar) stays 1 because the extension also scales F90 by it,
while the model's Schlick term goes to 1 at grazing angles. sRGB encoding quantizes small
``a_s`` (typical dielectrics, 0.02-0.08) about 3x more finely than a linear 8-bit channel
(half a step at a_s = 0.04: 7e-4 against 2e-3); the coarsest half step is 4.5e-3 near 1.

USD (``UsdPreviewSurface``, ``useSpecularWorkflow = 1``)::

    diffuseColor  = UsdUVTexture(diffuse.png,  sourceColorSpace "sRGB").rgb  = a_d
    specularColor = UsdUVTexture(specular.png, sourceColorSpace "sRGB").rgb  = a_s
    roughness     = UsdUVTexture(metallic_roughness.png, "raw").g             = r

``specularColor`` is a colour input, so its texture is decoded from sRGB like ``diffuseColor``
(UsdUVTexture decodes per texture; "raw" is kept for the data input ``roughness``), which
gives USD the same file, and the same precision for small ``a_s``, as glTF.

Where the formats and DESIGN section 3 differ: glTF (and common UsdPreviewSurface
implementations such as Storm) weight the diffuse lobe by (1 - F) for energy conservation,
DESIGN's model adds the lobes. Under the collocated light F = a_s, so a glTF viewer shows the
diffuse part darker by the factor (1 - a_s) (4 % at a_s = 0.04). The stored parameters are the
model's (to 8-bit quantization); the project's own renderer reproduces the model exactly.

Frames and units
----------------
Vertex data are stored in the cameras.json frame, unchanged (``optimize/mesh.obj``'s
coordinates). Both formats are +Y up with metres as the unit, so the asset's root transform
(glTF: the node's ``rotation``/``scale``; USD: ``xformOp:transform`` of ``/asset/geom``)
maps the cameras.json frame to a +Y-up frame: ``object_to_world = meters_per_unit * R``,
where R (with ``ExportSettings.up = "cameras"``) is the smallest rotation taking the mean
camera up vector (each camera's -y axis, OpenCV axes) to +Y. A capture's frame has no up of
its own; the photographer's "up" is the best guess there is. When the views disagree (the
mean up is shorter than ``min_up_agreement``) or there are no cameras, R is the identity and
the cameras.json +Y is declared up. The transform is recorded in glTF ``asset.extras`` and
in USD ``customLayerData`` under ``recon``. One cameras.json unit is ``meters_per_unit``
metres (default 1: the frame's scale is not known from photos alone).

UVs: OBJ and USD put the UV origin at the image's bottom-left (v up); glTF at the top-left.
The flip ``v_gltf = 1 - v_obj`` is :func:`recon.export.gltf.uv_obj_to_gltf`, the only place
it happens.
"""

from __future__ import annotations

__all__ = ["TEXTURE_FILES", "F0_IOR_1_5", "SPECULAR_COLOR_FACTOR"]

TEXTURE_FILES = {
    "diffuse": "diffuse.png",
    "specular": "specular.png",
    "metallic_roughness": "metallic_roughness.png",
}
"""File names of the exported textures (beside asset.usda, packaged in the usdz)."""

F0_IOR_1_5 = ((1.5 - 1.0) / (1.5 + 1.0)) ** 2
"""KHR_materials_specular's dielectric F0 for the default IOR 1.5 (0.04)."""

SPECULAR_COLOR_FACTOR = 1.0 / F0_IOR_1_5
"""glTF ``specularColorFactor`` (each channel): F0 = 0.04 * 25 * a_s = a_s."""
