"""Tabletop captures: the object on a lit, textured table, hand-held cameras above it, gt of the object alone."""

import json

import numpy as np
import pytest
from _geometry_scene import silhouette
from _tabletop_scene import TABLETOP_TEST, tabletop_capture

from recon import sections
from recon.__main__ import build_parser
from recon.brdf import radiance_collocated
from recon.io.cameras import load_cameras
from recon.io.images import read_exr, read_mask
from recon.io.mesh import read_obj
from recon.support import load_plane
from recon.synth import tabletop as tt
from recon.synth.capture import (PRESETS, TABLETOP_FIELDS, SynthError, SynthSettings, make_capture,
                                 recorded_settings)
from recon.synth.cli import command_line, settings_from_args


@pytest.fixture(scope="module")
def cap(tmp_path_factory):
    return tabletop_capture(tmp_path_factory.getbasetemp())


def test_folder_contract_and_ground_truth(cap):
    stems = [f"{i:04d}" for i in range(24)]
    files = {str(p.relative_to(cap)) for p in cap.rglob("*") if p.is_file()}
    expect = {f"images/{s}.exr" for s in stems} | {f"gt/masks/{s}.png" for s in stems} \
        | {"cameras.json", "gt/mesh.obj", "gt/diffuse.exr", "gt/specular.exr",
           "gt/roughness.exr", "gt/cameras.json", "gt/synth.json", "gt/README.md", "gt/plane.json"}
    assert files == expect  # no masks/ unless asked: the pipeline must find the object itself
    mesh = read_obj(cap / "gt" / "mesh.obj")
    plane = load_plane(cap / "gt" / "plane.json")
    np.testing.assert_allclose(plane.normal, [0, 0, 1])
    # the object stands on the plane: its lowest points lie on it, a flat base of many vertices
    h = plane.height(mesh.v_pos)
    assert abs(h.min()) < 1e-9 and (h < 1e-6).sum() > 20
    meta = json.loads((cap / "gt" / "synth.json").read_text())
    assert meta["settings"]["scene"] == "tabletop" and set(TABLETOP_FIELDS) <= set(meta["settings"])
    assert "plane.json" in (cap / "gt" / "README.md").read_text()


def test_gt_masks_are_the_object_alone(cap):
    """gt/masks is the object's silhouette (nothing occludes it), while the photos show the table
    around it lit about as brightly as the object (the point of the scene)."""
    cams = load_cameras(cap / "gt" / "cameras.json")
    mesh = read_obj(cap / "gt" / "mesh.obj")
    import cv2

    for cam in cams.frames[::6]:
        gt = read_mask(cap / "gt" / "masks" / f"{cam.stem}.png")
        ray = silhouette(mesh, cam)  # pixel centers hitting the mesh
        assert (gt & ray).sum() / (gt | ray).sum() > 0.95
        photo = read_exr(cap / cam.image)
        lum = photo.mean(-1)
        ring = cv2.dilate(gt.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool) & ~gt
        ring[: int(np.argwhere(gt)[:, 0].mean())] = False  # the table in front of the object
        ratio = np.median(lum[ring]) / np.median(lum[gt])
        assert 0.25 < ratio < 4.0, ratio  # the table beside the object: about as bright


def test_table_radiance_follows_the_model(cap):
    """Pixels that see the table: I_e f(mu) mu / r^2 with the table's texture (a_d), a_s = 0.04, r = 0.45."""
    cams = load_cameras(cap / "gt" / "cameras.json")
    plane = load_plane(cap / "gt" / "plane.json")
    s = sections.replace(SynthSettings(), **TABLETOP_TEST)
    tex = tt.table_texture(s.tabletop.table_texture_size, s.tabletop.table_half_size, s.seed)
    cam = cams.frames[0]
    gt = read_mask(cap / "gt" / "masks" / f"{cam.stem}.png")
    photo = read_exr(cap / cam.image)
    rows, cols = np.mgrid[cam.height - 30:cam.height - 2:3, 10:cam.width - 10:5]
    rows, cols = rows.ravel(), cols.ravel()
    keep = ~gt[rows, cols]
    rows, cols = rows[keep], cols[keep]
    pix = np.stack([cols + 0.5, rows + 0.5, np.ones_like(rows, dtype=float)], 1)
    d = pix @ (cam.camera_to_world[:3, :3] @ np.linalg.inv(cam.K)).T
    t = plane.ray_hit(cam.center, d)
    P = cam.center + t[:, None] * d
    size = tex.shape[0]
    j = np.clip(((P[:, 0] + s.tabletop.table_half_size) / (2 * s.tabletop.table_half_size) * size).astype(int), 0, size - 1)
    i = np.clip(((s.tabletop.table_half_size - P[:, 1]) / (2 * s.tabletop.table_half_size) * size).astype(int), 0, size - 1)
    dist = np.linalg.norm(P - cam.center, axis=1)
    mu = plane.height(cam.center) / dist
    expect = radiance_collocated(mu, dist, tex[i, j], np.full((len(P), 1), tt.TABLE_SPECULAR), tt.TABLE_ROUGHNESS,
                                 cams.light_intensity)
    ratio = photo[rows, cols].sum(-1) / expect.sum(-1)
    assert abs(np.median(ratio) - 1.0) < 0.05, np.median(ratio)


