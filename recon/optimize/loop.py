"""The optimize stage: coarse-to-fine analysis by synthesis of shape and SVBRDF (sec. 3.2-3.4).

Per iteration: sample views (deterministically from (seed, stage, iteration)), render them with
the current mesh and maps, compare after the tone map Phi (eq. 6), add the sec. 3.3 priors,
backpropagate, take an Adam step, and pass the new vertex positions through the surface guard
(no new self-intersections, folds or degenerate faces). Between stages: remesh, re-unwrap, bake
the maps onto the new atlas (:mod:`recon.optimize.remesh`).

Timings are kept per phase, as in the paper's supplement: ``render`` (forward rendering),
``loss`` (rendering loss and priors), ``backward`` (backpropagation through both),
``step`` (optimizer), ``geometry`` (large-steps solves, waiting for and acting on the surface
guard, remeshing, unwrapping and baking), ``setup`` (building renderers and targets for a
stage, writing checkpoints), ``material`` (material selection, plateau tests), ``cameras``
(aligning the held-out views' poses to the fitted model). The guard's self-intersection test
runs in a worker thread while the next iteration renders; its CPU time is reported apart
(``guard_check_seconds``).

Cameras refined by the renderer (issue 17, :mod:`recon.optimize.camera_refine`): with
``refine_cameras`` on (cameras from SfM) every training view's pose and the shared intrinsics
are parameters of the same objective (their prior is its ``camera`` term), stepped by their own
Adam after the surface's, the similarity gauge projected out after each step. With "select"
the run is made twice, without (the control) and with the refinement, from the same start and
seeds; each run's held-out poses are then aligned to its fixed final model for the same number
of steps (their SfM errors would otherwise blur both), and the refined run is kept only when
its held-out error is lower by more than the noise (:func:`recon.optimize.material.compare`).
``optimize/cameras.json`` holds the cameras the final model goes with: the refined training
views, the aligned held-out views, the input cameras otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from recon.io.atomic import atomic_path
from recon.io.cameras import Camera, CameraSet, load_cameras, save_cameras
from recon.io.images import write_exr
from recon.io.mesh import Mesh, read_mesh, write_obj
from recon.optimize import checkpoint as ckpt
from recon.optimize import objective
from recon.optimize.camera_refine import CameraRefinement, scene_extent
from recon.optimize import regularizers as reg
from recon.optimize.radiometry import (ESTIMATE_SIZE, CollapseError, LightScale, LightScaleError,
                                       check_not_collapsed, clipped_fraction, estimate_light_scale, mask_coverage)
from recon.optimize.guard import SurfaceGuard, self_intersecting_faces
from recon.optimize.largesteps import AdamUniform, LargeSteps
from recon.optimize.gbuffer import build_gbuffer
from recon.optimize.formation import ImagingModel, ImagingParams
from recon.optimize.imaging import (ImagingProblem, ImagingSettings, heldout_tiles_under, material_scorer_under,
                                    refit_under)
from recon.optimize.imaging_select import run_imaging_selection, select_for_loop
from recon.optimize.loop_imaging import LoopImaging
from recon.optimize.material import compare, heldout_error, model_from_settings, select_material
from recon.optimize.tracks import TrackTerm
from recon.optimize.params import TexturePyramid, albedo_param, constant_map, roughness_param
from recon.optimize.remesh import rasterize_atlas, remesh, remesh_and_rebake, topology_report, unwrap
from recon.optimize.settings import OptimizeSettings, StageSettings
from recon.optimize.views import (Views, ViewSet, capture_is_ldr, pixel_footprint, recorded_exposures,
                                  view_exposures)
from recon.render import CollocatedRenderer, RenderSettings
from recon.support import PlaneError, SupportPlane, plane_if_found

log = logging.getLogger(__name__)

PHASES = ("render", "loss", "backward", "step", "geometry", "setup", "material", "cameras")
MAP_NAMES = ("diffuse", "specular", "roughness")
CAMERAS_FILE = "cameras.json"


class OptimizeError(ValueError):
    """Inputs the optimize stage cannot work with; the message names the file and the fix."""


@dataclass
class _Stage:
    """Everything that lives for one stage (rebuilt from a checkpoint on resume)."""

    index: int
    settings: StageSettings
    h: float  # absolute target edge length
    bbox_scale: float  # longest side of the initial mesh's bounding box
    mesh: Mesh  # connectivity + UVs; v_pos = accepted positions
    v_init: np.ndarray  # positions at the start of the stage (the guard's baseline)
    covered: np.ndarray  # (T, T) bool, texels inside the charts
    topo: reg.MeshTopology
    geom: torch.Tensor  # u (large steps) or v (adam), float64, requires grad
    maps: dict  # name -> TexturePyramid of the raw (parameterized) map
    opt_geom: torch.optim.Optimizer
    opt_tex: torch.optim.Optimizer
    ls: LargeSteps | None
    guard: SurfaceGuard | None
    renderer: object
    targets: ViewSet
    executor: object = None  # worker thread of the surface checks
    pending: object = None  # Future of the check of ``proposed``
    proposed: np.ndarray | None = None  # positions stepped to, not yet checked
    proposed_record: dict | None = None  # log record of the iteration that proposed them
    resting: np.ndarray | None = None  # (V,) bool, the base on the support plane (held on it)


@dataclass(frozen=True)
class _Run:
    """What a run knows, built once by :func:`optimize_capture`: the settings and the values
    derived from them, the views and where checkpoints go."""

    settings: OptimizeSettings
    stages: tuple  # effective StageSettings
    views: Views  # training views
    heldout: Views | None
    bbox_scale: float  # longest side of the initial mesh's bounding box
    weights: dict  # objective.weights(settings)
    tone_scale: float
    light: float  # the flash's I_e (given, or estimated from the photos: light_scale)
    ckpt_dir: Path
    fingerprint: str
    cameras: "_CameraFit | None" = None  # the camera refinement (None: the cameras are fixed)
    plane: SupportPlane | None = None  # the table the object stands on: no vertex goes below it
    imaging: LoopImaging | None = None  # imaging terms in the loop (imaging_loop: select)
    ldr: bool | None = None  # the photos were JPEG/PNG (the tone curve is tried)
    light_scale: LightScale | None = None  # where ``light`` came from; the initial diffuse albedo
    area_init: float = 0.0  # the initial mesh's area (the collapse check)
    exposure: dict | None = None  # stem -> the recorded (EXIF) exposure linearize divided out (the tone curve's domain)

    def lr_geometry(self, factor: float = 1.0) -> float:
        """Adam's geometry rate: ``lr_geometry`` is a fraction of the bounding box per step."""
        return self.settings.lr_geometry * self.bbox_scale * factor

    def lr_texture(self, factor: float = 1.0) -> float:
        return self.settings.lr_texture * factor


class _CameraFit:
    """A run's camera refinement: the training views' corrections and their optimizer, which
    live across the coarse-to-fine stages (the views are the same in every stage)."""

    def __init__(self, views: Views, settings: OptimizeSettings, first_stage: int = 0):
        self.first_stage = int(first_stage)  # the cameras are held before this stage (camera_first_stage)
        self.ref = CameraRefinement(views.cameras, settings.camera_prior(), intrinsics=settings.camera_intrinsics)
        self.opt = torch.optim.Adam(self.ref.param_groups(), betas=settings.betas)
        for g in self.opt.param_groups:
            g["base_lr"] = g["lr"]

    def step(self, factor: float) -> None:
        """Adam step at the base rates times ``factor`` (the stage's schedule), then the gauge."""
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * factor
        self.opt.step()
        self.ref.fix_gauge()

    def state(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.ref.state_dict().items()},
                "optimizer": self.opt.state_dict()}

    def load(self, state: dict) -> None:
        self.ref.load_state_dict(state["params"])
        self.opt.load_state_dict(state["optimizer"])


