"""Benchmark: how far the renderer's camera alignment can bring SfM's cameras when the model is
exactly right (issue 17's diagnosis: is the refinement limited by the shape it is fitted with,
or by what the photos tell?).

Takes a synthetic capture (with ``gt/``) and the results folder of its SfM run through the
workflow (``bench/sfm_cameras.py``'s ``results/sfm``). The true mesh and maps are mapped into
SfM's frame (the similarity of the camera centres; the light intensity scaled by 1/s^2) and
SfM's training cameras are aligned to that fixed, true model with
:func:`recon.optimize.cameras.align_views`, the held-out views' alignment (per-view pose
corrections, the camera prior, rates decaying to 1/10, exposure gains of their own), under the
imaging terms the run's loop chose. Printed: the camera errors against the truth before and
after (rotation, centre / object size, reprojection of true surface points in the photos'
pixels), per image size and step count, with SfM's focal length or the true one
(``--true-focal``: the poses alone, as the alignment does not refine intrinsics).

    .venv/bin/python bench/camera_observability.py /tmp/sfm_cameras/capture \
        /tmp/sfm_cameras/results/sfm --sizes 256 640 --steps 40 200 --true-focal

``--tracks W ...``: SfM's tracks (``poses/sparse``) reprojected through the aligned cameras as
a second term of weight W (:mod:`recon.optimize.tracks`), with a line comparing how well the
tracks fit SfM's cameras and the true ones.

On the idealised captures the same alignment removes ~85 % of a perturbation
(docs/camera_refine.md); what it removes here is what the phone's photos allow.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from camera_refine import camera_errors  # noqa: E402 (bench helper beside this file)

from recon import sections  # noqa: E402
from recon.config import load_preset  # noqa: E402
from recon.io.cameras import Camera, CameraSet, load_cameras  # noqa: E402
from recon.io.images import read_exr  # noqa: E402
from recon.io.mesh import Mesh, read_mesh  # noqa: E402
from recon.metrics import align_cameras  # noqa: E402
from recon.optimize import objective, settings_from_dict  # noqa: E402
from recon.optimize.camera_refine import CameraRefinement, scene_extent  # noqa: E402
from recon.optimize.loop_imaging import LoopImaging  # noqa: E402
from recon.optimize.cameras import align_views  # noqa: E402
from recon.optimize.tracks import SfmTracks, TrackTerm  # noqa: E402
from recon.poses.frame import rotate_cameras  # noqa: E402
from recon.optimize.views import Views  # noqa: E402

MAP_CHANNELS = {"diffuse": 3, "specular": 1, "roughness": 1}


def true_model_in_sfm_frame(cap: Path, sfm: CameraSet) -> tuple[Mesh, dict, float]:
    """The true mesh mapped into SfM's frame, its maps (tensors) and the similarity's scale."""
    gt_cams = load_cameras(cap / "gt" / "cameras.json")
    sim = align_cameras(sfm, gt_cams)  # SfM frame -> true frame
    g = read_mesh(cap / "gt" / "mesh.obj")
    v = ((g.v_pos - sim.translation) @ sim.rotation) / sim.scale
    maps = {k: torch.tensor(np.ascontiguousarray(read_exr(cap / "gt" / f"{k}.exr")[..., :c]))
            for k, c in MAP_CHANNELS.items()}
    return Mesh(v, g.t_pos_idx, g.v_tex, g.t_tex_idx), maps, float(sim.scale)


def tracks_under_the_truth(res: Path, sfm: CameraSet, frames: list[Camera], gt: CameraSet) -> str:
    """SfM's tracks with their points re-triangulated (Gauss-Newton, Huber) under SfM's
    training cameras and under the true ones mapped into SfM's frame (same intrinsics): when the
    truth fits them no better, the tracks cannot tell the two apart (or prefer SfM's)."""
    sim = align_cameras(CameraSet(tuple(frames), 1.0), gt)  # SfM frame -> true frame
    t = gt.by_stem()
    moved = rotate_cameras(CameraSet(tuple(t[c.stem] for c in frames), 1.0), sim.inverse()).frames
    truth = [Camera(c.image, c.width, c.height, c.K, m.world_to_camera) for c, m in zip(frames, moved, strict=True)]
    tr = SfmTracks.load(res / "poses" / "sparse", sfm, [c.stem for c in frames])
    ss = []
    for cams in (frames, truth):
        term = TrackTerm(tr)
        ref = CameraRefinement(cams, gauge=False)
        term.retriangulate(ref, cams, iterations=5)
        ss.append(float((term.residuals(ref, cams).detach() ** 2).sum()))
    # chi^2 of the truth against SfM's optimum in units of the keypoints' own noise (2 coordinates
    # per observation); a least-squares estimate sits ~(its free parameters) below the truth
    sigma2 = ss[0] / (2 * tr.n_observations)
    dof = 6 * len(frames) - 7
    return (f"tracks ({tr.n_observations} observations), points re-triangulated: rms {np.sqrt(ss[0] / tr.n_observations):.4f} px "
            f"through SfM's cameras, {np.sqrt(ss[1] / tr.n_observations):.4f} px through the true ones; "
            f"chi^2 of the truth {(ss[1] - ss[0]) / sigma2:.0f} against {dof} pose parameters")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path, help="synthetic capture folder (with gt/)")
    p.add_argument("results", type=Path, help="the capture's results folder of an SfM run (poses/, optimize/)")
    p.add_argument("--preset", default="balanced", help="renderer and alignment settings (spp, prior, rates)")
    p.add_argument("--sizes", type=int, nargs="+", default=[256])
    p.add_argument("--steps", type=int, nargs="+", default=[40, 200])
    p.add_argument("--true-focal", action="store_true", help="start from SfM's poses with the true intrinsics")
    p.add_argument("--tracks", type=float, nargs="+", default=[0.0],
                   help="weights of SfM's tracks reprojected through the aligned cameras (0: the renderer alone)")
    p.add_argument("--ideal", action="store_true", help="render the ideal formation, not the run's loop imaging")
    args = p.parse_args(argv)

    cap, res = args.capture, args.results
    summary_json = res / "optimize" / "summary.json"  # without an optimize run: every view, ideal formation
    held = set(json.loads(summary_json.read_text())["holdout"]["held_out"]) if summary_json.is_file() else set()
    sfm = load_cameras(res / "poses" / "cameras.json")
    true_k = {c.stem: c.K for c in load_cameras(cap / "gt" / "cameras.json").frames}
    frames = [Camera(c.image, c.width, c.height, true_k[c.stem] if args.true_focal else c.K, c.world_to_camera)
              for c in sfm.frames if c.stem not in held]
    mesh, maps, scale = true_model_in_sfm_frame(cap, sfm)
    gt = load_cameras(cap / "gt" / "cameras.json")
    g = read_mesh(cap / "gt" / "mesh.obj")
    lo, hi = g.bbox()
    size_obj = float(np.max(hi - lo))
    pts = g.v_pos[np.random.default_rng(0).choice(len(g.v_pos), min(2000, len(g.v_pos)), replace=False)]
    light = json.loads((cap / "gt" / "imaging.json").read_text())["light_intensity"] / scale ** 2
    imaging = LoopImaging(0.01, 0.25)
    ckpt = res / "optimize" / "checkpoints" / "last.pt"
    if ckpt.is_file() and not args.ideal:
        ck = torch.load(ckpt, map_location="cpu", weights_only=False)
        if ck.get("imaging") is not None:
            imaging.load(ck["imaging"])
    chosen = imaging.report()["chosen"]

    def fmt(e):
        return (f"rotation {e['rotation_deg']:.3f} deg (max {e['rotation_deg_max']:.3f}), centre "
                f"{100 * e['center']:.2f} % of the object, reprojection {e['reprojection_px']:.3f} px")

    print(f"{len(frames)} training views; imaging terms of the run's loop: {', '.join(chosen) or 'none'}; "  # noqa: T201
          f"focal: {'true' if args.true_focal else 'SfM'}")
    print(f"before: {fmt(camera_errors(frames, gt, size_obj, pts))}")  # noqa: T201
    if any(w > 0 for w in args.tracks):
        print(tracks_under_the_truth(res, sfm, frames, gt))  # noqa: T201
    base = dict(load_preset(args.preset).get("optimize") or {})
    for size in args.sizes:
        views_dir = res / "poses" / "undistorted"
        v = Views([views_dir / f"{c.stem}.exr" for c in frames], [views_dir / "masks" / f"{c.stem}.png" for c in frames],
                  None, CameraSet(tuple(frames), sfm.light_intensity), size)
        vs = v.at(size)
        for steps, wt in itertools.product(args.steps, args.tracks):
            s = sections.replace(settings_from_dict(base, "bench"), align_iterations=int(steps))
            t0 = time.perf_counter()
            tr = None
            if wt > 0:
                tr = (TrackTerm(SfmTracks.load(res / "poses" / "sparse", sfm, [c.stem for c in frames])), frames)
            r = align_views(mesh, maps, vs, list(vs.cameras), s, light, v.median_foreground,
                            {**objective.weights(s), "tracks": wt}, imaging, scene_extent(frames), tracks=tr)
            after = [Camera(c.image, c.width, c.height, c.K, a.world_to_camera)
                     for c, a in zip(frames, r["viewset"].cameras, strict=True)]
            extra = ""
            if tr is not None:
                extra = (f"; tracks {tr[0].tracks.reprojection(frames).mean():.3f} -> "
                         f"{tr[0].tracks.reprojection(after).mean():.3f} px (points as SfM's)")
            print(f"{size} px, {steps} steps, tracks {wt:g} ({time.perf_counter() - t0:.0f} s): "  # noqa: T201
                  f"{fmt(camera_errors(after, gt, size_obj, pts))}{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
