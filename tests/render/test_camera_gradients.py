"""Gradients of the rendered image with respect to the cameras (pose and intrinsics), the
parameters of camera refinement: against central finite differences of the forward, on a scene
whose silhouettes lie in front of a lit backdrop (the boundary term carries much of the
derivative) and on one with only outer silhouettes against the void; finite at extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from render_scenes import camera, textures, two_spheres_scene, uv_sphere

from recon.io.cameras import Camera
from recon.render import CollocatedRenderer, RenderSettings, camera_table
from recon.render.torch_bridge import camera_table_torch

LIGHT = 10.0


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the axis-angle vector ``w`` (3,), differentiable at 0."""
    theta2 = (w * w).sum()
    K = torch.zeros(3, 3, dtype=w.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    theta = torch.sqrt(theta2 + 1e-30)
    a = torch.where(theta2 > 1e-12, torch.sin(theta) / theta, 1 - theta2 / 6)
    b = torch.where(theta2 > 1e-12, (1 - torch.cos(theta)) / (theta2 + 1e-30), 0.5 - theta2 / 24)
    return torch.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


def _perturbed(cam: Camera, p: torch.Tensor):
    """(K, world_to_camera) of ``cam`` moved by p = (rotation w (3, camera frame), translation
    (3, camera frame), log focal scale (1)): world_to_camera' = [exp(w) R | exp(w) t + dt]."""
    K0 = torch.tensor(cam.K, dtype=torch.float64)
    T0 = torch.tensor(cam.world_to_camera, dtype=torch.float64)
    R = _rodrigues(p[:3]) @ T0[:3, :3]
    t = _rodrigues(p[:3]) @ T0[:3, 3] + p[3:6]
    f = torch.exp(p[6])
    K = torch.stack([K0[0] * torch.stack([f, torch.ones((), dtype=p.dtype), torch.ones((), dtype=p.dtype)]),
                     K0[1] * torch.stack([torch.ones((), dtype=p.dtype), f, torch.ones((), dtype=p.dtype)]),
                     K0[2]])
    w2c = torch.cat([torch.cat([R, t[:, None]], 1), T0[3:]], 0)
    return K, w2c


def _camera_at(cam: Camera, p: np.ndarray) -> Camera:
    K, w2c = _perturbed(cam, torch.tensor(p, dtype=torch.float64))
    return Camera(cam.image, cam.width, cam.height, K.numpy(), w2c.numpy())


def _scene(kind: str):
    if kind == "backdrop":
        (v, f, t, ft), _, cam = two_spheres_scene()
    else:
        v, f, t, ft = uv_sphere(24, 12, radius=0.8)
        cam = camera((0.2, -3.5, 0.6))
    d, s, r = textures(np.random.default_rng(2))
    return (v, f, t, ft), (d, s, r), cam


def _weights(cam):
    x = np.arange(cam.width) / cam.width
    y = np.arange(cam.height) / cam.height
    w = (0.5 + x[None, :, None] + 0.3 * y[:, None, None]) * np.array([1.0, 0.8, 0.6])
    return torch.tensor(w, dtype=torch.float32)


def _ad(mesh, maps, cam, direction, seeds=(0, 1, 2, 3), boundary="edge", spp=64):
    v, f, t, ft = mesh
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=spp, boundary=boundary, edge_samples_per_pixel=16.0))
    w = _weights(cam)
    out = []
    for seed in seeds:
        p = torch.zeros(7, dtype=torch.float64, requires_grad=True)
        K, w2c = _perturbed(cam, p)
        table = camera_table_torch(K[None], w2c[None]).to(torch.float32)
        img = r.render_torch(torch.tensor(v, dtype=torch.float32), *(torch.tensor(m) for m in maps), [cam], LIGHT,
                             seed, camera_table=table)[0]
        (img * w).sum().backward()
        out.append(float(p.grad @ torch.tensor(direction, dtype=torch.float64)))
    return float(np.mean(out)), float(np.std(out) / np.sqrt(len(out)))


def _fd(mesh, maps, cam, direction, h, spp=4096):
    v, f, t, ft = mesh
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=spp, boundary="none"))
    w = _weights(cam).numpy().astype(np.float64)
    vals = []
    for sgn in (1.0, -1.0):
        c = _camera_at(cam, sgn * h * np.asarray(direction, np.float64))
        vals.append(float((r.render(v, *maps, [c], LIGHT, 0)[0].numpy() * w).sum()))
    return (vals[0] - vals[1]) / (2 * h)


