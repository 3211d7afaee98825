"""A run of the coarse-to-fine loop: what it knows, its stages one after the other, its
checkpoints (sec. 3.2-3.4).

:func:`execute` resumes a run from its checkpoint when that matches, else starts it, and runs
its stages (:func:`recon.optimize.iteration.run_iteration` per iteration). Between stages:
remesh, re-unwrap, bake the maps onto the new atlas (:mod:`recon.optimize.remesh`), check that
the surface did not collapse, select the loop's imaging terms (``imaging.loop: select``) and test
for a plateau (:func:`recon.optimize.schedule.plateau`).

Timings are kept per phase, as in the paper's supplement: ``render`` (forward rendering),
``loss`` (rendering loss and priors), ``backward`` (backpropagation through both),
``step`` (optimizer), ``geometry`` (large-steps solves, waiting for and acting on the surface
guard, remeshing, unwrapping and baking), ``setup`` (building renderers and targets for a
stage, writing checkpoints), ``material`` (material selection, plateau tests), ``cameras``
(aligning the held-out views' poses to the fitted model). The guard's self-intersection test
runs in a worker thread while the next iteration renders; its CPU time is reported apart
(``guard_check_seconds``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from recon.io.mesh import Mesh
from recon.optimize import checkpoint as ckpt
from recon.optimize import schedule
from recon.optimize.imaging_select import select_for_loop
from recon.optimize.iteration import PHASES, Stage, build_stage, map_values, resolve, run_iteration, stage_state
from recon.optimize.loop_imaging import LoopImaging
from recon.optimize.material import model_from_settings
from recon.optimize.params import constant_map
from recon.optimize.radiometry import CollapseError, LightScale, check_not_collapsed, mask_coverage
from recon.optimize.remesh import rasterize_atlas, remesh, remesh_and_rebake, topology_report, unwrap
from recon.optimize.settings import OptimizeSettings, StageSettings
from recon.optimize.views import Views, pixel_footprint
from recon.support import SupportPlane

if TYPE_CHECKING:
    from recon.optimize.cameras import CameraFit
    from recon.optimize.foot import FootZone

log = logging.getLogger(__name__)


class OptimizeError(ValueError):
    """Inputs the optimize stage cannot work with; the message names the file and the fix."""


@dataclass(frozen=True)
class Run:
    """What a run knows, built once by :func:`recon.optimize.loop.optimize_capture`: the settings and the values
    derived from them, the views and where checkpoints go."""

    settings: OptimizeSettings
    stages: tuple  # effective StageSettings
    views: Views  # training views
    heldout: Views | None
    bbox_scale: float  # longest side of the initial mesh's bounding box
    weights: dict  # objective.weights(settings)
    tone_scale: float
    light: float  # the flash's I_e (given, or estimated from the photos: light.scale)
    ckpt_dir: Path
    fingerprint: str
    cameras: "CameraFit | None" = None  # the camera refinement (None: the cameras are fixed)
    plane: SupportPlane | None = None  # the table the object stands on: no vertex goes below it
    imaging: LoopImaging | None = None  # imaging terms in the loop (imaging.loop: select)
    ldr: bool | None = None  # the photos were JPEG/PNG (the tone curve is tried)
    light_scale: LightScale | None = None  # where ``light`` came from; the initial diffuse albedo
    area_init: float = 0.0  # the initial mesh's area (the collapse check)
    exposure: dict | None = None  # stem -> the recorded (EXIF) exposure linearize divided out (the tone curve's domain)
    foot: "FootZone | None" = None  # tabletop masks' doubtful foot pixels, out of the image term (recon.optimize.foot)


@dataclass
class Progress:
    """What a run accumulates (saved in checkpoints) and reports to."""

    timer: "Timer"
    records: list
    stage_infos: list
    executor: object = None
    bar: object = None
    callback: Callable[[dict], None] | None = None


class Timer:
    def __init__(self):
        self.total = {p: 0.0 for p in PHASES}

    def add(self, phase: str, seconds: float) -> None:
        self.total[phase] += seconds


def execute(run: Run, init: Mesh, progress: bool, callback) -> tuple[Stage, Progress]:
    """One run of the coarse-to-fine loop, resumed from its checkpoint when that matches."""
    stages = run.stages
    state = ckpt.load(run.ckpt_dir, run.fingerprint)
    timer = Timer()
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
    prog = Progress(timer, records, stage_infos, bar=bar, callback=callback,
                     executor=ThreadPoolExecutor(max_workers=1, thread_name_prefix="surface-guard"))
    try:
        st = _run_stages(run, prog, init, state, start_stage, start_it)
    finally:
        prog.executor.shutdown(wait=True)
    if bar is not None:
        bar.close()
    return st, prog


def _run_stages(run: Run, prog: Progress, init: Mesh, state: dict | None, start_stage: int,
                start_it: int) -> Stage:
    """The coarse-to-fine loop; returns the last stage (its accepted mesh and maps)."""
    settings, stages, views, timer = run.settings, run.stages, run.views, prog.timer
    stage_infos, bar = prog.stage_infos, prog.bar
    st: Stage | None = None
    prev_mesh, prev_maps = None, None
    lo, hi = init.bbox()
    footprint_full = pixel_footprint(views.cameras, (lo + hi) / 2)
    for si in range(start_stage, len(stages)):
        stage = stages[si]
        h, h_req, h_min = schedule.stage_edge_length(stage, settings, views, footprint_full, run.bbox_scale)
        t0 = time.perf_counter()
        if state is not None and si == start_stage:
            m = state["mesh"]
            mesh = Mesh(m["v_pos"], m["t_pos_idx"], m["v_tex"], m["t_tex_idx"])
            st = build_stage(run, si, stage, h, mesh, np.asarray(m["v_init"]), np.asarray(state["covered"]),
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
            st = build_stage(run, si, stage, h, mesh, mesh.v_pos.copy(), covered, maps)
            timer.add("setup", time.perf_counter() - t1)
            it0 = 0
            log.info("stage %d: %d vertices, %d faces, %dx%d maps, %dx%d images, edge %.4g",
                     si, len(mesh.v_pos), len(mesh.t_pos_idx), stage.texture_size, stage.texture_size,
                     st.targets.cameras[0].width, st.targets.cameras[0].height, h)
            stage_infos.append({**_stage_info(st), "edge_length_requested": h_req, "edge_length_min": h_min})
            save(run, prog, st, 0, done=False)
        st.executor = prog.executor
        for it in range(it0, int(stage.iterations)):
            rec = run_iteration(st, it, run, timer)
            prog.records.append(rec)
            if bar is not None:
                bar.set_postfix(stage=si, loss=f"{rec['loss']:.4g}", refresh=False)
                bar.update(1)
            if (it + 1) % int(settings.schedule.checkpoint_every) == 0 or it + 1 == int(stage.iterations):
                t0 = time.perf_counter()
                resolve(st)  # checkpoints hold checked positions only
                timer.add("geometry", time.perf_counter() - t0)
                save(run, prog, st, it + 1, done=False)
            if prog.callback is not None:
                prog.callback(rec)
        prev_mesh = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
        t0 = time.perf_counter()
        stage_infos[-1]["mask_coverage"] = _check_collapse(run, prev_mesh, st, si)
        timer.add("geometry", time.perf_counter() - t0)
        with torch.no_grad():
            prev_maps = {k: v.numpy().astype(np.float32) for k, v in map_values(settings, st.maps).items()}
        if run.imaging is not None and run.imaging.evidence is None and si >= int(settings.imaging.loop_stage) \
                and si + 1 < len(stages):
            t0 = time.perf_counter()
            _select_loop_imaging(run, prev_mesh, prev_maps, st.covered, si)
            timer.add("material", time.perf_counter() - t0)
        if settings.select.stop_on_plateau and run.heldout is not None:
            t0 = time.perf_counter()
            stop = schedule.plateau(run, si, prev_mesh, prev_maps, stage_infos)
            timer.add("material", time.perf_counter() - t0)
            if stop and si + 1 < len(stages):
                if bar is not None:
                    bar.total = bar.n
                    bar.refresh()
                log.info("stage %d: held-out error did not improve on stage %d's; skipping the remaining %d "
                         "stage(s) (stop_on_plateau)", si, si - 1, len(stages) - si - 1)
                save(run, prog, st, int(stage.iterations), done=False)
                break
    return st


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
        "diffuse": constant_map(T, 3, settings.material.init_diffuse if init_diffuse is None else init_diffuse),
        "specular": constant_map(T, settings.material.specular_channels, settings.material.init_specular),
        "roughness": constant_map(T, 1, settings.material.init_roughness),
    }
    return mesh, maps, face >= 0


def _stage_info(st: Stage) -> dict:
    return {
        "stage": st.index,
        "edge_length": st.h,
        "texture_size": int(st.settings.texture_size),
        "image_size": [int(st.targets.cameras[0].width), int(st.targets.cameras[0].height)],
        "vertices": int(len(st.mesh.v_pos)),
        "faces": int(len(st.mesh.t_pos_idx)),
        "largesteps_lambda": st.ls.lam if st.ls is not None else None,
        "foot_pixels_out": st.foot_out,
    }


def _check_collapse(run: Run, mesh: Mesh, st: Stage, si: int) -> dict:
    """Stop a run whose surface left the masks or shrank away (:func:`check_not_collapsed`)."""
    cov = mask_coverage(mesh, st.targets.cameras, st.targets.masks)
    log.info("stage %d: the surface covers %.1f %% of the masks (worst view %.1f %%), %.1f %% of it outside them",
             si, 100 * cov["covered_mean"], 100 * cov["covered_min"], 100 * cov["outside_mean"])
    try:
        check_not_collapsed(f"optimize stage {si}", cov, float(mesh.area()), run.area_init, run.light_scale,
                            run.settings.light.collapse_min_covered, run.settings.light.collapse_min_area)
    except CollapseError as e:
        raise OptimizeError(str(e)) from e
    return cov


def _select_loop_imaging(run: Run, mesh: Mesh, maps: dict, covered: np.ndarray, si: int) -> None:
    """``imaging.loop: select``: the imaging selection on stage ``si``'s model; the later stages
    optimize under the chosen terms (:class:`recon.optimize.loop_imaging.LoopImaging`)."""
    settings = run.settings
    size = int(settings.select.select_image_size)
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
    params, ev = select_for_loop(settings, mesh, maps, model_from_settings(settings.material.specular_channels), covered,
                                 train_vs, held_vs, run.light, run.tone_scale, run.ldr, exposure=run.exposure)
    ev["after_stage"] = si
    run.imaging.adopt(params, ev)
    log.info("imaging terms for the loop: %s", ", ".join(ev["chosen"]) or "none (the ideal formation)")


def save(run: Run, prog: Progress, st: Stage, next_it: int, done: bool) -> None:
    t0 = time.perf_counter()
    state = stage_state(st, next_it)
    state.update(fingerprint=run.fingerprint, records=prog.records, stage_infos=prog.stage_infos,
                 timings=dict(prog.timer.total), done=done)
    if run.cameras is not None:
        state["cameras"] = run.cameras.state()
    if run.imaging is not None:
        state["imaging"] = run.imaging.state()
    ckpt.save(run.ckpt_dir, state)
    prog.timer.add("setup", time.perf_counter() - t0)
