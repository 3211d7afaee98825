"""Snakemake adapter of the check step: calls recon.validate.run_check (no logic here)."""

from recon.logs import stage
from recon.validate import run_check

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    run_check(
        snakemake.params.capture_dir,  # noqa: F821
        snakemake.output.report,  # noqa: F821
        snakemake.config["preset"],  # noqa: F821 (capture.yaml may pick its own)
    )
