import json

import numpy as np
import pytest

from recon.io.cameras import Camera, CameraError, CameraSet, intrinsics, load_cameras, look_at, save_cameras


def _cam(eye=(0, -3, 0)):
    return Camera("images/0000.png", 64, 48, intrinsics(64, 48, 40.0), look_at(eye, (0, 0, 0)))


def test_look_at_projects_target_to_center_and_up_is_up():
    c = _cam()
    xy, z = c.project(np.array([[0.0, 0, 0], [0, 0, 0.5]]))
    np.testing.assert_allclose(xy[0], [32, 24], atol=1e-9)
    assert z[0] == pytest.approx(3.0)
    assert xy[1, 1] < 24  # world +z (up) is image up (smaller row)
    np.testing.assert_allclose(c.center, [0, -3, 0], atol=1e-12)


def test_round_trip_and_validation(tmp_path):
    cams = CameraSet((_cam(), _cam((3, 0, 1))), light_intensity=2.0)
    save_cameras(tmp_path / "cameras.json", cams)
    back = load_cameras(tmp_path / "cameras.json")
    assert back.light_intensity == 2.0 and len(back) == 2
    np.testing.assert_allclose(back.frames[1].world_to_camera, cams.frames[1].world_to_camera)
    data = json.loads((tmp_path / "cameras.json").read_text())
    data["frames"][0]["world_to_camera"][0][0] = 5.0
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(CameraError, match=r"bad.json: frames\[0\].world_to_camera: .* not a rotation"):
        load_cameras(tmp_path / "bad.json")
    with pytest.raises(CameraError, match="not valid JSON"):
        (tmp_path / "x.json").write_text("{")
        load_cameras(tmp_path / "x.json")


def test_scaled_camera_keeps_pixel_edges():
    c = _cam()
    h = c.scaled(0.5)
    p = np.array([[0.2, 0.1, -0.3]])
    np.testing.assert_allclose(h.project(p)[0], c.project(p)[0] * 0.5, atol=1e-9)
