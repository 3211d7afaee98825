# Check (issue 20): the whole capture validated before its first stage runs (recon.validate:
# capture.yaml's sections, the photos, cameras.json against the photos, the masks, a given
# init_mesh.ply's topology and fit to the cameras). check/check.json exists only for a capture
# that passed; linearize and uv (the stages that read the capture first) take it as input, so
# nothing else runs for a bad capture while the other captures go on.
#
# It tracks the photos alone (their names and dates): it reruns when they change, when every
# stage reruns anyway. Tracking capture.yaml or the given files here would rerun the whole
# chain after any edit; a stage that reruns after such an edit checks what it reads itself.


rule check:
    input:
        images=get_images,
    output:
        report=f"{RESULTS}/{{capture}}/check/check.json",
    log:
        f"{RESULTS}/{{capture}}/logs/check.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/check.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        capture_dir=untracked(get_capture_dir),
        capture_files=capture_files(get_images),
    script:
        "../scripts/check.py"
