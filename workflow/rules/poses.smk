# Poses (DESIGN section 2): cameras.json in the object frame, the COLMAP model and the views
# undistorted to pinhole. recon.poses.run_poses replaces the whole poses/ folder atomically.
#
# Skipping SfM: a capture with its own cameras.json never needs this rule. Every consumer of
# cameras and pinhole views asks the input functions below, which point straight at the
# capture's cameras.json, the linear/ images and the masks/ folder in that case (the photos
# are pinhole already, DESIGN section 1), so Snakemake does not schedule `poses` at all.
# Asked for explicitly, the rule passes the given cameras through (validated).


def get_cameras(wildcards):
    """cameras.json for later stages: the capture's own (no SfM), else the poses stage's."""
    if has_cameras(wildcards.capture):
        return str(capture_dir(wildcards.capture) / "cameras.json")
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
    """Folder of the masks in the pinhole views (<stem>.png)."""
    if has_cameras(wildcards.capture):
        return f"{RESULTS}/{wildcards.capture}/masks"
    return f"{RESULTS}/{wildcards.capture}/poses/undistorted/masks"


def get_view_masks(wildcards):
    """The file that marks the masks of get_view_masks_dir as complete."""
    if has_cameras(wildcards.capture):
        return f"{RESULTS}/{wildcards.capture}/masks/masks.json"
    return f"{RESULTS}/{wildcards.capture}/poses/poses.json"


def get_given_cameras(wildcards):
    return get_cameras(wildcards) if has_cameras(wildcards.capture) else ""


rule poses:
    input:
        linear=f"{RESULTS}/{{capture}}/linear/linear.json",
        masks=f"{RESULTS}/{{capture}}/masks/masks.json",
    output:
        cameras=f"{RESULTS}/{{capture}}/poses/cameras.json",
        diagnostics=f"{RESULTS}/{{capture}}/poses/poses.json",
    log:
        f"{RESULTS}/{{capture}}/logs/poses.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/poses.tsv"
    params:
        given=get_given_cameras,
        settings=get_settings("poses"),
    script:
        "../scripts/poses.py"
