"""Snakemake adapter of the init_mesh stage: calls recon.init_mesh.run_init_mesh (no logic here)."""

from pathlib import Path

from recon.config import build_settings, job_settings
from recon.init_mesh import InitMeshSettings, run_init_mesh
from recon.logs import stage

with stage(snakemake.log[0]):  # noqa: F821 (injected by Snakemake); errors: see recon.logs
    run_init_mesh(
        snakemake.input.cameras,  # noqa: F821
        snakemake.params.masks_dir,  # noqa: F821
        Path(snakemake.output.mesh).parent,  # noqa: F821
        build_settings(InitMeshSettings, job_settings("init_mesh", snakemake)),  # noqa: F821
        given_mesh=snakemake.params.given or None,  # noqa: F821
        plane_json=snakemake.params.plane,  # noqa: F821
        sparse_dir=snakemake.params.sparse or None,  # noqa: F821
        views_dir=snakemake.params.views,  # noqa: F821
    )
