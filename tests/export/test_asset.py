"""export_asset: appearance preserved through independent readers, conventions, frames, errors."""

from __future__ import annotations

import os

import numpy as np
import pytest
from export_model import Model, make_cameras, write_model
from export_readers import read_glb, read_usdz, srgb_decode, srgb_encode

from recon.config import build_settings
from recon.export import ExportError, ExportSettings, export_asset, object_to_world, up_rotation
from recon.io.cameras import Camera, CameraSet, look_at, save_cameras
from recon.io.images import read_exr, write_exr
from recon.io.mesh import Mesh, write_obj
from recon.synth.textures import bilinear_lookup

READERS = {"glb": read_glb, "usdz": read_usdz}
HALF_STEP = 0.5 / 255 + 1e-6  # 8-bit quantization, in the stored (encoded) domain


@pytest.fixture(scope="module", params=["glb", "usdz"])
def readback(request, exported):
    return request.param, READERS[request.param](exported[request.param])


# ---- Appearance ----
@pytest.fixture(scope="module")
def reference_renders(model, mi):
    from recon.render.mitsuba_bsdf import render_reference

    return [render_reference(model.mesh, model.maps, cam, model.cameras.light_intensity,
                             spp=16, seed=k) for k, cam in enumerate(model.cameras.frames)]


def _render_asset(asset, mesh, cam, light_intensity, seed, textures=None):
    """Render the read-back asset in its own (+Y up) frame with the camera moved there too."""
    from recon.render.mitsuba_bsdf import render_reference

    w2c = cam.world_to_camera @ np.linalg.inv(asset.object_to_world)
    moved = Camera(cam.image, cam.width, cam.height, cam.K, w2c)
    textures = textures or {"diffuse": asset.a_d, "specular": asset.a_s, "roughness": asset.r}
    return render_reference(mesh, textures, moved, light_intensity, spp=16, seed=seed)


def _rmse_srgb(a, b):
    return float(np.sqrt(np.mean((srgb_encode(a) - srgb_encode(b)) ** 2)))


def test_appearance_preserved(model, readback, reference_renders):
    """Each read-back asset, rendered with the collocated light (the Mitsuba forward reference,
    DESIGN section 3), matches the optimized model: contract RMSE < 0.01 in sRGB; 8-bit
    textures allow ~1e-3, measured ~3e-4."""
    fmt, asset = readback
    for k, (cam, ref) in enumerate(zip(model.cameras.frames, reference_renders, strict=True)):
        assert (ref.sum(axis=2) > 0).mean() > 0.2, "the object must fill the view"
        img = _render_asset(asset, asset.mesh, cam, model.cameras.light_intensity, seed=k)
        assert np.all(np.isfinite(img))
        rmse = _rmse_srgb(img, ref)
        assert rmse < 0.002, f"{fmt} view {k}: sRGB RMSE {rmse:.5f}"


def test_appearance_check_detects_a_uv_flip(model, readback, reference_renders):
    """The same comparison fails for a v-flipped UV set, so it can tell a convention error."""
    fmt, asset = readback
    m = asset.mesh
    flipped = Mesh(m.v_pos, m.t_pos_idx, np.stack([m.v_tex[:, 0], 1 - m.v_tex[:, 1]], 1), m.t_tex_idx)
    cam = model.cameras.frames[0]
    rmse = _rmse_srgb(_render_asset(asset, flipped, cam, model.cameras.light_intensity, 0),
                      reference_renders[0])
    assert rmse > 0.01, f"{fmt}: a UV flip went unnoticed (RMSE {rmse:.5f})"


# ---- Conventions, texel by texel ----
def test_maps_survive_to_8bit(model, readback):
    """a_d and a_s (sRGB-encoded) and r (linear) survive within half an 8-bit step, every texel."""
    fmt, asset = readback
    a_s_in = np.repeat(model.maps["specular"], asset.a_s.shape[2], axis=2)
    for name, got, want, encode in (
        ("a_d", asset.a_d, model.maps["diffuse"], srgb_encode),
        ("a_s", asset.a_s, a_s_in, srgb_encode),
        ("r", asset.r, model.maps["roughness"], lambda x: x),
    ):
        assert got.shape == want.shape, f"{fmt} {name}: {got.shape} vs {want.shape}"
        err = np.abs(encode(got) - encode(want)).max()
        assert err <= HALF_STEP, f"{fmt} {name}: max encoded error {err * 255:.3f} / 255"


