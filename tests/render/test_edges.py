"""Edge topology and image-space silhouette segments."""

from __future__ import annotations

import numpy as np
from render_scenes import camera, uv_sphere
from scipy.spatial import ConvexHull

from recon.render.edges import edge_topology, silhouette_segments


def test_topology_of_a_closed_sphere():
    v, f, _, _ = uv_sphere(12, 6)
    topo = edge_topology(f)
    assert len(topo) == 3 * len(f) // 2
    assert np.all(topo.face_b >= 0) and not topo.always.any() and topo.consistent.all()
    assert np.all(topo.edges[:, 0] < topo.edges[:, 1])
    # each edge's two faces both contain it
    for e, fa, fb in zip(topo.edges[:20], topo.face_a[:20], topo.face_b[:20], strict=True):
        assert set(e) <= set(f[fa]) and set(e) <= set(f[fb]) and fa != fb


def test_topology_open_and_non_manifold_edges():
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    topo = edge_topology(quad)
    assert len(topo) == 5 and topo.always.sum() == 4
    assert np.array_equal(topo.edges[~topo.always][0], [0, 2])
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge (0, 1) has three faces
    topo = edge_topology(fan)
    k = np.flatnonzero((topo.edges == [0, 1]).all(axis=1))[0]
    assert topo.always[k]
    # degenerate faces keep their real edges and add none from repeated vertices
    topo = edge_topology(np.array([[0, 0, 1]]))
    assert len(topo) == 1 and np.array_equal(topo.edges[0], [0, 1])


def test_convex_silhouette_is_the_hull_of_the_projection():
    """For a convex mesh seen from outside, the silhouette edges project onto the boundary
    of the convex hull of the projected vertices."""
    v, f, _, _ = uv_sphere(20, 10, radius=0.8, center=(0.1, 0.2, -0.1))
    cam = camera((1.5, -3.0, 1.0), 128, 96)
    seg = silhouette_segments(v, f, edge_topology(f), [cam])
    xy, _ = cam.project(v)
    hull = ConvexHull(xy)
    assert np.isclose(seg.total_length[0], hull.area, rtol=1e-9)  # 2D hull "area" = perimeter
    assert np.isclose(seg.length.sum(), seg.total_length[0])
    assert np.all(seg.view == 0)


def test_flipped_face_does_not_change_the_silhouette():
    v, f, _, _ = uv_sphere(20, 10)
    cam = camera((1.0, -3.0, 0.5))
    ref = silhouette_segments(v, f, edge_topology(f), [cam])
    g = f.copy()
    g[7] = g[7, ::-1]  # one face wound the other way
    topo = edge_topology(g)
    assert (~topo.consistent).sum() == 3
    seg = silhouette_segments(v, g, topo, [cam])
    key = lambda s: sorted(zip(np.minimum(s.v0, s.v1), np.maximum(s.v0, s.v1), strict=True))  # noqa: E731
    assert key(seg) == key(ref)


def test_clipping_to_the_image_matches_dense_sampling():
    """Segments are clipped to [0, w] x [0, h]: the clipped length equals the length of the
    inside part of each projected edge found by dense sampling."""
    v, f, _, _ = uv_sphere(20, 10, radius=1.0)
    topo = edge_topology(f)
    cam = camera((0.0, -3.0, 0.0), 64, 48, fov_x=40.0, target=(1.0, 0.0, 0.5))  # half out
    seg = silhouette_segments(v, f, topo, [cam])
    assert len(seg) > 0
    assert seg.a.min() >= -1e-9 and seg.b.min() >= -1e-9
    assert seg.a[:, 0].max() <= 64 + 1e-9 and seg.b[:, 1].max() <= 48 + 1e-9
    xy, z = cam.project(v)
    assert np.all(z > 0)
    s = (np.arange(4000) + 0.5) / 4000
    inside_len = {}
    pairs = set(zip(seg.v0, seg.v1, strict=True))
    for a, b in pairs:
        p = xy[a][None, :] + s[:, None] * (xy[b] - xy[a])[None, :]
        ok = (p[:, 0] >= 0) & (p[:, 0] <= 64) & (p[:, 1] >= 0) & (p[:, 1] <= 48)
        inside_len[(a, b)] = ok.mean() * np.linalg.norm(xy[b] - xy[a])
    clipped = 0
    for a, b, length in zip(seg.v0, seg.v1, seg.length, strict=True):
        full = np.linalg.norm(xy[b] - xy[a])
        assert abs(length - inside_len[(a, b)]) < 2e-3 * full + 1e-9
        clipped += length < 0.99 * full
    assert clipped >= 2  # the silhouette leaves and re-enters the image


def test_near_plane_and_behind_camera():
    v, f, _, _ = uv_sphere(20, 10, radius=1.0)
    topo = edge_topology(f)
    # camera just outside the sphere looking along its surface: edges cross the camera plane
    cam = camera((0.0, -1.05, 0.0), target=(1.0, -1.05, 0.0))
    _, z = cam.project(v)
    assert (z < 0).any() and (z > 0).any()
    seg = silhouette_segments(v, f, topo, [cam])
    assert np.all(np.isfinite(seg.a)) and np.all(np.isfinite(seg.b)) and np.all(seg.length > 0)
    assert seg.a.min() >= -1e-9 and seg.a[:, 0].max() <= cam.width + 1e-9
    # everything behind the camera: nothing to sample
    cam = camera((0.0, -3.0, 0.0), target=(0.0, -6.0, 0.0))
    seg = silhouette_segments(v, f, topo, [cam, camera((0.0, -3.0, 0.0))])
    assert seg.total_length[0] == 0 and seg.total_length[1] > 0 and np.all(seg.view == 1)