@dataclass
class _Progress:
    """What a run accumulates (saved in checkpoints) and reports to."""

    timer: "_Timer"
    records: list
    stage_infos: list
    executor: object = None
    bar: object = None
    callback: Callable[[dict], None] | None = None


class _Timer:
    def __init__(self):
        self.total = {p: 0.0 for p in PHASES}

    def add(self, phase: str, seconds: float) -> None:
        self.total[phase] += seconds


def _params(settings: OptimizeSettings) -> dict:
    kind = settings.parameterization
    return {
        "diffuse": albedo_param(kind),
        "specular": albedo_param(kind),
        "roughness": roughness_param(settings.r_min, kind),
    }


def _map_values(settings: OptimizeSettings, maps: dict) -> dict:
    """name -> (T, T, C) values in range, differentiable w.r.t. the pyramid levels."""
    p = _params(settings)
    return {k: p[k].value(maps[k].full()) for k in MAP_NAMES}


# ---------------------------------------------------------------------- stage set-up
def _initial_stage_mesh(init: Mesh, settings: OptimizeSettings, stage: StageSettings, h: float,
                        init_diffuse=None):
    v, f = remesh(init.v_pos, init.t_pos_idx, h)
    topo = topology_report(v, f)
    if not topo["is_mesh_two_manifold"]:
        raise OptimizeError(
            f"the initial mesh remeshed to edge length {h:.4g} is not manifold; "
            "check uv/mesh.obj (init_mesh stage) or use a larger first-stage edge_length"
        )
    T = int(stage.texture_size)
    mesh = unwrap(v, f, T)
    face, _, _ = rasterize_atlas(mesh, T)
    maps = {
        "diffuse": constant_map(T, 3, settings.init_diffuse if init_diffuse is None else init_diffuse),
        "specular": constant_map(T, settings.specular_channels, settings.init_specular),
        "roughness": constant_map(T, 1, settings.init_roughness),
    }
    return mesh, maps, face >= 0


def _make_renderer(settings: OptimizeSettings, mesh: Mesh):
    rs = RenderSettings(spp=int(settings.spp), boundary=settings.boundary, variant=settings.variant,
                        r_min=settings.r_min)
    return CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, rs)


def _build_stage(run: _Run, index, stage_settings, h, mesh, v_init, covered, map_values,
                 opt_state=None, geom_raw=None, map_raw=None) -> _Stage:
    """Set up a stage from its mesh and map values (or, on resume, the saved raw tensors)."""
    settings, bbox_scale = run.settings, run.bbox_scale
    topo = reg.MeshTopology.from_faces(mesh.t_pos_idx, len(mesh.v_pos))
    ls = None
    if settings.optimizer == "largesteps":
        ls = LargeSteps(mesh.t_pos_idx, len(mesh.v_pos), stage_lambda(settings, stage_settings, h / bbox_scale))
        geom0 = torch.from_numpy(ls.M @ mesh.v_pos)
    else:
        geom0 = torch.from_numpy(mesh.v_pos.copy())
    geom = (geom_raw.clone() if geom_raw is not None else geom0).to(torch.float64).requires_grad_(True)
    p = _params(settings)
    maps = {}
    for k in MAP_NAMES:
        if map_raw is not None:
            maps[k] = TexturePyramid.from_state(map_raw[k])
        else:
            maps[k] = TexturePyramid(p[k].raw(map_values[k]), settings.texture_levels)
    # start rates; the stage's lr_scale and decay are set before every step (_iteration)
    lr_g = run.lr_geometry()
    lr_t = run.lr_texture()
    # Adam's eps in the units of the gradients, which scale as 1 / bbox_scale: the steps are the
    # same in any scene units (an absolute 1e-8 damps them for a scene in millimetres)
    eps_g = 1e-8 / bbox_scale
    if ls is not None and settings.largesteps_uniform_adam:
        opt_geom = AdamUniform([geom], lr=lr_g, betas=settings.betas, eps=eps_g)
    else:
        opt_geom = torch.optim.Adam([geom], lr=lr_g, betas=settings.betas, eps=eps_g)
    opt_tex = torch.optim.Adam([t for k in MAP_NAMES for t in maps[k].parameters()], lr=lr_t, betas=settings.betas)
    if opt_state is not None:
        opt_geom.load_state_dict(opt_state["geom"])
        opt_tex.load_state_dict(opt_state["tex"])
    guard = (
        SurfaceGuard(mesh.t_pos_idx, topo, v_init, max_halvings=settings.guard_max_halvings)
        if settings.guard else None
    )
    targets = run.views.at(settings.stage_image_size(stage_settings))
    renderer = _make_renderer(settings, mesh)
    return _Stage(index, stage_settings, h, bbox_scale, mesh, v_init, covered, topo, geom, maps, opt_geom, opt_tex, ls,
                  guard, renderer, targets)


def _positions(st: _Stage) -> torch.Tensor:
    """(V, 3) float64 vertex positions, differentiable w.r.t. the geometry parameter."""
    return st.ls.from_differential(st.geom) if st.ls is not None else st.geom


def _stage_state(st: _Stage, next_iteration: int) -> dict:
    return {
        "stage": st.index,
        "iteration": next_iteration,
        "mesh": {"t_pos_idx": st.mesh.t_pos_idx, "v_tex": st.mesh.v_tex, "t_tex_idx": st.mesh.t_tex_idx,
                 "v_pos": st.mesh.v_pos, "v_init": st.v_init},
        "covered": st.covered,
        "geom": st.geom.detach().clone(),
        "maps": {k: v.state() for k, v in st.maps.items()},
        "optimizer": {"geom": st.opt_geom.state_dict(), "tex": st.opt_tex.state_dict()},
        "rng": {"scheme": "counter: numpy default_rng([seed, stage, iteration]); render seed blake2b"},
    }


# ---------------------------------------------------------------------- one iteration
def _forward_backward(st: _Stage, it: int, idx: np.ndarray, run: _Run, times: dict):
    """Render the views ``idx``, evaluate the loss and backpropagate (gradients in the parameters)."""
    settings, weights = run.settings, run.weights
    t0 = time.perf_counter()
    v = _positions(st)
    t1 = time.perf_counter()
    vals = _map_values(settings, st.maps)
    cams = [st.targets.cameras[i] for i in idx]
    table = None
    ref = run.cameras.ref if run.cameras is not None else None
    if ref is not None:  # the corrected cameras, differentiable through the table
        table = ref.table(idx, cams)
        cams = ref.cameras(idx, cams)
    lighting = run.imaging.lighting() if run.imaging is not None else {}
    img = st.renderer.render_torch(v.to(torch.float32), vals["diffuse"], vals["specular"], vals["roughness"],
                                   cams, run.light, seed=ckpt.render_seed(settings.seed, st.index, it),
                                   camera_table=table, **lighting)
    if run.imaging is not None:
        img = run.imaging.apply(img, idx)
    t2 = time.perf_counter()
    terms = {"render": objective.render_loss(img, st.targets.images[idx], st.targets.weights[idx], settings.tone_map,
                                             run.tone_scale),
             **objective.geometry_terms(v, st.topo, st.h, settings.laplacian, weights)}
    terms.update(objective.material_terms(
        vals["specular"], vals["diffuse"], vals["roughness"], torch.from_numpy(st.covered), weights,
        settings.bilateral_sigma_space, settings.bilateral_sigma_color, settings.bilateral_radius))
    terms.update(objective.camera_terms(ref, idx, weights))
    if run.imaging is not None and run.imaging.active and weights.get("imaging"):
        terms["imaging"] = run.imaging.prior()
    total = objective.total(terms, weights)
    t3 = time.perf_counter()
    st.opt_geom.zero_grad(set_to_none=True)
    st.opt_tex.zero_grad(set_to_none=True)
    if run.cameras is not None:
        run.cameras.opt.zero_grad(set_to_none=True)
    if run.imaging is not None:
        run.imaging.zero_grad()
    total.backward()
    t4 = time.perf_counter()
    for phase, dt in (("geometry", t1 - t0), ("render", t2 - t1), ("loss", t3 - t2), ("backward", t4 - t3)):
        times[phase] += dt
    return total, terms


