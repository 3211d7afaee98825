import numpy as np
import pytest

from recon.io.mesh import Mesh, MeshError, read_mesh, write_mesh


def _tetra():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return Mesh(v, f, v[:, :2].copy(), f.copy())


def test_volume_area_normals():
    m = _tetra()
    assert m.volume() == pytest.approx(1 / 6)
    assert m.area() == pytest.approx(1.5 + np.sqrt(3) / 2)
    n = m.vertex_normals()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1)
    # vertex 0 touches three axis-aligned faces of equal area: normal along -(1,1,1)
    np.testing.assert_allclose(n[0], -np.ones(3) / np.sqrt(3), atol=1e-12)


@pytest.mark.parametrize("ext", [".obj", ".ply"])
def test_round_trip(tmp_path, ext):
    m = _tetra()
    write_mesh(tmp_path / f"m{ext}", m)
    b = read_mesh(tmp_path / f"m{ext}")
    np.testing.assert_allclose(b.v_pos, m.v_pos, atol=1e-6)
    np.testing.assert_array_equal(b.t_pos_idx, m.t_pos_idx)
    if ext == ".obj":
        np.testing.assert_allclose(b.v_tex, m.v_tex)
        np.testing.assert_array_equal(b.t_tex_idx, m.t_tex_idx)


def test_sampling_is_on_surface_and_area_uniform():
    m = Mesh(np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]))
    p = m.sample_surface(20000, np.random.default_rng(0))
    assert np.all(p[:, 2] == 0) and p[:, 0].min() >= 0 and p[:, 0].max() <= 2
    assert abs(np.mean(p[:, 0] < 1) - 0.5) < 0.02


def test_bad_files(tmp_path):
    (tmp_path / "a.obj").write_text("v 0 0 0\nf 1 2 x\n")
    with pytest.raises(MeshError, match="a.obj:2"):
        read_mesh(tmp_path / "a.obj")
    with pytest.raises(MeshError, match="unknown mesh format"):
        read_mesh(tmp_path / "a.stl")
    (tmp_path / "e.obj").write_text("# nothing\n")
    with pytest.raises(MeshError, match="no vertices"):
        read_mesh(tmp_path / "e.obj")
