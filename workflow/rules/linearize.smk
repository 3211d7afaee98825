# Linearize (DESIGN section 2): every photo of a capture to float32 linear Rec.709 on one
# exposure scale, with clipped-pixel masks, sRGB previews and per-image metadata.
# recon.linearize.linearize_capture replaces the whole linear/ folder atomically; linear.json
# (written last) is the declared output. The log and the benchmark live outside linear/.


rule linearize:
    input:
        check=f"{RESULTS}/{{capture}}/check/check.json",
        images=get_images,
    output:
        meta=f"{RESULTS}/{{capture}}/linear/linear.json",
    log:
        f"{RESULTS}/{{capture}}/logs/linearize.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/linearize.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        capture_dir=untracked(get_capture_dir),
        capture_files=capture_files(get_images),
        settings=get_settings("linearize"),
    script:
        "../scripts/linearize.py"