def _timed_check(guard: SurfaceGuard, v: np.ndarray):
    t0 = time.perf_counter()
    bad = guard.new_bad_faces(v)
    return bad, time.perf_counter() - t0


def _resolve(st: _Stage) -> bool:
    """Wait for the pending check of the proposed positions; accept them or back off.

    Returns True when the positions were changed (the proposal had new defects).
    """
    if st.pending is None:
        return False
    bad, dt = st.pending.result()
    st.pending = None
    changed = bool(bad.any())
    info = {"halvings": 0, "frozen": 0, "reverted": False}
    if changed:
        v_acc, info = st.guard.accept(st.mesh.v_pos, st.proposed, first_bad=bad)
        with torch.no_grad():
            st.geom.copy_(torch.from_numpy(st.ls.M @ v_acc if st.ls is not None else v_acc))
    else:
        v_acc = st.proposed
    st.mesh.v_pos = v_acc
    st.proposed = None
    if st.proposed_record is not None:
        st.proposed_record.update(guard_halvings=info["halvings"], guard_frozen=info["frozen"],
                                  guard_reverted=bool(info["reverted"]), t_guard_check=dt)
        st.proposed_record = None
    return changed


def _iteration(st: _Stage, it: int, run: _Run, timer: _Timer) -> dict:
    """One step. The surface check of a step's result runs in a worker thread while the next
    iteration renders with it; the optimizer only steps after the check. When the check finds
    new defects, the positions are backed off and this iteration's forward/backward pass is
    redone, so the accepted trajectory is exactly that of checking synchronously."""
    settings = run.settings
    n = len(st.targets)
    B = min(int(settings.views_per_iteration), n)
    idx = np.sort(iteration_views(settings.seed, st.index, it, n, B))
    times = {p: 0.0 for p in PHASES}
    total, terms = _forward_backward(st, it, idx, run, times)
    t0 = time.perf_counter()
    redo = _resolve(st)
    times["geometry"] += time.perf_counter() - t0
    if redo:
        total, terms = _forward_backward(st, it, idx, run, times)
    t4 = time.perf_counter()
    f = st.settings.lr_factor(it)
    for g in st.opt_geom.param_groups:
        g["lr"] = run.lr_geometry(f)
    for g in st.opt_tex.param_groups:
        g["lr"] = run.lr_texture(f)
    st.opt_geom.step()
    st.opt_tex.step()
    if run.cameras is not None and st.index >= run.cameras.first_stage:
        run.cameras.step(f)
    if run.imaging is not None:
        run.imaging.step(f)
    p = _params(settings)
    for k in MAP_NAMES:
        st.maps[k].project_(p[k])
    t5 = time.perf_counter()
    times["step"] += t5 - t4
    # ---- the proposed positions: accepted now (no guard) or checked in the background ----
    g = st.geom.detach().numpy()
    v_new = st.ls.solve_np(g) if st.ls is not None else g.copy()
    v_new, n_below = _keep_above_plane(st, run.plane, v_new)
    rec = {
        "stage": st.index,
        "iteration": it,
        "views": idx.tolist(),
        "loss": float(total.detach()),
        **{f"loss_{k}": float(t.detach()) for k, t in terms.items()},
        "guard_halvings": 0,
        "guard_frozen": 0,
        "guard_reverted": False,
        "t_guard_check": 0.0,
        "plane_projected": n_below,
    }
    if st.guard is None:
        st.mesh.v_pos = v_new
    else:
        st.proposed, st.proposed_record = v_new, rec
        st.pending = st.executor.submit(_timed_check, st.guard, v_new)
    times["geometry"] += time.perf_counter() - t5
    for phase in ("render", "loss", "backward", "step", "geometry"):
        timer.add(phase, times[phase])
        rec[f"t_{phase}"] = times[phase]
    return rec


# The base an object stands on: the stage's vertices within this fraction of the bounding box of
# the support plane whose normals face it. Measured on a phone capture of a blob on a table
# (bench/tabletop_e2e.py --phone --given-masks, draft): with the plane only a floor, the unseen
# base, moved by the priors alone, lifted and took the lower 15 % of the object inward by up to
# 5 % of its size (accuracy 0.0051 hull -> 0.0066 final); held on the plane: 0.0037.
RESTING_TOL = 0.02


def _keep_above_plane(st: _Stage, plane: SupportPlane | None, v: np.ndarray) -> tuple[np.ndarray, int]:
    """The support plane's constraint, a projection after each step: vertices a step took below
    the table go back onto it (along its normal), the base the object stands on (on the plane
    at the stage's start, facing it) stays on it, and the geometry parameter follows them. The
    base is never seen by a camera above the table, so it gets no gradient from the images:
    left free, the priors alone lift it and pull the object's foot in."""
    if plane is None:
        return v, 0
    if st.resting is None:
        normals = Mesh(st.v_init, st.mesh.t_pos_idx).vertex_normals()
        st.resting = plane.resting(st.v_init, normals, RESTING_TOL * st.bbox_scale)
        log.info("stage %d: %d vertices rest on the support plane and are held on it", st.index,
                 int(st.resting.sum()))
    v, moved = plane.hold(v, st.resting)
    n = int(moved.sum())
    if n:
        with torch.no_grad():
            st.geom.copy_(torch.from_numpy(st.ls.M @ v if st.ls is not None else v))
    return v, n


def iteration_views(seed: int, stage: int, iteration: int, n_views: int, per_iteration: int) -> np.ndarray:
    """The view indices of one iteration (distinct, a function of its arguments only)."""
    return ckpt.iteration_rng(seed, stage, iteration).choice(n_views, size=min(per_iteration, n_views), replace=False)


