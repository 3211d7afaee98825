# recon: flash photos of an object -> relightable 3D asset.
# Stages (DESIGN section 2; names, order and outputs in recon/stages.py, which a test holds these
# rules to): check -> linearize -> masks -> poses -> init_mesh -> uv -> optimize -> export -> report
#   snakemake --cores 2 all [--config captures=DIR results=DIR preset=draft|balanced|accurate]
from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


validate(config, "workflow/schemas/config.schema.yaml")


include: "workflow/rules/common.smk"


# One run at a time per results folder (recon.runlock: a lock that a crash cannot leave
# behind; profiles/default turns Snakemake's own lock off). Taken when the jobs start, so
# dry runs (-n) never wait for it.
onstart:
    lock_run()


rule all:
    default_target: True
    input:
        get_all_targets,


include: "workflow/rules/check.smk"
include: "workflow/rules/linearize.smk"
include: "workflow/rules/masks.smk"
include: "workflow/rules/poses.smk"
include: "workflow/rules/init_mesh.smk"
include: "workflow/rules/uv.smk"
include: "workflow/rules/optimize.smk"
include: "workflow/rules/export.smk"
include: "workflow/rules/report.smk"


# One readable file per run, <results>/summary.md (+ summary.json): which captures finished,
# which failed, at which stage and why (recon.summary; with --keep-going, the profiles' default on
# a cluster, after every capture that could go on has finished).
onsuccess:
    write_run_summary(RESULTS, CAPTURES, "success")


onerror:
    write_run_summary(RESULTS, CAPTURES, "error")