def test_cameras_are_handheld_rings_above_the_table(cap):
    cams = load_cameras(cap / "gt" / "cameras.json")
    plane = load_plane(cap / "gt" / "plane.json")
    centers = np.stack([c.center for c in cams])
    assert (plane.height(centers) > 0).all()  # nothing from below
    elev = np.degrees(np.arcsin(centers[:, 2] / np.linalg.norm(centers, axis=1)))
    assert 15.0 <= elev.min() and elev.max() <= 60.0
    assert elev.max() - elev.min() > 20  # several rings
    dist = np.linalg.norm(centers, axis=1)
    assert dist.std() / dist.mean() > 0.03  # people do not keep a fixed distance
    # aim near the object's middle, not exactly at it; a little roll
    axes = np.stack([c.camera_to_world[:3, 2] for c in cams])
    miss = np.linalg.norm(np.cross(axes, -centers), axis=1)
    assert miss.max() < 0.5 and np.median(miss) > 0.01
    roll = np.degrees(np.arcsin(np.stack([c.camera_to_world[:3, 0] for c in cams])[:, 2]))
    assert 0.5 < roll.std() < 10
    again = tt.tabletop_cameras(sections.replace(SynthSettings(), **TABLETOP_TEST))
    np.testing.assert_allclose(again.frames[5].world_to_camera, cams.frames[5].world_to_camera, atol=1e-12)


def test_marker_mat_is_a_detectable_charuco_board(tmp_path):
    import cv2

    tex = tt.table_texture(512, 4.0, seed=1)
    info = tt.add_marker_mat(tex, 4.0, square=0.6)
    assert info["square"] == 0.6 and info["board"]["squares"] == [5, 7]
    board = cv2.aruco.CharucoBoard((5, 7), 0.6, 0.6 * 0.75,
                                   cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    gray = (np.clip(tex.mean(-1) / 0.8, 0, 1) * 255).astype(np.uint8)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    assert ids is not None and len(ids) == 4 * 6  # every inner corner
    # the recorded position: a square of the board spans `square` in world units
    per_unit = 512 / 8.0
    c = corners.reshape(-1, 2)[np.argsort(ids.ravel())]  # row by row, 4 inner corners a row
    step = np.median(np.linalg.norm(np.diff(c[:4], axis=0), axis=1)) / per_unit
    assert step == pytest.approx(0.6, rel=0.02)
    with pytest.raises(ValueError, match="does not fit"):
        tt.add_marker_mat(tt.table_texture(64, 4.0), 4.0, square=2.0)


def test_plain_table_has_almost_no_texture():
    """The plain table (a white desk): its albedo varies by a few percent at most, where the wooden
    one's varies by a factor of several (what SIFT and the masks' plane sweep feed on)."""
    plain = tt.table_texture(256, 4.0, seed=3, kind="plain")
    wood = tt.table_texture(256, 4.0, seed=3)
    assert plain.shape == wood.shape == (256, 256, 3) and np.isfinite(plain).all()
    lum, wlum = plain.mean(-1), wood.mean(-1)
    assert 0.45 < lum.mean() < 0.65 and lum.std() / lum.mean() < 0.03
    assert np.percentile(lum, 99) / np.percentile(lum, 1) < 1.1 < 2.0 < np.percentile(wlum, 99) / np.percentile(wlum, 1)
    with pytest.raises(ValueError, match="table kind"):
        tt.table_texture(16, 4.0, kind="marble")


def test_marker_mat_capture_records_it(tmp_path):
    s = sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 2, "width": 48, "height": 36, "spp": 2, "mesh_level": 2,
                         "texture_size": 64, "table_texture_size": 256, "marker_square": 0.5, "scale": 0.1,
                         "background": 0.0})
    out = make_capture(tmp_path / "mat", s)
    plane = json.loads((out / "gt" / "plane.json").read_text())
    assert plane["marker_mat"]["square"] == pytest.approx(0.05)  # in scene units (scale 0.1)
    assert plane["table_half_size"] == pytest.approx(0.4)
    assert load_plane(out / "gt" / "plane.json").height(read_obj(out / "gt" / "mesh.obj").v_pos).min() \
        == pytest.approx(0.0, abs=1e-9)


