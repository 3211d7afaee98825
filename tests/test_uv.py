import json

import numpy as np
import pytest
from _geometry_scene import blob_mesh, icosphere

from recon import uv as ruv
from recon.io.mesh import Mesh, read_obj, write_ply


@pytest.fixture(scope="module")
def blob():
    return blob_mesh(subdivisions=4)  # 5120 faces


def _chart_of_faces(m: Mesh) -> np.ndarray:
    """Chart id per face: faces connected through shared UV vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = m.t_tex_idx
    n = len(m.v_tex)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    return label[f[:, 0]]


def _bilinear_texels(m: Mesh, size: int, per_edge: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Texels (flat index) touched by bilinear lookups at dense samples of every face, and the
    face's chart."""
    chart = _chart_of_faces(m)
    k = np.arange(per_edge + 1)
    a, b = np.meshgrid(k, k, indexing="ij")
    keep = a + b <= per_edge
    bary = np.stack([a[keep], b[keep], per_edge - a[keep] - b[keep]], 1) / per_edge  # (S, 3)
    uv = np.einsum("sk,fkd->fsd", bary, m.v_tex[m.t_tex_idx])  # (F, S, 2)
    x = uv[..., 0] * size - 0.5  # texel centers at integers
    y = (1.0 - uv[..., 1]) * size - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    texels, owners = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            tx = np.clip(x0 + dx, 0, size - 1)
            ty = np.clip(y0 + dy, 0, size - 1)
            texels.append((ty * size + tx).ravel())
            owners.append(np.repeat(chart, uv.shape[1]))
    return np.concatenate(texels), np.concatenate(owners)


@pytest.mark.parametrize("size", [256, 1024])
def test_unwrap_keeps_geometry_and_pads_charts(blob, size):
    out, stats = ruv.unwrap(blob, ruv.UVSettings(texture_size=size, padding=2))
    # positions untouched: same vertices, same faces (the mesh stays watertight)
    np.testing.assert_array_equal(out.t_pos_idx, blob.t_pos_idx)
    np.testing.assert_array_equal(out.v_pos, blob.v_pos)
    assert out.has_uv and out.t_tex_idx.shape == out.t_pos_idx.shape
    assert np.all(np.isfinite(out.v_tex))
    assert out.v_tex.min() >= 0 and out.v_tex.max() <= 1
    assert stats["charts"] >= 1 and 0.3 < stats["utilization"] <= 1
    assert max(stats["atlas_width"], stats["atlas_height"]) <= size
    # UV triangles are not degenerate
    t = out.v_tex[out.t_tex_idx]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert (area > 0).all()
    # bilinear lookups anywhere in a chart never touch a texel another chart uses
    texels, owners = _bilinear_texels(out, size)
    order = np.lexsort((owners, texels))
    texels, owners = texels[order], owners[order]
    same_texel = texels[1:] == texels[:-1]
    assert not np.any(same_texel & (owners[1:] != owners[:-1]))
    assert stats["charts"] == len(np.unique(_chart_of_faces(out)))


def test_small_components_are_dropped(blob):
    speck = icosphere(0)  # 20 faces
    speck = Mesh(speck.v_pos * 0.01 + 2.0, speck.t_pos_idx + len(blob.v_pos))
    both = Mesh(np.concatenate([blob.v_pos, speck.v_pos]), np.concatenate([blob.t_pos_idx, speck.t_pos_idx]))
    out, stats = ruv.unwrap(both, ruv.UVSettings(texture_size=256, min_component_faces=32))
    assert stats["dropped_components"] == 1
    assert len(out.t_pos_idx) == len(blob.t_pos_idx)
    assert out.v_pos.max() < 1.5  # the speck at (2, 2, 2) is gone


def test_run_uv_writes_obj_with_uvs(blob, tmp_path):
    src = tmp_path / "mesh.ply"
    write_ply(src, blob)
    stats = ruv.run_uv(src, tmp_path / "uv", ruv.UVSettings(texture_size=256))
    back = read_obj(tmp_path / "uv" / "mesh.obj")
    assert back.has_uv and len(back.t_pos_idx) == len(blob.t_pos_idx)
    np.testing.assert_allclose(back.v_pos, blob.v_pos, atol=1e-6)  # PLY is float32
    assert json.loads((tmp_path / "uv" / "uv.json").read_text())["charts"] == stats["charts"]


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="padding must be >= 2"):
        ruv.UVSettings(padding=1)
    with pytest.raises(ruv.UVError, match="no faces"):
        ruv.unwrap(Mesh(np.zeros((3, 3)), np.zeros((0, 3))))
    with pytest.raises(ruv.UVError, match="nothing left"):
        ruv.unwrap(icosphere(0), ruv.UVSettings(min_component_faces=100))
    with pytest.raises(ruv.UVError, match=r"missing\.ply: file not found; rerun the init_mesh stage"):
        ruv.run_uv(tmp_path / "missing.ply", tmp_path / "uv")
    assert not (tmp_path / "uv").exists()


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_atlas_does_not_depend_on_units(blob, scale):
    """Regression: at 1e-3 units xatlas took every face as degenerate (float32, absolute area
    epsilon) and no packing fitted; the atlas must be that of the same mesh at unit scale."""
    settings = ruv.UVSettings(texture_size=128)
    ref, ref_stats = ruv.unwrap(blob, settings)
    out, stats = ruv.unwrap(Mesh(blob.v_pos * scale, blob.t_pos_idx), settings)
    np.testing.assert_array_equal(out.t_tex_idx, ref.t_tex_idx)
    np.testing.assert_allclose(out.v_tex, ref.v_tex, atol=1e-6)
    assert stats["charts"] == ref_stats["charts"] and stats["attempts"] == ref_stats["attempts"]
    assert stats["texels_per_unit"] == pytest.approx(ref_stats["texels_per_unit"] / scale, rel=1e-6)


