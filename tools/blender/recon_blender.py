"""Open a recon asset (asset.glb or asset.usdz) in Blender, describe it, and render it.

Runs inside Blender's Python, never in the project's environment: either the ``bpy`` wheel in
its own virtual environment (``tools/blender/.venv``, made by ``scripts/setup.sh``)::

    tools/blender/.venv/bin/python tools/blender/recon_blender.py ASSET OUT [--views views.json]

or a Blender installation::

    blender -b --factory-startup -P tools/blender/recon_blender.py -- ASSET OUT [...]

It imports only ``bpy`` and numpy (no ``recon``): what it reports is what Blender made of the
file. It writes into the folder OUT:

- ``scene.json``: the scene after import (objects, world bounding box, unit settings), every
  material's node tree (nodes, properties, socket values, links) and every image (colour
  space, size, 16x16 block means of the stored pixel values, first row = top);
- ``loops.npz``: per face corner, the world position (Blender's Z-up frame), the UV, the
  custom (split) normal, and the face index;
- with ``--views``: ``view_<k>.exr`` (RGBA, linear) rendered by Cycles on the CPU with a point
  light at each camera (recon's collocated flash) and direct light only, then
  ``specular_<k>.exr`` the same with every Principled BSDF's Base Color set to black (the
  specular lobe alone, which a whole-image comparison hides under the diffuse).

``views.json`` holds ``{"views": [{"K": 3x3, "world_to_camera": 4x4, "width": W,
"height": H}], "light_intensity": I, "spp": N}`` with the cameras in the asset's own frame
(+Y up, metres: glTF's and the USD stage's), OpenCV axes (x right, y down, z forward), and
``I`` the point light's radiant intensity in W/sr (recon's ``light.intensity``).

``--fix-usd-specular`` applies :func:`fix_usd_specular` after import (see there).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import bpy
import numpy as np

# glTF and USD (upAxis Y) are +Y up; Blender is +Z up. Both importers turn the asset's frame
# into Blender's with this rotation: (x, y, z) -> (x, -z, y).
Y_UP_TO_BLENDER = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])

# UsdPreviewSurface's specular workflow: F0 = specularColor. Blender's USD importer feeds
# specularColor to the Principled BSDF's "Specular Tint", which multiplies the F0 of its IOR
# (0.04 at the default 1.5), so the highlight is 25 times too weak unless multiplied back.
F0_IOR_1_5 = 0.04


def reset_scene() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def import_asset(path: Path) -> list:
    """Import a .glb/.gltf or .usd/.usda/.usdc/.usdz into an empty scene; returns the mesh objects."""
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        bpy.ops.import_scene.gltf(filepath=str(path))
    elif suffix in (".usd", ".usda", ".usdc", ".usdz"):
        bpy.ops.wm.usd_import(filepath=str(path))
    else:
        raise SystemExit(f"{path}: not a glTF or USD file")
    meshes = [o for o in bpy.data.objects if o.type == "MESH"]
    if not meshes:
        raise SystemExit(f"{path}: Blender imported no mesh")
    return meshes


def _principled_nodes(material):
    return [n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED"]


def fix_usd_specular(materials=None) -> int:
    """Scale what feeds "Specular Tint" by 1 / F0(IOR) in materials imported from USD.

    Blender's USD importer reads UsdPreviewSurface's ``specularColor`` (F0 in the specular
    workflow) as the Principled BSDF's Specular Tint, a factor on the F0 of the IOR. Putting a
    Multiply by 1 / F0(IOR) (25 at IOR 1.5) between them gives F0 = specularColor, as the
    glTF importer does for KHR_materials_specular. Returns the number of sockets changed.
    """
    changed = 0
    for mat in materials or bpy.data.materials:
        if mat.node_tree is None:
            continue
        for bsdf in _principled_nodes(mat):
            tint = bsdf.inputs["Specular Tint"]
            ior = bsdf.inputs["IOR"].default_value
            f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
            factor = 1.0 / f0
            nodes, links = mat.node_tree.nodes, mat.node_tree.links
            mix = nodes.new("ShaderNodeMix")
            mix.data_type = "RGBA"
            mix.blend_type = "MULTIPLY"
            mix.clamp_result = False
            mix.label = "F0 = specularColor (recon)"
            mix.inputs["Factor"].default_value = 1.0
            mix.inputs[7].default_value = (factor, factor, factor, 1.0)
            if tint.is_linked:
                src = tint.links[0].from_socket
                links.remove(tint.links[0])
                links.new(src, mix.inputs[6])
            else:
                mix.inputs[6].default_value = tuple(tint.default_value)
            links.new(mix.outputs[2], tint)
            changed += 1
    return changed


# ---- Description ----
def _value(socket):
    if not hasattr(socket, "default_value"):
        return None
    v = socket.default_value
    try:
        return [float(x) for x in v]
    except TypeError:
        return float(v) if isinstance(v, (int, float, bool)) else str(v)


_NODE_PROPS = ("blend_type", "clamp_result", "clamp_factor", "data_type", "operation", "use_clamp",
               "interpolation", "extension", "projection", "uv_map", "distribution",
               "subsurface_method", "mode", "factor_mode")


def describe_node_tree(tree) -> dict:
    nodes = {}
    for n in tree.nodes:
        props = {p: getattr(n, p) for p in _NODE_PROPS if hasattr(n, p)}
        props = {k: (v if isinstance(v, (bool, int, float)) else str(v)) for k, v in props.items()}
        if n.type == "TEX_IMAGE":
            props["image"] = n.image.name if n.image else None
        inputs = []
        for i, s in enumerate(n.inputs):
            entry = {"index": i, "name": s.name, "identifier": s.identifier, "enabled": s.enabled,
                     "value": _value(s)}
            if s.is_linked:
                link = s.links[0]
                entry["link"] = {"node": link.from_node.name, "socket": link.from_socket.name,
                                 "index": list(link.from_node.outputs).index(link.from_socket)}
            inputs.append(entry)
        nodes[n.name] = {"type": n.type, "idname": n.bl_idname, "props": props, "inputs": inputs,
                         "outputs": [s.name for s in n.outputs]}
    return nodes


def _block_means(image, blocks: int = 16) -> list:
    w, h = image.size
    px = np.empty(w * h * 4, dtype=np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)[::-1]  # Blender's first row is the bottom one
    bh, bw = h // blocks, w // blocks
    px = px[: bh * blocks, : bw * blocks].reshape(blocks, bh, blocks, bw, 4).mean(axis=(1, 3))
    return px.tolist()


def describe_scene(meshes) -> tuple[dict, dict]:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    scene = bpy.context.scene
    out = {
        "blender": bpy.app.version_string,
        "unit_system": scene.unit_settings.system,
        "scale_length": scene.unit_settings.scale_length,
        "objects": [],
        "materials": {},
        "images": {},
    }
    arrays = {}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k, obj in enumerate(meshes):
        ev = obj.evaluated_get(depsgraph)
        me = ev.to_mesh()
        M = np.array(obj.matrix_world)
        co = np.empty(len(me.vertices) * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
        lo, hi = np.minimum(lo, co.min(axis=0)), np.maximum(hi, co.max(axis=0))
        loop_vert = np.empty(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("vertex_index", loop_vert)
        normals = np.empty(len(me.loops) * 3, dtype=np.float64)
        me.corner_normals.foreach_get("vector", normals)
        Nm = np.linalg.inv(M[:3, :3]).T
        normals = normals.reshape(-1, 3) @ Nm.T
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        loop_face = np.empty(len(me.loops), dtype=np.int64)
        for p in me.polygons:
            loop_face[p.loop_start: p.loop_start + p.loop_total] = p.index
        uv_layers = [u.name for u in me.uv_layers]
        if me.uv_layers.active is not None:
            uv = np.empty(len(me.loops) * 2, dtype=np.float64)
            me.uv_layers.active.uv.foreach_get("vector", uv)
            arrays[f"uv_{k}"] = uv.reshape(-1, 2)
        arrays[f"position_{k}"] = co[loop_vert]
        arrays[f"normal_{k}"] = normals
        arrays[f"face_{k}"] = loop_face
        sides = np.array([p.loop_total for p in me.polygons])
        out["objects"].append({
            "name": obj.name,
            "vertices": len(me.vertices),
            "faces": len(me.polygons),
            "face_sides": sorted(set(int(s) for s in sides)),
            "uv_layers": uv_layers,
            "active_uv": me.uv_layers.active.name if me.uv_layers.active else None,
            "active_render_uv": next((u.name for u in me.uv_layers if u.active_render), None),
            "materials": [m.name for m in me.materials if m is not None],
            "matrix_world": M.tolist(),
        })
        ev.to_mesh_clear()
        for mat in obj.data.materials:
            if mat is not None and mat.name not in out["materials"]:
                out["materials"][mat.name] = describe_node_tree(mat.node_tree)
    out["bbox_min"], out["bbox_max"] = lo.tolist(), hi.tolist()
    for img in bpy.data.images:
        if img.type != "IMAGE":
            continue
        out["images"][img.name] = {
            "filepath": img.filepath,
            "colorspace": img.colorspace_settings.name,
            "size": list(img.size),
            "channels": img.channels,
            "is_float": img.is_float,
            "block_means": _block_means(img),
        }
    return out, arrays


# ---- Rendering ----
def _look_through(cam_obj, K, w2c, width, height) -> None:
    """Place a Blender camera for an OpenCV pinhole camera given in the asset's +Y-up frame."""
    K, w2c = np.asarray(K, float), np.asarray(w2c, float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx - fy) > 1e-6 * fx:
        raise SystemExit("only square pixels (fx = fy) can be rendered in Blender")
    cam = cam_obj.data
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL" if width >= height else "VERTICAL"
    cam.sensor_width = cam.sensor_height = 36.0
    size = max(width, height)
    cam.lens = fx * 36.0 / size
    cam.shift_x = (width / 2 - cx) / size
    cam.shift_y = (cy - height / 2) / size
    cam.clip_start, cam.clip_end = 1e-3, 1e4
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1  # OpenCV (y down, z forward) -> Blender camera (y up, looks down -z)
    M = Y_UP_TO_BLENDER @ c2w
    import mathutils

    cam_obj.matrix_world = mathutils.Matrix(M.tolist())


