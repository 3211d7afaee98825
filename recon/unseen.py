"""The visual hull's part that no photo saw, below everything the photos saw: cut flat.

Photos taken from above an object that stands on something (a plain desk whose height nothing
gives, a floor, a shelf) leave the visual hull open downwards: a point under the object
projects inside its silhouette in every view, so the hull goes on below the object as a keel,
as deep as the cones from the views' highest elevations allow (on a box on a plain desk seen
from 20-60 degrees: 20 % of the final surface, all of it under the desk).

No photo can see that keel. A ray from a camera that reaches a point of the hull inside the
view's mask meets the object first (the pixel is the object's), and the object lies inside the
hull; so when every camera is above the support, every ray meets the hull above the support
before it could reach a point below it. The lowest point the photos see of the hull is
therefore at the support or above it, and what lies below it is unobserved: the initial mesh
is cut there, along the cameras' up, and closed flat. Where the cameras see the object from
below too (all around it in the void), the lowest seen point is the hull's lowest and nothing
is cut. An object whose lowest part is hidden (a ball resting on a point) gets a flat base where
its unseen cap was: no photo says otherwise.

:func:`seen_heights` casts rays through the masks' pixels at the hull with open3d (rays that
meet it edge-on, along a view's own silhouette cone, do not count); :func:`unseen_base` gives the cut.
Used by :func:`recon.init_mesh.visual_hull_mesh` when no support plane was found; with one the
hull is cut at the plane instead.
"""

from __future__ import annotations

import numpy as np

from recon.io.cameras import CameraSet
from recon.io.mesh import Mesh
from recon.support import SupportPlane


def seen_heights(mesh: Mesh, cams: CameraSet, masks: dict[str, np.ndarray], up: np.ndarray,
                 min_cos: float = 0.2, rays_per_view: int = 20000, seed: int = 0) -> dict[str, np.ndarray]:
    """Per view, the heights along ``up`` of the points of ``mesh`` it sees first through the pixels
    of its mask (at most ``rays_per_view`` of them, drawn with a fixed seed), where the ray meets the surface at a cosine of at least ``min_cos``: the hull's faces
    that a view's own silhouette cone made are seen edge-on by that view, and a ray through the
    mask's rim runs along them. Views without a mask are left out."""
    import open3d as o3d

    from recon.masks.geometry import pixel_rays

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.v_pos, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(mesh.t_pos_idx, dtype=np.uint32)))
    rng = np.random.default_rng(seed)
    out = {}
    for cam in cams:
        mask = masks.get(cam.stem)
        if mask is None:
            continue
        i, j = np.nonzero(np.asarray(mask) > 0.5)
        if len(i) > rays_per_view:
            pick = rng.choice(len(i), rays_per_view, replace=False)
            i, j = i[pick], j[pick]
        d = pixel_rays(cam)[i, j]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        o = np.broadcast_to(cam.center, d.shape)
        rays = np.concatenate([o, d], 1).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        cos = np.abs(np.sum(ans["primitive_normals"].numpy() * d, axis=1))
        hit = np.isfinite(t) & (cos >= min_cos)
        out[cam.stem] = (o[hit] + t[hit, None] * d[hit]) @ up
    return out


def unseen_base(mesh: Mesh, cams: CameraSet, masks: dict[str, np.ndarray], step: float,
                quantile: float = 0.001, view_share: float = 0.2, margin_voxels: float = 1.0,
                min_depth_voxels: float = 4.0, min_hits: int = 200) -> tuple[SupportPlane | None, dict]:
    """Where to cut ``mesh`` (the hull, world units; ``step`` its voxel size): the plane normal
    to the cameras' up, ``margin_voxels`` below the height that ``view_share`` of the views see
    below (each view's lowest: the ``quantile`` of the heights it sees, :func:`seen_heights`);
    None when the hull reaches less than ``min_depth_voxels`` below it (everything was seen).

    Not the lowest point any view sees: a view whose mask takes a strip of table at the object's
    foot (a plain desk's shadow band) sees down into the keel through it (a box on a plain desk:
    one of 30 views saw down to 0.11 of its size below the desk, the next lowest 0.004 below it). Also returns what was measured (heights above the hull's lowest point, voxels)."""
    up = cams.up()
    heights = seen_heights(mesh, cams, masks, up)
    lowest = np.array([np.quantile(h, quantile) for h in heights.values() if len(h) >= min_hits])
    low = float(np.min(mesh.v_pos @ up))
    info = {"up": np.round(up, 6).tolist(), "views": int(len(lowest)), "cut": False}
    if len(lowest) < 3:  # too few views met the hull to say what was seen
        return None, info
    seen = float(np.quantile(lowest, view_share))
    cut = seen - margin_voxels * step
    info.update(seen_low_voxels=(seen - low) / step, depth_voxels=(cut - low) / step)
    if cut - low < min_depth_voxels * step:
        return None, info
    info["cut"] = True
    return SupportPlane.through(cut * up, up), info