def _porous_sphere(res: int = 32) -> Mesh:
    """A ball (radius 0.5) drilled by 27 tunnels along the three axes (genus 29): the kind of
    surface a visual hull with one view's mask errors became on the real skull (genus 27-86).
    xatlas cuts it into hundreds of small charts."""
    from recon.hull import Grid
    from recon.init_mesh import isosurface, largest_component

    grid = Grid.cube(np.zeros(3), 0.6, res)
    p = grid.points()
    sdf = 0.5 - np.linalg.norm(p, axis=1)
    for ax in range(3):
        u, w = [a for a in range(3) if a != ax]
        for a in (-0.3, 0.0, 0.3):
            for b in (-0.3, 0.0, 0.3):
                sdf = np.minimum(sdf, np.hypot(p[:, u] - a, p[:, w] - b) - 0.06)
    return largest_component(isosurface(sdf.reshape(res, res, res).astype(np.float32), grid))


def test_atlas_grows_when_the_charts_cannot_fit(caplog):
    """Regression: on the real skull's hull (genus 27) the stage stopped with "xatlas could not
    fit the charts into 256x256 texels in 6 attempts; raise texture_size or lower padding": the
    4-texel padding around each of hundreds of charts fills a 256^2 map at any texel density, so
    lowering the density cannot help (and no setting of the user's should be needed). The map
    now grows until the charts fit, with a warning, and uv.json says which size it is."""
    mesh = _porous_sphere()
    from recon.init_mesh import topology

    assert topology(mesh)["genus"] > 20
    settings = ruv.UVSettings(texture_size=256, padding=4)
    with caplog.at_level("WARNING", logger="recon.uv"):
        out, stats = ruv.unwrap(mesh, settings)
    T = stats["texture_size"]
    assert stats["requested_texture_size"] == 256 and T in (512, 1024)
    assert stats["charts"] * 11**2 > 0.8 * 256**2  # the padding alone would fill the requested map
    assert "growing the map" in caplog.text
    np.testing.assert_array_equal(out.t_pos_idx, mesh.t_pos_idx)  # positions untouched
    assert out.v_tex.min() >= 0 and out.v_tex.max() <= 1
    assert max(stats["atlas_width"], stats["atlas_height"]) <= T
    # the padding holds in texels of the grown map: bilinear lookups stay in their chart
    texels, owners = _bilinear_texels(out, T)
    order = np.lexsort((owners, texels))
    texels, owners = texels[order], owners[order]
    assert not np.any((texels[1:] == texels[:-1]) & (owners[1:] != owners[:-1]))
    # a caller whose map size is fixed gets an error that names the real condition
    with pytest.raises(ruv.UVError, match=r"into 256x256 texels: \d+ charts with 4-texel padding need at least "
                                          r"\d+ texels.*many tunnels or fragments"):
        ruv.unwrap(mesh, ruv.UVSettings(texture_size=256, padding=4, max_texture_size=256))
    with pytest.raises(ValueError, match="max_texture_size"):
        ruv.UVSettings(texture_size=512, max_texture_size=256)


def test_atlases_are_destroyed_late_and_boundedly(monkeypatch):
    """xatlas can hang when an atlas is destroyed right after generate() (a lost wakeup in its
    ~TaskScheduler: recon.uv._RETIRE_AGE_S). pack_atlas keeps each atlas it made, so none is
    destroyed when the function returns; a kept atlas goes once it is _RETIRE_AGE_S old, or once
    _RETIRED_ATLASES newer ones exist (the memory held stays bounded). The clock is set by hand."""
    clock = [1000.0]
    monkeypatch.setattr(ruv.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(ruv, "_retired", type(ruv._retired)())
    m = icosphere(2)
    n = ruv.pack_atlas(m.v_pos, m.t_pos_idx, 64, 1, fill=0.5)[2]["attempts"]  # one atlas per attempt
    first = [a for _, a in ruv._retired]
    assert len(first) == n
    clock[0] += 0.4 * ruv._RETIRE_AGE_S
    n2 = ruv.pack_atlas(m.v_pos, m.t_pos_idx, 64, 1, fill=0.5)[2]["attempts"]
    kept = [a for _, a in ruv._retired]
    assert len(kept) == n + n2 and all(a is b for a, b in zip(first, kept[:n], strict=True))  # young: kept
    clock[0] += 0.7 * ruv._RETIRE_AGE_S  # the first call's now 1.1 ages old, the second's 0.7
    n3 = ruv.pack_atlas(m.v_pos, m.t_pos_idx, 64, 1, fill=0.5)[2]["attempts"]
    kept = [a for _, a in ruv._retired]
    assert len(kept) == n2 + n3 and not any(a is b for a in kept for b in first)
    for _ in range(ruv._RETIRED_ATLASES + 3):  # a tight loop: the count bounds them
        ruv.pack_atlas(m.v_pos, m.t_pos_idx, 64, 1, fill=0.5)
    assert len(ruv._retired) == ruv._RETIRED_ATLASES
