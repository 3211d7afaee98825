"""Export: the optimized model as ``asset.glb`` (glTF 2.0 + KHR_materials_specular) and
``asset.usdz`` / ``asset.usda`` (UsdPreviewSurface, specular workflow), with validators.

Conventions (material mappings, sRGB/linear textures, UV origin, up axis and units) are
documented in :mod:`recon.export.conventions`.
"""

from recon.export.asset import (
    ExportError,
    ExportSettings,
    Material,
    export_asset,
    load_model,
    object_to_world,
    up_rotation,
)
from recon.export.validate import ValidatorUnavailable, gltf_errors, validate_gltf, validate_usdz

__all__ = [
    "ExportError",
    "ExportSettings",
    "Material",
    "export_asset",
    "load_model",
    "object_to_world",
    "up_rotation",
    "validate_gltf",
    "gltf_errors",
    "validate_usdz",
    "ValidatorUnavailable",
]
