# recon: flash photos of an object -> relightable 3D asset.
# Stages (DESIGN section 2): linearize -> masks -> poses -> init_mesh -> uv -> optimize -> export -> report
#   snakemake --cores 2 all [--config captures=DIR results=DIR preset=draft|balanced|accurate]
from pathlib import Path

from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


validate(config, "workflow/schemas/config.schema.yaml")


include: "workflow/rules/common.smk"


rule all:
    input:
        get_all_targets,
    default_target: True


for _stage in STAGES:
    if Path(workflow.basedir, "workflow", "rules", f"{_stage}.smk").exists():
        INCLUDED_STAGES.append(_stage)

        include: f"workflow/rules/{_stage}.smk"
