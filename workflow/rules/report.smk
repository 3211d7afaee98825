# Report (DESIGN sections 2, 5, 6): report/index.html (opens offline: inputs beside re-renders
# and error maps, texture maps, loss curves, timings, the asset in model-viewer) and
# report/metrics.json. recon.report.make_report replaces the whole report/ folder atomically,
# so the log and the benchmark live outside it. Per-stage wall times are read from
# results/<capture>/benchmarks/*.tsv; metrics against <capture>/gt/ when that folder exists
# (its files are inputs: adding, removing or editing one reruns the report).
# Each view's linear image is taken from poses/undistorted/ when the poses stage wrote one
# there, else from linear/; its mask likewise from poses/undistorted/masks/ (an object on a
# table: the masks without the table), else masks/.
# Outputs flagged update(): the previous report stays in place until the new folder replaces it
# (README "If a run is interrupted").


rule report:
    input:
        mesh=f"{RESULTS}/{{capture}}/optimize/mesh.obj",
        diffuse=f"{RESULTS}/{{capture}}/optimize/diffuse.exr",
        specular=f"{RESULTS}/{{capture}}/optimize/specular.exr",
        roughness=f"{RESULTS}/{{capture}}/optimize/roughness.exr",
        optimize_log=f"{RESULTS}/{{capture}}/optimize/log.jsonl",
        glb=f"{RESULTS}/{{capture}}/export/asset.glb",
        cameras=f"{RESULTS}/{{capture}}/optimize/cameras.json",
        linear=f"{RESULTS}/{{capture}}/linear/linear.json",
        masks=f"{RESULTS}/{{capture}}/masks/masks.json",
        gt=get_gt_files,
    output:
        html=update(f"{RESULTS}/{{capture}}/report/index.html"),
        metrics=update(f"{RESULTS}/{{capture}}/report/metrics.json"),
    log:
        f"{RESULTS}/{{capture}}/logs/report.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/report.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        capture_dir=untracked(get_capture_dir),
        capture_files=capture_files(get_gt_files),
        preset=get_preset,
        undistorted=f"{RESULTS}/{{capture}}/poses/undistorted",
        benchmarks=f"{RESULTS}/{{capture}}/benchmarks",
        settings=get_settings("report"),
    script:
        "../scripts/report.py"
