"""A picture of the object's foot: the true mesh beside the final meshes of optimize variants.

For each scene of a ``bench/tabletop_e2e.py --family ... --variant ...`` output folder, the true
mesh and every variant's final mesh (``<out>/variants/<variant>/<scene>/mesh.obj``, moved into the
true frame by the cameras' similarity, as the bench measures it) are rendered grey under the
collocated flash from a camera 8 degrees above the table, at the azimuth and distance of the
capture's lowest true camera, aimed at a third of the object's height (the foot, where the
skirt grows), and the tiles are set side by side, one row per scene, with the final accuracy in
each tile.

    .venv/bin/python bench/foot_sheet.py --out /tmp/e2e --scenes wood-blob room-smooth dark-bowl \\
        --variants default background --image docs/img/foot_background.jpg
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from recon.io.cameras import Camera, intrinsics, load_cameras, look_at  # noqa: E402
from recon.io.images import linear_to_srgb  # noqa: E402
from recon.io.mesh import Mesh, read_obj  # noqa: E402
from recon.metrics import align_cameras  # noqa: E402

sys.path.insert(0, str(REPO / "bench"))
from tabletop_e2e import render  # noqa: E402


def grey(mesh: Mesh, cam, light: float) -> np.ndarray:
    """(h, w, 3) linear render of ``mesh`` with albedo 0.5, no specular lobe
    (bench/tabletop_e2e.py's renderer, uniform maps: the UVs do not matter)."""
    f = np.asarray(mesh.t_pos_idx)
    maps = {"diffuse": np.full((4, 4, 3), 0.5, np.float32), "specular": np.zeros((4, 4, 1), np.float32),
            "roughness": np.full((4, 4, 1), 0.5, np.float32)}
    return render(Mesh(mesh.v_pos, f, np.zeros((1, 2)), np.zeros_like(f)), maps, [cam], light, spp=16)[0]


def foot_camera(cams, gt: Mesh, up: np.ndarray, width: int = 480, height: int = 300) -> Camera:
    """A camera ``ELEVATION_DEG`` above the table at the lowest true camera's azimuth and distance,
    aimed at a third of the object's height above its lowest point."""
    low = min(cams.frames, key=lambda c: abs(float(c.world_to_camera[2, :3] @ up)))
    h = gt.v_pos @ up
    target = gt.v_pos.mean(0) + (h.min() + (h.max() - h.min()) / 3 - float(gt.v_pos.mean(0) @ up)) * up
    d = low.center - target
    horiz = d - (d @ up) * up
    dist = float(np.linalg.norm(d))
    e = np.radians(ELEVATION_DEG)
    eye = target + dist * (np.cos(e) * horiz / np.linalg.norm(horiz) + np.sin(e) * up)
    return Camera("images/foot.exr", width, height, intrinsics(width, height, 30.0), look_at(eye, target, up))


ELEVATION_DEG = 8.0


def main(argv=None) -> int:
    import cv2

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="bench/tabletop_e2e.py's --out folder")
    p.add_argument("--scenes", nargs="+", required=True)
    p.add_argument("--variants", nargs="+", required=True)
    p.add_argument("--image", type=Path, required=True)
    p.add_argument("--width", type=int, default=320)
    args = p.parse_args(argv)
    measured = json.loads((args.out / "tabletop_e2e_variants.json").read_text())["results"]
    rows = []
    for scene in args.scenes:
        cap, res = args.out / "captures" / scene, args.out / "results" / scene
        true = load_cameras(cap / "gt" / "cameras.json")
        plane = json.loads((cap / "gt" / "plane.json").read_text()) if (cap / "gt" / "plane.json").is_file() else None
        up = np.asarray(plane["normal"], float) if plane else np.array([0.0, 0.0, 1.0])
        sim = align_cameras(load_cameras(res / "poses" / "cameras.json"), true)
        gt = read_obj(cap / "gt" / "mesh.obj")
        cam = foot_camera(true, gt, up)
        light = 2.0 * float(np.linalg.norm(cam.center - gt.v_pos.mean(0))) ** 2  # mid-grey at the object
        tiles = [(gt, "truth")]
        for v in args.variants:
            m = read_obj(args.out / "variants" / v / scene / "mesh.obj")
            acc = measured.get(scene, {}).get(v, {}).get("accuracy")
            tiles.append((Mesh(sim.apply(m.v_pos), m.t_pos_idx), f"{v}" + (f" {acc:.4f}" if acc else "")))
        row = []
        for mesh, label in tiles:
            img = linear_to_srgb(np.clip(grey(mesh, cam, light), 0, 1))
            img = (255 * np.clip(img, 0, 1)).astype(np.uint8)[:, :, ::-1]
            h = int(round(img.shape[0] * args.width / img.shape[1]))
            img = np.ascontiguousarray(cv2.resize(img, (args.width, h), interpolation=cv2.INTER_AREA))
            cv2.putText(img, f"{scene}: {label}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1,
                        cv2.LINE_AA)
            row.append(img)
        rows.append(np.concatenate(row, axis=1))
    args.image.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.image), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 90])
    print(args.image)  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
