"""Settings of the optimize stage: one frozen dataclass, built from a preset's ``optimize:`` section.

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

OPTIMIZERS = ("largesteps", "adam")
BOUNDARIES = ("edge", "none", "projective")
LAPLACIANS = ("uniform", "cotangent")
TONE_MAPS = ("log", "srgb", "linear")
PARAMETERIZATIONS = ("sigmoid", "clamp")
CAMERA_MODES = ("off", "on", "select")


@dataclass(frozen=True)
class StageSettings:
    """One coarse-to-fine stage: mesh topology and texture size stay fixed within it.

    edge_length : target edge length of the remeshed surface, as a fraction of the bounding box's
        longest side (the paper's "upsample the mesh" step, sec. 3.4).
    texture_size : side of the square texture maps (texels).
    iterations : optimizer steps in this stage.
    image_size : longest image side (pixels) the photos are downsampled to; 0 = ``resolution``.
    lr_scale : multiplies every learning rate in this stage (finer stages often take smaller steps).
    lr_decay : the learning rates fall exponentially within the stage, to ``lr_decay`` times their
        start at its last iteration (1 = constant).
    lambda_scale : multiplies ``largesteps_lambda`` in this stage, on top of the automatic
        ``(largesteps_reference_edge / edge_length)^2`` of stages finer than the reference.
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


@dataclass(frozen=True)
class OptimizeSettings:
    """Everything the optimize stage needs beyond its input files.

    Rendering: ``resolution`` (longest image side in pixels, per stage overridable), ``spp``,
    ``boundary`` (the renderer's silhouette term: "edge", "projective", or "none" = ablation),
    ``variant`` (Mitsuba variant, None = recon.mi's default).

    Schedule: ``stages`` (coarse to fine), ``views_per_iteration``, ``seed``,
    ``checkpoint_every`` (iterations), ``coarse_to_fine`` (False = ablation: one stage with the
    last stage's mesh/texture size and all iterations), ``min_edge_pixels``: no stage remeshes
    finer than this many pixel footprints (median over the views of depth / focal length at the
    object's center, at the stage's image size), whatever its ``edge_length``; finer triangles
    are not constrained by the photos and fit their noise (0 = no limit).

    Optimizer: ``optimizer`` "largesteps" (Nicolet et al. 2021: vertex positions through
    u = (I + lambda L) v, L the combinatorial Laplacian, and Adam on u) or "adam" (the paper:
    plain Adam on v with the Laplacian regularizer); ``lr_geometry`` (relative to the bbox's
    longest side), ``lr_texture`` (in parameter units), ``largesteps_lambda``,
    ``largesteps_reference_edge`` (fraction of the bbox; a stage whose edges h are shorter than
    it multiplies lambda by (reference / h)^2: the preconditioner smooths over about sqrt(lambda)
    edges, so this keeps its smoothing length on the surface as the mesh is refined; 0 = the
    same lambda in every stage),
    ``largesteps_uniform_adam`` (Nicolet's AdamUniform for u instead of Adam), ``betas``.

    Loss (the paper's eq. 6 and sec. 3.3; each term normalized as documented in
    :mod:`recon.optimize.regularizers`): ``w_render``, ``w_laplacian``, ``w_edge``, ``w_normal``,
    ``w_specular``, ``w_roughness``; ``laplacian`` "uniform" or "cotangent"; ``tone_map``
    (Phi: "log" = log(1 + x/s) with s the median foreground target value, "srgb", "linear");
    ``bilateral_sigma_space`` (texels), ``bilateral_sigma_color``, ``bilateral_radius``.
    Ablation switches: ``use_laplacian``, ``use_normal_edge``, ``use_material_priors``.

    The flash's scale (:mod:`recon.optimize.radiometry`): ``light_scale`` "auto" uses the
    light intensity ``cameras.json`` states and estimates it from the photos when it states none
    (after SfM); "estimate" always estimates it; "given" requires it. An estimated I_e makes the
    albedo relative (its convention in the radiometry module) and sets the initial diffuse map
    from the photos. A run whose surface covers less than ``collapse_min_covered`` of the masks,
    or whose area falls below ``collapse_min_area`` of the initial mesh's, stops (collapse).

    Materials: ``init_diffuse``, ``init_specular``, ``init_roughness`` (constant initial maps,
    as in the paper; the diffuse one only when the flash's intensity is given), ``specular_channels`` (1 or 3), ``r_min``, ``parameterization``
    ("sigmoid": value = sigmoid(logit), roughness = r_min + (1 - r_min) sigmoid; "clamp": the
    value itself, projected back into range after each step), ``texture_levels`` (each raw map
    is a sum of this many levels, full size, 1/2, 1/4, ...: coarse levels learn low-frequency
    content from all the texels they cover; 1 = a plain texel map).

    Robust surface evolution: ``guard`` (reject self-intersections by halving the displacement
    of the offending vertices), ``guard_max_halvings``.

    Model only what the scene requires (:mod:`recon.optimize.material`): with ``select_material``
    or ``stop_on_plateau`` every ``holdout_every``-th view is held out of the optimization
    (at least 2 views, and only when at least 4 remain for it). ``select_material``: after the
    last stage, fit material models of increasing complexity on the fixed final mesh and keep a
    richer one only when the held-out error drops by more than ``select_z`` standard errors
    and ``select_min_gain`` (relative); fits run ``select_iterations`` Adam steps at rate
    ``select_lr`` on images of longest side ``select_image_size`` with ``select_spp`` samples
    per pixel; ``select_material_under_imaging`` (default true): when the loop ran under a
    phone's imaging terms (``imaging_loop``), fit and compare the candidates under them, with the
    held-out views' own exposure gains (false: under the ideal formation, the maps refitted under
    the terms after). ``stop_on_plateau``: after each coarse-to-fine stage, measure the held-out error
    and skip the remaining stages when it did not improve on the previous stage's by more than
    its noise (same test).

    Cameras refined by the renderer (:mod:`recon.optimize.camera_refine`, issue 17):
    ``refine_cameras`` "off", "on" (refine every training view's pose and the shared
    intrinsics with the surface) or "select" (run the optimization without and with the
    refinement and keep the refined one only when the held-out error drops by more than
    ``select_z`` standard errors and ``select_min_gain``, after each run's held-out poses were
    aligned to its fixed model for ``camera_align_iterations`` steps, the same for both).
    Cameras the capture gave (``poses.json`` source "given", or no record of the source) are
    exact by contract and never refined unless ``refine_given_cameras``. ``camera_intrinsics``:
    refine the shared focal length and principal point too. Prior (Gaussian, weight
    ``w_camera`` in the objective, per view in the batch): standard deviations
    ``camera_sigma_rotation_deg`` (degrees), ``camera_sigma_translation`` (fraction of the
    scene size, the mean distance of the cameras from their centroid), ``camera_sigma_focal``
    (relative), ``camera_sigma_principal`` (fraction of the image size). Adam rates per step:
    ``camera_lr_rotation_deg``, ``camera_lr_translation`` (fraction of the scene size),
    ``camera_lr_focal`` (log focal), ``camera_lr_principal``; they follow the stage's
    ``lr_scale`` and ``lr_decay`` like the other rates. ``camera_first_stage``: the cameras are
    held through the coarse-to-fine stages before this one and stepped from it on (0: every
    stage; 1 keeps the coarsest surface's shape errors out of the cameras: better for cameras
    good to a few tenths of a pixel, worse for errors of a degree, docs/camera_refine.md;
    "auto": for JPEG/PNG photos the first stage rendered under the loop's imaging terms,
    ``imaging_loop_stage`` + 1, when ``imaging_loop`` is on and there are held-out views to
    choose them (before a phone's auto-exposure and tone curve are modelled the refinement
    explains a view's exposure by its distance, the flash being at the lens), else 0).
    The camera's imaging (:mod:`recon.optimize.formation`, DESIGN section 7; chosen in
    :mod:`recon.optimize.imaging_select`): ``select_imaging``
    (after the material model, on the same held-out views) tries the terms of ``imaging_terms``
    (flash_offset, exposure, ambient, falloff, tone) and keeps each only where it pays off the
    same way; ``tone`` is tried only for JPEG/PNG captures (``tone_curve: auto`` reads the
    linearize stage's linear.json beside the views; ``fit`` / ``identity`` force it).
    ``flash_offset``: the flash's known position in camera coordinates (cameras.json units),
    used in every fit instead of fitting it.
    ``imaging_loop: select``: the same selection runs on the mesh of stage ``imaging_loop_stage``
    (the coarse model) and the later stages optimize the shape under the chosen terms (the flash
    offset and ambient light fixed in the renderer; exposure gains, falloff and tone curve
    refined with the shape at Adam rate ``imaging_loop_lr``, 0: fixed), so the geometry is no
    longer fitted to photos the ideal formation cannot explain. ``off``: the ideal formation in
    the loop (terms, if any, only after it).
    """

    resolution: int = 256
    spp: int = 4
    boundary: str = "edge"
    variant: str | None = None
    views_per_iteration: int = 4
    stages: tuple = field(default_factory=_default_stages)
    seed: int = 0
    checkpoint_every: int = 50
    coarse_to_fine: bool = True
    min_edge_pixels: float = 2.5
    optimizer: str = "largesteps"
    lr_geometry: float = 0.005
    lr_texture: float = 0.03
    largesteps_lambda: float = 2.0
    largesteps_reference_edge: float = 0.025
    largesteps_uniform_adam: bool = False
    betas: tuple = (0.9, 0.999)
    w_render: float = 1.0
    w_laplacian: float = 0.1
    w_edge: float = 1.0
    w_normal: float = 0.01
    w_specular: float = 0.01
    w_roughness: float = 0.001
    laplacian: str = "uniform"
    tone_map: str = "log"
    bilateral_sigma_space: float = 1.0
    bilateral_sigma_color: float = 0.1
    bilateral_radius: int = 2
    use_laplacian: bool = True
    use_normal_edge: bool = True
    use_material_priors: bool = True
    light_scale: str = "auto"
    collapse_min_covered: float = 0.3
    collapse_min_area: float = 0.1
    init_diffuse: float = 0.3
    init_specular: float = 0.1
    init_roughness: float = 0.4
    specular_channels: int = 1
    r_min: float = 0.02
    parameterization: str = "sigmoid"
    texture_levels: int = 4
    guard: bool = True
    guard_max_halvings: int = 8
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
    refine_cameras: str = "select"
    refine_given_cameras: bool = False
    camera_intrinsics: bool = True
    w_camera: float = 0.001
    camera_sigma_rotation_deg: float = 0.5
    camera_sigma_translation: float = 0.01
    camera_sigma_focal: float = 0.02
    camera_sigma_principal: float = 0.01
    camera_lr_rotation_deg: float = 0.02
    camera_lr_translation: float = 0.0005
    camera_lr_focal: float = 0.0005
    camera_lr_principal: float = 0.0002
    camera_align_iterations: int = 40
    camera_first_stage: int | str = "auto"
    select_imaging: bool = False
    imaging_terms: tuple = ("flash_offset", "exposure", "ambient", "falloff", "tone")
    flash_offset: tuple | None = None
    tone_curve: str = "auto"
    imaging_loop: str = "off"
    imaging_loop_stage: int = 0
    imaging_loop_lr: float = 0.01
    imaging_min_gain: float = 0.015
    w_imaging: float = 0.001

    def __post_init__(self):
        stages = tuple(
            s if isinstance(s, StageSettings) else build_settings(StageSettings, s, "optimize.stages")
            for s in (self.stages or ())
        )
        if not stages:
            raise ValueError("stages must list at least one stage")
        object.__setattr__(self, "stages", stages)
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        object.__setattr__(self, "imaging_terms", tuple(self.imaging_terms))
        from recon.optimize.formation import TERMS as IMAGING_TERMS

        if set(self.imaging_terms) - set(IMAGING_TERMS):
            raise ValueError(f"imaging_terms must be a subset of {IMAGING_TERMS}, got {self.imaging_terms!r}")
        if self.flash_offset is not None:
            off = tuple(float(x) for x in self.flash_offset)
            if len(off) != 3 or not np.all(np.isfinite(off)):
                raise ValueError(f"flash_offset must be 3 finite numbers (camera coordinates), got {self.flash_offset!r}")
            object.__setattr__(self, "flash_offset", off)
        if self.tone_curve not in ("auto", "fit", "identity"):
            raise ValueError(f"tone_curve must be 'auto', 'fit' or 'identity', got {self.tone_curve!r}")
        if self.imaging_loop not in ("off", "select"):
            raise ValueError(f"imaging_loop must be 'off' or 'select', got {self.imaging_loop!r}")
        if not (isinstance(self.imaging_loop_stage, int) and self.imaging_loop_stage >= 0):
            raise ValueError(f"imaging_loop_stage must be an integer >= 0, got {self.imaging_loop_stage!r}")
        if not (np.isfinite(self.imaging_loop_lr) and self.imaging_loop_lr >= 0):
            raise ValueError(f"imaging_loop_lr must be a finite number >= 0, got {self.imaging_loop_lr!r}")
        choices = {
            "optimizer": OPTIMIZERS,
            "boundary": BOUNDARIES,
            "laplacian": LAPLACIANS,
            "tone_map": TONE_MAPS,
            "parameterization": PARAMETERIZATIONS,
            "light_scale": ("auto", "estimate", "given"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        for name in ("resolution", "spp", "views_per_iteration", "checkpoint_every", "select_image_size", "select_spp"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (0 <= self.largesteps_reference_edge < 1):
            raise ValueError(f"largesteps_reference_edge must be in [0, 1) (fraction of the bbox; 0 = off), "
                             f"got {self.largesteps_reference_edge}")
        if not self.min_edge_pixels >= 0:
            raise ValueError(f"min_edge_pixels must be >= 0, got {self.min_edge_pixels}")
        if int(self.texture_levels) < 1:
            raise ValueError(f"texture_levels must be >= 1, got {self.texture_levels}")
        if self.specular_channels not in (1, 3):
            raise ValueError(f"specular_channels must be 1 or 3, got {self.specular_channels}")
        if not (0 < self.r_min < 1):
            raise ValueError(f"r_min must be in (0, 1), got {self.r_min}")
        if not (0 <= self.collapse_min_covered < 1 and 0 <= self.collapse_min_area < 1):
            raise ValueError("collapse_min_covered and collapse_min_area must be in [0, 1), got "
                             f"{self.collapse_min_covered} and {self.collapse_min_area}")
        for name in ("init_diffuse", "init_specular"):
            if not (0 <= getattr(self, name) <= 1):
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not (self.r_min <= self.init_roughness <= 1):
            raise ValueError(f"init_roughness must be in [r_min, 1], got {self.init_roughness}")
        for name in ("lr_geometry", "lr_texture", "largesteps_lambda", "w_render"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if int(self.holdout_every) < 2:
            raise ValueError(f"holdout_every must be >= 2, got {self.holdout_every}")
        if int(self.select_iterations) < 0:
            raise ValueError(f"select_iterations must be >= 0, got {self.select_iterations}")
        for name in ("select_lr", "select_z"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.select_min_gain < 0:
            raise ValueError(f"select_min_gain must be >= 0, got {self.select_min_gain}")
        if self.refine_cameras not in CAMERA_MODES:
            raise ValueError(f"refine_cameras must be one of {CAMERA_MODES}, got {self.refine_cameras!r}")
        if int(self.camera_align_iterations) < 0:
            raise ValueError(f"camera_align_iterations must be >= 0, got {self.camera_align_iterations}")
        if self.camera_first_stage != "auto" and not (
                isinstance(self.camera_first_stage, int) and not isinstance(self.camera_first_stage, bool)
                and self.camera_first_stage >= 0):
            raise ValueError(f"camera_first_stage must be \"auto\" or an integer >= 0, got {self.camera_first_stage!r}")
        self.camera_prior()  # validates the camera prior's values
        for name in ("w_laplacian", "w_edge", "w_normal", "w_specular", "w_roughness", "w_camera"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    # ---- derived ----
    def effective_stages(self) -> tuple[StageSettings, ...]:
        """The stages actually run: all of them, or (ablation) one with the last stage's sizes."""
        if self.coarse_to_fine or len(self.stages) == 1:
            return self.stages
        last = self.stages[-1]
        total = sum(int(s.iterations) for s in self.stages)
        return (dataclasses.replace(last, iterations=total),)

    def stage_image_size(self, stage: StageSettings) -> int:
        return int(stage.image_size) or int(self.resolution)

    @property
    def holds_out(self) -> bool:
        """Whether views are held out of the optimization (for selection or the plateau test)."""
        return bool(self.select_material or self.stop_on_plateau or self.select_imaging or self.imaging_loop != "off")

    def imaging_selection_settings(self):
        """The selection settings of the imaging terms: those of the material selection with
        ``imaging_min_gain`` as the smallest relative gain (see config/README.md)."""
        return dataclasses.replace(self.selection_settings(), min_gain=float(self.imaging_min_gain))

    def selection_settings(self):
        return SelectionSettings(
            iterations=int(self.select_iterations), lr=float(self.select_lr), z=float(self.select_z),
            min_gain=float(self.select_min_gain), tone_map=self.tone_map, r_min=float(self.r_min),
            parameterization=self.parameterization, texture_levels=int(self.texture_levels),
            w_specular=objective.weights(self)["specular"],
            w_roughness=objective.weights(self)["roughness"],
            bilateral_sigma_space=self.bilateral_sigma_space, bilateral_sigma_color=self.bilateral_sigma_color,
            bilateral_radius=int(self.bilateral_radius))

    def camera_prior(self) -> CameraPrior:
        """The camera refinement's prior widths and learning rates."""
        try:
            return CameraPrior(
                sigma_rotation_deg=self.camera_sigma_rotation_deg, sigma_translation=self.camera_sigma_translation,
                sigma_focal=self.camera_sigma_focal, sigma_principal=self.camera_sigma_principal,
                lr_rotation_deg=self.camera_lr_rotation_deg, lr_translation=self.camera_lr_translation,
                lr_focal=self.camera_lr_focal, lr_principal=self.camera_lr_principal)
        except ValueError as e:
            raise ValueError(str(e).replace("camera prior ", "camera_")) from None

    def camera_start(self, n_stages: int, imaging_in_loop: bool) -> int:
        """The coarse-to-fine stage the cameras are refined from (``camera_first_stage``):
        ``imaging_in_loop``: the loop's imaging selection will run (``imaging_loop`` on, held-out
        views) on photos it is needed for (JPEG/PNG); with "auto" the cameras then wait for its
        terms, if a later stage renders under them."""
        if self.camera_first_stage != "auto":
            return int(self.camera_first_stage)
        after = int(self.imaging_loop_stage) + 1
        return after if imaging_in_loop and after < int(n_stages) else 0

    def camera_mode(self, source: str | None) -> tuple[str, str]:
        """("off" | "on" | "select", why) for cameras from ``source`` ("sfm", "given" or None =
        unknown, taken as given)."""
        if self.refine_cameras == "off":
            return "off", "refine_cameras: off"
        if source != "sfm" and not self.refine_given_cameras:
            return "off", (f"the cameras were given ({source or 'no poses.json beside cameras.json'}): exact by "
                           "contract (refine_given_cameras: false)")
        return self.refine_cameras, f"refine_cameras: {self.refine_cameras} (cameras from {source or 'unknown'})"

    def weights(self) -> dict[str, float]:
        """Loss weights after the ablation switches (:func:`recon.optimize.objective.weights`)."""
        return objective.weights(self)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["stages"] = [dataclasses.asdict(s) for s in self.stages]
        d["betas"] = list(self.betas)
        d["imaging_terms"] = list(self.imaging_terms)
        d["flash_offset"] = None if self.flash_offset is None else list(self.flash_offset)
        return d


def settings_from_dict(values: dict | None, source: str = "optimize settings") -> OptimizeSettings:
    """Build :class:`OptimizeSettings` from a preset/capture.yaml section (unknown keys rejected)."""
    try:
        return build_settings(OptimizeSettings, values, source)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:  # raised while building the nested stages
        raise ConfigError(f"{source}: invalid optimize settings ({e})") from e
