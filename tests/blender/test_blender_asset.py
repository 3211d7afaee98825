"""The exported asset.glb and asset.usdz opened in a real, headless Blender (bpy 5.0.1).

What Blender made of each file is compared with what the file says (read by the independent
readers of tests/export) and with recon's own renderer:

- the mesh: vertex and face counts, the bounding box in metres in Blender's Z-up world, the
  capture's up direction as Blender's +Z, one UV layer whose corner UVs are the file's, the
  stored normals;
- the Principled BSDF: every input that matters traced through the node tree to its source
  (base colour = the diffuse map as sRGB, roughness = the G channel as Non-Color, metallic 0,
  the specular map reaching Specular Tint with F0 = a_s), the neutral inputs at their neutral
  values; each mismatch is reported with the socket's name;
- the appearance: Cycles on the CPU, a point light at each of 3 cameras, against recon's
  render of the same asset and cameras (sRGB RMSE over the union of the masks).

Blender's USD importer reads UsdPreviewSurface's specularColor (F0) as Specular Tint, a factor
on the IOR's F0 of 0.04, so the usdz's specular is 25x weaker in Blender than the file says;
the tests pin that behaviour and check that ``fix_usd_specular`` (tools/blender) repairs it.
"""

from __future__ import annotations

import io
import math
import zipfile

import numpy as np
import pytest
from blender_case import Y_UP_TO_BLENDER, BlenderResult
from PIL import Image
from scipy.spatial import cKDTree

from recon.export.conventions import TEXTURE_FILES
from recon.io.images import read_exr
from recon.metrics import image_rmse

pytestmark = pytest.mark.blender

FORMATS = [("glb", False), ("usdz", False), ("usdz", True)]
IDS = ["glb", "usdz", "usdz-fixed"]

# sRGB RMSE between Blender (Cycles, Principled BSDF) and recon's renderer on the same asset,
# cameras and light. The two shading models differ (Blender's diffuse sits under the specular
# layer and loses what it reflects; recon adds the lobes), so the bound is calibrated on the
# ground-truth asset of captures/demo (see docs/viewers.md for the measured values).
RMSE_LIMIT = {("glb", False): 0.11, ("usdz", False): 0.11, ("usdz", True): 0.11}
SPECULAR_RMSE_LIMIT = 0.032
# The specular-only comparison is also bounded relative to the lobe's own strength in each view
# (the sRGB RMSE of recon's specular-only render against black): an optimized asset may carry a
# lobe 10x weaker than the ground truth's (the draft demo: a_s ~0.08, r ~0.5), and there a wrong
# roughness or a lost specular map moves the image by less than 0.032 although it is the whole
# lobe. On the ground truth the glb's lobe matches within 0.08-0.13 of the lobe (docs/viewers.md:
# 0.021 of 0.16, 0.009 of 0.07, 0.017 of 0.21), r -> r^2 misses by 0.35-0.63 of it.
SPECULAR_RMSE_REL = 0.25

NEUTRAL = {  # Principled BSDF inputs that must stay at these values (unlinked)
    "Alpha": 1.0, "Coat Weight": 0.0, "Sheen Weight": 0.0, "Transmission Weight": 0.0,
    "Subsurface Weight": 0.0, "Emission Strength": 0.0, "Anisotropic": 0.0,
    "Diffuse Roughness": 0.0, "Thin Film Thickness": 0.0,
}


@pytest.fixture(params=FORMATS, ids=IDS)
def result(request, blender) -> tuple[str, bool, BlenderResult]:
    fmt, fix = request.param
    return fmt, fix, blender(fmt, fix)


# ---- The mesh ----
def _corners(res: BlenderResult):
    """The file's face corners in Blender's world: positions, UVs (v up), normals."""
    m = res.asset.mesh
    pos = m.v_pos[m.t_pos_idx.ravel()] @ Y_UP_TO_BLENDER.T
    uv = m.v_tex[m.t_tex_idx.ravel()]
    nrm = res.asset.normals[m.t_pos_idx.ravel()] @ Y_UP_TO_BLENDER.T
    return pos, uv, nrm


def _expected_vertex_count(fmt: str, res: BlenderResult) -> int:
    m = res.asset.mesh
    # glTF has one index per vertex, split at UV seams; USD keeps the points, UVs per corner.
    return len(m.v_tex) if fmt == "glb" else len(m.v_pos)


