# Masks (DESIGN section 2): one object mask per view, results/<capture>/masks/<stem>.png.
# The capture's masks/<stem>.png are used as given; other views get a mask derived from the
# linear image (flash falloff: see recon.masks). recon.masks.run_masks replaces the whole
# masks/ folder atomically; masks.json (per-view source and coverage) is the declared output.


rule masks:
    input:
        linear=f"{RESULTS}/{{capture}}/linear/linear.json",
        given=get_given_masks,
    output:
        summary=f"{RESULTS}/{{capture}}/masks/masks.json",
    log:
        f"{RESULTS}/{{capture}}/logs/masks.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/masks.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        given_dir=untracked(get_given_masks_dir),
        capture_files=capture_files(get_given_masks),
        stems=get_image_stems,
        settings=get_settings("masks"),
    script:
        "../scripts/masks.py"