def test_known_texel_values(tmp_path):
    """Constant maps through both formats: a_s = 0.04 (a typical dielectric) comes back within
    half an sRGB 8-bit step there (7e-4, against 2e-3 for a linear 8-bit channel); a_d = 0.5
    within its half step (3e-3); r = 0.3 within half a linear step."""
    m = write_model(tmp_path / "cap")
    write_exr(m.exr("diffuse"), np.full((4, 4, 3), 0.5, np.float32))
    write_exr(m.exr("specular"), np.full((4, 4, 1), 0.04, np.float32))
    write_exr(m.exr("roughness"), np.full((4, 4, 1), 0.3, np.float32))
    out = export_asset(*m.inputs(), tmp_path / "export", ExportSettings(up="identity"))

    def srgb_half_step(x):
        return float(srgb_decode(srgb_encode(x) + 0.5 / 255) - x) + 1e-6

    assert srgb_half_step(0.04) < 7.5e-4
    for fmt, read in READERS.items():
        a = read(out[fmt])
        assert np.abs(a.a_s - 0.04).max() <= srgb_half_step(0.04), fmt
        assert np.abs(a.a_d - 0.5).max() <= srgb_half_step(0.5), fmt
        assert np.abs(a.r - 0.3).max() <= HALF_STEP, fmt


def test_uv_lookups_match_the_input(model, readback):
    """At every face corner, the read-back maps looked up at the read-back UVs equal the input
    maps at the input UVs (UV origin and image row order agree)."""
    fmt, asset = readback
    m = asset.mesh
    # Corners in face order: glTF/USD keep the OBJ's triangles in order.
    assert len(m.t_tex_idx) == len(model.mesh.t_pos_idx)
    T = asset.object_to_world
    corners = m.v_pos[m.t_pos_idx].reshape(-1, 3)
    local = (corners - T[:3, 3]) @ np.linalg.inv(T[:3, :3]).T
    assert np.abs(local - model.mesh.v_pos[model.mesh.t_pos_idx].reshape(-1, 3)).max() < 1e-5
    uv_got = m.v_tex[m.t_tex_idx].reshape(-1, 2)
    uv_want = model.mesh.v_tex[model.mesh.t_tex_idx].reshape(-1, 2)
    for got, want, tol in ((asset.a_d, model.maps["diffuse"], 5e-3),
                           (asset.r, model.maps["roughness"], HALF_STEP)):
        err = np.abs(bilinear_lookup(got, uv_got) - bilinear_lookup(want, uv_want)).max()
        assert err <= tol, f"{fmt}: lookup error {err:.4g}"


def test_stored_normals_are_area_weighted(readback):
    """The file's normals are the area-weighted vertex normals of DESIGN section 3 (so viewers
    shade like the project's renderer), also at UV seams."""
    fmt, asset = readback
    want = asset.mesh.vertex_normals()
    assert np.abs(asset.normals - want).max() < 1e-5, fmt


# ---- Frames and units ----
def test_up_axis_from_the_cameras(model, readback):
    """Default settings: the mean camera up (+Z in the capture frame) becomes +Y."""
    fmt, asset = readback
    R = asset.object_to_world[:3, :3]
    ups = np.array([-c.world_to_camera[1, :3] for c in model.cameras])
    mean = R @ ups.mean(axis=0)
    assert np.allclose(mean / np.linalg.norm(mean), [0, 1, 0], atol=1e-6), fmt
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0


def test_meters_per_unit_scales_the_root(tmp_path, model):
    out = export_asset(*model.inputs(), tmp_path / "export",
                       ExportSettings(up="identity", meters_per_unit=0.25))
    for fmt, read in READERS.items():
        a = read(out[fmt])
        assert np.allclose(a.object_to_world, np.diag([0.25, 0.25, 0.25, 1.0]), atol=1e-7), fmt
        assert np.allclose(np.ptp(a.mesh.v_pos, axis=0), 0.25 * np.ptp(model.mesh.v_pos, axis=0),
                           atol=1e-6), fmt