def render_views(views: dict, out: Path, distribution: str | None = None) -> list[Path]:
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(views.get("spp", 64))
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.cycles.max_bounces = 0  # direct light only, as recon's image formation
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.light_sampling_threshold = 0.0
    scene.cycles.seed = 0
    scene.render.film_transparent = True
    scene.world = None
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = "32"
    scene.render.resolution_percentage = 100
    if distribution:
        for mat in bpy.data.materials:
            if mat.node_tree is not None:
                for n in _principled_nodes(mat):
                    n.distribution = distribution

    cam_obj = bpy.data.objects.new("recon_camera", bpy.data.cameras.new("recon_camera"))
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    light = bpy.data.lights.new("recon_flash", "POINT")
    light.shadow_soft_size = 0.0
    light.use_soft_falloff = False
    # A point light of power P watts has radiant intensity P / (4 pi) W/sr in Cycles.
    light.energy = float(views["light_intensity"]) * 4.0 * math.pi
    light_obj = bpy.data.objects.new("recon_flash", light)
    scene.collection.objects.link(light_obj)

    written = []
    for prefix in ("view", "specular"):
        if prefix == "specular":
            _black_base_color()
        for k, v in enumerate(views["views"]):
            scene.render.resolution_x, scene.render.resolution_y = int(v["width"]), int(v["height"])
            _look_through(cam_obj, v["K"], v["world_to_camera"], v["width"], v["height"])
            light_obj.matrix_world = cam_obj.matrix_world.copy()
            path = out / f"{prefix}_{k}.exr"
            scene.render.filepath = str(path)
            bpy.ops.render.render(write_still=True)
            written.append(path)
    return written


def _black_base_color() -> None:
    for mat in bpy.data.materials:
        if mat.node_tree is None:
            continue
        for n in _principled_nodes(mat):
            sock = n.inputs["Base Color"]
            for link in list(sock.links):
                mat.node_tree.links.remove(link)
            sock.default_value = (0.0, 0.0, 0.0, 1.0)


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("asset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--views", type=Path, help="views.json: cameras in the asset frame, light, spp")
    ap.add_argument("--fix-usd-specular", action="store_true")
    ap.add_argument("--distribution", choices=["GGX", "MULTI_GGX"],
                    help="override the Principled BSDF's microfacet distribution for rendering")
    args = ap.parse_args(argv)
    if not args.asset.is_file():
        raise SystemExit(f"{args.asset}: file not found")
    args.out.mkdir(parents=True, exist_ok=True)
    reset_scene()
    meshes = import_asset(args.asset.resolve())
    if args.fix_usd_specular:
        fix_usd_specular()
    desc, arrays = describe_scene(meshes)
    (args.out / "scene.json").write_text(json.dumps(desc, indent=1))
    np.savez(args.out / "loops.npz", **arrays)
    if args.views:
        render_views(json.loads(args.views.read_text()), args.out, args.distribution)


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    main(argv)
