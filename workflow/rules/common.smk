# Helpers shared by every rule: capture discovery, settings, and input functions (get_*).
import sys
from pathlib import Path

import recon.config as rc
from recon.runlock import RunLockError, lock_results
from recon.io.images import IMAGE_EXTENSIONS
from recon.stages import FINAL
from recon.summary import write_run_summary

RESULTS = config["results"]
CAPTURES_ROOT = config["captures"]
PRESET = config["preset"]
PRESETS_DIR = str(Path(workflow.basedir) / "config" / "presets")


def stop(error):
    """End the run before anything starts with a user error's message alone (no traceback)."""
    sys.stderr.write(f"recon: error: {error}\n")
    sys.exit(1)


try:
    CAPTURES = rc.discover_captures(CAPTURES_ROOT)
    rc.check_results_location(RESULTS, CAPTURES_ROOT)
except rc.ConfigError as e:
    stop(e)


wildcard_constraints:
    capture="[^/]+",


def capture_dir(capture):
    return Path(CAPTURES_ROOT) / capture


def get_images(wildcards):
    """The capture's input photos (every file in images/ with a known extension; hidden files
    such as macOS ._* AppleDouble files are not photos: the check step notes them)."""
    folder = capture_dir(wildcards.capture) / "images"
    return sorted(
        str(p)
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")
    )


def get_image_stems(wildcards):
    return [Path(p).stem for p in get_images(wildcards)]


def _sorted_keys(value):
    """``value`` with every mapping's keys in sorted order (Snakemake compares params by repr)."""
    if isinstance(value, dict):
        return {key: _sorted_keys(value[key]) for key in sorted(value)}
    if isinstance(value, list):
        return [_sorted_keys(item) for item in value]
    return value


def get_settings(stage):
    """A params function: the effective settings of ``stage`` for the capture (no preset name,
    no source paths, keys sorted: only a change of the values reruns the stage; the job's script
    reads the same values with their sources through recon.config.job_settings).
    A capture.yaml that cannot be read gives {"error": message}: the DAG of the other captures
    still builds, and the capture's check step fails with the message."""

    def settings(wildcards):
        try:
            values = rc.effective_settings(
                stage, PRESET, capture_dir(wildcards.capture), PRESETS_DIR
            )
        except rc.ConfigError as e:
            return {"error": str(e)}
        return _sorted_keys(values)

    return settings


def get_preset(wildcards):
    """The preset the capture runs with (its capture.yaml's, else the config's). Only the report
    tracks it (it names the preset); other stages track the settings the preset gives them.
    A capture.yaml that cannot be read: the config's (the capture's check step fails).
    """
    try:
        return rc.capture_preset(capture_dir(wildcards.capture), PRESET)
    except rc.ConfigError:
        return PRESET


# ---- What a rule tracks of the capture folder ----
# profiles/default/config.yaml leaves out Snakemake's "input" rerun trigger, which compares the
# inputs' full paths (so moving the captures folder reran every stage). A rule tracks instead the
# names of its capture files relative to the capture (capture_files: adding, removing or renaming
# one reruns it; editing one does through its date), and takes the capture's paths as untracked
# params.
def capture_files(get_inputs):
    """A params function: the paths that the input function ``get_inputs`` gives inside the
    capture folder, relative to it (files outside it, i.e. results, are left out)."""

    def names(wildcards):
        folder = capture_dir(wildcards.capture)
        paths = get_inputs(wildcards)
        paths = [paths] if isinstance(paths, str) else paths
        return sorted(
            Path(p).relative_to(folder).as_posix()
            for p in paths
            if p and Path(p).is_relative_to(folder)
        )

    return names


def untracked(get_path):
    """A params function giving ``get_path``'s value that Snakemake does not compare between runs:
    a params function that takes ``input`` counts as derived from the inputs, whose changes are
    tracked elsewhere (here: capture_files). For the capture's own paths, which change when the
    captures folder moves while nothing in it does."""

    def param(wildcards, input):
        return get_path(wildcards)

    return param


def has_cameras(capture):
    return (capture_dir(capture) / "cameras.json").is_file()


def has_init_mesh(capture):
    return (capture_dir(capture) / "init_mesh.ply").is_file()


def has_masks(capture):
    return (capture_dir(capture) / "masks").is_dir()