DIRECTIONS = {
    "rotation": ([0.0, 1.0, 0.2, 0, 0, 0, 0], 2e-3),   # mostly a pan about the camera's y axis
    "translation": ([0, 0, 0, 1.0, 0.0, 0.3, 0], 5e-3),  # sideways and forward, camera frame
    "focal": ([0, 0, 0, 0, 0, 0, 1.0], 5e-3),          # log focal length (zoom)
}


@pytest.mark.parametrize("kind", ["backdrop", "void"])
@pytest.mark.parametrize("name", list(DIRECTIONS))
def test_camera_gradients_match_finite_differences(kind, name):
    """Directional derivatives of sum(w * image) along a camera rotation, translation and focal
    length agree with central differences within 5 %; without the boundary term they do not
    where silhouettes lie in front of the lit backdrop."""
    mesh, maps, cam = _scene(kind)
    direction, h = DIRECTIONS[name]
    ours, se = _ad(mesh, maps, cam, direction)
    fd = _fd(mesh, maps, cam, direction, h)
    assert abs(ours - fd) < 0.05 * abs(fd) + 3 * se, (ours, se, fd)
    if kind == "backdrop":
        interior, _ = _ad(mesh, maps, cam, direction, seeds=(0,), boundary="none")
        assert abs(interior - fd) > 0.2 * abs(fd), (interior, fd)


def test_camera_table_matches_numpy_and_batches():
    """The torch table equals the renderer's own (numpy) one, and a two-view batch's camera
    gradient for view 0 equals that of view 0 rendered alone (same seed, same samples)."""
    mesh, maps, cam = _scene("backdrop")
    cams = [cam, camera((2.5, -3.0, 0.8))]
    K = torch.tensor(np.stack([c.K for c in cams]))
    T = torch.tensor(np.stack([c.world_to_camera for c in cams]))
    np.testing.assert_allclose(camera_table_torch(K, T).numpy(), camera_table(cams), rtol=1e-12, atol=1e-12)
    v, f, t, ft = mesh
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=4, boundary="edge"))
    w = _weights(cam)

    def grad(views):
        table = camera_table_torch(K[views], T[views]).to(torch.float32).requires_grad_(True)
        img = r.render_torch(torch.tensor(v, dtype=torch.float32), *(torch.tensor(m) for m in maps),
                             [cams[i] for i in views], LIGHT, 3, camera_table=table)
        (img[0] * w).sum().backward()
        return table.grad[0].numpy()

    # Each of the 24 camera-table entries gathers from every sample of the view, n = 64^2 4 + the
    # edge samples, scatter-added by several drjit threads in an order the scheduler picks:
    # about sqrt(n) u max|g| = 7.9e-6 max|g| apart (tests/_float_sums.py; measured at most
    # 1.1e-6 max|g| over 20 runs on 2 threads); the tolerance is 13 times that scale.
    np.testing.assert_allclose(grad([0, 1]), grad([0]), rtol=1e-4, atol=1e-4 * np.abs(grad([0])).max())


@pytest.mark.parametrize("case", ["nearly_behind", "tiny_focal", "huge_focal"])
def test_camera_gradients_finite_at_extremes(case):
    """A camera whose view holds the object's near side behind it (the object straddles the
    camera plane), and focal lengths 1e-3 and 1e6 px: values and camera gradients finite."""
    mesh, maps, cam = _scene("void")
    v, f, t, ft = mesh
    if case == "nearly_behind":
        cam = camera((0.0, -0.5, 0.0), target=(0.0, 1.0, 0.0))  # inside the sphere's extent
    else:
        K = cam.K.copy()
        K[0, 0] = K[1, 1] = 1e-3 if case == "tiny_focal" else 1e6
        cam = Camera(cam.image, cam.width, cam.height, K, cam.world_to_camera)
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=4, boundary="edge"))
    table = torch.tensor(camera_table([cam]), dtype=torch.float32, requires_grad=True)
    v_t = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    img = r.render_torch(v_t, *(torch.tensor(m) for m in maps), [cam], LIGHT, 0, camera_table=table)
    assert torch.isfinite(img).all()
    (img * _weights(cam)).sum().backward()
    assert torch.isfinite(table.grad).all() and torch.isfinite(v_t.grad).all()
