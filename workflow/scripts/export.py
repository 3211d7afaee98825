"""Snakemake adapter of the export stage: calls recon.export.export_asset (no logic here)."""

import logging
from pathlib import Path

from recon.config import build_settings
from recon.export import ExportSettings, export_asset

logging.basicConfig(
    filename=snakemake.log[0],  # noqa: F821 (injected by Snakemake)
    level=logging.INFO,
    format="%(asctime)s %(levelname)s %(name)s: %(message)s",
)
export_asset(
    snakemake.input.mesh,  # noqa: F821
    snakemake.input.diffuse,  # noqa: F821
    snakemake.input.specular,  # noqa: F821
    snakemake.input.roughness,  # noqa: F821
    Path(snakemake.output.glb).parent,  # noqa: F821
    build_settings(ExportSettings, snakemake.params.settings),  # noqa: F821
    cameras_json=snakemake.input.cameras,  # noqa: F821
)