def test_mesh_counts_and_bounding_box(result):
    fmt, _, res = result
    s = res.scene
    assert len(s["objects"]) == 1, f"{fmt}: expected one mesh object, got {s['objects']}"
    (obj,) = s["objects"]
    m = res.asset.mesh
    assert obj["faces"] == len(m.t_pos_idx), f"{fmt}: {obj['faces']} faces in Blender"
    assert obj["face_sides"] == [3], f"{fmt}: faces with {obj['face_sides']} sides"
    assert obj["vertices"] == _expected_vertex_count(fmt, res), \
        f"{fmt}: {obj['vertices']} vertices in Blender"
    assert s["unit_system"] == "METRIC" and s["scale_length"] == 1.0, "scene units are not metres"
    pos = m.v_pos @ Y_UP_TO_BLENDER.T  # metres: the file's root transform is applied
    lo, hi = np.array(s["bbox_min"]), np.array(s["bbox_max"])
    tol = 1e-5 * float(np.ptp(pos, axis=0).max())
    assert np.allclose(lo, pos.min(axis=0), atol=tol) and np.allclose(hi, pos.max(axis=0), atol=tol), \
        f"{fmt}: Blender's bounding box {lo}..{hi} m, the file's {pos.min(axis=0)}..{pos.max(axis=0)} m"


def test_up_is_blender_z(result, case):
    """The photographer's up (mean camera up, cameras.json frame) is +Z in Blender."""
    fmt, _, res = result
    obj = res.scene["objects"][0]
    T = res.asset.object_to_world
    ups = np.array([-c.world_to_camera[1, :3] for c in case.cameras.frames])
    ups /= np.linalg.norm(ups, axis=1, keepdims=True)
    # Where Blender put the asset: the world matrix maps the mesh data; the file's T maps the
    # cameras.json frame to +Y up. Blender's world = Y_UP_TO_BLENDER @ T (checked by the bbox).
    up = Y_UP_TO_BLENDER @ (T[:3, :3] @ ups.mean(axis=0))
    up /= np.linalg.norm(up)
    angle = math.degrees(math.acos(min(1.0, float(up[2]))))
    assert angle < 0.1, f"{fmt}: the capture's up is {angle:.2f} deg from Blender's +Z"
    assert obj["matrix_world"] is not None


def test_uvs_are_the_files(result):
    fmt, _, res = result
    obj = res.scene["objects"][0]
    assert len(obj["uv_layers"]) == 1, f"{fmt}: UV layers {obj['uv_layers']}"
    assert obj["active_render_uv"] == obj["uv_layers"][0], f"{fmt}: render UV {obj['active_render_uv']}"
    pos, uv, _ = _corners(res)
    got = np.concatenate([res.loops["position_0"], res.loops["uv_0"]], axis=1)
    want = np.concatenate([pos, uv], axis=1)
    d_got, _ = cKDTree(want).query(got)
    d_want, _ = cKDTree(got).query(want)
    assert d_got.max() < 1e-4 and d_want.max() < 1e-4, \
        f"{fmt}: {int((d_got >= 1e-4).sum())} Blender face corners have a position/UV the file " \
        f"does not, {int((d_want >= 1e-4).sum())} of the file's are missing in Blender"
    flipped = np.concatenate([res.loops["position_0"], res.loops["uv_0"] * [1, -1] + [0, 1]], axis=1)
    assert (cKDTree(want).query(flipped)[0] >= 1e-4).mean() > 0.5, "the UV check cannot tell a v flip"


def test_normals_are_the_files(result):
    fmt, _, res = result
    pos, _, nrm = _corners(res)
    _, idx = cKDTree(pos).query(res.loops["position_0"])
    cos = np.sum(res.loops["normal_0"] * nrm[idx], axis=1)
    worst = math.degrees(math.acos(float(np.clip(cos.min(), -1, 1))))
    assert worst < 0.5, f"{fmt}: a shading normal in Blender is {worst:.2f} deg from the file's"


