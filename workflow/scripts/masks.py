"""Snakemake adapter of the masks stage: calls recon.masks.run_masks (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.masks import MaskSettings, run_masks

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    run_masks(
        Path(snakemake.input.linear).parent,  # noqa: F821
        Path(snakemake.output.summary).parent,  # noqa: F821
        build_settings(MaskSettings, job_settings("masks", snakemake)),  # noqa: F821
        given_dir=snakemake.params.given_dir or None,  # noqa: F821
        stems=list(snakemake.params.stems),  # noqa: F821
    )
