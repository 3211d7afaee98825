"""Settings of the optimize stage, built from a preset's ``optimize:`` section.

:class:`OptimizeSettings` holds the coarse-to-fine ``stages``, the ``seed`` and the Mitsuba
``variant`` at its top and the rest in sections, frozen dataclasses themselves
(:mod:`recon.sections`): ``render``, ``schedule``, ``optim`` (the optimizer), ``loss``,
``light``, ``material``, ``select`` (the held-out views and the material selection),
``cameras`` (the camera refinement) and ``imaging`` (the camera's image formation). Each
section's docstring documents its keys. A preset or ``capture.yaml`` gives them the same way::

    optimize:
      render: {resolution: 256, spp: 4}
      loss: {w_edge: 0.01}
      cameras: {refine: select}
      stages:
        - {edge_length: 0.04, texture_size: 256, iterations: 100}

A flat key of an older ``capture.yaml`` (``optimize: {spp: 8}``, ``refine_cameras: off``) still
works, with a one-line warning naming its place (:data:`OptimizeSettings.MOVED` lists the keys
renamed on the way: the cameras' and the imaging model's lost the prefix their section now says).
:meth:`OptimizeSettings.to_dict` records the settings flat, under the names from before the
sections (``optimize/summary.json``, the checkpoints' fingerprint), so older results and
checkpoints read as before.

Lengths are relative to the initial mesh's bounding box (longest side = 1), so one preset fits
any object size; learning rates of the geometry are scaled the same way.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from recon.config import ConfigError, build_settings
from recon.optimize import objective
from recon.optimize.camera_refine import CameraPrior
from recon.optimize.material import SelectionSettings
from recon.sections import flatten, get_path, leaf_paths, move_flat, sectioned

OPTIMIZERS = ("largesteps", "adam")
BOUNDARIES = ("edge", "none", "projective")
LAPLACIANS = ("uniform", "cotangent")
TONE_MAPS = ("log", "srgb", "linear")
FOOT_MODES = ("exclude", "background")  # recon.optimize.foot
PARAMETERIZATIONS = ("sigmoid", "clamp")
CAMERA_MODES = ("off", "on", "select")
LIGHT_SCALES = ("auto", "estimate", "given")


@dataclass(frozen=True)
class StageSettings:
    """One coarse-to-fine stage: mesh topology and texture size stay fixed within it.

    edge_length : target edge length of the remeshed surface, as a fraction of the bounding box's
        longest side (the paper's "upsample the mesh" step, sec. 3.4).
    texture_size : side of the square texture maps (texels).
    iterations : optimizer steps in this stage.
    image_size : longest image side (pixels) the photos are downsampled to; 0 = ``render.resolution``.
    lr_scale : multiplies every learning rate in this stage (finer stages often take smaller steps).
    lr_decay : the learning rates fall exponentially within the stage, to ``lr_decay`` times their
        start at its last iteration (1 = constant).
    lambda_scale : multiplies ``optim.largesteps_lambda`` in this stage, on top of the automatic
        ``(optim.largesteps_reference_edge / edge_length)^2`` of stages finer than the reference.
    """

    edge_length: float = 0.02
    texture_size: int = 256
    iterations: int = 100
    image_size: int = 0
    lr_scale: float = 1.0
    lr_decay: float = 1.0
    lambda_scale: float = 1.0

    def __post_init__(self):
        if not (0 < self.edge_length < 1):
            raise ValueError(f"edge_length must be in (0, 1) (fraction of the bbox), got {self.edge_length}")
        if not (4 <= int(self.texture_size) <= 8192):
            raise ValueError(f"texture_size must be in [4, 8192], got {self.texture_size}")
        if int(self.iterations) < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        if int(self.image_size) < 0:
            raise ValueError(f"image_size must be >= 0, got {self.image_size}")
        if not self.lr_scale > 0:
            raise ValueError(f"lr_scale must be > 0, got {self.lr_scale}")
        if not self.lambda_scale > 0:
            raise ValueError(f"lambda_scale must be > 0, got {self.lambda_scale}")
        if not 0 < self.lr_decay <= 1:
            raise ValueError(f"lr_decay must be in (0, 1], got {self.lr_decay}")

    def lr_factor(self, iteration: int) -> float:
        """``lr_scale * lr_decay ** (iteration / (iterations - 1))``."""
        n = max(int(self.iterations) - 1, 1)
        return float(self.lr_scale * self.lr_decay ** (min(iteration, n) / n))


def _default_stages() -> tuple[StageSettings, ...]:
    return (
        StageSettings(edge_length=0.04, texture_size=128, iterations=100, image_size=128),
        StageSettings(edge_length=0.025, texture_size=256, iterations=150),
        StageSettings(edge_length=0.015, texture_size=512, iterations=150, lr_scale=0.5),
    )



def _positive(section, *names: str) -> None:
    for name in names:
        if not getattr(section, name) > 0:
            raise ValueError(f"{name} must be > 0, got {getattr(section, name)}")


def _at_least_one(section, *names: str) -> None:
    for name in names:
        if int(getattr(section, name)) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(section, name)}")


def _one_of(section, name: str, allowed: tuple) -> None:
    if getattr(section, name) not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {getattr(section, name)!r}")


@dataclass(frozen=True)
class RenderingSettings:
    """How the main loop renders.

    resolution : longest image side in pixels (a stage's ``image_size`` overrides it).
    spp : samples per pixel.
    boundary : the renderer's silhouette term: "edge" (edge-sampled silhouette gradients),
        "projective" (Mitsuba's, for comparison) or "none" (interior only, an ablation).
    """

    resolution: int = 256
    spp: int = 4
    boundary: str = "edge"

    def __post_init__(self):
        _one_of(self, "boundary", BOUNDARIES)
        _at_least_one(self, "resolution", "spp")


@dataclass(frozen=True)
class ScheduleSettings:
    """How the coarse-to-fine stages (``OptimizeSettings.stages``) run.

    views_per_iteration : views rendered in each iteration.
    checkpoint_every : iterations between checkpoints.
    coarse_to_fine : False = ablation: one stage with the last stage's mesh and texture size and
        all the stages' iterations.
    min_edge_pixels : no stage remeshes finer than this many pixel footprints (median over the
        views of depth / focal length at the object's center, at the stage's image size),
        whatever its ``edge_length``; finer triangles are not constrained by the photos and fit
        their noise (0 = no limit).
    """

    views_per_iteration: int = 4
    checkpoint_every: int = 50
    coarse_to_fine: bool = True
    min_edge_pixels: float = 2.5

    def __post_init__(self):
        _at_least_one(self, "views_per_iteration", "checkpoint_every")
        if not self.min_edge_pixels >= 0:
            raise ValueError(f"min_edge_pixels must be >= 0, got {self.min_edge_pixels}")


@dataclass(frozen=True)
class OptimSettings:
    """The optimizer and its steps.

    optimizer : "largesteps" (Nicolet et al. 2021: vertex positions through u = (I + lambda L) v,
        L the combinatorial Laplacian, and Adam on u) or "adam" (the paper: plain Adam on v with
        the Laplacian regularizer).
    lr_geometry : learning rate of the vertex positions (relative to the bbox's longest side).
    lr_texture : learning rate of the texture maps (in parameter units).
    largesteps_lambda : lambda of the large-steps preconditioner.
    largesteps_reference_edge : fraction of the bbox; a stage whose edges h are shorter than it
        multiplies lambda by (reference / h)^2: the preconditioner smooths over about
        sqrt(lambda) edges, so this keeps its smoothing length on the surface as the mesh is
        refined (0 = the same lambda in every stage).
    largesteps_uniform_adam : Nicolet's AdamUniform for u instead of Adam.
    betas : Adam's betas.
    guard : robust surface evolution: reject self-intersections by halving the displacement of
        the offending vertices, at most ``guard_max_halvings`` times.
    """

    optimizer: str = "largesteps"
    lr_geometry: float = 0.005
    lr_texture: float = 0.03
    largesteps_lambda: float = 2.0
    largesteps_reference_edge: float = 0.025
    largesteps_uniform_adam: bool = False
    betas: tuple = (0.9, 0.999)
    guard: bool = True
    guard_max_halvings: int = 8

    def __post_init__(self):
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        _one_of(self, "optimizer", OPTIMIZERS)
        if not (0 <= self.largesteps_reference_edge < 1):
            raise ValueError(f"largesteps_reference_edge must be in [0, 1) (fraction of the bbox; 0 = off), "
                             f"got {self.largesteps_reference_edge}")
        _positive(self, "lr_geometry", "lr_texture", "largesteps_lambda")


@dataclass(frozen=True)
class LossSettings:
    """The objective (the paper's eq. 6 and sec. 3.3; each term normalized as documented in
    :mod:`recon.optimize.regularizers`, assembled in :mod:`recon.optimize.objective`).

    w_render, w_laplacian, w_edge, w_normal, w_specular, w_roughness : weights of the image term
        and of the mesh and material priors.
    w_camera : weight of the camera prior (section ``cameras``) per view in the batch.
    w_imaging : weight of the imaging terms' prior (the exposure gains' log gain ~ N(0, 0.25)
        around the EXIF exposure; section ``imaging``).
    laplacian : "uniform" or "cotangent".
    tone_map : Phi: "log" = log(1 + x/s) with s the median foreground target value, "srgb",
        "linear".
    bilateral_sigma_space (texels), bilateral_sigma_color, bilateral_radius : the specular
        albedo's bilateral prior.
    use_laplacian, use_normal_edge, use_material_priors : ablation switches
        (:func:`recon.optimize.objective.weights`).
    uncertain_foot : on a table with tabletop masks, the pixels near a silhouette that see the
        object's foot or the table beside it, up to this multiple of the masks' parallax band
        above the table, where the mesh overhangs them, are in doubt (:mod:`recon.optimize.foot`,
        docs/tabletop.md); 0: off.
    uncertain_foot_mode : "background" (default): a doubted mask pixel whose colour and brightness
        are the table's becomes background (target 0, full weight), so the render is pushed off the
        table the masks took in; one too dark to tell, or with the table's colour but not its
        brightness, gets ``uncertain_foot_weight``. "exclude": every
        doubted pixel gets ``uncertain_foot_weight`` (session 17's form).
    uncertain_foot_weight : the weight of the doubted pixels left in doubt (0: out of the term).
    """

    w_render: float = 1.0
    w_laplacian: float = 0.1
    w_edge: float = 1.0
    w_normal: float = 0.01
    w_specular: float = 0.01
    w_roughness: float = 0.001
    w_camera: float = 0.001
    w_imaging: float = 0.001
    laplacian: str = "uniform"
    tone_map: str = "log"
    bilateral_sigma_space: float = 1.0
    bilateral_sigma_color: float = 0.1
    bilateral_radius: int = 2
    use_laplacian: bool = True
    use_normal_edge: bool = True
    use_material_priors: bool = True
    uncertain_foot: float = 1.5
    uncertain_foot_weight: float = 0.0
    uncertain_foot_mode: str = "background"  # measured against "exclude": docs/tabletop.md

    def __post_init__(self):
        _one_of(self, "laplacian", LAPLACIANS)
        _one_of(self, "uncertain_foot_mode", FOOT_MODES)
        if not 0 <= self.uncertain_foot <= 10:
            raise ValueError(f"uncertain_foot must be in [0, 10] (multiples of the masks' parallax band), got "
                             f"{self.uncertain_foot}")
        if not 0 <= self.uncertain_foot_weight <= 1:
            raise ValueError(f"uncertain_foot_weight must be in [0, 1], got {self.uncertain_foot_weight}")
        _one_of(self, "tone_map", TONE_MAPS)
        _positive(self, "w_render")
        for name in ("w_laplacian", "w_edge", "w_normal", "w_specular", "w_roughness", "w_camera"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class LightSettings:
    """The flash's scale (:mod:`recon.optimize.radiometry`) and the collapse it prevents.

    scale : "auto" uses the light intensity ``cameras.json`` states and estimates it from the
        photos when it states none (after SfM); "estimate" always estimates it; "given" requires
        it. An estimated I_e makes the albedo relative (its convention in the radiometry
        module) and sets the initial diffuse map from the photos.
    collapse_min_covered, collapse_min_area : a run whose surface covers less than
        ``collapse_min_covered`` of the masks, or whose area falls below ``collapse_min_area``
        of the initial mesh's, stops (collapse).
    """

    scale: str = "auto"
    collapse_min_covered: float = 0.3
    collapse_min_area: float = 0.1

    def __post_init__(self):
        _one_of(self, "scale", LIGHT_SCALES)
        if not (0 <= self.collapse_min_covered < 1 and 0 <= self.collapse_min_area < 1):
            raise ValueError("collapse_min_covered and collapse_min_area must be in [0, 1), got "
                             f"{self.collapse_min_covered} and {self.collapse_min_area}")


@dataclass(frozen=True)
class MaterialSettings:
    """The material maps.

    init_diffuse, init_specular, init_roughness : constant initial maps, as in the paper (the
        diffuse one only when the flash's intensity is given).
    specular_channels : 1 or 3.
    r_min : the smallest roughness.
    parameterization : "sigmoid": value = sigmoid(logit), roughness = r_min + (1 - r_min)
        sigmoid; "clamp": the value itself, projected back into range after each step.
    texture_levels : each raw map is a sum of this many levels, full size, 1/2, 1/4, ...: coarse
        levels learn low-frequency content from all the texels they cover; 1 = a plain texel map.
    """

    init_diffuse: float = 0.3
    init_specular: float = 0.1
    init_roughness: float = 0.4
    specular_channels: int = 1
    r_min: float = 0.02
    parameterization: str = "sigmoid"
    texture_levels: int = 4

    def __post_init__(self):
        _one_of(self, "parameterization", PARAMETERIZATIONS)
        if int(self.texture_levels) < 1:
            raise ValueError(f"texture_levels must be >= 1, got {self.texture_levels}")
        if self.specular_channels not in (1, 3):
            raise ValueError(f"specular_channels must be 1 or 3, got {self.specular_channels}")
        if not (0 < self.r_min < 1):
            raise ValueError(f"r_min must be in (0, 1), got {self.r_min}")
        for name in ("init_diffuse", "init_specular"):
            if not (0 <= getattr(self, name) <= 1):
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not (self.r_min <= self.init_roughness <= 1):
            raise ValueError(f"init_roughness must be in [r_min, 1], got {self.init_roughness}")


@dataclass(frozen=True)
class SelectSettings:
    """Model only what the scene requires (:mod:`recon.optimize.material`).

    select_material : after the last stage, fit material models of increasing complexity on the
        fixed final mesh and keep a richer one only when the held-out error drops by more than
        ``select_z`` standard errors and ``select_min_gain`` (relative).
    select_material_under_imaging : when the loop ran under a phone's imaging terms
        (``imaging.loop``), fit and compare the candidates under them, with the held-out views'
        own exposure gains (false: under the ideal formation, the maps refitted under the terms
        after).
    stop_on_plateau : after each coarse-to-fine stage, measure the held-out error and skip the
        remaining stages when it did not improve on the previous stage's by more than its noise
        (same test).
    holdout_every : with ``select_material`` or ``stop_on_plateau`` (or the camera and imaging
        selections) every ``holdout_every``-th view is held out of the optimization (at least 2
        views, and only when at least 4 remain for it).
    select_iterations, select_lr, select_image_size, select_spp : the candidates' fits run
        ``select_iterations`` Adam steps at rate ``select_lr`` on images of longest side
        ``select_image_size`` with ``select_spp`` samples per pixel.
    select_z, select_min_gain : the paired test every selection on the held-out views shares.
    """

    select_material: bool = False
    select_material_under_imaging: bool = True
    stop_on_plateau: bool = False
    holdout_every: int = 8
    select_iterations: int = 150
    select_lr: float = 0.05
    select_image_size: int = 128
    select_spp: int = 4
    select_z: float = 2.0
    select_min_gain: float = 0.005

    def __post_init__(self):
        _at_least_one(self, "select_image_size", "select_spp")
        if int(self.holdout_every) < 2:
            raise ValueError(f"holdout_every must be >= 2, got {self.holdout_every}")
        if int(self.select_iterations) < 0:
            raise ValueError(f"select_iterations must be >= 0, got {self.select_iterations}")
        _positive(self, "select_lr", "select_z")
        if self.select_min_gain < 0:
            raise ValueError(f"select_min_gain must be >= 0, got {self.select_min_gain}")


@dataclass(frozen=True)
class CameraSettings:
    """Cameras refined by the renderer (:mod:`recon.optimize.camera_refine`, issue 17).

    refine : "off", "on" (refine every training view's pose and the shared intrinsics with the
        surface) or "select" (run the optimization without and with the refinement and keep the
        refined one only when the held-out error drops by more than ``select.select_z`` standard
        errors and ``select.select_min_gain``, after each run's held-out poses were aligned to
        its fixed model for ``align_iterations`` steps, the same for both).
    refine_given : cameras the capture gave (``poses.json`` source "given", or no record of the
        source) are exact by contract and never refined unless this is set.
    intrinsics : refine the shared focal length and principal point too.
    sigma_rotation_deg (degrees), sigma_translation (fraction of the scene size, the mean
        distance of the cameras from their centroid), sigma_focal (relative), sigma_principal
        (fraction of the image size) : standard deviations of the Gaussian prior (its weight:
        ``loss.w_camera``).
    lr_rotation_deg, lr_translation (fraction of the scene size), lr_focal (log focal),
        lr_principal : Adam rates per step; they follow the stage's ``lr_scale`` and ``lr_decay``
        like the other rates.
    align_iterations : steps of the held-out poses' alignment.
    first_stage : the cameras are held through the coarse-to-fine stages before this one and
        stepped from it on (0: every stage; 1 keeps the coarsest surface's shape errors out of
        the cameras: better for cameras good to a few tenths of a pixel, worse for errors of a
        degree, docs/camera_refine.md; "auto": for JPEG/PNG photos the first stage rendered
        under the loop's imaging terms, ``imaging.loop_stage`` + 1, when ``imaging.loop`` is on
        and there are held-out views to choose them (before a phone's auto-exposure and tone
        curve are modelled the refinement explains a view's exposure by its distance, the flash
        being at the lens), else 0).
    """

    refine: str = "select"
    refine_given: bool = False
    intrinsics: bool = True
    sigma_rotation_deg: float = CameraPrior.sigma_rotation_deg
    sigma_translation: float = CameraPrior.sigma_translation
    sigma_focal: float = CameraPrior.sigma_focal
    sigma_principal: float = CameraPrior.sigma_principal
    lr_rotation_deg: float = CameraPrior.lr_rotation_deg
    lr_translation: float = CameraPrior.lr_translation
    lr_focal: float = CameraPrior.lr_focal
    lr_principal: float = CameraPrior.lr_principal
    align_iterations: int = 40
    first_stage: int | str = "auto"

    def __post_init__(self):
        _one_of(self, "refine", CAMERA_MODES)
        if int(self.align_iterations) < 0:
            raise ValueError(f"align_iterations must be >= 0, got {self.align_iterations}")
        if self.first_stage != "auto" and not (
                isinstance(self.first_stage, int) and not isinstance(self.first_stage, bool)
                and self.first_stage >= 0):
            raise ValueError(f"first_stage must be \"auto\" or an integer >= 0, got {self.first_stage!r}")
        self.prior()  # validates the prior's values

    def prior(self) -> CameraPrior:
        """The prior's widths and the learning rates."""
        try:
            return CameraPrior(**{f.name: getattr(self, f.name) for f in dataclasses.fields(CameraPrior)})
        except ValueError as e:
            raise ValueError(str(e).replace("camera prior ", "")) from None


@dataclass(frozen=True)
class ImagingModelSettings:
    """The camera's imaging (:mod:`recon.optimize.formation`, DESIGN section 7; chosen in
    :mod:`recon.optimize.imaging_select`).

    select_imaging : after the material model, on the same held-out views, try the ``terms``
        and keep each only where it pays off the same way (``select.select_z``), with
        ``min_gain`` as the smallest relative gain.
    terms : a subset of flash_offset, exposure, ambient, falloff, tone; ``tone`` is tried only
        for JPEG/PNG captures.
    flash_offset : the flash's known position in camera coordinates (cameras.json units), used
        in every fit instead of fitting it.
    tone_curve : "auto" reads the linearize stage's linear.json beside the views; "fit" /
        "identity" force it.
    loop : "select": the same selection runs on the mesh of stage ``loop_stage`` (the coarse
        model) and the later stages optimize the shape under the chosen terms (the flash offset
        and ambient light fixed in the renderer; exposure gains, falloff and tone curve refined
        with the shape at Adam rate ``loop_lr``, 0: fixed), so the geometry is no longer fitted
        to photos the ideal formation cannot explain. "off": the ideal formation in the loop
        (terms, if any, only after it).
    min_gain : the imaging terms' smallest relative held-out gain (config/README.md).
    """

    select_imaging: bool = False
    terms: tuple = ("flash_offset", "exposure", "ambient", "falloff", "tone")
    flash_offset: tuple | None = None
    tone_curve: str = "auto"
    loop: str = "off"
    loop_stage: int = 0
    loop_lr: float = 0.01
    min_gain: float = 0.015

    def __post_init__(self):
        object.__setattr__(self, "terms", tuple(self.terms))
        from recon.optimize.formation import TERMS as IMAGING_TERMS

        if set(self.terms) - set(IMAGING_TERMS):
            raise ValueError(f"terms must be a subset of {IMAGING_TERMS}, got {self.terms!r}")
        if self.flash_offset is not None:
            off = tuple(float(x) for x in self.flash_offset)
            if len(off) != 3 or not np.all(np.isfinite(off)):
                raise ValueError(f"flash_offset must be 3 finite numbers (camera coordinates), got {self.flash_offset!r}")
            object.__setattr__(self, "flash_offset", off)
        if self.tone_curve not in ("auto", "fit", "identity"):
            raise ValueError(f"tone_curve must be 'auto', 'fit' or 'identity', got {self.tone_curve!r}")
        if self.loop not in ("off", "select"):
            raise ValueError(f"loop must be 'off' or 'select', got {self.loop!r}")
        if not (isinstance(self.loop_stage, int) and self.loop_stage >= 0):
            raise ValueError(f"loop_stage must be an integer >= 0, got {self.loop_stage!r}")
        if not (np.isfinite(self.loop_lr) and self.loop_lr >= 0):
            raise ValueError(f"loop_lr must be a finite number >= 0, got {self.loop_lr!r}")


RECORDED_ORDER = (
    "resolution", "spp", "boundary", "variant", "views_per_iteration", "stages", "seed", "checkpoint_every",
    "coarse_to_fine", "min_edge_pixels", "optimizer", "lr_geometry", "lr_texture", "largesteps_lambda",
    "largesteps_reference_edge", "largesteps_uniform_adam", "betas", "w_render", "w_laplacian", "w_edge",
    "w_normal", "w_specular", "w_roughness", "laplacian", "tone_map", "bilateral_sigma_space",
    "bilateral_sigma_color", "bilateral_radius", "use_laplacian", "use_normal_edge", "use_material_priors",
    "light_scale", "collapse_min_covered", "collapse_min_area", "init_diffuse", "init_specular",
    "init_roughness", "specular_channels", "r_min", "parameterization", "texture_levels", "guard",
    "guard_max_halvings", "select_material", "select_material_under_imaging", "stop_on_plateau",
    "holdout_every", "select_iterations", "select_lr", "select_image_size", "select_spp", "select_z",
    "select_min_gain", "refine_cameras", "refine_given_cameras", "camera_intrinsics", "w_camera",
    "camera_sigma_rotation_deg", "camera_sigma_translation", "camera_sigma_focal", "camera_sigma_principal",
    "camera_lr_rotation_deg", "camera_lr_translation", "camera_lr_focal", "camera_lr_principal",
    "camera_align_iterations", "camera_first_stage", "select_imaging", "imaging_terms", "flash_offset",
    "tone_curve", "imaging_loop", "imaging_loop_stage", "imaging_loop_lr", "imaging_min_gain", "w_imaging",
    "uncertain_foot", "uncertain_foot_weight", "uncertain_foot_mode")
"""The flat names of :meth:`OptimizeSettings.to_dict`, in its order: the fields of the flat class
before the sections (settings added later follow, in their sections' order)."""


@sectioned
@dataclass(frozen=True)
class OptimizeSettings:
    """Everything the optimize stage needs beyond its input files (module docstring; each
    section's docstring has its keys).

    stages : the coarse-to-fine stages (:class:`StageSettings`), coarse to fine.
    seed : seeds the views of each iteration and the renderer's samples
        (:func:`recon.optimize.checkpoint.iteration_rng`, :func:`~recon.optimize.checkpoint.render_seed`).
    variant : the Mitsuba variant, None = :func:`recon.mi.default_variant`'s (a Snakemake job
        given a GPU sets ``cuda_ad_rgb``, :func:`recon.config.job_settings`).
    """

    MOVED = {
        "light_scale": "light.scale",
        "refine_cameras": "cameras.refine",
        "refine_given_cameras": "cameras.refine_given",
        "camera_intrinsics": "cameras.intrinsics",
        "camera_sigma_rotation_deg": "cameras.sigma_rotation_deg",
        "camera_sigma_translation": "cameras.sigma_translation",
        "camera_sigma_focal": "cameras.sigma_focal",
        "camera_sigma_principal": "cameras.sigma_principal",
        "camera_lr_rotation_deg": "cameras.lr_rotation_deg",
        "camera_lr_translation": "cameras.lr_translation",
        "camera_lr_focal": "cameras.lr_focal",
        "camera_lr_principal": "cameras.lr_principal",
        "camera_align_iterations": "cameras.align_iterations",
        "camera_first_stage": "cameras.first_stage",
        "imaging_terms": "imaging.terms",
        "imaging_loop": "imaging.loop",
        "imaging_loop_stage": "imaging.loop_stage",
        "imaging_loop_lr": "imaging.loop_lr",
        "imaging_min_gain": "imaging.min_gain",
    }
    """The keys renamed into their sections (old flat name -> dotted place); every other flat key
    keeps its name in its section (:func:`recon.sections.leaf_paths`)."""

    stages: tuple = field(default_factory=_default_stages)
    seed: int = 0
    variant: str | None = None
    render: RenderingSettings = field(default_factory=RenderingSettings)
    schedule: ScheduleSettings = field(default_factory=ScheduleSettings)
    optim: OptimSettings = field(default_factory=OptimSettings)
    loss: LossSettings = field(default_factory=LossSettings)
    light: LightSettings = field(default_factory=LightSettings)
    material: MaterialSettings = field(default_factory=MaterialSettings)
    select: SelectSettings = field(default_factory=SelectSettings)
    cameras: CameraSettings = field(default_factory=CameraSettings)
    imaging: ImagingModelSettings = field(default_factory=ImagingModelSettings)

    def __post_init__(self):
        stages = tuple(
            s if isinstance(s, StageSettings) else build_settings(StageSettings, s, "optimize.stages")
            for s in (self.stages or ())
        )
        if not stages:
            raise ValueError("stages must list at least one stage")
        object.__setattr__(self, "stages", stages)

    # ---- derived ----
    def effective_stages(self) -> tuple[StageSettings, ...]:
        """The stages actually run: all of them, or (ablation) one with the last stage's sizes."""
        if self.schedule.coarse_to_fine or len(self.stages) == 1:
            return self.stages
        last = self.stages[-1]
        total = sum(int(s.iterations) for s in self.stages)
        return (dataclasses.replace(last, iterations=total),)

    def stage_image_size(self, stage: StageSettings) -> int:
        return int(stage.image_size) or int(self.render.resolution)

    @property
    def holds_out(self) -> bool:
        """Whether views are held out of the optimization (for selection or the plateau test)."""
        return bool(self.select.select_material or self.select.stop_on_plateau or self.imaging.select_imaging
                    or self.imaging.loop != "off")

    def imaging_selection_settings(self):
        """The selection settings of the imaging terms: those of the material selection with
        ``imaging.min_gain`` as the smallest relative gain (see config/README.md)."""
        return dataclasses.replace(self.selection_settings(), min_gain=float(self.imaging.min_gain))

    def selection_settings(self):
        sel, mat, loss = self.select, self.material, self.loss
        return SelectionSettings(
            iterations=int(sel.select_iterations), lr=float(sel.select_lr), z=float(sel.select_z),
            min_gain=float(sel.select_min_gain), tone_map=loss.tone_map, r_min=float(mat.r_min),
            parameterization=mat.parameterization, texture_levels=int(mat.texture_levels),
            w_specular=objective.weights(self)["specular"],
            w_roughness=objective.weights(self)["roughness"],
            bilateral_sigma_space=loss.bilateral_sigma_space, bilateral_sigma_color=loss.bilateral_sigma_color,
            bilateral_radius=int(loss.bilateral_radius))

    def camera_prior(self) -> CameraPrior:
        """The camera refinement's prior widths and learning rates (:meth:`CameraSettings.prior`)."""
        return self.cameras.prior()

    def camera_start(self, n_stages: int, imaging_in_loop: bool) -> int:
        """The coarse-to-fine stage the cameras are refined from (``cameras.first_stage``):
        ``imaging_in_loop``: the loop's imaging selection will run (``imaging.loop`` on, held-out
        views) on photos it is needed for (JPEG/PNG); with "auto" the cameras then wait for its
        terms, if a later stage renders under them."""
        if self.cameras.first_stage != "auto":
            return int(self.cameras.first_stage)
        after = int(self.imaging.loop_stage) + 1
        return after if imaging_in_loop and after < int(n_stages) else 0

    def camera_mode(self, source: str | None) -> tuple[str, str]:
        """("off" | "on" | "select", why) for cameras from ``source`` ("sfm", "given" or None =
        unknown, taken as given)."""
        refine = self.cameras.refine
        if refine == "off":
            return "off", "cameras.refine: off"
        if source != "sfm" and not self.cameras.refine_given:
            return "off", (f"the cameras were given ({source or 'no poses.json beside cameras.json'}): exact by "
                           "contract (cameras.refine_given: false)")
        return refine, f"cameras.refine: {refine} (cameras from {source or 'unknown'})"

    def weights(self) -> dict[str, float]:
        """Loss weights after the ablation switches (:func:`recon.optimize.objective.weights`)."""
        return objective.weights(self)

    def to_dict(self) -> dict:
        """The settings flat, under their names before the sections, in :data:`RECORDED_ORDER`
        (lists for tuples, the stages as mappings): what ``optimize/summary.json`` records and the
        checkpoints' fingerprint hashes, so both read as before the sections.
        :func:`settings_from_record` builds the settings back."""
        paths = leaf_paths(OptimizeSettings)
        names = list(RECORDED_ORDER)
        recorded = {paths.get(name, name) for name in names}
        names += [name for name in flatten(self) if paths.get(name, name) not in recorded]  # added later
        d = {}
        for name in names:
            value = get_path(self, paths.get(name, name))
            if name == "stages":
                value = [dataclasses.asdict(s) for s in value]
            elif isinstance(value, tuple):
                value = list(value)
            d[name] = value
        return d


def settings_from_dict(values: dict | None, source: str = "optimize settings") -> OptimizeSettings:
    """Build :class:`OptimizeSettings` from a preset/capture.yaml section (unknown keys rejected;
    a flat key from before the sections moved to its place with a warning)."""
    try:
        return build_settings(OptimizeSettings, values, source)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:  # raised while building the nested stages
        raise ConfigError(f"{source}: invalid optimize settings ({e})") from e


def settings_from_record(record: dict, source: str = "optimize settings record") -> OptimizeSettings:
    """Build :class:`OptimizeSettings` from :meth:`~OptimizeSettings.to_dict`'s flat record (a
    summary.json's ``settings``, older ones too) without the flat keys' warnings."""
    values, _ = move_flat(OptimizeSettings, record)
    return settings_from_dict(values, source)
