"""Snakemake adapter of the export stage: calls recon.export.export_asset (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.export import ExportSettings, export_asset

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    export_asset(
        snakemake.input.mesh,  # noqa: F821
        snakemake.input.diffuse,  # noqa: F821
        snakemake.input.specular,  # noqa: F821
        snakemake.input.roughness,  # noqa: F821
        Path(snakemake.output.glb).parent,  # noqa: F821
        build_settings(ExportSettings, job_settings("export", snakemake)),  # noqa: F821
        cameras_json=snakemake.input.cameras,  # noqa: F821
        plane_json=snakemake.params.plane,  # noqa: F821
        views_dir=snakemake.params.views_dir,  # noqa: F821
        masks_dir=snakemake.params.masks_dir,  # noqa: F821
    )
