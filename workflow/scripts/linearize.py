"""Snakemake adapter of the linearize stage: calls recon.linearize.linearize_capture (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.linearize import LinearizeSettings, linearize_capture

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    linearize_capture(
        snakemake.params.capture_dir,  # noqa: F821
        Path(snakemake.output.meta).parent,  # noqa: F821
        build_settings(LinearizeSettings, job_settings("linearize", snakemake)),  # noqa: F821
    )
