# Helpers shared by every rule: capture discovery, settings, and input functions (get_*).
from pathlib import Path

import recon.config as rc
from recon.io.images import IMAGE_EXTENSIONS

RESULTS = config["results"]
CAPTURES_ROOT = config["captures"]
PRESET = config["preset"]
PRESETS_DIR = str(Path(workflow.basedir) / "config" / "presets")
CAPTURES = rc.discover_captures(CAPTURES_ROOT)
STAGES = list(rc.STAGES)
INCLUDED_STAGES = []  # filled by the Snakefile as it includes workflow/rules/<stage>.smk


wildcard_constraints:
    capture="[^/]+",


def capture_dir(capture):
    return Path(CAPTURES_ROOT) / capture


def get_images(wildcards):
    """The capture's input photos (every file in images/ with a known extension)."""
    folder = capture_dir(wildcards.capture) / "images"
    return sorted(str(p) for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)


def get_image_stems(wildcards):
    return [Path(p).stem for p in get_images(wildcards)]


def get_settings(stage):
    """A params function: the merged settings dict of ``stage`` for the capture."""

    def settings(wildcards):
        return rc.stage_settings(stage, PRESET, capture_dir(wildcards.capture), PRESETS_DIR)

    return settings


def has_cameras(capture):
    return (capture_dir(capture) / "cameras.json").is_file()


def has_init_mesh(capture):
    return (capture_dir(capture) / "init_mesh.ply").is_file()


def has_masks(capture):
    return (capture_dir(capture) / "masks").is_dir()


def has_gt(capture):
    return (capture_dir(capture) / "gt").is_dir()


def get_capture_dir(wildcards):
    return str(capture_dir(wildcards.capture))


def get_all_targets(wildcards):
    """The last output of every implemented stage, for every capture."""
    finals = {
        "report": "report/index.html",
        "export": "export/asset.glb",
        "optimize": "optimize/mesh.obj",
        "uv": "uv/mesh.obj",
        "init_mesh": "init_mesh/mesh.ply",
        "poses": "poses/cameras.json",
        "masks": "masks/masks.json",
        "linearize": "linear/linear.json",
    }
    targets = []
    for capture in CAPTURES:
        for stage, path in finals.items():
            if stage in INCLUDED_STAGES:
                targets.append(f"{RESULTS}/{capture}/{path}")
                break
    return targets