@pytest.mark.parametrize("up", [(0, 0, 1), (0, -1, 0), (0, 1, 0), (0.3, -0.5, 0.8)])
def test_up_rotation_maps_up_to_y(up):
    up = np.asarray(up, float) / np.linalg.norm(up)
    cams = [Camera("a", 8, 8, np.eye(3), look_at(e, np.zeros(3), up))
            for e in ([3, 0.1, 0.2], [0.1, 3, 0.3], [-2, -2, 0.4], [0.5, 0.2, -3])
            if abs(np.dot(np.asarray(e, float) / np.linalg.norm(e), up)) < 0.9]
    R = up_rotation(cams)
    ups = np.array([-c.world_to_camera[1, :3] for c in cams])
    mean = R @ ups.mean(axis=0)
    assert np.allclose(mean / np.linalg.norm(mean), [0, 1, 0], atol=1e-9)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)


def test_up_rotation_keeps_identity_when_views_disagree():
    cams = [Camera("a", 8, 8, np.eye(3), look_at([3, 0, 0], np.zeros(3), up))
            for up in ([0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1])]
    assert np.array_equal(up_rotation(cams), np.eye(3))
    assert np.array_equal(object_to_world(ExportSettings(up="identity")), np.eye(4))


def test_the_poses_stage_up_wins_over_the_cameras(tmp_path):
    """SfM's cameras.json says its frame's up (the poses stage read each photo's EXIF
    Orientation): cameras whose pixels are stored sideways disagree on -y, but the asset still
    stands on the frame's z."""
    from recon.io.cameras import CameraSet, save_cameras

    frames = []
    for k in range(8):
        W = look_at([3 * np.cos(k), 3 * np.sin(k), 1.0], np.zeros(3), [0, 0, 1]).copy()
        W[:2] = np.stack([W[1], -W[0]])  # portrait: the displayed up is the stored -x
        frames.append(Camera(f"images/{k}.jpg", 8, 8, np.eye(3), W))
    save_cameras(tmp_path / "plain.json", CameraSet(tuple(frames)))
    save_cameras(tmp_path / "sfm.json", CameraSet(tuple(frames), 1.0, {"up": [0.0, 0.0, 1.0]}))
    R = object_to_world(ExportSettings(), tmp_path / "sfm.json")[:3, :3]
    assert np.allclose(R @ [0, 0, 1], [0, 1, 0], atol=1e-9)
    R = object_to_world(ExportSettings(), tmp_path / "plain.json")[:3, :3]
    assert not np.allclose(R @ [0, 0, 1], [0, 1, 0], atol=0.1)


def test_settings_from_config_and_bad_values():
    s = build_settings(ExportSettings, {"up": "identity", "meters_per_unit": 2})
    assert s == ExportSettings(up="identity", meters_per_unit=2.0)
    for bad in ({"up": "z"}, {"meters_per_unit": 0.0}, {"meters_per_unit": float("nan")},
                {"min_up_agreement": 1.5}):
        with pytest.raises(ValueError):
            ExportSettings(**bad)


# ---- Outputs and atomicity ----
def test_outputs(exported):
    names = {p.name for p in exported["glb"].parent.iterdir()}
    assert names == {"asset.glb", "asset.usdz", "asset.usda", "diffuse.png", "specular.png",
                     "metallic_roughness.png"}
    assert all(exported[k].stat().st_size > 0 for k in exported)
    mask = os.umask(0)
    os.umask(mask)
    for p in [exported["glb"].parent, *exported.values()]:  # shareable, not mkstemp's 0600
        assert p.stat().st_mode & 0o777 == (0o777 if p.is_dir() else 0o666) & ~mask, p


