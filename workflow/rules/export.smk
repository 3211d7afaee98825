# Export (DESIGN section 2, issue 6): the optimized model as glTF 2.0 (.glb, with
# KHR_materials_specular) and USD (.usdz packaging asset.usda and its PNG textures).
# The whole export/ folder is replaced atomically by recon.export.export_asset, so the log
# and the benchmark live outside it.
# Outputs flagged update(): Snakemake would delete the previous asset when the job starts; kept,
# an interrupted re-export (--forcerun export, then Ctrl-C or a crash) leaves the previous
# deliverables in place until the new folder replaces them (README "If a run is interrupted").


rule export:
    input:
        mesh=f"{RESULTS}/{{capture}}/optimize/mesh.obj",
        diffuse=f"{RESULTS}/{{capture}}/optimize/diffuse.exr",
        specular=f"{RESULTS}/{{capture}}/optimize/specular.exr",
        roughness=f"{RESULTS}/{{capture}}/optimize/roughness.exr",
        cameras=f"{RESULTS}/{{capture}}/optimize/cameras.json",
        masks=get_view_masks,
        views=get_views,
    output:
        glb=update(f"{RESULTS}/{{capture}}/export/asset.glb"),
        usdz=update(f"{RESULTS}/{{capture}}/export/asset.usdz"),
        usda=update(f"{RESULTS}/{{capture}}/export/asset.usda"),
    log:
        f"{RESULTS}/{{capture}}/logs/export.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/export.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        plane=get_plane,
        views_dir=get_views_dir,
        masks_dir=get_view_masks_dir,
        settings=get_settings("export"),
    script:
        "../scripts/export.py"