# ---------------------------------------------------------------------- the stage function
def optimize_capture(
    images: Sequence[str | os.PathLike],
    masks: Sequence[str | os.PathLike] | None,
    saturation_masks: Sequence[str | os.PathLike | None] | None,
    cameras_json: str | os.PathLike,
    init_mesh_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: OptimizeSettings | None = None,
    progress: bool = True,
    callback: Callable[[dict], None] | None = None,
    cameras_source: str | None = None,
    plane_json: str | os.PathLike | None = None,
) -> dict:
    """Optimize shape and SVBRDF maps from flash photos; write the optimize stage's outputs.

    Parameters
    ----------
    images : linear RGB ``.exr`` photos (``poses/undistorted/<stem>.exr`` or ``linear/<stem>.exr``),
        paired with cameras by stem.
    masks : one ``masks/<stem>.png`` per image (nonzero = object), or None (all object).
    saturation_masks : one ``linear/<stem>.sat.png`` per image (nonzero = clipped), or None.
    cameras_json : ``poses/cameras.json``.
    init_mesh_obj : ``uv/mesh.obj`` (positions are used; the stage makes its own atlas).
    out_dir : ``results/<capture>/optimize``; gets ``mesh.obj``, ``diffuse.exr``, ``specular.exr``,
        ``roughness.exr``, ``log.jsonl``, ``summary.json``, ``cameras.json`` (the cameras of the
        final model, in the frame of ``cameras_json``) and ``checkpoints/``.
    settings : OptimizeSettings (None = the defaults)
    progress : show a tqdm bar (loss and ETA).
    callback : called after every iteration with its log record (dict).
    cameras_source : where the cameras came from, "sfm" or "given" (None: the ``source`` of
        ``poses.json`` beside ``cameras_json``, else "given"); decides ``refine_cameras``.
    plane_json : the support plane (``plane.json`` beside the masks; absent when none was found):
        no vertex goes below it (:func:`_keep_above_plane`).

    Returns
    -------
    dict, the summary also written to ``summary.json``.

    A run whose ``checkpoints/last.pt`` matches these inputs and settings resumes from it and
    ends with the same result as an uninterrupted run.
    """
    t_start = time.perf_counter()
    settings = settings if settings is not None else OptimizeSettings()
    out_dir = Path(out_dir)
    ckpt_dir = out_dir / "checkpoints"
    cams = load_cameras(cameras_json)
    source = cameras_source if cameras_source is not None else cameras_source_of(cameras_json)
    mode, why = settings.camera_mode(source)
    stages = settings.effective_stages()
    views = Views(images, masks, saturation_masks, cams, max(settings.stage_image_size(s) for s in stages))
    views, heldout, holdout_info = split_holdout(views, settings, force=mode == "select")
    if mode != "off" and len(views) < 3:
        mode, why = "off", f"only {len(views)} training views (camera refinement needs at least 3)"
    if mode == "select" and heldout is None:
        mode, why = "off", "no held-out views to decide on (refine_cameras: select needs at least 6 views)"
    if mode != "off" or settings.refine_cameras != "off":
        log.info("camera refinement: %s (%s)", mode, why)
    init = read_mesh(init_mesh_obj)
    lo, hi = init.bbox()
    bbox_scale = float(np.max(hi - lo))
    if not bbox_scale > 0:
        raise OptimizeError(f"{init_mesh_obj}: the initial mesh has an empty bounding box")
    weights = objective.weights(settings)
    try:
        plane = plane_if_found(plane_json)
    except PlaneError as e:
        raise OptimizeError(f"{e}; rerun the masks stage") from e
    if plane is not None:
        log.info("support plane %s: the surface is kept above it", plane_json)
        if np.any(plane.height(init.v_pos) < -0.01 * bbox_scale):
            log.warning("%s: the initial mesh reaches %.3g below the support plane (%s); those vertices are "
                        "moved onto it", init_mesh_obj, -plane.height(init.v_pos).min(), plane_json)
    files = [cameras_json, init_mesh_obj, *images, *(masks or []), *(saturation_masks or []),
             plane_json if plane is not None else None]
    fp = ckpt.fingerprint(settings.to_dict(), [str(f) if f is not None else None for f in files])
    tone_scale = views.median_foreground
    light_scale = _light_scale(settings, cams, views, init, cameras_json)
    light = light_scale.intensity

    base = _Run(settings, tuple(stages), views, heldout, bbox_scale, weights, tone_scale, light, ckpt_dir, fp,
                plane=plane, light_scale=light_scale, area_init=float(init.area()),
                exposure=recorded_exposures(images))
    if settings.imaging_loop != "off":
        if heldout is None:
            log.warning("imaging_loop: %s needs held-out views (at least 6 views); the loop renders the ideal "
                        "formation", settings.imaging_loop)
        else:
            base = dataclasses.replace(base, ldr=capture_is_ldr(images))
    # linear photos (RAW, EXR) carry their exposure: the cameras need not wait for the imaging terms
    camera_start = settings.camera_start(len(stages), settings.imaging_loop != "off" and heldout is not None
                                         and base.ldr is True)
    if mode != "off":
        log.info("camera refinement from stage %d (camera_first_stage: %s)", camera_start, settings.camera_first_stage)
    runs = []
    if mode in ("off", "select"):
        runs.append(base)
    if mode in ("on", "select"):
        # its own checkpoints beside the control's, so either run resumes alone
        runs.append(dataclasses.replace(base, ckpt_dir=ckpt_dir / "cameras" if mode == "select" else ckpt_dir,
                                        fingerprint=fp + "+cameras", cameras=_CameraFit(views, settings, camera_start)))
    if settings.imaging_loop != "off" and heldout is not None:
        # one per run; when the cameras are held until the selection has run, the runs are the
        # same up to there and the refined run takes the control's choice: the held-out test then
        # compares cameras, not two draws of the imaging selection
        prior = ImagingSettings().exposure_prior
        e = view_exposures(views.cameras, base.exposure)  # the training views' (None: all 1)
        e = None if e is None else e.numpy()
        control = LoopImaging(settings.imaging_loop_lr, prior, exposure=e)
        shared = control if mode == "select" and camera_start > int(settings.imaging_loop_stage) else None
        runs = [dataclasses.replace(r, imaging=control if r.cameras is None else
                                    LoopImaging(settings.imaging_loop_lr, prior, shared_from=shared, exposure=e))
                for r in runs]
    done = [_execute(run, init, progress, callback) for run in runs]

    # ---- the cameras: held-out poses aligned, the refinement selected ----
    cam_timer = _Timer()
    aligned = {}
    if mode != "off" and heldout is not None:
        for run, (st, _) in zip(runs, done, strict=True):
            t0 = time.perf_counter()
            aligned[id(run)] = align_heldout(run, st)
            cam_timer.add("cameras", time.perf_counter() - t0)
    camera_info = {"requested": settings.refine_cameras, "mode": mode, "reason": why, "source": source,
                   "refined": False, "first_stage": camera_start if mode != "off" else None}
    chosen = len(runs) - 1  # "on": the refined run; "off": the only one
    if mode == "select":
        ctrl, cand = (aligned[id(r)] for r in runs)
        run_imaging_active = any(r.imaging is not None and r.imaging.active for r in runs)
        cmp = compare(cand["tiles"], ctrl["tiles"], settings.selection_settings())
        chosen = 1 if cmp["accepted"] else 0
        camera_info["selection"] = {
            "criterion": f"keep the refined cameras when the held-out error (each run's held-out poses aligned "
                         f"to its fixed model for {int(settings.camera_align_iterations)} steps"
                         + (", under the loop's imaging terms with the views' own exposure gains"
                            if run_imaging_active else "") + ") is lower than the "
                         f"control's (same run without refinement) by > {settings.select_z} x SE of the paired "
                         f"per-tile difference and by > {100 * settings.select_min_gain:.3g} %",
            "control_heldout_error": float(np.nanmean(ctrl["tiles"])),
            "refined_heldout_error": float(np.nanmean(cand["tiles"])),
            **cmp,
            "run_seconds": [float(sum(p.timer.total.values())) for _, p in done],
        }
        log.info("camera refinement: held-out %.5f (control %.5f, gain %+.5f, SE %.5f): %s",
                 camera_info["selection"]["refined_heldout_error"], camera_info["selection"]["control_heldout_error"],
                 cmp["gain"], cmp["se"], "kept" if cmp["accepted"] else "rejected")
    run, (st, prog) = runs[chosen], done[chosen]
    if any(r.cameras is not None for r in runs):
        fit = next(r.cameras for r in runs if r.cameras is not None)
        camera_info["refined"] = run.cameras is not None
        camera_info["corrections"] = fit.ref.corrections(object_size=bbox_scale,
                                                         cameras=[cams.by_stem()[s] for s in views.stems])
        camera_info["intrinsics_refined"] = bool(settings.camera_intrinsics)
    held_cams = aligned.get(id(run))
    if held_cams is not None:
        camera_info["heldout_alignment"] = held_cams["corrections"]
    timer = _Timer()
    for t in [p.timer for _, p in done] + [cam_timer]:
        for k, v in t.total.items():
            timer.add(k, v)
    records, stage_infos = prog.records, prog.stage_infos

    # ---- outputs ----
    with torch.no_grad():
        final_maps = {k: v.numpy().astype(np.float32) for k, v in _map_values(settings, st.maps).items()}
    final = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
    model = model_from_settings(settings.specular_channels)
    selection = None
    train_vs = held_vs = None  # the views at the selections' size with the final model's cameras
    loop_imaging = run.imaging is not None and run.imaging.active
    if heldout is not None and (settings.select_material or settings.select_imaging or loop_imaging):
        size = int(settings.select_image_size)
        train_vs, held_vs = views.at(size), heldout.at(size)
        if run.cameras is not None:
            train_vs = dataclasses.replace(
                train_vs, cameras=tuple(run.cameras.ref.cameras(range(len(train_vs)), train_vs.cameras)))
        if held_cams is not None:
            held_vs = held_cams["viewset"]
    scorer = None  # the material selection's, when it fits the candidates under the loop's imaging terms
    if settings.select_material and heldout is not None:
        t0 = time.perf_counter()
        s_mat = settings.selection_settings()
        # under the loop's imaging terms the candidates' maps are fitted under them: the chosen
        # fit's maps are then those the asset carries (no refit after)
        if loop_imaging and settings.select_material_under_imaging:
            scorer = material_scorer_under(run.imaging.params, final, st.covered, train_vs, held_vs, light,
                                           tone_scale, s_mat, spp=int(settings.select_spp),
                                           seed=int(settings.seed) + 29, exposure=run.exposure)
        log.info("material model selection on %d held-out views%s", len(heldout),
                 "" if scorer is None else " under the loop's imaging terms")
        fit, selection = select_material(
            final, final_maps, st.covered, train_vs, held_vs, light, tone_scale,
            s_mat, spp=int(settings.select_spp), seed=int(settings.seed),
            progress=lambda m, f: log.info("material: fitted %s: held-out error %.5f", m.label(), f.heldout),
            scorer=scorer)
        final_maps, model = fit.maps, fit.model
        selection["under_imaging"] = scorer is not None
        timer.add("material", time.perf_counter() - t0)
        log.info("material model: %s", model.label())
    if loop_imaging and not settings.select_imaging and scorer is None:
        t0 = time.perf_counter()
        refit = refit_under(run.imaging.params, model, final, final_maps, st.covered, train_vs, light, tone_scale,
                            settings.imaging_selection_settings(), spp=int(settings.select_spp), seed=int(settings.seed) + 29,
                            exposure=run.exposure)
        final_maps = refit.material.maps
        timer.add("material", time.perf_counter() - t0)
        log.info("maps refitted under the loop's imaging terms (%s): %.1f s", ", ".join(run.imaging.params.model.terms)
                 or "flash offset given", time.perf_counter() - t0)
    imaging = None
    if settings.select_imaging and heldout is not None:
        t0 = time.perf_counter()
        final_maps, model, imaging = run_imaging_selection(
            settings, final, final_maps, model, st.covered, views, heldout, light, tone_scale, images,
            train_set=train_vs, heldout_set=held_vs)
        log.info("imaging model: %s (%.1f s)", ", ".join(imaging["chosen"]) or "ideal", time.perf_counter() - t0)
    topo = topology_report(final.v_pos, final.t_pos_idx)
    n_si = int(self_intersecting_faces(final.v_pos, final.t_pos_idx).sum())
    wall = time.perf_counter() - t_start
    summary = _summary(settings, stage_infos, records, timer, final, topo, n_si, wall, bbox_scale)
    summary["light_intensity"] = float(light)
    summary["light"] = {**light_scale.to_dict(),
                        "diffuse_clipped_fraction": clipped_fraction(final_maps["diffuse"], st.covered)}
    if light_scale.source == "estimated" and summary["light"]["diffuse_clipped_fraction"] > 0.02:
        log.warning("%.1f %% of the diffuse map is at albedo 1: the estimated flash intensity is low for these "
                    "photos", 100 * summary["light"]["diffuse_clipped_fraction"])
    summary["material_model"] = model.to_dict()
    summary["material_model_label"] = model.label()
    summary["material_selection"] = selection
    summary["imaging_selection"] = imaging
    summary["imaging_model"] = imaging["chosen"] if imaging else []
    summary["holdout"] = holdout_info
    summary["camera_refinement"] = camera_info
    summary["imaging_loop"] = None if run.imaging is None else {
        "setting": settings.imaging_loop, "stage": int(settings.imaging_loop_stage), **run.imaging.report()}
    _save(run, prog, st, int(stages[-1].iterations), done=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    for k in MAP_NAMES:
        write_exr(out_dir / f"{k}.exr", final_maps[k])
    with atomic_path(out_dir / "log.jsonl") as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in records))
    with atomic_path(out_dir / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1))
    save_cameras(out_dir / CAMERAS_FILE, output_cameras(cams, run, held_cams, camera_info))
    write_obj(out_dir / "mesh.obj", final)
    log.info("optimize: done in %.1f s (geometry processing %.1f%% of the iteration time)", wall,
             100 * summary["phase_fraction"]["geometry"])
    return summary