# ---- The material ----
def _trace(nodes: dict, node_name: str, output_index: int) -> dict:
    """What a node output computes, for the few node kinds the importers use.

    Returns ``{"kind": "const", "value": [...]}``, ``{"kind": "tex", "node": name,
    "channel": "rgb"|"r"|"g"|"b"|"a", "scale": (3,) array}`` or ``{"kind": "other",
    "what": description}``.
    """
    node = nodes[node_name]
    t, p = node["type"], node["props"]

    def inp(i):
        s = node["inputs"][i]
        if "link" in s:
            return _trace(nodes, s["link"]["node"], s["link"]["index"])
        v = s["value"]
        return {"kind": "const", "value": np.atleast_1d(np.asarray(v, dtype=float))}

    if t == "TEX_IMAGE":
        channel = {0: "rgb", 1: "a"}[output_index]
        return {"kind": "tex", "node": node_name, "channel": channel, "scale": np.ones(3)}
    if t == "SEPARATE_COLOR" and p.get("mode") == "RGB":
        src = inp(0)
        c = "rgb"[output_index]
        if src["kind"] == "tex" and src["channel"] == "rgb":
            return {**src, "channel": c, "scale": np.full(3, src["scale"]["rgb".index(c)])}
        if src["kind"] == "const":
            return {"kind": "const", "value": src["value"][output_index:output_index + 1]}
    if (t == "MIX" and p.get("data_type") == "RGBA" and p.get("blend_type") == "MULTIPLY") or \
            (t == "MATH" and p.get("operation") == "MULTIPLY"):
        if p.get("clamp_result") or p.get("use_clamp"):
            return {"kind": "other", "what": f"{node_name} clamps its result to [0, 1]"}
        if t == "MIX":
            factor = inp(0)
            if factor["kind"] != "const" or factor["value"][0] != 1.0:
                return {"kind": "other", "what": f"{node_name}: mix factor is not 1"}
            a, b = inp(6), inp(7)
        else:
            a, b = inp(0), inp(1)
        if a["kind"] == "const" and b["kind"] == "const":
            return {"kind": "const", "value": a["value"][:3] * b["value"][:3]}
        for x, y in ((a, b), (b, a)):
            if x["kind"] == "tex" and y["kind"] == "const":
                return {**x, "scale": x["scale"] * y["value"][:3]}
        return {"kind": "other", "what": f"{node_name} multiplies two textures"}
    return {"kind": "other", "what": f"{node_name} ({t}, output {output_index})"}


def _principled(res: BlenderResult) -> tuple[dict, dict]:
    mats = res.scene["materials"]
    assert len(mats) == 1, f"expected one material, got {list(mats)}"
    (nodes,) = mats.values()
    bsdfs = [n for n, v in nodes.items() if v["type"] == "BSDF_PRINCIPLED"]
    assert len(bsdfs) == 1, f"expected one Principled BSDF, got {bsdfs}"
    return nodes, nodes[bsdfs[0]]


def _socket(nodes, bsdf, name) -> dict:
    (s,) = [s for s in bsdf["inputs"] if s["name"] == name]
    if "link" in s:
        return _trace(nodes, s["link"]["node"], s["link"]["index"])
    return {"kind": "const", "value": np.atleast_1d(np.asarray(s["value"], dtype=float))}


def _png_block_means(data: bytes, blocks: int = 16) -> np.ndarray:
    a = np.asarray(Image.open(io.BytesIO(data)).convert("RGBA"), dtype=np.float64) / 255.0
    h, w = a.shape[:2]
    bh, bw = h // blocks, w // blocks
    return a[: bh * blocks, : bw * blocks].reshape(blocks, bh, blocks, bw, 4).mean(axis=(1, 3))


def _exported_pngs(case, fmt) -> dict[str, np.ndarray]:
    """Block means of the texture files the asset carries (the usdz's own members)."""
    if fmt == "usdz":
        with zipfile.ZipFile(case.export / "asset.usdz") as z:
            return {k: _png_block_means(z.read(v)) for k, v in TEXTURE_FILES.items()}
    return {k: _png_block_means((case.export / v).read_bytes()) for k, v in TEXTURE_FILES.items()}


def _which_file(res: BlenderResult, node: dict, pngs: dict) -> str | None:
    img = res.scene["images"][node["props"]["image"]]
    got = np.asarray(img["block_means"])
    diffs = {k: float(np.abs(got - v).max()) for k, v in pngs.items() if v.shape == got.shape}
    best = min(diffs, key=diffs.get, default=None)
    return best if best is not None and diffs[best] < 2.0 / 255 else None


