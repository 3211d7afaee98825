"""One iteration of the main loop (sec. 3.2-3.4): the stage's parameters, the forward and
backward pass, the Adam steps and the surface guard.

Per iteration: sample views (deterministically from (seed, stage, iteration)), render them with
the current mesh and maps, compare after the tone map Phi (eq. 6), add the sec. 3.3 priors
(:mod:`recon.optimize.objective`), backpropagate, take an Adam step at the stage's rates
(:mod:`recon.optimize.schedule`), and pass the new vertex positions through the surface guard
(no new self-intersections, folds or degenerate faces) and the support plane. The guard's
self-intersection test runs in a worker thread while the next iteration renders.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from recon.io.mesh import Mesh
from recon.optimize import checkpoint as ckpt
from recon.optimize import foot
from recon.optimize import objective, schedule
from recon.optimize import regularizers as reg
from recon.optimize.guard import SurfaceGuard
from recon.optimize.largesteps import AdamUniform, LargeSteps
from recon.optimize.params import TexturePyramid, albedo_param, roughness_param
from recon.optimize.settings import OptimizeSettings, StageSettings
from recon.optimize.views import ViewSet
from recon.render import CollocatedRenderer, RenderSettings
from recon.support import SupportPlane

if TYPE_CHECKING:
    from recon.optimize.run import Run, Timer

log = logging.getLogger(__name__)

PHASES = ("render", "loss", "backward", "step", "geometry", "setup", "material", "cameras")
MAP_NAMES = ("diffuse", "specular", "roughness")


@dataclass
class Stage:
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
    # share of the mask pixels in doubt at the object's foot (recon.optimize.foot; with loss.uncertain_foot_mode
    # background those showing the table are made background, the rest left out)
    foot_out: float | None = None


def map_params(settings: OptimizeSettings) -> dict:
    kind = settings.material.parameterization
    return {
        "diffuse": albedo_param(kind),
        "specular": albedo_param(kind),
        "roughness": roughness_param(settings.material.r_min, kind),
    }


def map_values(settings: OptimizeSettings, maps: dict) -> dict:
    """name -> (T, T, C) values in range, differentiable w.r.t. the pyramid levels."""
    p = map_params(settings)
    return {k: p[k].value(maps[k].full()) for k in MAP_NAMES}


def make_renderer(settings: OptimizeSettings, mesh: Mesh):
    rs = RenderSettings(spp=int(settings.render.spp), boundary=settings.render.boundary, variant=settings.variant,
                        r_min=settings.material.r_min)
    return CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, rs)


def build_stage(run: Run, index, stage_settings, h, mesh, v_init, covered, map_values,
                 opt_state=None, geom_raw=None, map_raw=None) -> Stage:
    """Set up a stage from its mesh and map values (or, on resume, the saved raw tensors)."""
    settings, bbox_scale = run.settings, run.bbox_scale
    topo = reg.MeshTopology.from_faces(mesh.t_pos_idx, len(mesh.v_pos))
    ls = None
    if settings.optim.optimizer == "largesteps":
        ls = LargeSteps(mesh.t_pos_idx, len(mesh.v_pos), schedule.stage_lambda(settings, stage_settings, h / bbox_scale))
        geom0 = torch.from_numpy(ls.M @ mesh.v_pos)
    else:
        geom0 = torch.from_numpy(mesh.v_pos.copy())
    geom = (geom_raw.clone() if geom_raw is not None else geom0).to(torch.float64).requires_grad_(True)
    p = map_params(settings)
    maps = {}
    for k in MAP_NAMES:
        if map_raw is not None:
            maps[k] = TexturePyramid.from_state(map_raw[k])
        else:
            maps[k] = TexturePyramid(p[k].raw(map_values[k]), settings.material.texture_levels)
    # start rates; the stage's lr_scale and decay are set before every step (run_iteration)
    lr_g, lr_t = schedule.learning_rates(settings, bbox_scale)
    # Adam's eps in the units of the gradients, which scale as 1 / bbox_scale: the steps are the
    # same in any scene units (an absolute 1e-8 damps them for a scene in millimetres)
    eps_g = 1e-8 / bbox_scale
    if ls is not None and settings.optim.largesteps_uniform_adam:
        opt_geom = AdamUniform([geom], lr=lr_g, betas=settings.optim.betas, eps=eps_g)
    else:
        opt_geom = torch.optim.Adam([geom], lr=lr_g, betas=settings.optim.betas, eps=eps_g)
    opt_tex = torch.optim.Adam([t for k in MAP_NAMES for t in maps[k].parameters()], lr=lr_t, betas=settings.optim.betas)
    if opt_state is not None:
        opt_geom.load_state_dict(opt_state["geom"])
        opt_tex.load_state_dict(opt_state["tex"])
    guard = (
        SurfaceGuard(mesh.t_pos_idx, topo, v_init, max_halvings=settings.optim.guard_max_halvings)
        if settings.optim.guard else None
    )
    targets = run.views.at(settings.stage_image_size(stage_settings))
    foot_out = None
    if run.foot is not None:
        cls = run.foot.classes(targets.cameras, targets.masks,
                               run.views.photos_at(settings.stage_image_size(stage_settings)))
        inside = targets.masks > 0.5
        # background: a mask pixel showing the table becomes background (target 0, full weight) and
        # only those too dark to tell stay in doubt; exclude: every doubted pixel stays in doubt
        background = settings.loss.uncertain_foot_mode == "background"
        table = cls == foot.TABLE if background else np.zeros(cls.shape, bool)
        w = np.where((cls == foot.DOUBT) if background else (cls > foot.KEEP), np.float32(run.foot.weight),
                     np.float32(1.0)).astype(np.float32)
        targets = dataclasses.replace(targets, images=torch.where(torch.from_numpy(table)[..., None], torch.zeros(()),
                                                                  targets.images),
                                      masks=np.where(table, np.float32(0), targets.masks),
                                      weights=targets.weights * torch.from_numpy(w)[..., None])
        foot_out = float(((cls > foot.KEEP) & inside).sum()) / max(float(inside.sum()), 1.0)
        log.info("stage %d: %.1f %% of the mask pixels at the object's foot in doubt (tabletop masks cannot tell it "
                 "from the table there): %d pixels showing the table made background, %d left out of the image term",
                 index, 100 * foot_out, int(table.sum()), int((w < 1).sum()))
    renderer = make_renderer(settings, mesh)
    return Stage(index, stage_settings, h, bbox_scale, mesh, v_init, covered, topo, geom, maps, opt_geom, opt_tex, ls,
                  guard, renderer, targets, foot_out=foot_out)


def _positions(st: Stage) -> torch.Tensor:
    """(V, 3) float64 vertex positions, differentiable w.r.t. the geometry parameter."""
    return st.ls.from_differential(st.geom) if st.ls is not None else st.geom


def stage_state(st: Stage, next_iteration: int) -> dict:
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
def _forward_backward(st: Stage, it: int, idx: np.ndarray, run: Run, times: dict):
    """Render the views ``idx``, evaluate the loss and backpropagate (gradients in the parameters)."""
    settings, weights = run.settings, run.weights
    t0 = time.perf_counter()
    v = _positions(st)
    t1 = time.perf_counter()
    vals = map_values(settings, st.maps)
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
    terms = {"render": objective.render_loss(img, st.targets.images[idx], st.targets.weights[idx], settings.loss.tone_map,
                                             run.tone_scale),
             **objective.geometry_terms(v, st.topo, st.h, settings.loss.laplacian, weights)}
    terms.update(objective.material_terms(
        vals["specular"], vals["diffuse"], vals["roughness"], torch.from_numpy(st.covered), weights,
        settings.loss.bilateral_sigma_space, settings.loss.bilateral_sigma_color, settings.loss.bilateral_radius))
    terms.update(objective.camera_terms(ref, idx, weights))
    terms.update(objective.imaging_terms(run.imaging.prior if run.imaging is not None and run.imaging.active
                                         else None, weights))
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


def resolve(st: Stage) -> bool:
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


def run_iteration(st: Stage, it: int, run: Run, timer: Timer) -> dict:
    """One step. The surface check of a step's result runs in a worker thread while the next
    iteration renders with it; the optimizer only steps after the check. When the check finds
    new defects, the positions are backed off and this iteration's forward/backward pass is
    redone, so the accepted trajectory is exactly that of checking synchronously."""
    settings = run.settings
    n = len(st.targets)
    B = min(int(settings.schedule.views_per_iteration), n)
    idx = np.sort(iteration_views(settings.seed, st.index, it, n, B))
    times = {p: 0.0 for p in PHASES}
    total, terms = _forward_backward(st, it, idx, run, times)
    t0 = time.perf_counter()
    redo = resolve(st)
    times["geometry"] += time.perf_counter() - t0
    if redo:
        total, terms = _forward_backward(st, it, idx, run, times)
    t4 = time.perf_counter()
    f = st.settings.lr_factor(it)
    lr_g, lr_t = schedule.learning_rates(settings, run.bbox_scale, f)
    for g in st.opt_geom.param_groups:
        g["lr"] = lr_g
    for g in st.opt_tex.param_groups:
        g["lr"] = lr_t
    st.opt_geom.step()
    st.opt_tex.step()
    if run.cameras is not None and st.index >= run.cameras.first_stage:
        run.cameras.step(f)
    if run.imaging is not None:
        run.imaging.step(f)
    p = map_params(settings)
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


def _keep_above_plane(st: Stage, plane: SupportPlane | None, v: np.ndarray) -> tuple[np.ndarray, int]:
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