def get_gt_files(wildcards):
    """The files of the capture's gt/ folder (synthetic captures; only the report reads them)."""
    folder = capture_dir(wildcards.capture) / "gt"
    return (
        sorted(str(p) for p in folder.iterdir() if p.is_file())
        if folder.is_dir()
        else []
    )


def get_capture_dir(wildcards):
    return str(capture_dir(wildcards.capture))


def get_all_targets(wildcards):
    """The report of every capture (the last stage of recon.stages: it needs every other
    stage's outputs)."""
    return [f"{RESULTS}/{capture}/{FINAL.output('html')}" for capture in CAPTURES]


# ---- Input functions of the geometry stages (given files skip the stages that make them) ----
def get_given_masks(wildcards):
    """The capture's own mask files (tracked, so editing one reruns the stage)."""
    folder = capture_dir(wildcards.capture) / "masks"
    return (
        sorted(str(p) for p in folder.glob("*.png") if not p.name.startswith("."))
        if folder.is_dir()
        else []
    )


def get_given_masks_dir(wildcards):
    return (
        str(capture_dir(wildcards.capture) / "masks")
        if has_masks(wildcards.capture)
        else ""
    )


def get_cameras(wildcards):
    """poses/cameras.json for later stages: SfM's cameras, or the capture's own passed through
    (validated, with capture.yaml's light_intensity written in): one route for every capture.
    """
    return f"{RESULTS}/{wildcards.capture}/poses/cameras.json"


def get_views_dir(wildcards):
    """Folder of the pinhole linear views (<stem>.exr, <stem>.sat.png)."""
    if has_cameras(wildcards.capture):
        return f"{RESULTS}/{wildcards.capture}/linear"
    return f"{RESULTS}/{wildcards.capture}/poses/undistorted"


def get_views(wildcards):
    """The file that marks the pinhole views of get_views_dir as complete."""
    if has_cameras(wildcards.capture):
        return f"{RESULTS}/{wildcards.capture}/linear/linear.json"
    return f"{RESULTS}/{wildcards.capture}/poses/poses.json"


def get_view_masks_dir(wildcards):
    """Folder of the masks in the pinhole views (<stem>.png): the poses stage's, for given
    cameras and SfM alike (an object standing on a table is separated from it there)."""
    return f"{RESULTS}/{wildcards.capture}/poses/undistorted/masks"


def get_view_masks(wildcards):
    """The file that marks the masks of get_view_masks_dir as complete."""
    return f"{RESULTS}/{wildcards.capture}/poses/poses.json"


def get_plane(wildcards, input):
    """The support plane (recon.support): poses/plane.json, beside poses.json (an input), which
    the poses stage writes only when it found a plane; the stages reading it keep their
    behaviour for an object in the void when it is absent."""
    return str(Path(input.masks).parent / "plane.json")


def get_sparse_dir(wildcards):
    """SfM's sparse model (poses/sparse), or "" for the capture's own cameras: init_mesh carves
    the space its points were seen through (recon.freespace)."""
    if has_cameras(wildcards.capture):
        return ""
    return f"{RESULTS}/{wildcards.capture}/poses/sparse"


def get_given_cameras(wildcards):
    """The capture's own cameras.json, or "" (SfM)."""
    return (
        str(capture_dir(wildcards.capture) / "cameras.json")
        if has_cameras(wildcards.capture)
        else ""
    )


def get_given_cameras_input(wildcards):
    """As get_given_cameras, as an input list (editing the file reruns poses)."""
    given = get_given_cameras(wildcards)
    return [given] if given else []


def get_init_mesh(wildcards):
    """The initial mesh for later stages: the capture's init_mesh.ply, else this stage's."""
    if has_init_mesh(wildcards.capture):
        return str(capture_dir(wildcards.capture) / "init_mesh.ply")
    return f"{RESULTS}/{wildcards.capture}/init_mesh/mesh.ply"


def get_given_init_mesh(wildcards):
    return get_init_mesh(wildcards) if has_init_mesh(wildcards.capture) else ""


def lock_run():
    """Take the results folder's run lock (recon.runlock) or stop, naming the run holding it
    (the message alone: no traceback, nothing has started)."""
    try:
        lock_results(RESULTS)
    except RunLockError as e:
        stop(e)
