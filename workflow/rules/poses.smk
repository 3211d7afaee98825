# Poses (DESIGN section 2): cameras.json in the object frame, the COLMAP model and the views
# undistorted to pinhole. recon.poses.run_poses replaces the whole poses/ folder atomically.
#
# Skipping SfM: a capture with its own cameras.json never needs this rule. Every consumer of
# cameras and pinhole views asks the input functions below, which point straight at the
# capture's cameras.json, the linear/ images and the masks/ folder in that case (the photos
# are pinhole already, DESIGN section 1), so Snakemake does not schedule `poses` at all.
# Asked for explicitly, the rule passes the given cameras through (validated).


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
    conda:
        "../../envs/recon.yaml"
    script:
        "../scripts/poses.py"
