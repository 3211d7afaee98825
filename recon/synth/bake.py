"""UV atlases (xatlas) and baking 3D material fields into texture maps (DESIGN section 2).

The texel in row i, column j of an H x W map holds the field at the surface point whose OBJ
uv is ((j + 0.5)/W, 1 - (i + 0.5)/H). Texels outside every chart are filled by dilation
(``pad`` rings of averages of their filled neighbours, so bilinear lookups at chart borders
stay on the surface's values), the rest with the mean value.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from recon.io.mesh import Mesh

log = logging.getLogger(__name__)


def unwrap(mesh: Mesh, resolution: int = 1024, padding: int = 3) -> Mesh:
    """The mesh with an xatlas UV atlas: positions and faces unchanged, ``v_tex``/``t_tex_idx`` new.

    Parameters
    ----------
    mesh : Mesh
        ``v_pos (V, 3)``, ``t_pos_idx (F, 3)``.
    resolution : int
        Texture size the atlas is packed for.
    padding : int
        Gap between charts, in texels at ``resolution``.
    """
    # xatlas is called here directly, not through recon.uv.pack_atlas: this layout (xatlas's own
    # normalized UVs stretched over the map) made the bundled captures/demo, which must regenerate
    # bit-identically (tests/synth/test_demo_capture.py); the ground truth needs no packing retries
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.v_pos.astype(np.float32), mesh.t_pos_idx.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    vmapping, indices, uvs = atlas[0]
    indices = np.asarray(indices, dtype=np.int64)
    t_pos_idx = np.asarray(vmapping, dtype=np.int64)[indices]
    if t_pos_idx.shape != mesh.t_pos_idx.shape:
        raise RuntimeError(f"xatlas changed the face count ({len(mesh.t_pos_idx)} -> {len(t_pos_idx)})")
    log.debug("xatlas: %d charts, atlas %dx%d", atlas.chart_count, atlas.width, atlas.height)
    return Mesh(mesh.v_pos.copy(), t_pos_idx, np.asarray(uvs, dtype=np.float64), indices)


def rasterize_uv(mesh: Mesh, height: int, width: int, chunk: int = 20000):
    """Which triangle covers each texel center, and where.

    Returns
    -------
    face : (H, W) int64
        Face index, -1 where no triangle covers the texel center.
    bary : (H, W, 3) float64
        Barycentric coordinates in that face (0 where ``face == -1``).
    """
    if not mesh.has_uv:
        raise ValueError("rasterize_uv needs a mesh with UVs (run unwrap first)")
    face = np.full((height, width), -1, dtype=np.int64)
    bary = np.zeros((height, width, 3))
    # triangle corners in continuous pixel coordinates (texel centers at integer + 0.5)
    uv = mesh.v_tex[mesh.t_tex_idx]  # (F, 3, 2)
    xy = np.stack([uv[..., 0] * width, (1.0 - uv[..., 1]) * height], axis=-1)
    for start in range(0, len(xy), chunk):
        tri = xy[start:start + chunk]
        fid = np.arange(start, start + len(tri))
        j0 = np.clip(np.floor(tri[..., 0].min(1) - 0.5).astype(np.int64), 0, width - 1)
        j1 = np.clip(np.ceil(tri[..., 0].max(1) - 0.5).astype(np.int64), 0, width - 1)
        i0 = np.clip(np.floor(tri[..., 1].min(1) - 0.5).astype(np.int64), 0, height - 1)
        i1 = np.clip(np.ceil(tri[..., 1].max(1) - 0.5).astype(np.int64), 0, height - 1)
        nw, nh = j1 - j0 + 1, i1 - i0 + 1
        count = nw * nh
        rep = np.repeat(np.arange(len(tri)), count)
        k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        jj = j0[rep] + k % nw[rep]
        ii = i0[rep] + k // nw[rep]
        px, py = jj + 0.5, ii + 0.5
        a, b, c = tri[rep, 0], tri[rep, 1], tri[rep, 2]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        ok = np.abs(det) > 1e-18
        det = np.where(ok, det, 1.0)
        l1 = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / det
        l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        l0 = 1.0 - l1 - l2
        eps = -1e-9
        inside = ok & (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
        face[ii[inside], jj[inside]] = fid[rep[inside]]
        bary[ii[inside], jj[inside]] = np.stack([l0, l1, l2], 1)[inside]
    return face, bary


def dilate(image: np.ndarray, filled: np.ndarray, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow the ``filled (H, W)`` region of ``image (H, W, C)`` by ``rings`` texels.

    Each new texel gets the mean of its filled 8-neighbours. Returns the new image and mask.
    """
    img = image.copy()
    mask = filled.copy()
    h, w = mask.shape
    for _ in range(int(rings)):
        pad_i = np.pad(img * mask[..., None], ((1, 1), (1, 1), (0, 0)))
        pad_m = np.pad(mask.astype(np.float64), 1)
        acc = np.zeros_like(img)
        cnt = np.zeros((h, w))
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == 0 and dj == 0:
                    continue
                acc += pad_i[1 + di:1 + di + h, 1 + dj:1 + dj + w]
                cnt += pad_m[1 + di:1 + di + h, 1 + dj:1 + dj + w]
        grow = (~mask) & (cnt > 0)
        if not grow.any():
            break
        img[grow] = acc[grow] / cnt[grow, None]
        mask = mask | grow
    return img, mask


def bake(mesh: Mesh, field: Callable[[np.ndarray], tuple[np.ndarray, ...]], size: int,
         pad: int = 4) -> tuple[list[np.ndarray], np.ndarray]:
    """Evaluate ``field(points (N, 3)) -> (values (N, C_k), ...)`` at every covered texel center.

    Parameters
    ----------
    mesh : Mesh
        With UVs.
    field : callable
        Returns one or more ``(N, C_k)`` arrays per call (e.g. ``MaterialFields.evaluate``).
    size : int
        The maps are ``size x size``.
    pad : int
        Dilation rings around the charts.

    Returns
    -------
    maps : list of (size, size, C_k) float32
    coverage : (size, size) bool
        Texel centers inside a chart.
    """
    face, bary = rasterize_uv(mesh, size, size)
    covered = face >= 0
    f = face[covered]
    p = np.einsum("ni,nij->nj", bary[covered], mesh.v_pos[mesh.t_pos_idx[f]])
    values = field(p)
    if isinstance(values, np.ndarray):
        values = (values,)
    maps = []
    for v in values:
        v = np.asarray(v, dtype=np.float64).reshape(len(p), -1)
        img = np.zeros((size, size, v.shape[1]))
        img[covered] = v
        img, mask = dilate(img, covered, pad)
        img[~mask] = v.mean(axis=0)
        maps.append(img.astype(np.float32))
    return maps, covered
