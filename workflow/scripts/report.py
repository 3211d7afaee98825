"""Snakemake adapter of the report stage: calls recon.report.make_report (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.logs import stage
from recon.report import ReportSettings, make_report

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    make_report(
        capture=snakemake.wildcards.capture,  # noqa: F821
        optimize_dir=Path(snakemake.input.mesh).parent,  # noqa: F821
        glb=snakemake.input.glb,  # noqa: F821
        cameras=snakemake.input.cameras,  # noqa: F821
        image_dirs=[snakemake.params.undistorted, Path(snakemake.input.linear).parent],  # noqa: F821
        mask_dirs=[Path(snakemake.params.undistorted) / "masks", Path(snakemake.input.masks).parent],  # noqa: F821
        out_dir=Path(snakemake.output.html).parent,  # noqa: F821
        settings=build_settings(ReportSettings, job_settings("report", snakemake)),  # noqa: F821
        gt_dir=Path(snakemake.params.capture_dir) / "gt",  # noqa: F821 (skipped when absent)
        benchmarks_dir=snakemake.params.benchmarks,  # noqa: F821
        preset=snakemake.params.preset,  # noqa: F821
    )
