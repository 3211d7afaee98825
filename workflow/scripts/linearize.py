"""Snakemake adapter of the linearize stage: calls recon.linearize.linearize_capture (no logic here)."""

import logging
from pathlib import Path

from recon.config import build_settings
from recon.linearize import LinearizeSettings, linearize_capture

logging.basicConfig(
    filename=snakemake.log[0],  # noqa: F821 (injected by Snakemake)
    level=logging.INFO,
    format="%(asctime)s %(levelname)s %(name)s: %(message)s",
)
linearize_capture(
    snakemake.params.capture_dir,  # noqa: F821
    Path(snakemake.output.meta).parent,  # noqa: F821
    build_settings(LinearizeSettings, snakemake.params.settings),  # noqa: F821
)