def test_void_captures_record_no_tabletop_settings():
    void = recorded_settings(SynthSettings())
    assert not set(TABLETOP_FIELDS) & set(void)
    table = recorded_settings(sections.replace(SynthSettings(), scene="tabletop"))
    assert set(TABLETOP_FIELDS) <= set(table)
    assert PRESETS["tabletop-mug"].object == "mug" and PRESETS["tabletop-blob"].scene == "tabletop"


def test_cli_tabletop_options_round_trip():
    args = build_parser().parse_args(["synth", "out", "--preset", "tabletop", "--object", "mug",
                                      "--elevations", "20", "50", "--rings", "2", "--background", "0",
                                      "--marker-square", "0.4", "--views", "12", "--table", "plain"])
    s = settings_from_args(args)
    assert (s.scene, s.object, s.tabletop.elevation_range, s.tabletop.rings, s.tabletop.background, s.tabletop.marker_square,
            s.tabletop.table) == ("tabletop", "mug", (20.0, 50.0), 2, 0.0, 0.4, "plain")
    again = settings_from_args(build_parser().parse_args(command_line(args).split()[3:]))
    assert again == s


@pytest.mark.parametrize("change,match", [
    ({"scene": "desk"}, "scene"),
    ({"elevation_range": (-10.0, 40.0)}, "elevation_range"),
    ({"elevation_range": (30.0, 95.0)}, "elevation_range"),
    ({"rings": 0}, "rings"),
    ({"table_half_size": 1.0}, "table_half_size"),
    ({"background": 2.0}, "background"),
    ({"background_distance": 6.0}, "background_distance"),
    ({"base_cut": 0.7}, "base_cut"),
    ({"marker_square": -1.0}, "marker_square"),
    ({"table": "marble"}, "table"),
])
def test_bad_tabletop_settings_raise(change, match):
    with pytest.raises(SynthError, match=match):
        sections.replace(sections.replace(SynthSettings(), **TABLETOP_TEST), **change)


def test_tabletop_void_is_the_same_capture_without_the_table(cap, tmp_path_factory):
    """scene="tabletop_void": the same object (base cut flat), cameras and gt files as the
    tabletop capture, and photos that hold the object alone (black around it)."""
    void = tabletop_capture(tmp_path_factory.getbasetemp(), scene="tabletop_void")
    table_cams = load_cameras(cap / "gt" / "cameras.json")
    void_cams = load_cameras(void / "gt" / "cameras.json")
    for a, b in zip(void_cams.frames, table_cams.frames, strict=True):
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-12)
    np.testing.assert_allclose(read_obj(void / "gt" / "mesh.obj").v_pos, read_obj(cap / "gt" / "mesh.obj").v_pos)
    p, q = load_plane(void / "gt" / "plane.json"), load_plane(cap / "gt" / "plane.json")
    np.testing.assert_allclose([*p.normal, p.offset], [*q.normal, q.offset], atol=1e-12)
    for cam in void_cams.frames[::4]:
        gt = read_mask(void / "gt" / "masks" / f"{cam.stem}.png")
        np.testing.assert_array_equal(gt, read_mask(cap / "gt" / "masks" / f"{cam.stem}.png"))
        photo = read_exr(void / cam.image)
        far = ~cv2_dilate(gt, 5)
        assert abs(photo.mean(-1)[far].mean()) < 0.01 * np.median(photo.mean(-1)[gt])  # noise only


def cv2_dilate(mask, r):
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
