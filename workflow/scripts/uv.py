"""Snakemake adapter of the uv stage: calls recon.uv.run_uv (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.uv import UVSettings, run_uv

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    run_uv(
        snakemake.input.mesh,  # noqa: F821
        Path(snakemake.output.mesh).parent,  # noqa: F821
        build_settings(UVSettings, job_settings("uv", snakemake)),  # noqa: F821
    )
