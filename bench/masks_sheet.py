"""A contact sheet of masks over their photos (PNG), to judge masks by eye where there is no truth.

Each tile is a linear view (``<images>/<stem>.exr``, sRGB-encoded) with its mask's outline in
green and the pixels outside the mask dimmed; ``--masks`` may be given twice to compare two sets
(the second outlined in magenta).

    .venv/bin/python bench/masks_sheet.py --images /tmp/skull/results/skull/poses/undistorted \\
        --masks /tmp/skull/views_masks --out docs/img/masks_skull.png [--columns 6] [--width 320]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon.io.images import read_exr, read_mask  # noqa: E402
from recon.masks.common import display_image  # noqa: E402


def tile(rgb_linear: np.ndarray, masks: list[np.ndarray], width: int, label: str) -> np.ndarray:
    """(h, width, 3) uint8 BGR: the view, dimmed outside the first mask, each mask's outline drawn."""
    import cv2

    img = display_image(rgb_linear)[:, :, ::-1].copy()
    h = int(round(img.shape[0] * width / img.shape[1]))
    small = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    colours = [(0, 255, 0), (255, 0, 255)]
    for k, m in enumerate(masks):
        ms = cv2.resize(m.astype(np.uint8), (width, h), interpolation=cv2.INTER_NEAREST)
        if k == 0:
            small = np.where(ms[..., None] > 0, small, (0.35 * small).astype(np.uint8))
        contours, _ = cv2.findContours(ms, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(small, contours, -1, colours[k % 2], 1)
    cv2.putText(small, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return small


def contact_sheet(images: Path, masks: list[Path], stems: list[str], columns: int, width: int) -> np.ndarray:
    tiles = [tile(read_exr(images / f"{s}.exr"), [read_mask(m / f"{s}.png") for m in masks], width, s)
             for s in stems]
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    return np.vstack([np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)])


def main(argv=None) -> int:
    import cv2

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--images", type=Path, required=True, help="folder of <stem>.exr linear views")
    p.add_argument("--masks", type=Path, action="append", required=True, help="folder of <stem>.png (1 or 2)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--stems", nargs="+", help="these views (default: every mask of the first folder)")
    p.add_argument("--every", type=int, default=1, help="every n-th view")
    p.add_argument("--columns", type=int, default=6)
    p.add_argument("--width", type=int, default=320, help="tile width in pixels")
    args = p.parse_args(argv)
    stems = args.stems or sorted(q.stem for q in args.masks[0].glob("*.png"))
    stems = stems[::args.every]
    sheet = contact_sheet(args.images, args.masks, stems, args.columns, args.width)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{args.out}: {len(stems)} views, {sheet.shape[1]}x{sheet.shape[0]}")  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
