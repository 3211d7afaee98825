"""Helpers of tests/blender: exported assets opened and rendered in a real Blender
(tools/blender/recon_blender.py), shared by the fixtures (conftest.py) and measure.py.

Blender runs as the ``bpy`` wheel in its own environment, ``tools/blender/.venv`` (made by
``scripts/setup.sh``; override with ``RECON_BLENDER_PYTHON``). The assets:

- ``gt``: the ground truth of the bundled synthetic capture ``captures/demo/gt`` exported with
  the default settings (always; it calibrates the appearance thresholds);
- ``results``: the export of a pipeline run, when ``RECON_BLENDER_RESULTS`` names its
  ``results/<capture>`` folder (CI sets it to the demo's after ``run_demo.sh``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "export"))  # the independent readers of the formats

from export_readers import Asset  # noqa: E402

from recon.io.cameras import Camera, CameraSet  # noqa: E402

TOOL = REPO / "tools" / "blender" / "recon_blender.py"
BLENDER_PYTHON = Path(os.environ.get("RECON_BLENDER_PYTHON",
                                     REPO / "tools" / "blender" / ".venv" / "bin" / "python"))
DEMO_GT = REPO / "captures" / "demo" / "gt"

# glTF and USD stages are +Y up, Blender +Z up: (x, y, z) -> (x, -z, y).
Y_UP_TO_BLENDER = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])

RENDER_WIDTH = 96  # pixels; the cameras are scaled to it
RENDER_SPP = 64


@dataclass
class Case:
    """An exported asset and the cameras of its capture (cameras.json frame)."""

    name: str
    export: Path
    cameras: CameraSet


@dataclass
class BlenderResult:
    scene: dict
    loops: dict
    out: Path
    views: list  # the Cameras rendered, moved into the asset's +Y-up metre frame
    light_intensity: float
    asset: Asset  # the file as the independent reader sees it


def asset_views(cameras: CameraSet, T: np.ndarray, n: int = 3) -> tuple[list[Camera], float]:
    """``n`` cameras spread over the capture, scaled to RENDER_WIDTH and moved into the asset's
    frame (p_asset = T p, T = s R), and the light intensity that gives the same image there."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    R = T[:3, :3] / s
    frames = cameras.frames
    out = []
    for i in np.linspace(0, len(frames), n, endpoint=False).astype(int):
        c = frames[i].scaled(RENDER_WIDTH / frames[i].width)
        w2c = np.eye(4)
        w2c[:3, :3] = c.world_to_camera[:3, :3] @ R.T
        w2c[:3, 3] = s * c.world_to_camera[:3, 3]
        out.append(Camera(c.image, c.width, c.height, c.K, w2c))
    return out, cameras.light_intensity * s * s


def run_blender(asset_path: Path, out: Path, views: list[Camera] | None = None,
                light_intensity: float = 1.0, extra: tuple[str, ...] = ()) -> tuple[dict, dict]:
    if not BLENDER_PYTHON.is_file():
        pytest.fail(f"{BLENDER_PYTHON} not found: run `bash scripts/setup.sh`, which installs "
                    "Blender's bpy into tools/blender/.venv (or set RECON_BLENDER_PYTHON)")
    out.mkdir(parents=True, exist_ok=True)
    cmd = [str(BLENDER_PYTHON), str(TOOL), str(asset_path), str(out), *extra]
    if views:
        (out / "views.json").write_text(json.dumps({
            "views": [{"K": v.K.tolist(), "world_to_camera": v.world_to_camera.tolist(),
                       "width": v.width, "height": v.height} for v in views],
            "light_intensity": light_intensity, "spp": RENDER_SPP}))
        cmd += ["--views", str(out / "views.json")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    if proc.returncode != 0:
        pytest.fail(f"Blender failed on {asset_path} ({' '.join(cmd)}):\n{proc.stdout[-3000:]}\n"
                    f"{proc.stderr[-3000:]}")
    scene = json.loads((out / "scene.json").read_text())
    with np.load(out / "loops.npz") as z:
        loops = {k: z[k] for k in z.files}
    return scene, loops
