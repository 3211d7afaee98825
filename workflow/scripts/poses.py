"""Snakemake adapter of the poses stage: calls recon.poses.run_poses (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.poses import PoseSettings, run_poses

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    run_poses(
        Path(snakemake.input.linear).parent,  # noqa: F821
        Path(snakemake.output.cameras).parent,  # noqa: F821
        build_settings(PoseSettings, job_settings("poses", snakemake)),  # noqa: F821
        masks_dir=Path(snakemake.input.masks).parent,  # noqa: F821
        linear_json=snakemake.input.linear,  # noqa: F821
        given_cameras=snakemake.params.given or None,  # noqa: F821
    )
