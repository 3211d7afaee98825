# Poses (DESIGN section 2): cameras.json in the object frame, the COLMAP model and the views
# undistorted to pinhole. recon.poses.run_poses replaces the whole poses/ folder atomically.
#
# Skipping SfM: a capture with its own cameras.json runs this rule as a pass-through: the given
# cameras are validated and written to poses/cameras.json with capture.yaml's light_intensity
# (one route for that value, whichever way the cameras came). The pinhole views are then the
# linear/ images and the masks/ folder (the photos are pinhole already, DESIGN section 1).


rule poses:
    input:
        linear=f"{RESULTS}/{{capture}}/linear/linear.json",
        masks=f"{RESULTS}/{{capture}}/masks/masks.json",
        given=get_given_cameras_input,
    output:
        cameras=f"{RESULTS}/{{capture}}/poses/cameras.json",
        diagnostics=f"{RESULTS}/{{capture}}/poses/poses.json",
    log:
        f"{RESULTS}/{{capture}}/logs/poses.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/poses.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        given=untracked(get_given_cameras),
        capture_files=capture_files(get_given_cameras),
        settings=get_settings("poses"),
    script:
        "../scripts/poses.py"