def _execute(run: _Run, init: Mesh, progress: bool, callback) -> tuple[_Stage, _Progress]:
    """One run of the coarse-to-fine loop, resumed from its checkpoint when that matches."""
    stages = run.stages
    state = ckpt.load(run.ckpt_dir, run.fingerprint)
    timer = _Timer()
    records: list[dict] = []
    stage_infos: list[dict] = []
    start_stage, start_it = 0, 0
    if state is not None:
        start_stage, start_it = int(state["stage"]), int(state["iteration"])
        records = list(state["records"])
        stage_infos = list(state["stage_infos"])
        timer.total.update(state["timings"])
        if run.cameras is not None:
            run.cameras.load(state["cameras"])
        if run.imaging is not None and state.get("imaging") is not None:
            run.imaging.load(state["imaging"])
        log.info("resuming from checkpoint: stage %d, iteration %d", start_stage, start_it)
    elif run.cameras is not None:
        log.info("optimizing with the cameras refined")

    total_iters = sum(int(s.iterations) for s in stages)
    done_iters = sum(int(s.iterations) for s in stages[:start_stage]) + start_it
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total_iters, initial=done_iters, unit="it", dynamic_ncols=True,
                   desc="optimize (cameras refined)" if run.cameras is not None else "optimize")
    prog = _Progress(timer, records, stage_infos, bar=bar, callback=callback,
                     executor=ThreadPoolExecutor(max_workers=1, thread_name_prefix="surface-guard"))
    try:
        st = _run_stages(run, prog, init, state, start_stage, start_it)
    finally:
        prog.executor.shutdown(wait=True)
    if bar is not None:
        bar.close()
    return st, prog


def align_heldout(run: _Run, st: _Stage) -> dict:
    """Align the held-out views' poses to a run's fixed final model; their held-out error.

    The held-out cameras (with the run's refined intrinsics, if any) get per-view pose
    corrections (no gauge: the model is fixed) fitted for ``camera_align_iterations`` Adam steps
    on the rendering loss at ``select_image_size`` (rates decaying to 1/10, the camera prior
    added), as bundle-adjusting methods evaluate novel views. Returns ``viewset`` (the held-out
    targets with the aligned cameras), ``world_to_camera`` (stem -> aligned (4, 4) pose),
    ``tiles`` (per-tile held-out errors, :func:`recon.optimize.material.heldout_error`) and
    ``corrections`` (of the held-out poses).

    Under the loop's imaging terms (``imaging_loop``) the held-out views are rendered as the
    training views are (flash offset and ambient in the renderer, falloff and tone curve on the
    images) with exposure gains of their own, fitted with the poses (exposure prior); their
    errors are those of the imaging selection (gains cross-fitted on a checkerboard's tiles,
    fitted on one colour, errors on the other: :func:`recon.optimize.imaging.heldout_tiles_under`). Rendered
    under the ideal formation instead, a photo's exposure or tone would be explained by the pose
    (with the flash at the lens, brightness and distance trade) and the two runs compared on
    errors the cameras do not cause.
    """
    settings = run.settings
    size = int(settings.select_image_size)
    vs = run.heldout.at(size)
    at_size = list(vs.cameras)
    if run.cameras is not None:
        at_size = run.cameras.ref.with_intrinsics(at_size)
    with torch.no_grad():
        maps = _map_values(settings, st.maps)
    mesh = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
    return align_views(mesh, maps, vs, at_size, settings, run.light, run.tone_scale, run.weights, run.imaging,
                       scene_extent(run.views.cameras), run.bbox_scale, exposure=run.exposure)


