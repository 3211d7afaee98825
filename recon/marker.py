"""Metric scale from a printed marker mat (a ChArUco board) under the object (issue 15 item 4).

Photos alone fix a reconstruction only up to scale. A ChArUco board of known square size in
the photos gives it back: OpenCV's ``cv2.aruco.CharucoDetector`` finds the board's inner
corners (each with its id) in every view, each corner seen in two or more views is
triangulated with the known cameras (linear least squares over all its views), and the
distances between corners that are neighbours on the board (one square apart along a row or a
column) are, in the cameras' units, one square. The median over them gives::

    metres per unit = square size in metres / median neighbour distance in units

Corners whose reprojection error exceeds ``max_error_px`` in any view are dropped. The
board's layout (squares, dictionary, marker size) is :class:`MarkerBoard`; the default is the
board the synthetic captures print (:data:`recon.synth.tabletop.MARKER_BOARD`), OpenCV's
5 x 7 ChArUco with DICT_4X4_50 markers of 0.75 squares. Print such a board
(``cv2.aruco.CharucoBoard.generateImage``), measure one square, and give its side in metres.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.cameras import CameraSet, load_cameras
from recon.io.images import ImageError, read_exr

log = logging.getLogger(__name__)


class MarkerError(ValueError):
    """A marker mat that cannot give the scale; the message says why and what to try."""


@dataclass(frozen=True)
class MarkerBoard:
    """A ChArUco board: ``squares`` (x, y), the ArUco ``dictionary`` name (``cv2.aruco``), the
    marker side as a fraction of the square, and the printed square's side in metres."""

    square_m: float
    squares: tuple[int, int] = (5, 7)
    dictionary: str = "DICT_4X4_50"
    marker_fraction: float = 0.75

    def __post_init__(self):
        if not (np.isfinite(self.square_m) and self.square_m > 0):
            raise ValueError(f"the mat's square size must be a length in metres > 0, got {self.square_m}")
        if len(self.squares) != 2 or min(self.squares) < 2:
            raise ValueError(f"squares must be two counts >= 2, got {self.squares}")
        if not 0 < self.marker_fraction < 1:
            raise ValueError(f"marker_fraction must be in (0, 1), got {self.marker_fraction}")

    def detector(self):
        import cv2

        name = self.dictionary
        if not hasattr(cv2.aruco, name):
            raise ValueError(f"unknown ArUco dictionary {name!r} (e.g. DICT_4X4_50, DICT_5X5_100)")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        board = cv2.aruco.CharucoBoard(tuple(int(s) for s in self.squares), 1.0, self.marker_fraction, d)
        return cv2.aruco.CharucoDetector(board)

    def neighbours(self) -> list[tuple[int, int]]:
        """Pairs of inner-corner ids one square apart (ids run row by row, ``squares[0] - 1`` a row)."""
        nx, ny = self.squares[0] - 1, self.squares[1] - 1
        pairs = []
        for r in range(ny):
            for c in range(nx):
                i = r * nx + c
                if c + 1 < nx:
                    pairs.append((i, i + 1))
                if r + 1 < ny:
                    pairs.append((i, i + nx))
        return pairs


def _gray8(rgb_linear: np.ndarray) -> np.ndarray:
    """8-bit grey for the detector: the view's luminance scaled so its 99th percentile is white,
    sRGB-encoded."""
    from recon.io.images import linear_to_srgb

    y = np.nan_to_num(np.maximum(rgb_linear[:, :, :3], 0.0)).mean(-1)
    top = float(np.percentile(y, 99)) or 1.0
    return (np.clip(linear_to_srgb(np.clip(y / top, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)


def detect_corners(images: dict[str, np.ndarray], board: MarkerBoard) -> dict[str, dict[int, np.ndarray]]:
    """Per view stem: inner-corner id -> (2,) pixel position (DESIGN pixel coordinates: the
    top-left pixel spans [0, 1]^2)."""
    det = board.detector()
    out = {}
    for stem, img in images.items():
        corners, ids, _, _ = det.detectBoard(_gray8(img))
        if ids is None or len(ids) == 0:
            continue
        out[stem] = {int(i): c.reshape(2).astype(np.float64) + 0.5 for i, c in zip(ids.ravel(), corners, strict=True)}
    return out


def _triangulate(obs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Linear (DLT) triangulation from (P (3, 4), xy (2,)) pairs."""
    A = []
    for P, (x, y) in obs:
        A.append(x * P[2] - P[0])
        A.append(y * P[2] - P[1])
    _, _, vt = np.linalg.svd(np.asarray(A))
    X = vt[-1]
    return X[:3] / X[3]


def marker_scale(images: dict[str, np.ndarray], cams: CameraSet, board: MarkerBoard,
                 max_error_px: float = 2.0, min_pairs: int = 4) -> tuple[float, dict]:
    """Metres per cameras.json unit from the board in ``images`` (stem -> linear RGB, pinhole
    views of ``cams``). Raises :class:`MarkerError` when too few corners are found."""
    by_stem = cams.by_stem()
    found = detect_corners({s: im for s, im in images.items() if s in by_stem}, board)
    P = {s: by_stem[s].K @ by_stem[s].world_to_camera[:3, :] for s in found}
    seen: dict[int, list] = {}
    for s, corners in found.items():
        for i, xy in corners.items():
            seen.setdefault(i, []).append((s, xy))
    points, errors = {}, []
    for i, obs in seen.items():
        if len(obs) < 2:
            continue
        X = _triangulate([(P[s], xy) for s, xy in obs])
        err = []
        for s, xy in obs:
            h = P[s] @ np.append(X, 1.0)
            err.append(np.inf if h[2] <= 0 else float(np.linalg.norm(h[:2] / h[2] - xy)))
        if max(err) <= max_error_px:
            points[i] = X
            errors.append(float(np.mean(err)))
    d = [np.linalg.norm(points[a] - points[b]) for a, b in board.neighbours() if a in points and b in points]
    info = {"views_with_corners": len(found), "views": len(images), "corners_triangulated": len(points),
            "neighbour_pairs": len(d), "square_m": board.square_m}
    if len(d) < min_pairs:
        raise MarkerError(f"the marker mat gave {len(d)} pairs of neighbouring corners (need >= {min_pairs}; "
                          f"corners found in {len(found)} of {len(images)} views): keep the whole mat flat and in "
                          "focus in the photos, or give export.object_height_m instead")
    unit_square = float(np.median(d))
    spread = float(np.percentile(d, 90) / np.percentile(d, 10) - 1) if len(d) >= 3 else 0.0
    mpu = board.square_m / unit_square
    info.update({"square_units": unit_square, "square_spread": spread, "meters_per_unit": mpu,
                 "reprojection_px": float(np.mean(errors)) if errors else None})
    log.info("marker mat: %d corners in %d views, square %.5g units -> %.5g m per unit", len(points), len(found),
             unit_square, mpu)
    return mpu, info


def marker_scale_from_dirs(views_dir: str | os.PathLike, cameras_json: str | os.PathLike,
                           board: MarkerBoard) -> tuple[float, dict]:
    """:func:`marker_scale` on the views ``views_dir/<stem>.exr`` of ``cameras_json``."""
    cams = load_cameras(cameras_json)
    images = {}
    for c in cams:
        p = Path(views_dir) / f"{c.stem}.exr"
        try:
            images[c.stem] = read_exr(p)
        except ImageError as e:
            raise MarkerError(f"{e}; rerun the stage that writes {views_dir}") from e
    return marker_scale(images, cams, board)
