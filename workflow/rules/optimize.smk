# Optimize (DESIGN section 2, issue 5): coarse-to-fine analysis by synthesis of the mesh and
# the SVBRDF maps (recon.optimize). Every view of the cameras is used: the linear (or
# undistorted) views, their masks and clipped-pixel masks come from the folders that
# get_views_dir / get_view_masks_dir name (common.smk).
# optimize/checkpoints/ is deliberately not an output: Snakemake leaves it in place when the
# job is killed or fails, and a rerun (--rerun-incomplete) resumes from its last checkpoint.


rule optimize:
    input:
        views=get_views,
        masks=get_view_masks,
        cameras=get_cameras,
        mesh=f"{RESULTS}/{{capture}}/uv/mesh.obj",
    output:
        mesh=f"{RESULTS}/{{capture}}/optimize/mesh.obj",
        diffuse=f"{RESULTS}/{{capture}}/optimize/diffuse.exr",
        specular=f"{RESULTS}/{{capture}}/optimize/specular.exr",
        roughness=f"{RESULTS}/{{capture}}/optimize/roughness.exr",
        log=f"{RESULTS}/{{capture}}/optimize/log.jsonl",
        summary=f"{RESULTS}/{{capture}}/optimize/summary.json",
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