def align_views(mesh: Mesh, maps: dict, vs: ViewSet, cameras: list[Camera], settings: OptimizeSettings, light: float,
                tone_scale: float, weights: dict, imaging: LoopImaging | None, scene_size: float,
                object_size: float | None = None, tracks: tuple[TrackTerm, list[Camera]] | None = None,
                exposure: dict | None = None) -> dict:
    """:func:`align_heldout` of views ``vs`` (starting from ``cameras``, at the size of ``vs``)
    to a fixed model: ``mesh`` and its map values (``diffuse``, ``specular``, ``roughness``
    tensors), rendered under ``imaging`` (the loop's imaging terms, if it has chosen any; None:
    ``imaging_loop`` off). With the loop on the errors are always the imaging selection's white
    tiles (the ideal formation's when it chose nothing), so that two runs compare tile for tile
    whatever each chose. ``scene_size``: the translation unit of the camera prior (the training
    cameras' extent). ``tracks``: SfM's tracks of these views and the views' cameras at the
    photos' size, reprojected through the aligned cameras as a second term (weight
    ``weights["tracks"]``; :mod:`recon.optimize.tracks`). ``exposure``: stem -> recorded exposure
    (:func:`recon.optimize.views.recorded_exposures`), where the tone curve acts."""
    ali = CameraRefinement(cameras, settings.camera_prior(), intrinsics=False, gauge=False, scene_size=scene_size)
    idx = list(range(len(cameras)))
    im_settings = ImagingSettings()
    loop_on = imaging is not None
    if imaging is not None and not imaging.active:
        imaging = None  # the loop chose nothing: the ideal formation
    own = None  # these views' own exposure gains, fitted with their poses (the loop's other terms as they are)
    if imaging is not None and imaging.params.model.has("exposure"):
        own = imaging.params.clone(n_views=len(idx), normalize_gains=False)
        with torch.no_grad():
            own.log_gain.zero_()
    held_e = view_exposures(vs.cameras, exposure)  # these views' recorded exposures (None: all 1)
    n = int(settings.camera_align_iterations)
    if n > 0:
        renderer = _make_renderer(settings, mesh)
        v = torch.from_numpy(mesh.v_pos).to(torch.float32)
        groups = ali.param_groups() + ([] if own is None else [{"params": [own.log_gain], "lr": im_settings.lr}])
        w_tracks = weights.get("tracks", 0.0) if tracks is not None else 0.0
        opt = torch.optim.Adam(groups, betas=settings.betas)
        base_lr = [g["lr"] for g in opt.param_groups]
        w = weights.get("camera", 0.0)
        w_exposure = weights.get("imaging", 0.0)
        lighting = imaging.lighting() if imaging is not None else {}
        for it in range(n):
            for g, lr in zip(opt.param_groups, base_lr, strict=True):
                g["lr"] = lr * 0.1 ** (it / max(n - 1, 1))
            img = renderer.render_torch(v, maps["diffuse"], maps["specular"], maps["roughness"], ali.cameras(idx, cameras),
                                        light, seed=ckpt.render_seed(settings.seed, 1000, it),
                                        camera_table=ali.table(idx, cameras), **lighting)
            if imaging is not None:
                img = imaging.apply(img, idx, gains=None if own is None else own.gains(), exposure=held_e)
            loss = objective.render_loss(img, vs.images, vs.weights, settings.tone_map, tone_scale)
            if w:
                loss = loss + w * ali.prior_loss()
            if own is not None and w_exposure:
                loss = loss + w_exposure * own.prior(im_settings.exposure_prior)
            if w_tracks:
                tracks[0].retriangulate(ali, tracks[1])
                loss = loss + w_tracks * tracks[0].loss(ali, tracks[1])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    aligned = dataclasses.replace(vs, cameras=tuple(ali.cameras(idx, cameras)))
    maps_np = {k: x.detach().numpy().astype(np.float32) for k, x in maps.items()}
    sel = settings.selection_settings()
    if not loop_on:
        tiles = heldout_error(mesh, maps_np, aligned, light, tone_scale, sel, spp=int(settings.select_spp),
                              seed=int(settings.seed))
    else:
        gb = build_gbuffer(mesh, list(aligned.cameras), int(settings.select_spp), int(settings.seed))
        prob = ImagingProblem(gb, aligned, sel.tone_map, tone_scale, sel.tile, exposure=exposure)
        params = imaging.params if imaging is not None else ImagingParams(ImagingModel(()), len(idx), 1.0, tone_scale)
        tiles, _ = heldout_tiles_under(maps_np, model_from_settings(maps_np["specular"].shape[2]), params,
                                       prob, light, sel, im_settings)
    return {"viewset": aligned, "world_to_camera": {c.stem: c.world_to_camera for c in aligned.cameras},
            "tiles": tiles, "corrections": ali.corrections(object_size=object_size)}


def cameras_source_of(cameras_json: str | os.PathLike) -> str | None:
    """The ``source`` ("sfm" or "given") the poses stage recorded in ``poses.json`` beside
    ``cameras_json``; None when there is no such record."""
    p = Path(cameras_json).with_name("poses.json")
    if not p.is_file():
        return None
    try:
        src = json.loads(p.read_text()).get("source")
    except (json.JSONDecodeError, AttributeError, OSError) as e:
        raise OptimizeError(f"{p}: unreadable ({e}); rerun the poses stage") from e
    return src if isinstance(src, str) else None


def output_cameras(cams: CameraSet, run: _Run, heldout: dict | None, info: dict) -> CameraSet:
    """The cameras of the final model, full size: refined training views, aligned held-out
    views, every other frame of ``cams`` as it was; ``optimize_cameras`` records how."""
    given = cams.by_stem()
    by_stem = {}
    if run.cameras is not None:
        ref = run.cameras.ref
        full = [given[s] for s in run.views.stems]
        by_stem.update({c.stem: c for c in ref.cameras(range(len(full)), full)})
        if run.heldout is not None:
            by_stem.update({c.stem: c for c in ref.with_intrinsics([given[s] for s in run.heldout.stems])})
    if heldout is not None:  # aligned poses (independent of the image size)
        for stem, w2c in heldout["world_to_camera"].items():
            c = by_stem.get(stem, given[stem])
            by_stem[stem] = Camera(c.image, c.width, c.height, c.K, np.array(w2c, dtype=np.float64))
    frames = tuple(by_stem.get(c.stem, c) for c in cams.frames)
    extra = dict(cams.extra)
    extra["optimize_cameras"] = {
        "refined": bool(run.cameras is not None),
        "heldout_aligned": heldout is not None,
        "mode": info.get("mode"),
        "reason": info.get("reason"),
    }
    return CameraSet(frames, cams.light_intensity, extra, light_known=cams.light_known)


