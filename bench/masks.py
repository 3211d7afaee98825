"""Masks on a family of captures that vary what makes masks hard: IoU against the true silhouettes.

The family (``SCENES``; ``python -m recon synth`` settings, :mod:`recon.synth`): objects whose
colours and brightness are close to the table's (``wood`` palette), plain glazes without texture,
glossy, dark, tall, low, concave and handled shapes, a wall and room lamps in a dim room, views
cut by the frame's edge, phone JPEGs (tone curve, vignetting, auto-exposure, a flash beside the
lens, ambient light) and DNGs, 512, 1008 and 1600 px wide, and an object on a display stand (no table).

For each scene:

1. makes the capture (only when missing; ``<out>/captures/<scene>``),
2. linearizes it (:func:`recon.linearize.linearize_capture`),
3. runs the masks the pipeline makes with known cameras (``gt/cameras.json``;
   :func:`recon.masks.run_view_masks`: the support plane from points triangulated in the views,
   the tabletop masks on it, or the flash-falloff masks made consistent across the views when
   there is no plane),
4. and the masks stage's own per-view masks (no cameras: :func:`recon.masks.run_masks`),

and prints one row per scene and method: mean / median / min IoU against ``gt/masks`` (the
object alone; for the stand scene the stand is left out, see docs/masks.md), the worst view and
seconds; for tabletop masks whether the flash's shadow was found beside the object
(:mod:`recon.masks.shadow`). ``--methods views_no_shadow`` adds the peer with that model off (the
same known cameras, in the same process). ``--only`` picks scenes, ``--make-only`` just renders.
Results in ``<out>/masks.json``.

    .venv/bin/python bench/masks.py --out /tmp/masks_bench [--only glaze-bell wood-blob] [--make-only]

``--sfm RESULTS CAPTURE``: the same masks on a capture's own poses results (SfM's cameras), e.g.
``--sfm /tmp/var/results/torus-table /tmp/var/captures/torus-table`` (docs/masks.md).

``--score RESULTS CAPTURE``: no run, the masks a results folder holds (the masks stage's
``masks/`` and the poses stage's ``poses/undistorted/masks/``) against ``<capture>/gt/masks``, e.g.
two results folders of the same capture made by two versions of the code (docs/masks.md).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon import sections
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.images import read_mask  # noqa: E402
from recon.synth.capture import SynthSettings, make_capture  # noqa: E402

log = logging.getLogger("bench.masks")

# a phone's imaging, every effect on (the "phone" preset's, with the flash 1.2 cm beside the lens of
# a 15-cm object: 0.15 object units)
PHONE = dict(format="jpg", exposure_variation=0.5, flash_offset=(0.15, 0.0, 0.0), ambient=0.05,
             exposure_jitter=0.25, wb_jitter=0.03, falloff=(-0.3, 0.0), tone_curve="phone")
TABLE = dict(scene="tabletop", fov=50.0, distance=5.0, n_views=40, width=512, height=384, spp=16,
             mesh_level=5, texture_size=1024, table_texture_size=1024, write_cameras=True,
             write_masks=False, write_gt_linear=False)

SCENES: dict[str, dict] = {
    # the capture: a glazed bell (cream, blue, orange; no texture, glossy bands) on the
    # wooden table, a wall and lamps in a dim room, phone JPEGs of 1008 x 756, some views cut
    "glaze-bell": {**TABLE, **PHONE, "object": "bell", "palette": "glaze", "texture_pattern": False,
                   "wall": 0.5, "lamps": 0.2, "closeups": 0.1, "n_views": 60, "width": 1008, "height": 756,
                   "table_texture_size": 2048, "seed": 3},
    # an object in the table's own colours and brightness (textured), DNG
    "wood-blob": {**TABLE, "object": "blob", "palette": "wood", "seed": 4},
    # tall, in the table's colours, no texture, phone JPEG
    "wood-vase": {**TABLE, **PHONE, "object": "vase", "palette": "wood", "texture_pattern": False, "seed": 5},
    # low and concave, dark glazes, DNG
    "dark-bowl": {**TABLE, "object": "bowl", "palette": "dark", "seed": 6},
    # glossy, plain glazes, a handle, phone JPEG, views cut by the frame
    "glossy-mug": {**TABLE, **PHONE, "object": "mug", "palette": "glaze", "texture_pattern": False,
                   "specular": 0.6, "roughness": 0.12, "closeups": 0.2, "seed": 7},
    # little texture in a dim room: two lamps, a wall, more ambient light; views cut by the frame
    "room-smooth": {**TABLE, "object": "smooth", "texture_pattern": False, "wall": 0.6, "lamps": 0.5,
                    "ambient": 0.1, "closeups": 0.25, "seed": 8},
    # larger photos of a textured object in the table's colours, phone JPEG
    "wood-bell-1008": {**TABLE, **PHONE, "object": "bell", "palette": "wood", "n_views": 48, "width": 1008,
                       "height": 756, "table_texture_size": 2048, "seed": 9},
    # the same kind of capture at a phone's full-width preview size (1600 px): the masks' scale-dependent
    # parts (the band near the table, the graph cut's neighbourhoods, the closing) at 3x the pixels
    "wood-bell-1600": {**TABLE, **PHONE, "object": "bell", "palette": "wood", "n_views": 40, "width": 1600,
                       "height": 1200, "table_texture_size": 2048, "seed": 11},
    # a handle through the whole object (genus 1) lying on a weakly textured table (its grain wider
    # than the sweep's windows at the working size: docs/masks.md "The sweep at two scales"),
    # gamma-2.2 JPEGs, the flash 1.2 cm beside the lens, exposure error, some close-ups
    "glaze-torus": {**TABLE, "object": "torus", "palette": "glaze", "texture_pattern": False, "format": "jpg",
                    "tone_curve": "gamma22", "flash_offset": (0.12, 0.0, 0.0), "exposure_jitter": 0.2,
                    "closeups": 0.1, "n_views": 36, "width": 640, "height": 480, "seed": 21},
    # a plain desk (a light laminate, no texture): SfM finds no plane in its points, and the lit desk
    # is brighter than the object near the camera (docs/masks.md "A plain table"); phone JPEG
    "plain-blob": {**TABLE, **PHONE, "object": "blob", "table": "plain", "seed": 12},
    # a glazed vase on the plain desk, filmic JPEGs: by SfM a few points on the desk give a plane,
    # the tabletop masks take the desk, and the plain table's model must be tried after them
    # (docs/masks.md "A plain table with a few points on it")
    "plain-vase": {**TABLE, **PHONE, "object": "vase", "palette": "glaze", "table": "plain", "tone_curve": "filmic",
                   "seed": 13},
    # the flash 0.2 of the object's size beside the lens and 0.1 below it (a phone's flash at a close
    # distance): a dark band on the table beside the vase in every view (recon.masks.shadow)
    "shadow-vase": {**TABLE, **PHONE, "object": "vase", "flash_offset": (0.2, 0.1, 0.0), "ambient": 0.02,
                    "seed": 14},
    # no table: the object on a display stand (a thin pole, a white base) in a dim room with a wall
    "stand-blob": {**TABLE, **PHONE, "scene": "stand", "object": "blob", "palette": "glaze",
                   "elevation_range": (5.0, 65.0), "wall": 0.4, "lamps": 0.15, "seed": 10},
}


def _cached_table_texture():
    """The table texture is a pure function of its arguments and takes minutes at 2048^2: one per
    run (a copy each call: the marker mat is printed into it in place)."""
    import recon.synth.capture as capture

    original = capture.table_texture
    memo = functools.lru_cache(maxsize=4)(original)
    capture.table_texture = lambda *a, **k: memo(*a, **k).copy()
    return original


def make(name: str, out: Path) -> Path:
    cap = out / "captures" / name
    if not (cap / "gt" / "cameras.json").is_file():
        t0 = time.perf_counter()
        make_capture(cap, sections.replace(SynthSettings(), **SCENES[name]), command=f"bench/masks.py ({name})")
        log.info("%s: made in %.0f s", name, time.perf_counter() - t0)
    return cap


def iou_per_view(masks_dir: Path, gt_dir: Path, stems: list[str]) -> dict[str, float]:
    out = {}
    for s in stems:
        m, g = read_mask(masks_dir / f"{s}.png"), read_mask(gt_dir / f"{s}.png")
        out[s] = float((m & g).sum() / max((m | g).sum(), 1))
    return out


def summary(ious: dict[str, float], seconds: float) -> dict:
    v = np.array(list(ious.values()))
    return {"iou_mean": float(v.mean()), "iou_median": float(np.median(v)), "iou_min": float(v.min()),
            "worst_view": min(ious, key=ious.get), "views": len(v), "seconds": seconds, "per_view": ious}


def run_scene(name: str, out: Path, methods: list[str]) -> dict:
    from recon.linearize import linearize_capture
    from recon.masks import run_masks, run_view_masks

    cap = make(name, out)
    work = out / "runs" / name
    cams_path = cap / "gt" / "cameras.json"
    stems = [c.stem for c in load_cameras(cams_path)]
    gt = cap / "gt" / "masks"
    linear = work / "linear"
    if not (linear / "linear.json").is_file():
        linearize_capture(cap, linear)
    res = {"settings": {k: v for k, v in SCENES[name].items() if k not in ("write_cameras", "write_masks",
                                                                            "write_gt_linear")}}
    if "views" in methods:
        t0 = time.perf_counter()
        info = info_views = run_view_masks(linear, cams_path, work / "masks_views")
        res["views"] = summary(iou_per_view(work / "masks_views", gt, stems), time.perf_counter() - t0)
        res["views"]["method"] = info["method"]
    if "views_no_shadow" in methods:  # the peer: the same without the flash's shadow (recon.masks.shadow)
        from recon.masks.shadow import ShadowSettings
        from recon.masks.tabletop import SegmentSettings

        t0 = time.perf_counter()
        info = run_view_masks(linear, cams_path, work / "masks_views_no_shadow",
                              settings=SegmentSettings(shadow=ShadowSettings(enabled=False)))
        res["views_no_shadow"] = summary(iou_per_view(work / "masks_views_no_shadow", gt, stems),
                                         time.perf_counter() - t0)
        res["views_no_shadow"]["method"] = info["method"]
    if "views" in methods and res["views"].get("method") == "tabletop":
        res["views"]["shadow"] = {k: v for k, v in (info_views.get("segment") or {}).get("shadow", {}).items()
                                  if k in ("found", "resultant", "agree", "views", "share_of_silhouette")}
    if "per_view" in methods:
        t0 = time.perf_counter()
        run_masks(linear, work / "masks_per_view")
        res["per_view"] = summary(iou_per_view(work / "masks_per_view", gt, stems), time.perf_counter() - t0)
        res["per_view"]["method"] = "flash_falloff"
    return res


def run_on_sfm(results: Path, capture: Path, out: Path) -> dict:
    """The masks the pipeline makes on a capture's poses results (SfM's cameras and points,
    ``<results>/poses``) against ``<capture>/gt/masks``: the undistorted views are compared with the
    true masks pixel for pixel, right only for photos without lens distortion (``recon.synth``'s)."""
    from recon.masks import run_view_masks

    poses = results / "poses"
    t0 = time.perf_counter()
    info = run_view_masks(poses / "undistorted", poses / "cameras.json", out, points=poses / "points.ply")
    stems = [c.stem for c in load_cameras(poses / "cameras.json")]
    res = summary(iou_per_view(out, capture / "gt" / "masks", stems), time.perf_counter() - t0)
    res["method"] = info["method"]
    return res


def score(results: Path, capture: Path) -> dict:
    """The masks already in ``results`` (``masks/``, then ``poses/undistorted/masks/``: the ones
    init_mesh reads) against ``<capture>/gt/masks``, for the views both hold."""
    out = {}
    for key, folder in (("masks stage", results / "masks"), ("poses", results / "poses" / "undistorted" / "masks")):
        stems = sorted(p.stem for p in folder.glob("*.png") if (capture / "gt" / "masks" / p.name).is_file())
        if stems:
            out[key] = {**summary(iou_per_view(folder, capture / "gt" / "masks", stems), 0.0), "method": "as saved"}
    return out


def print_table(results: dict) -> None:
    head = f"{'scene':<16} {'masks':<15} {'method':<14} {'mean':>6} {'median':>6} {'min':>6} {'worst':>6} {'s':>6} shadow"
    print(head)  # noqa: T201
    print("-" * len(head))  # noqa: T201
    for name, r in results.items():
        for key in ("views", "views_no_shadow", "per_view", "masks stage", "poses"):
            if key in r:
                m = r[key]
                sh = m.get("shadow") or {}
                shadow = "" if not sh else (f"found ({100 * sh.get('share_of_silhouette', 0):.1f}% of the silhouette)"
                                            if sh.get("found") else "none")
                print(f"{name:<16} {key:<15} {m['method']:<14} {m['iou_mean']:6.3f} {m['iou_median']:6.3f} "  # noqa: T201
                      f"{m['iou_min']:6.3f} {m['worst_view']:>6} {m['seconds']:6.0f} {shadow}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, default=Path("bench/out/masks"))
    p.add_argument("--only", nargs="+", choices=sorted(SCENES), help="these scenes (default: all)")
    p.add_argument("--methods", nargs="+", default=["views", "per_view"], choices=["views", "views_no_shadow", "per_view"])
    p.add_argument("--make-only", action="store_true", help="render the captures and stop")
    p.add_argument("--sfm", nargs=2, type=Path, metavar=("RESULTS", "CAPTURE"),
                   help="instead: the masks on RESULTS/poses (SfM's cameras) against CAPTURE/gt/masks")
    p.add_argument("--score", nargs=2, type=Path, metavar=("RESULTS", "CAPTURE"),
                   help="instead: the masks already in RESULTS (masks/, poses/undistorted/masks/) against CAPTURE/gt/masks")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.score:
        found = score(*args.score)
        if not found:
            print(f"no masks in {args.score[0]} with a true mask in {args.score[1]}/gt/masks")  # noqa: T201
            return 1
        print_table({args.score[1].name: found})
        return 0
    if args.sfm:
        name = args.sfm[1].name
        print_table({name: {"views": run_on_sfm(*args.sfm, args.out / "sfm" / name)}})
        return 0
    _cached_table_texture()
    names = args.only or list(SCENES)
    if args.make_only:
        for name in names:
            make(name, args.out)
        return 0
    results = {}
    t0 = time.perf_counter()
    for name in names:
        results[name] = run_scene(name, args.out, args.methods)
        print_table({name: results[name]})
    path = args.out / "masks.json"
    old = json.loads(path.read_text())["results"] if path.is_file() else {}
    path.write_text(json.dumps({"command": " ".join(sys.argv), "results": {**old, **results},
                                "seconds": time.perf_counter() - t0}, indent=1, default=float))
    print()  # noqa: T201
    print_table(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
