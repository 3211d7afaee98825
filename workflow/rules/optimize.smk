# Optimize (DESIGN section 2, issue 5): coarse-to-fine analysis by synthesis of the mesh and
# the SVBRDF maps (recon.optimize). Every view of the cameras is used: the linear (or
# undistorted) views, their masks and clipped-pixel masks come from the folders that
# get_views_dir / get_view_masks_dir name (common.smk).
# optimize/cameras.json: the cameras of the final model (SfM cameras refined by the renderer
# where the held-out views kept the refinement, else poses/cameras.json's); later stages that
# render views (export's up axis, the report) read it.
# optimize/checkpoints/ is deliberately not an output: Snakemake leaves it in place when the
# job is killed or fails, and the next run (the profile's rerun-incomplete) resumes from its
# last checkpoint. Outputs flagged update(): the previous result (minutes of compute) stays in
# place when the job starts, until the new files replace it.


rule optimize:
    input:
        views=get_views,
        masks=get_view_masks,
        cameras=get_cameras,
        mesh=f"{RESULTS}/{{capture}}/uv/mesh.obj",
    output:
        mesh=update(f"{RESULTS}/{{capture}}/optimize/mesh.obj"),
        diffuse=update(f"{RESULTS}/{{capture}}/optimize/diffuse.exr"),
        specular=update(f"{RESULTS}/{{capture}}/optimize/specular.exr"),
        roughness=update(f"{RESULTS}/{{capture}}/optimize/roughness.exr"),
        log=update(f"{RESULTS}/{{capture}}/optimize/log.jsonl"),
        summary=update(f"{RESULTS}/{{capture}}/optimize/summary.json"),
        cameras=update(f"{RESULTS}/{{capture}}/optimize/cameras.json"),
    log:
        f"{RESULTS}/{{capture}}/logs/optimize.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/optimize.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        views_dir=get_views_dir,
        masks_dir=get_view_masks_dir,
        plane=get_plane,
        settings=get_settings("optimize"),
    script:
        "../scripts/optimize.py"