def material_mismatches(res: BlenderResult, case, fmt: str, fixed: bool) -> list[str]:
    """Every way the Principled BSDF differs from the file's meaning, one line per socket."""
    nodes, bsdf = _principled(res)
    pngs = _exported_pngs(case, fmt)
    uv_layer = res.scene["objects"][0]["uv_layers"][0]
    bad = []

    def texture(socket, expr, file_key, colorspace, channel, scale):
        if expr["kind"] != "tex":
            bad.append(f"{socket}: fed by {expr.get('what', expr.get('value'))}, not the "
                       f"{TEXTURE_FILES[file_key]} texture")
            return
        node = nodes[expr["node"]]
        got_file = _which_file(res, node, pngs)
        img = res.scene["images"][node["props"]["image"]]
        if got_file != file_key:
            bad.append(f"{socket}: texture {node['props']['image']} is {got_file}, not {file_key}")
        if img["colorspace"] != colorspace:
            bad.append(f"{socket}: texture colour space {img['colorspace']!r}, not {colorspace!r}")
        if expr["channel"] != channel:
            bad.append(f"{socket}: channel {expr['channel']}, not {channel}")
        if not np.allclose(expr["scale"], scale, rtol=1e-5):
            bad.append(f"{socket}: texture scaled by {expr['scale'].tolist()}, not {scale}")
        if node["props"].get("interpolation") != "Linear":
            bad.append(f"{socket}: texture interpolation {node['props'].get('interpolation')}, "
                       "not Linear (bilinear lookups)")
        if node["props"].get("extension") != "EXTEND":
            bad.append(f"{socket}: texture extension {node['props'].get('extension')}, not EXTEND "
                       "(clamp to edge)")
        vec = node["inputs"][0]
        if "link" in vec:
            src = nodes[vec["link"]["node"]]
            if src["type"] != "UVMAP" or src["props"].get("uv_map") not in ("", uv_layer):
                bad.append(f"{socket}: texture coordinates from {vec['link']['node']}, not UV "
                           f"map {uv_layer!r}")

    texture("Base Color", _socket(nodes, bsdf, "Base Color"), "diffuse", "sRGB", "rgb", 1.0)
    texture("Roughness", _socket(nodes, bsdf, "Roughness"), "metallic_roughness", "Non-Color",
            "g", 1.0)
    metallic = _socket(nodes, bsdf, "Metallic")
    zero = (metallic["kind"] == "const" and np.all(metallic["value"] == 0)) or \
        (metallic["kind"] == "tex" and np.all(metallic["scale"] == 0))
    if not zero:
        bad.append(f"Metallic: {metallic}, not 0")

    # Specular: F0 = F0(IOR) * 2 * Specular IOR Level * Specular Tint must be a_s.
    ior = _socket(nodes, bsdf, "IOR")
    level = _socket(nodes, bsdf, "Specular IOR Level")
    tint = _socket(nodes, bsdf, "Specular Tint")
    if ior["kind"] != "const" or level["kind"] != "const":
        bad.append(f"IOR / Specular IOR Level: textured ({ior}, {level}), expected constants")
    elif tint["kind"] == "tex":
        f0_ior = ((ior["value"][0] - 1) / (ior["value"][0] + 1)) ** 2
        factor = f0_ior * 2 * level["value"][0]
        # Blender's USD importer maps specularColor to Specular Tint unscaled (F0 = 0.04 a_s).
        want = 1.0 if fmt == "glb" or fixed else f0_ior
        texture("Specular Tint", tint, "specular", "sRGB", "rgb", want / factor)
    else:
        texture("Specular Tint", tint, "specular", "sRGB", "rgb", 1.0)

    for name, value in NEUTRAL.items():
        e = _socket(nodes, bsdf, name)
        if e["kind"] != "const" or not np.allclose(e["value"][0], value):
            bad.append(f"{name}: {e.get('value', e.get('what'))}, not {value}")
    normal = [s for s in bsdf["inputs"] if s["name"] == "Normal"][0]
    if "link" in normal:
        bad.append(f"Normal: linked to {normal['link']['node']} (the asset has no normal map)")
    outputs = [n for n in nodes.values() if n["type"] == "OUTPUT_MATERIAL"]
    surface = [s for s in outputs[0]["inputs"] if s["name"] == "Surface"][0] if outputs else {}
    if nodes.get(surface.get("link", {}).get("node"), {}).get("type") != "BSDF_PRINCIPLED":
        bad.append("Material Output Surface: not fed by the Principled BSDF")
    disp = [s for s in outputs[0]["inputs"] if s["name"] == "Displacement"] if outputs else []
    if disp and "link" in disp[0]:
        bad.append("Material Output Displacement: linked (the asset has no displacement)")
    return bad


def test_material_sockets(result, case):
    fmt, fixed, res = result
    bad = material_mismatches(res, case, fmt, fixed)
    assert not bad, f"{fmt}{' (fixed)' if fixed else ''}: the Principled BSDF differs from the file:\n" \
        + "\n".join(bad)


def test_material_check_names_a_wrong_socket(blender, case):
    """The socket check fails, naming the socket, on a roughness map read as sRGB and a
    specular tint clamped to [0, 1] (two classic import errors), built by editing the
    description Blender gave of the glb."""
    import copy

    res = blender("glb")
    broken = copy.deepcopy(res)
    nodes, bsdf = _principled(broken)
    rough = _socket(nodes, bsdf, "Roughness")
    broken.scene["images"][nodes[rough["node"]]["props"]["image"]]["colorspace"] = "sRGB"
    for n in nodes.values():
        if n["type"] == "MIX":
            n["props"]["clamp_result"] = True
    bad = material_mismatches(broken, case, "glb", False)
    assert any(b.startswith("Roughness: texture colour space 'sRGB'") for b in bad), bad
    assert any(b.startswith("Specular Tint:") and "clamps" in b for b in bad), bad