def test_failed_export_leaves_the_previous_one(tmp_path, model, monkeypatch):
    out = tmp_path / "export"
    export_asset(*model.inputs(), out, ExportSettings(up="identity"))
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    import recon.export.asset as asset

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(asset, "write_usd", fail)  # fails after the textures and the glb exist
    with pytest.raises(RuntimeError, match="disk full"):
        export_asset(*model.inputs(), out, ExportSettings())
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["export"]  # no temporary folder left


# ---- Bad input: errors name the file ----
@pytest.fixture
def fresh(tmp_path) -> Model:
    return write_model(tmp_path / "cap")


def _export(m: Model, tmp_path, **kw):
    return export_asset(*m.inputs(), tmp_path / "export", ExportSettings(), **kw)


def test_missing_texture(fresh, tmp_path):
    fresh.exr("specular").unlink()
    with pytest.raises(ExportError, match=str(fresh.exr("specular"))):
        _export(fresh, tmp_path)
    assert not (tmp_path / "export").exists()


def test_mesh_without_uvs(fresh, tmp_path):
    write_obj(fresh.mesh_obj, Mesh(fresh.mesh.v_pos, fresh.mesh.t_pos_idx))
    with pytest.raises(ExportError, match=f"{fresh.mesh_obj}.*no UVs"):
        _export(fresh, tmp_path)


def test_missing_mesh(fresh, tmp_path):
    fresh.mesh_obj.unlink()
    with pytest.raises(ExportError, match=str(fresh.mesh_obj)):
        _export(fresh, tmp_path)


@pytest.mark.parametrize("name,channels", [("diffuse", 1), ("specular", 4), ("roughness", 3)])
def test_wrong_channel_count(fresh, tmp_path, name, channels):
    write_exr(fresh.exr(name), np.full((8, 8, channels), 0.5, np.float32))
    with pytest.raises(ExportError, match=f"{fresh.exr(name)}.*{channels} channel"):
        _export(fresh, tmp_path)


@pytest.mark.parametrize("name", ["diffuse", "specular", "roughness"])
def test_nan_in_a_map(fresh, tmp_path, name):
    a = read_exr(fresh.exr(name))
    a[3, 5, 0] = np.nan
    write_exr(fresh.exr(name), a)
    with pytest.raises(ExportError, match=f"{fresh.exr(name)}.*1 texel.*NaN"):
        _export(fresh, tmp_path)


def test_bad_cameras_json(fresh, tmp_path):
    fresh.cameras_json.write_text("{not json")
    with pytest.raises(ExportError, match=str(fresh.cameras_json)):
        _export(fresh, tmp_path, cameras_json=fresh.cameras_json)


def test_out_of_range_values_are_clipped(fresh, tmp_path, caplog):
    a = read_exr(fresh.exr("diffuse"))
    a[0, 0] = (1.7, -0.2, 0.5)
    write_exr(fresh.exr("diffuse"), a)
    out = _export(fresh, tmp_path, cameras_json=fresh.cameras_json)
    assert "outside [0, 1]" in caplog.text and str(fresh.exr("diffuse")) in caplog.text
    got = read_glb(out["glb"]).a_d
    assert np.allclose(got[0, 0], (1.0, 0.0, 0.5), atol=3e-3)
    assert np.all((got >= 0) & (got <= 1))


def test_cameras_up_with_another_camera_set(tmp_path, fresh):
    """cameras.json whose views look up along -Y: the export turns the asset upside down."""
    cams = make_cameras()
    flipped = CameraSet(tuple(Camera(c.image, c.width, c.height, c.K,
                                     look_at(c.center[[0, 2, 1]] * [1, 1, -1], np.zeros(3),
                                             (0, -1, 0)))
                              for c in cams.frames), cams.light_intensity)
    save_cameras(fresh.cameras_json, flipped)
    out = _export(fresh, tmp_path, cameras_json=fresh.cameras_json)
    R = read_glb(out["glb"]).object_to_world[:3, :3]
    assert np.allclose(R @ [0, -1, 0], [0, 1, 0], atol=1e-6)


