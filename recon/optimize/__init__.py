"""The optimize stage: shape and SVBRDF from flash photos by differentiable rendering.

Public API: :func:`optimize_capture`, :func:`optimize_from_dirs` (the Snakemake entry), :class:`OptimizeSettings`, :class:`StageSettings`,
:func:`settings_from_dict`. Building blocks (importable for tests and benchmarks):
:mod:`~recon.optimize.params` (parameterizations), :mod:`~recon.optimize.regularizers`
(sec. 3.3 priors), :mod:`~recon.optimize.remesh` (stage changes: remesh, unwrap, bake),
:mod:`~recon.optimize.guard` (no self-intersections), :mod:`~recon.optimize.largesteps`
(Nicolet et al. preconditioning), :mod:`~recon.optimize.checkpoint`, :mod:`~recon.optimize.views`.
"""

from recon.optimize.loop import OptimizeError, optimize_capture, optimize_from_dirs
from recon.optimize.settings import OptimizeSettings, StageSettings, settings_from_dict

__all__ = ["OptimizeError", "OptimizeSettings", "StageSettings", "optimize_capture", "optimize_from_dirs",
           "settings_from_dict"]
