"""One pipeline run scored against its synthetic capture's truth: the initial and final meshes'
accuracy and seen completeness (fractions of the object's size), and how much of the surface is
far from the object.

A results folder of ``snakemake ... all`` on a capture made by ``python -m recon synth`` (its
``gt/`` holds the true mesh, cameras and, on a table, ``plane.json``). The run's meshes are in
its own frame (``poses/cameras.json``: SfM's, or the capture's cameras), aligned to the truth by
the cameras (:func:`recon.metrics.align_cameras`). The measure is
:func:`bench.tabletop_e2e.geometry`, the one of the family's table (docs/tabletop.md).

    .venv/bin/python bench/score_run.py CAPTURE RESULTS [MESH ...]

e.g. ``bench/score_run.py /tmp/var/captures/vase-stand /tmp/var/results/vase-stand``; extra
meshes (PLY or OBJ in the run's frame) are scored beside ``init_mesh/mesh.ply`` and
``optimize/mesh.obj``. One JSON line per mesh.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.mesh import MeshError, read_mesh  # noqa: E402
from recon.metrics import align_cameras  # noqa: E402
from recon.support import SupportPlane, load_plane  # noqa: E402


def score(capture: Path, results: Path, extra: list[Path] = (), samples: int = 20000) -> dict[str, dict]:
    import tabletop_e2e as e2e

    gt_dir = capture / "gt"
    if not (gt_dir / "mesh.obj").is_file() or not (gt_dir / "cameras.json").is_file():
        raise SystemExit(f"{gt_dir}: no mesh.obj and cameras.json (a capture made by `python -m recon synth`)")
    gt = read_mesh(gt_dir / "mesh.obj")
    true_cams = load_cameras(gt_dir / "cameras.json")
    # in the void: a plane under everything, so that nothing counts as below the table
    plane = (load_plane(gt_dir / "plane.json") if (gt_dir / "plane.json").is_file()
             else SupportPlane.through(gt.bbox()[0] - 0.5, np.array([0.0, 0.0, 1.0])))
    cams = load_cameras(results / "poses" / "cameras.json")
    sim = align_cameras(cams, true_cams)
    visible = e2e.visible_samples(gt, true_cams, samples, np.random.default_rng(0))
    out = {}
    for path in [results / "init_mesh" / "mesh.ply", results / "optimize" / "mesh.obj", *extra]:
        try:
            mesh = read_mesh(path)
        except (MeshError, OSError) as e:
            out[str(path)] = {"missing": str(e)}
            continue
        g = e2e.geometry(mesh, gt, visible, sim, np.random.default_rng(1), plane, n=samples)
        out[str(path)] = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in g.items()}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("capture", type=Path)
    p.add_argument("results", type=Path, help="the run's results/<capture> folder")
    p.add_argument("meshes", type=Path, nargs="*", help="more meshes in the run's frame")
    args = p.parse_args(argv)
    for path, g in score(args.capture, args.results, args.meshes).items():
        print(json.dumps({"mesh": path, **g}))  # noqa: T201 (the CLI's output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