def _run_stages(run: _Run, prog: _Progress, init: Mesh, state: dict | None, start_stage: int,
                start_it: int) -> _Stage:
    """The coarse-to-fine loop; returns the last stage (its accepted mesh and maps)."""
    settings, stages, views, timer = run.settings, run.stages, run.views, prog.timer
    stage_infos, bar = prog.stage_infos, prog.bar
    st: _Stage | None = None
    prev_mesh, prev_maps = None, None
    lo, hi = init.bbox()
    footprint_full = pixel_footprint(views.cameras, (lo + hi) / 2)
    for si in range(start_stage, len(stages)):
        stage = stages[si]
        h, h_req, h_min = _stage_edge_length(stage, settings, views, footprint_full, run.bbox_scale)
        t0 = time.perf_counter()
        if state is not None and si == start_stage:
            m = state["mesh"]
            mesh = Mesh(m["v_pos"], m["t_pos_idx"], m["v_tex"], m["t_tex_idx"])
            st = _build_stage(run, si, stage, h, mesh, np.asarray(m["v_init"]), np.asarray(state["covered"]),
                              None, opt_state=state["optimizer"], geom_raw=state["geom"], map_raw=state["maps"])
            timer.add("setup", time.perf_counter() - t0)
            it0 = start_it
        else:
            if si == 0:
                ls = run.light_scale
                mesh, maps, covered = _initial_stage_mesh(init, settings, stage, h,
                                                          None if ls is None else ls.init_diffuse)
            else:
                mesh, maps, covered = remesh_and_rebake(prev_mesh, prev_maps, h, int(stage.texture_size))
            if run.plane is not None:  # remeshing may leave base vertices a hair below the table
                mesh.v_pos = run.plane.clamp_above(mesh.v_pos)[0]
            t1 = time.perf_counter()
            timer.add("geometry", t1 - t0)
            st = _build_stage(run, si, stage, h, mesh, mesh.v_pos.copy(), covered, maps)
            timer.add("setup", time.perf_counter() - t1)
            it0 = 0
            log.info("stage %d: %d vertices, %d faces, %dx%d maps, %dx%d images, edge %.4g",
                     si, len(mesh.v_pos), len(mesh.t_pos_idx), stage.texture_size, stage.texture_size,
                     st.targets.cameras[0].width, st.targets.cameras[0].height, h)
            stage_infos.append({**_stage_info(st), "edge_length_requested": h_req, "edge_length_min": h_min})
            _save(run, prog, st, 0, done=False)
        st.executor = prog.executor
        for it in range(it0, int(stage.iterations)):
            rec = _iteration(st, it, run, timer)
            prog.records.append(rec)
            if bar is not None:
                bar.set_postfix(stage=si, loss=f"{rec['loss']:.4g}", refresh=False)
                bar.update(1)
            if (it + 1) % int(settings.checkpoint_every) == 0 or it + 1 == int(stage.iterations):
                t0 = time.perf_counter()
                _resolve(st)  # checkpoints hold checked positions only
                timer.add("geometry", time.perf_counter() - t0)
                _save(run, prog, st, it + 1, done=False)
            if prog.callback is not None:
                prog.callback(rec)
        prev_mesh = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
        t0 = time.perf_counter()
        stage_infos[-1]["mask_coverage"] = _check_collapse(run, prev_mesh, st, si)
        timer.add("geometry", time.perf_counter() - t0)
        with torch.no_grad():
            prev_maps = {k: v.numpy().astype(np.float32) for k, v in _map_values(settings, st.maps).items()}
        if run.imaging is not None and run.imaging.evidence is None and si >= int(settings.imaging_loop_stage) \
                and si + 1 < len(stages):
            t0 = time.perf_counter()
            _select_loop_imaging(run, prev_mesh, prev_maps, st.covered, si)
            timer.add("material", time.perf_counter() - t0)
        if settings.stop_on_plateau and run.heldout is not None:
            t0 = time.perf_counter()
            stop = _plateau(run, si, prev_mesh, prev_maps, stage_infos)
            timer.add("material", time.perf_counter() - t0)
            if stop and si + 1 < len(stages):
                if bar is not None:
                    bar.total = bar.n
                    bar.refresh()
                log.info("stage %d: held-out error did not improve on stage %d's; skipping the remaining %d "
                         "stage(s) (stop_on_plateau)", si, si - 1, len(stages) - si - 1)
                _save(run, prog, st, int(stage.iterations), done=False)
                break
    return st


def _light_scale(settings: OptimizeSettings, cams: CameraSet, views: Views, init: Mesh,
                 cameras_json) -> LightScale:
    """The flash's I_e: the one ``cameras.json`` states, else estimated from the training photos
    on the initial mesh (``light_scale``; :mod:`recon.optimize.radiometry`)."""
    if settings.light_scale == "given" and not cams.light_known:
        raise OptimizeError(f"{cameras_json}: states no light.intensity, and light_scale is 'given'; give "
                            "light_intensity in capture.yaml, or set optimize.light_scale: auto to estimate it")
    if cams.light_known and settings.light_scale != "estimate":
        log.info("flash intensity I_e = %.6g, given in %s: the albedo is absolute", cams.light_intensity, cameras_json)
        return LightScale(float(cams.light_intensity), "given")
    vs = views.at(ESTIMATE_SIZE)
    try:
        est = estimate_light_scale(init, vs.images.numpy(), vs.masks, vs.weights[..., 0].numpy() == 0, vs.cameras,
                                   seed=int(settings.seed))
    except LightScaleError as e:
        raise OptimizeError(f"{cameras_json}: {e}") from e
    log.info("flash intensity I_e = %.6g estimated from %d pixels of %d photos (the albedo is relative: %s); "
             "initial diffuse albedo %s", est.intensity, est.pixels, len(views), est.to_dict()["convention"],
             " ".join(f"{x:.3f}" for x in est.init_diffuse))
    if cams.light_known:
        log.info("the given I_e is %.6g: estimate / given = %.4f", cams.light_intensity,
                 est.intensity / cams.light_intensity)
    return est


def _check_collapse(run: _Run, mesh: Mesh, st: _Stage, si: int) -> dict:
    """Stop a run whose surface left the masks or shrank away (:func:`check_not_collapsed`)."""
    cov = mask_coverage(mesh, st.targets.cameras, st.targets.masks)
    log.info("stage %d: the surface covers %.1f %% of the masks (worst view %.1f %%), %.1f %% of it outside them",
             si, 100 * cov["covered_mean"], 100 * cov["covered_min"], 100 * cov["outside_mean"])
    try:
        check_not_collapsed(f"optimize stage {si}", cov, float(mesh.area()), run.area_init, run.light_scale,
                            run.settings.collapse_min_covered, run.settings.collapse_min_area)
    except CollapseError as e:
        raise OptimizeError(str(e)) from e
    return cov


def _select_loop_imaging(run: _Run, mesh: Mesh, maps: dict, covered: np.ndarray, si: int) -> None:
    """``imaging_loop: select``: the imaging selection on stage ``si``'s model; the later stages
    optimize under the chosen terms (:class:`recon.optimize.loop_imaging.LoopImaging`)."""
    settings = run.settings
    size = int(settings.select_image_size)
    train_vs, held_vs = run.views.at(size), run.heldout.at(size)
    if run.cameras is not None:
        with torch.no_grad():
            train_vs = dataclasses.replace(
                train_vs, cameras=tuple(run.cameras.ref.cameras(range(len(train_vs)), train_vs.cameras)))
    if run.imaging.share():
        log.info("imaging terms for the loop: the control run's (%s; the cameras were held until then)",
                 ", ".join(run.imaging.evidence["chosen"]) or "none")
        return
    log.info("imaging terms for the loop: selection on stage %d's model (%d held-out views)", si, len(held_vs))
    params, ev = select_for_loop(settings, mesh, maps, model_from_settings(settings.specular_channels), covered,
                                 train_vs, held_vs, run.light, run.tone_scale, run.ldr, exposure=run.exposure)
    ev["after_stage"] = si
    run.imaging.adopt(params, ev)
    log.info("imaging terms for the loop: %s", ", ".join(ev["chosen"]) or "none (the ideal formation)")


def _plateau(run: _Run, si, mesh, maps, stage_infos) -> bool:
    """Held-out error after stage ``si`` (kept in its stage info, so a resumed run decides the
    same); True when it is not lower than the previous stage's by more than its noise."""
    settings = run.settings
    info = stage_infos[si]
    if "heldout_tiles" not in info:
        s = settings.selection_settings()
        tiles = heldout_error(mesh, maps, run.heldout.at(int(settings.select_image_size)), run.light, run.tone_scale, s,
                              spp=int(settings.select_spp), seed=int(settings.seed))
        info["heldout_tiles"] = [float(x) for x in tiles]
        info["heldout_error"] = float(np.nanmean(tiles))
        prev = stage_infos[si - 1] if si > 0 else None
        if prev is not None and "heldout_tiles" in prev:
            cmp = compare(np.asarray(info["heldout_tiles"]), np.asarray(prev["heldout_tiles"]), s)
            info["heldout_vs_previous"] = cmp
            info["plateau_stop"] = not cmp["accepted"]
        else:
            info["plateau_stop"] = False
        log.info("stage %d: held-out error %.5f%s", si, info["heldout_error"],
                 " (no clear gain over the previous stage)" if info["plateau_stop"] else "")
    return bool(info["plateau_stop"])


