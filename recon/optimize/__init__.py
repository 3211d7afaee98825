"""The optimize stage: shape and SVBRDF from flash photos by differentiable rendering.

Public API: :func:`optimize_capture`, :func:`optimize_from_dirs` (the Snakemake entry),
:class:`OptimizeSettings` (in sections), :class:`StageSettings`, :func:`settings_from_dict` (a
preset's or capture.yaml's ``optimize:``), :func:`settings_from_record` (summary.json's flat
``settings``).

Where things are (:func:`~recon.optimize.loop.optimize_capture` is the stage's table of contents:
inputs -> run(s) -> selections -> outputs):

- the loss, every term and its weight: :mod:`~recon.optimize.objective`; every fit but the main
  loop's: :mod:`~recon.optimize.fitting`;
- the main loop: :mod:`~recon.optimize.run` (a run: its stages, checkpoints),
  :mod:`~recon.optimize.iteration` (one iteration), :mod:`~recon.optimize.schedule` (edge
  length, large-steps lambda, learning rates, plateau);
- the selections on held-out views, each deciding with the paired test of
  :mod:`~recon.optimize.heldout`: :mod:`~recon.optimize.material_select`,
  :mod:`~recon.optimize.imaging_select`, :mod:`~recon.optimize.cameras` (with the camera
  refinement's run-time part and the held-out views' alignment);
- the image formation: :mod:`~recon.optimize.formation`; the fits on fixed G-buffers:
  :mod:`~recon.optimize.material`, :mod:`~recon.optimize.imaging`, :mod:`~recon.optimize.gbuffer`;
  the loop's imaging terms: :mod:`~recon.optimize.loop_imaging`;
- building blocks (importable for tests and benchmarks): :mod:`~recon.optimize.params`
  (parameterizations), :mod:`~recon.optimize.regularizers` (sec. 3.3 priors),
  :mod:`~recon.optimize.remesh` (stage changes: remesh, unwrap, bake), :mod:`~recon.optimize.guard`
  (no self-intersections), :mod:`~recon.optimize.largesteps` (Nicolet et al. preconditioning),
  :mod:`~recon.optimize.camera_refine`, :mod:`~recon.optimize.tracks`,
  :mod:`~recon.optimize.radiometry`, :mod:`~recon.optimize.checkpoint`, :mod:`~recon.optimize.views`.
"""

from recon.optimize.loop import OptimizeError, optimize_capture, optimize_from_dirs
from recon.optimize.settings import OptimizeSettings, StageSettings, settings_from_dict, settings_from_record

__all__ = ["OptimizeError", "OptimizeSettings", "StageSettings", "optimize_capture", "optimize_from_dirs",
           "settings_from_dict", "settings_from_record"]
