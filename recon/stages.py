"""The pipeline's stages, once: name (= Snakemake rule), order, results folder, outputs, SLURM job.

Everything that lists the stages reads :data:`STAGES`: the settings (:mod:`recon.config`: which
stages have a section in the presets and ``capture.yaml``), the run summary
(:mod:`recon.summary`: stages done, the first that failed, the SLURM group logs), the capture
check (:mod:`recon.validate`: every section built before the first stage runs), the report
(:func:`recon.report.inputs.read_benchmarks`: wall times in pipeline order) and the workflow
(``workflow/rules/common.smk``). Two readers cannot import Python and are held to the table by
``tests/workflow/test_stage_table.py`` instead: the Snakefile (each rule's name, order and named
outputs, written out in full in ``workflow/rules/<stage>.smk`` as the Snakemake catalog's style
asks) and ``profiles/slurm/config.yaml`` (its ``groups``, ``set-threads`` and ``set-resources``,
YAML that Snakemake reads before any of this runs).

This module imports nothing of recon's: the Snakefile loads it (through ``recon.summary``) when it
parses, and every stage's package may import it without a cycle.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline (DESIGN section 2).

    name : the Snakemake rule, the stem of its log (``logs/<name>.log``) and benchmark
        (``benchmarks/<name>.tsv``), and its settings section (when ``settings``).
    folder : its folder under ``<results>/<capture>/``.
    outputs : its declared outputs as ``(name, path)``, the path relative to ``<results>/<capture>/``,
        in the rule's order.
    settings : whether it has a ``<name>:`` section in the presets and ``capture.yaml``.
    group : the SLURM job it shares with its neighbours (profiles/slurm ``groups``), or None: a job
        of its own.
    gpu : whether its job renders on a GPU when given one (:func:`recon.config.job_variant`).
    """

    name: str
    folder: str
    outputs: tuple[tuple[str, str], ...]
    settings: bool = True
    group: str | None = None
    gpu: bool = False

    @property
    def rule(self) -> str:
        """The Snakemake rule that runs the stage (its name)."""
        return self.name

    def output(self, name: str) -> str:
        """The path of the output called ``name`` (relative to ``<results>/<capture>/``)."""
        return dict(self.outputs)[name]

    @property
    def output_paths(self) -> tuple[str, ...]:
        """The declared outputs' paths relative to ``<results>/<capture>/``, in order."""
        return tuple(path for _, path in self.outputs)


STAGES: tuple[Stage, ...] = (
    # the whole capture validated before anything else runs (recon.validate)
    Stage("check", "check", (("report", "check/check.json"),), settings=False, group="prepare"),
    Stage("linearize", "linear", (("meta", "linear/linear.json"),), group="prepare"),
    Stage("masks", "masks", (("summary", "masks/masks.json"),), group="prepare"),
    Stage("poses", "poses", (("cameras", "poses/cameras.json"), ("diagnostics", "poses/poses.json")),
          group="prepare"),
    Stage("init_mesh", "init_mesh", (("mesh", "init_mesh/mesh.ply"),), group="prepare"),
    Stage("uv", "uv", (("mesh", "uv/mesh.obj"),), group="prepare"),
    # the long one, alone in its job: the one that can take a GPU
    Stage("optimize", "optimize", (
        ("mesh", "optimize/mesh.obj"), ("diffuse", "optimize/diffuse.exr"),
        ("specular", "optimize/specular.exr"), ("roughness", "optimize/roughness.exr"),
        ("log", "optimize/log.jsonl"), ("summary", "optimize/summary.json"),
        ("cameras", "optimize/cameras.json")), gpu=True),
    Stage("export", "export", (("glb", "export/asset.glb"), ("usdz", "export/asset.usdz"),
                               ("usda", "export/asset.usda")), group="finish"),
    Stage("report", "report", (("html", "report/index.html"), ("metrics", "report/metrics.json")),
          group="finish"),
)
"""The stages in pipeline order."""

NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
"""Every stage's name, in pipeline order."""

SETTINGS_STAGES: tuple[str, ...] = tuple(s.name for s in STAGES if s.settings)
"""The stages with a settings section (the sections of a preset and of ``capture.yaml``)."""

GPU_STAGES: tuple[str, ...] = tuple(s.name for s in STAGES if s.gpu)
"""The stages that render on a GPU when their job was given one."""

FINAL: Stage = STAGES[-1]
"""The last stage: a capture is finished when its outputs exist."""


def stage(name: str) -> Stage:
    """The :class:`Stage` called ``name``; ValueError naming the stages when there is none."""
    for s in STAGES:
        if s.name == name:
            return s
    raise ValueError(f"unknown stage {name!r}; stages are {', '.join(NAMES)}")


def slurm_groups() -> dict[str, str]:
    """``{stage: group}`` of the stages that share a SLURM job (profiles/slurm ``groups``)."""
    return {s.name: s.group for s in STAGES if s.group}
