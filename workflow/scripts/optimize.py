"""Snakemake adapter of the optimize stage: calls recon.optimize.optimize_from_dirs (no logic here)."""

from pathlib import Path

from recon.config import job_settings
from recon.logs import stage
from recon.optimize import optimize_from_dirs, settings_from_dict

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    optimize_from_dirs(
        snakemake.params.views_dir,  # noqa: F821
        snakemake.params.masks_dir,  # noqa: F821
        snakemake.input.cameras,  # noqa: F821
        snakemake.input.mesh,  # noqa: F821
        Path(snakemake.output.mesh).parent,  # noqa: F821
        settings_from_dict(job_settings("optimize", snakemake)),  # noqa: F821
        plane_json=snakemake.params.plane,  # noqa: F821
    )