def test_rgb_specular_map(fresh, tmp_path):
    """An RGB a_s (DESIGN 2: 'or RGB where the scene needs it') keeps its channels apart."""
    a_s = np.stack([np.full((6, 5), v, np.float32) for v in (0.03, 0.2, 0.9)], axis=-1)
    a_s[2, 3] = (0.5, 0.0, 1.0)
    write_exr(fresh.exr("specular"), a_s)
    out = _export(fresh, tmp_path, cameras_json=fresh.cameras_json)
    for fmt, read in READERS.items():
        got = read(out[fmt]).a_s
        assert got.shape == (6, 5, 3)
        assert np.abs(srgb_encode(got) - srgb_encode(a_s)).max() <= HALF_STEP, fmt


@pytest.mark.parametrize("height_m", [0.0, 0.12])
def test_support_plane_stands_the_asset_upright_at_scale(tmp_path, model, height_m, caplog):
    """A support plane (plane.json) under the object, tilted in the cameras.json frame: in both
    formats the plane's normal is +Y, the object's lowest point (on the plane) at y = 0, its
    bounding box centred in x and z; export.object_height_m gives the scale (the height above
    the plane, in metres); without a known length the asset is unitless, with a warning."""
    from recon.support import SupportPlane, save_plane

    n = np.array([0.3, -0.4, 0.85])
    n /= np.linalg.norm(n)
    plane = SupportPlane(n, -float((model.mesh.v_pos @ n).min()))  # touching the object's lowest point
    save_plane(tmp_path / "plane.json", plane)
    with caplog.at_level("WARNING"):
        out = export_asset(*model.inputs(), tmp_path / "export", ExportSettings(object_height_m=height_m),
                           cameras_json=model.cameras_json, plane_json=tmp_path / "plane.json")
    assert ("scale is unknown" in caplog.text) == (height_m == 0)
    true_height = float(plane.height(model.mesh.v_pos).max())
    scale = height_m / true_height if height_m else 1.0
    for fmt, read in READERS.items():
        a = read(out[fmt])
        v = a.mesh.v_pos
        assert abs(v[:, 1].min()) < 1e-6 * scale, fmt
        assert abs(v[:, 1].max() - scale * true_height) < 1e-5, fmt
        lo, hi = v.min(0), v.max(0)
        assert np.allclose([(lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2], 0, atol=1e-6), fmt
        T = a.object_to_world
        assert np.allclose(T[:3, :3] @ n / scale, [0, 1, 0], atol=1e-6), fmt  # the normal is +Y
    # no plane file (none found): today's frame (mean camera up) and no translation
    out = export_asset(*model.inputs(), tmp_path / "void", ExportSettings(), cameras_json=model.cameras_json,
                       plane_json=tmp_path / "absent.json")
    assert np.allclose(read_glb(out["glb"]).object_to_world[:3, 3], 0)


def test_marker_mat_sets_the_scale(tmp_path, tmp_path_factory, model):
    """export.marker_square_m: the scale comes from the ChArUco mat in the views (recon.marker),
    within 1 %; a declared mat missing from the views is an error naming the folder."""
    from _tabletop_scene import MAT_TEST, MAT_TEST_SQUARE_UNITS, tabletop_capture

    cap = tabletop_capture(tmp_path_factory.getbasetemp(), **MAT_TEST)
    s = ExportSettings(up="identity", marker_square_m=0.03, object_height_m=5.0)  # the mat wins
    out = export_asset(*model.inputs(), tmp_path / "export", s, cameras_json=cap / "gt" / "cameras.json",
                       views_dir=cap / "images")
    a = read_glb(out["glb"])
    true = 0.03 / MAT_TEST_SQUARE_UNITS
    scale = float(np.cbrt(np.linalg.det(a.object_to_world[:3, :3])))
    assert abs(scale / true - 1) < 0.01
    import pygltflib

    extras = pygltflib.GLTF2().load(str(out["glb"])).asset.extras["recon"]
    assert extras["scale_source"] == "marker mat" and extras["marker_mat"]["neighbour_pairs"] >= 6
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ExportError, match="empty"):
        export_asset(*model.inputs(), tmp_path / "export2", s, cameras_json=cap / "gt" / "cameras.json",
                     views_dir=empty)
