"""The tabletop masks' hull splats (:meth:`recon.masks.vote.Hull.project` and ``Hull.depth``)
against their former full-frame form, in the same process: seconds per view (project and depth) and the ratio, for
a table-sized slab (what a hull that took the table looks like) and an object-sized ball, seen
from three cameras at 640 and 1600 px. The outputs are compared too (they must be identical).

    .venv/bin/python bench/hull_splats.py
"""

from __future__ import annotations

import time

import numpy as np

from recon.io.cameras import Camera, intrinsics, look_at
from recon.masks.vote import Hull


def full_frame(hull: Hull, cam: Camera, which: str) -> np.ndarray:
    """The peer: ``which`` ("project" or "depth") as recon.masks.vote had it before session 29,
    each on its own (projecting the voxels), one pass per splat radius over the whole frame."""
    import cv2

    xy, z = cam.project(hull.surface)
    ij = np.floor(xy).astype(int)
    ok = (z > 1e-9) & (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
    ij, z = ij[ok], z[ok].astype(np.float32)
    radius = np.clip(np.ceil(0.5 * np.sqrt(3.0) * hull.step * 0.5 * (cam.K[0, 0] + cam.K[1, 1]) / z), 1, 64).astype(int)
    sil = np.zeros((cam.height, cam.width), np.uint8)
    depth = np.full((cam.height, cam.width), np.inf, np.float32)
    for r in np.unique(radius):
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r - 1, 2 * r - 1))
        layer, near = np.zeros_like(sil), np.full_like(depth, np.inf)
        sel = radius == r
        if which == "project":
            layer[ij[sel, 1], ij[sel, 0]] = 1
            sil |= cv2.dilate(layer, k)
        else:
            np.minimum.at(near, (ij[sel, 1], ij[sel, 0]), z[sel])
            depth = np.minimum(depth, cv2.erode(near, k, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf))
    return sil > 0 if which == "project" else depth


def hulls() -> dict[str, Hull]:
    step = 4.0 / 128
    g = np.mgrid[-64:64, -64:64, 0:12].reshape(3, -1).T * step + [0.0, 0.0, step / 2]
    surface = g[(g[:, 2] > 11 * step) | (np.abs(g[:, 0]) > 63 * step) | (np.abs(g[:, 1]) > 63 * step)]
    step2 = 1.2 / 128
    g2 = np.mgrid[-64:64, -64:64, 0:128].reshape(3, -1).T * step2 + [0.0, 0.0, step2 / 2]
    pts = g2[np.linalg.norm(g2 - [0, 0, 0.6], axis=1) < 0.6]
    shell = pts[np.abs(np.linalg.norm(pts - [0, 0, 0.6], axis=1) - 0.6 + step2) < step2]
    return {"slab 4 units": Hull(g, step, surface, surface), "ball 1.2 units": Hull(pts, step2, shell, shell)}


def main() -> None:
    hull_splats = hulls()
    full_frame(hull_splats["ball 1.2 units"], Camera("a.png", 64, 48, intrinsics(64, 48, 40.0),
                                                     look_at([0.0, -2.5, 1.2], [0.0, 0.0, 0.3])), "project")  # warm-up
    print("| hull | px | camera | full frame (s) | boxed (s) | ratio | identical |")  # noqa: T201
    print("|---|---|---|---|---|---|---|")  # noqa: T201
    for name, hull in hull_splats.items():
        for width in (640, 1600):
            for eye in ([0.0, -2.5, 1.2], [0.3, -1.2, 0.5], [4.0, 1.0, 3.0]):
                cam = Camera("a.png", width, width * 3 // 4, intrinsics(width, width * 3 // 4, 40.0),
                             look_at(eye, [0.0, 0.0, 0.3]))
                t0 = time.perf_counter()
                ref = full_frame(hull, cam, "project"), full_frame(hull, cam, "depth")
                t1 = time.perf_counter()
                new = hull.project(cam), hull.depth(cam)
                t2 = time.perf_counter()
                same = np.array_equal(ref[0], new[0]) and np.array_equal(ref[1], new[1])
                print(f"| {name} | {width} | {eye} | {t1 - t0:.3f} | {t2 - t1:.3f} | {(t1 - t0) / (t2 - t1):.1f} "  # noqa: T201
                      f"| {same} |", flush=True)


if __name__ == "__main__":
    main()