def split_holdout(views: Views, settings: OptimizeSettings, force: bool = False):
    """(training views, held-out views or None, info dict) for ``settings.holds_out`` (or
    ``force``: the camera refinement's selection needs them).

    Every ``holdout_every``-th view (starting at the middle of the first block) is held out,
    at least 2; none when fewer than 4 views would remain to optimize on.
    """
    n = len(views)
    if not (settings.holds_out or force):
        return views, None, None
    k = int(settings.holdout_every)
    held = list(range(k // 2, n, k))
    if len(held) < 2 and n >= 2:
        held = sorted({n // 4, (3 * n) // 4})
    train = [i for i in range(n) if i not in set(held)]
    if len(held) < 2 or len(train) < 4:
        log.warning("only %d views: none held out, so no material selection or plateau test "
                    "(need at least 6)", n)
        return views, None, {"held_out": [], "reason": f"only {n} views (need at least 6)"}
    return views.subset(train), views.subset(held), {"held_out": [views.stems[i] for i in held],
                                                     "train_views": len(train)}


def optimize_from_dirs(
    views_dir: str | os.PathLike,
    masks_dir: str | os.PathLike | None,
    cameras_json: str | os.PathLike,
    init_mesh_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: OptimizeSettings | None = None,
    progress: bool = True,
    plane_json: str | os.PathLike | None = None,
) -> dict:
    """:func:`optimize_capture` over every view of ``cameras_json`` found in the stage folders.

    ``views_dir`` holds ``<stem>.exr`` and, where pixels clipped, ``<stem>.sat.png`` (the
    linearize stage's folder, or ``poses/undistorted``); ``masks_dir`` holds ``<stem>.png``
    (None: no masks). Views without a camera (e.g. not registered by SfM) are not used.
    """
    views_dir = Path(views_dir)
    cams = load_cameras(cameras_json)
    images, masks, sats = [], [], []
    for c in cams.frames:
        img = views_dir / f"{c.stem}.exr"
        if not img.is_file():
            raise OptimizeError(f"{img}: the linear view of camera '{c.image}' is missing; rerun the "
                                "linearize (or poses) stage")
        images.append(img)
        if masks_dir is not None:
            m = Path(masks_dir) / f"{c.stem}.png"
            if not m.is_file():
                raise OptimizeError(f"{m}: no mask for view '{c.stem}'; rerun the masks stage")
            masks.append(m)
        sat = views_dir / f"{c.stem}.sat.png"
        sats.append(sat if sat.is_file() else None)
    return optimize_capture(images, masks if masks_dir is not None else None, sats, cameras_json, init_mesh_obj,
                            out_dir, settings, progress, plane_json=plane_json)


def _save(run: _Run, prog: _Progress, st: _Stage, next_it: int, done: bool) -> None:
    t0 = time.perf_counter()
    state = _stage_state(st, next_it)
    state.update(fingerprint=run.fingerprint, records=prog.records, stage_infos=prog.stage_infos,
                 timings=dict(prog.timer.total), done=done)
    if run.cameras is not None:
        state["cameras"] = run.cameras.state()
    if run.imaging is not None:
        state["imaging"] = run.imaging.state()
    ckpt.save(run.ckpt_dir, state)
    prog.timer.add("setup", time.perf_counter() - t0)


def stage_lambda(settings: OptimizeSettings, stage: StageSettings, edge_length: float) -> float:
    """The large-steps lambda of a stage whose edges are ``edge_length`` (fraction of the bbox):
    ``largesteps_lambda * lambda_scale``, times ``(largesteps_reference_edge / edge_length)^2`` when
    the edges are shorter than the reference (the smoothing length on the surface stays fixed)."""
    lam = float(settings.largesteps_lambda) * float(stage.lambda_scale)
    ref = float(settings.largesteps_reference_edge)
    if ref > 0 and edge_length < ref:
        lam *= (ref / edge_length) ** 2
    return lam


def _stage_edge_length(stage: StageSettings, settings: OptimizeSettings, views: Views, footprint_full: float,
                       bbox_scale: float) -> tuple[float, float, float]:
    """(edge length, requested length, lower limit) of a stage in world units: the stage's
    ``edge_length``, raised to ``min_edge_pixels`` pixel footprints at the stage's image size."""
    longest = max(views.cameras[0].width, views.cameras[0].height)
    size = min(settings.stage_image_size(stage), longest)  # the photos are never upsampled
    h_min = float(settings.min_edge_pixels) * footprint_full * longest / size
    h = float(stage.edge_length) * bbox_scale
    if h < h_min:
        log.info("stage edge length %.4g is below %.3g pixel footprints at %d px: using %.4g",
                 h, settings.min_edge_pixels, size, h_min)
    return max(h, h_min), h, h_min


def _stage_info(st: _Stage) -> dict:
    return {
        "stage": st.index,
        "edge_length": st.h,
        "texture_size": int(st.settings.texture_size),
        "image_size": [int(st.targets.cameras[0].width), int(st.targets.cameras[0].height)],
        "vertices": int(len(st.mesh.v_pos)),
        "faces": int(len(st.mesh.t_pos_idx)),
        "largesteps_lambda": st.ls.lam if st.ls is not None else None,
    }


def _mean_tail(recs: list[dict], key: str) -> float | None:
    tail = recs[-max(1, min(len(recs), 10)):]
    vals = [r[key] for r in tail if key in r]
    return float(np.mean(vals)) if vals else None


def _summary(settings, stage_infos, records, timer, final, topo, n_si, wall, bbox_scale) -> dict:
    loop_phases = ("render", "loss", "backward", "step", "geometry")
    stages = []
    for info in stage_infos:
        recs = [r for r in records if r["stage"] == info["stage"]]
        keys = sorted({k for r in recs for k in r if k.startswith("loss")})
        stages.append(dict(
            {k: v for k, v in info.items() if k != "heldout_tiles"},
            iterations=len(recs),
            seconds={p: float(sum(r[f"t_{p}"] for r in recs)) for p in loop_phases},
            final_losses={k: _mean_tail(recs, k) for k in keys},
            guard_backoffs=int(sum(r["guard_halvings"] > 0 or r["guard_frozen"] > 0 for r in recs)),
            guard_reverted=int(sum(r["guard_reverted"] for r in recs)),
        ))
    phase = dict(timer.total)
    in_loop = sum(phase[p] for p in loop_phases)
    keys = sorted({k for k in (records[-1] if records else {}) if k.startswith("loss")})
    return {
        "wall_seconds": wall,
        "phase_seconds": phase,
        "phase_fraction": {p: (phase[p] / in_loop if in_loop > 0 else 0.0) for p in loop_phases},
        # CPU time of the surface checks in the worker thread; overlapped with the next
        # iteration's rendering, so only the waiting for them is in phase_seconds["geometry"]
        "guard_check_seconds": float(sum(r.get("t_guard_check", 0.0) for r in records)),
        "stages": stages,
        "iterations": len(records),
        "final_losses": {k: _mean_tail(records, k) for k in keys},
        "mesh": {
            "vertices": int(len(final.v_pos)),
            "faces": int(len(final.t_pos_idx)),
            "manifold": bool(topo["is_mesh_two_manifold"]),
            "boundary_edges": int(topo["boundary_edges"]),
            "self_intersecting_faces": n_si,
        },
        "bbox_scale": bbox_scale,
        "settings": settings.to_dict(),
    }