# ---- Appearance ----
def _recon_renders(res: BlenderResult, part: str = "full", roughness=None):
    """recon's renders of the asset at the views Blender rendered: ``full`` or ``specular``
    (a_d = 0, the specular lobe alone)."""
    from recon.render.mitsuba_bsdf import render_reference

    a = res.asset
    textures = {"diffuse": a.a_d if part == "full" else np.zeros_like(a.a_d),
                "specular": a.a_s, "roughness": a.r if roughness is None else roughness}
    return [render_reference(a.mesh, textures, cam, res.light_intensity, spp=64, seed=k, alpha=True)
            for k, cam in enumerate(res.views)]


def appearance_rmse(res: BlenderResult, refs, part: str = "full") -> list[float]:
    """sRGB RMSE per view over the union of the masks (DESIGN section 5)."""
    out = []
    for k, ref in enumerate(refs):
        img = read_exr(res.out / f"{'view' if part == 'full' else 'specular'}_{k}.exr")
        assert img.shape == ref.shape, f"view {k}: Blender rendered {img.shape}, recon {ref.shape}"
        out.append(image_rmse(img[..., :3], ref[..., :3], img[..., 3] > 0.5, ref[..., 3] > 0.5))
    return out


@pytest.fixture(scope="session")
def recon_renders(blender, mi):
    cache = {}

    def get(fmt, part="full"):
        if (fmt, part) not in cache:
            cache[(fmt, part)] = _recon_renders(blender(fmt), part)
        return cache[(fmt, part)]

    return get


def test_appearance_matches_recon(result, recon_renders):
    fmt, fixed, res = result
    refs = recon_renders(fmt)
    for ref in refs:
        assert (ref[..., 3] > 0.5).mean() > 0.2, "the object must fill the view"
    rmse = appearance_rmse(res, refs)
    limit = RMSE_LIMIT[(fmt, fixed)]
    assert max(rmse) < limit, f"{fmt}{' (fixed)' if fixed else ''}: sRGB RMSE per view " \
        f"{[round(r, 4) for r in rmse]} against recon's render, limit {limit}"


def specular_limits(refs) -> list[float]:
    """Per view: the specular-only RMSE limit, SPECULAR_RMSE_LIMIT or SPECULAR_RMSE_REL of the
    lobe's strength (recon's specular-only render against black), whichever is smaller."""
    out = []
    for ref in refs:
        mask = ref[..., 3] > 0.5
        lobe = image_rmse(ref[..., :3], np.zeros_like(ref[..., :3]), mask, mask)
        out.append(min(SPECULAR_RMSE_LIMIT, SPECULAR_RMSE_REL * lobe))
    return out


def _rounded(values) -> list[float]:
    return [round(float(v), 4) for v in values]


def test_specular_lobe_matches_recon(result, recon_renders):
    """The specular lobe alone (Base Color black in Blender, a_d = 0 in recon): F0 = a_s,
    alpha = r^2 and the specular map's placement, without the diffuse that hides them."""
    fmt, fixed, res = result
    refs = recon_renders(fmt, "specular")
    rmse, limits = appearance_rmse(res, refs, "specular"), specular_limits(refs)
    said = f"specular-only sRGB RMSE per view {_rounded(rmse)}, limits {_rounded(limits)}"
    if fmt == "usdz" and not fixed:  # Blender's USD importer: F0 = 0.04 a_s, the lobe is lost
        assert all(r > lim for r, lim in zip(rmse, limits, strict=True)), f"usdz: the known weak specular is gone: {said}"
        return
    assert all(r < lim for r, lim in zip(rmse, limits, strict=True)), f"{fmt}{' (fixed)' if fixed else ''}: {said}"


def test_appearance_check_detects_a_roughness_error(blender):
    """Blender's specular renders of the glb, compared with recon's with roughness squared once
    more (r -> r^2, the most common roughness convention error), exceed the limit."""
    res = blender("glb")
    wrong = _recon_renders(res, "specular", roughness=res.asset.r ** 2)
    rmse, limits = appearance_rmse(res, wrong, "specular"), specular_limits(wrong)
    assert any(r > lim for r, lim in zip(rmse, limits, strict=True)), \
        f"r^2 went unnoticed: RMSE {_rounded(rmse)}, limits {_rounded(limits)}"
