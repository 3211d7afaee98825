"""Stage ``uv``: a texture atlas for the mesh (DESIGN section 2), by xatlas.

- Components smaller than ``min_component_faces`` faces or ``min_component_area`` of the
  total area are dropped first (specks make tiny charts that waste atlas space and xatlas
  time).
- xatlas packs at ``texture_size`` texels with ``padding`` empty texels between charts and
  ``bilinear=True``. xatlas may return an atlas larger than asked for; the texel density is
  then lowered and the atlas packed again until it fits, so the padding holds in texels of
  the real texture (a bilinear lookup anywhere inside a chart touches only that chart's
  texels when padding >= 2).
- When no texel density fits ``texture_size`` (a surface of many small charts: each needs
  ``padding`` texels around it, so their padding alone can fill a small map), the map doubles
  up to ``max_texture_size`` and the atlas is packed for that (``texture_size`` in ``uv.json``,
  with a warning). The stage stops only when even that map cannot hold the charts, naming their
  number (a surface with that many tunnels or fragments is the initial mesh's problem).
- xatlas sees the mesh scaled to a unit bounding box (its float32 epsilons are absolute), so
  the atlas is the same in any units; ``texels_per_unit`` is reported in the mesh's units.
- Positions keep their topology: xatlas splits vertices at seams, but ``t_pos_idx`` maps back
  through ``vmapping`` to the unsplit vertices (the mesh stays watertight) and only the UVs
  (``v_tex``, ``t_tex_idx``) are split.
- UVs follow the OBJ convention (v up): atlas texel (row i, column j) of the ``texture_size``
  square map is at u = (j + 0.5)/T, v = 1 - (i + 0.5)/T. The atlas sits in the top-left corner
  when it is smaller than the map.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_dir
from recon.io.mesh import Mesh, MeshError, read_mesh, write_obj

log = logging.getLogger(__name__)

# xatlas 0.0.11 can hang forever when an Atlas is destroyed: ~TaskScheduler sets a worker's wakeup
# flag and notifies its condition variable without holding the worker's mutex, then joins it. A
# worker that has just finished the atlas's tasks and is between checking the flag and going to
# sleep misses that notification and never wakes (a lost wakeup; gdb: the main thread in
# std::thread::join under xatlas::Destroy, the worker in condition_variable::wait). Destroying the
# atlas right after generate() hits that window on a busy machine (the unit suite beside two busy
# processes hung there once; a loop of pack_atlas on a small sphere beside them hung in 1 of 3
# one-minute runs, about 5,000 calls each). Atlases are therefore destroyed late, by _retire: each
# is kept until it is _RETIRE_AGE_S old, when its workers have long gone back to sleep (the window
# is a few instructions; a preempted worker on a loaded machine waits a few scheduler slices, tens
# of milliseconds), and at most _RETIRED_ATLASES are kept (a tight loop drops the oldest early).
# This makes the race unlikely, it does not remove it: the fix belongs in xatlas (set the flag with
# the worker's mutex held). The cost is the kept atlases (their meshes and charts, one sleeping
# thread per extra core each).
_RETIRE_AGE_S = 0.5
_RETIRED_ATLASES = 16
_retired: deque = deque()  # (time retired, atlas), oldest first


def _retire(atlas) -> None:
    """Keep ``atlas`` alive; destroy the kept ones that are old enough, or beyond the count."""
    now = time.monotonic()
    _retired.append((now, atlas))
    while _retired and (now - _retired[0][0] >= _RETIRE_AGE_S or len(_retired) > _RETIRED_ATLASES):
        _retired.popleft()


class UVError(ValueError):
    """A mesh that cannot be unwrapped; the message names the input and the fix."""


@dataclass(frozen=True)
class UVSettings:
    texture_size: int = 1024  # the square texture the atlas is packed for (texels)
    padding: int = 4  # empty texels between charts (>= 2 for bilinear lookups)
    min_component_faces: int = 16
    min_component_area: float = 1e-4  # fraction of the total area
    max_pack_attempts: int = 6  # packings per map size (lowering the texel density each time)
    # the map grows (doubling) up to this side when the charts cannot fit texture_size: the
    # padding around each of many small charts (a surface with many tunnels) fills a small map
    # whatever the texel density. uv.json records the size used (the optimize stage makes its
    # own atlas for its own maps; this one is the initial mesh's)
    max_texture_size: int = 4096

    def __post_init__(self):
        if self.texture_size < 16:
            raise ValueError(f"texture_size must be >= 16, got {self.texture_size}")
        if self.max_texture_size < self.texture_size:
            raise ValueError(f"max_texture_size ({self.max_texture_size}) must be >= texture_size "
                             f"({self.texture_size})")
        if self.padding < 2:
            raise ValueError(f"padding must be >= 2 texels for bilinear lookups, got {self.padding}")


def drop_small_components(mesh: Mesh, min_faces: int, min_area_fraction: float) -> tuple[Mesh, int]:
    """Remove connected components below the thresholds; returns the mesh and how many went."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.t_pos_idx
    nv = len(mesh.v_pos)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    n, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nv, nv)), directed=False)
    face_label = label[f[:, 0]]
    area = 0.5 * np.linalg.norm(mesh.face_normals(), axis=1)
    comp_faces = np.bincount(face_label, minlength=n)
    comp_area = np.bincount(face_label, weights=area, minlength=n)
    keep_comp = (comp_faces >= min_faces) & (comp_area >= min_area_fraction * area.sum())
    present = comp_faces > 0
    dropped = int((present & ~keep_comp).sum())
    if not keep_comp.any():
        raise UVError(f"every component is below {min_faces} faces / {min_area_fraction:.0e} of the area; "
                      "nothing left to unwrap")
    f = f[keep_comp[face_label]]
    used = np.unique(f)
    remap = np.full(nv, -1)
    remap[used] = np.arange(len(used))
    return Mesh(mesh.v_pos[used], remap[f]), dropped


def _min_texels_per_chart(padding: int) -> int:
    """The least area one chart takes in a packed atlas: a texel, the bilinear border and
    ``padding`` empty texels on each side."""
    return (2 * int(padding) + 3) ** 2


def pack_atlas(v_pos: np.ndarray, t_pos_idx: np.ndarray, texture_size: int, padding: int, *,
               fill: float | None = None, max_attempts: int = 6,
               max_texture_size: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """xatlas charts of a mesh packed into one ``texture_size`` x ``texture_size`` map.

    The one place the project calls xatlas (the uv stage, coarse-to-fine remeshing and the
    synthetic captures' bake all come here). Positions and faces are not changed.

    Parameters
    ----------
    v_pos, t_pos_idx : (V, 3) positions and (F, 3) faces; finite, non-empty bounding box.
    texture_size : the map's side T in texels.
    padding : empty texels between charts, in texels of the T map.
    fill : fraction of the map the charts should cover at the first attempt (sets xatlas's texel
        density from the surface area); None lets xatlas choose from ``texture_size``.
    max_attempts : packings tried per map size; after an atlas larger than T or on more than one
        page (its UVs would overlap the first), the texel density is lowered and the charts
        packed again.
    max_texture_size : the map may grow (doubling T) up to this side when the charts do not fit
        T: a surface of many small charts (a high genus) needs ``padding`` texels around each
        chart whatever the texel density, so below some T no density fits. None: T is fixed
        (a caller whose maps are T x T); the error then names the chart count.

    Returns
    -------
    v_tex : (T', 2) UVs, OBJ convention (v up): atlas texel (row i, column j) is at
        u = (j + 0.5)/T, v = 1 - (i + 0.5)/T; the atlas sits in the map's top-left corner.
    t_tex_idx : (F, 3) UV indices per face (vertices split at seams).
    stats : ``charts``, ``utilization``, ``atlas_width``/``atlas_height`` (texels used),
        ``texels_per_unit`` (per unit of the mesh's frame), ``attempts`` (packings in all),
        ``texture_size`` (the map's side T the UVs refer to: the requested one unless it grew).
    """
    import xatlas

    T = int(texture_size)
    T_max = T if max_texture_size is None else max(T, int(max_texture_size))
    v64 = np.asarray(v_pos, dtype=np.float64)
    f = np.asarray(t_pos_idx, dtype=np.int64)
    if len(f) == 0:
        raise UVError("the mesh has no faces")
    if not np.all(np.isfinite(v64)):
        raise UVError("the mesh has NaN or Inf vertex positions")
    # xatlas works in float32 with absolute epsilons (faces below ~1e-7 in area count as
    # degenerate): unwrap a copy scaled to a unit bounding box, so the atlas does not depend
    # on the scene's units (a 1 mm object unwraps like a 1 m one)
    lo, hi = v64.min(0), v64.max(0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise UVError("the mesh has an empty bounding box (all vertices at one point)")
    v_unit = (v64 - 0.5 * (lo + hi)) / extent
    v32 = v_unit.astype(np.float32)
    f32 = f.astype(np.uint32)
    p = v_unit[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()

    def first_density(size: int) -> float:  # 0: xatlas chooses from the resolution
        return float(np.sqrt(fill * size * size / area)) if fill is not None and area > 0 else 0.0

    tpu = first_density(T)
    attempts = 0
    charts = 0
    fitted = False
    while not fitted:
        for _ in range(int(max_attempts)):
            attempts += 1
            atlas = xatlas.Atlas()
            atlas.add_mesh(v32, f32)
            pack = xatlas.PackOptions()
            pack.resolution = T
            pack.padding = int(padding)
            pack.bilinear = True
            if tpu > 0:
                pack.texels_per_unit = tpu
            atlas.generate(xatlas.ChartOptions(), pack)
            _retire(atlas)  # destroyed later, not at the next rebinding (see _RETIRE_AGE_S)
            w, h, pages, charts = int(atlas.width), int(atlas.height), int(atlas.atlas_count), int(atlas.chart_count)
            # one page only: with texels_per_unit set, xatlas may spill charts onto a second page
            if max(w, h) <= T and pages == 1:
                fitted = True
                break
            if T_max > T and charts * _min_texels_per_chart(padding) > 0.8 * T * T:
                # only where the map may grow: at a fixed size (the optimize stage's maps) xatlas
                # still fits more charts than this bound (18-20 charts with 2-texel padding at 32^2)
                log.debug("%d charts with %d-texel padding cannot fit a %d-texel map at any density", charts,
                          padding, T)
                break  # no density helps: the padding alone fills the map
            # the shrink of the first packing rule (an atlas on a second page: 0.85; one shrunk to fit
            # T: 0.97): a larger step left the optimize stage's maps a quarter filled
            shrink = (T / max(w, h) if max(w, h) > T else 1.0) * (0.97 if pages == 1 else 0.85)
            tpu = float(atlas.texels_per_unit) * shrink
            log.debug("atlas %dx%d on %d page(s) does not fit one %d-texel page: packing again at %.2f "
                      "texels per unit", w, h, pages, T, tpu)
        if fitted:
            break
        if 2 * T > T_max:
            need = charts * _min_texels_per_chart(padding)
            what = (f"{charts} charts with {padding}-texel padding need at least {need} texels, "
                    f"{need / (T * T):.0%} of a {T}x{T} map" if need > 0.8 * T * T
                    else f"{charts} charts did not fit in {attempts} packings")
            raise UVError(f"xatlas could not fit the atlas into {T}x{T} texels: {what}. A surface with that many "
                          "charts has many tunnels or fragments (see the initial mesh's genus)")
        T *= 2
        while charts * _min_texels_per_chart(padding) > 0.4 * T * T and 2 * T <= T_max:
            T *= 2  # room for the padding and as much again for the charts themselves
        tpu = first_density(T)
        log.warning("the atlas's %d charts do not fit the map with %d-texel padding: growing the map to %dx%d",
                    charts, padding, T, T)
    vmapping, indices, uv_norm = atlas[0]
    indices = np.asarray(indices, dtype=np.int64)
    if indices.shape != f.shape or not np.array_equal(np.asarray(vmapping, dtype=np.int64)[indices], f):
        raise UVError("xatlas reordered the faces; cannot map the UVs back to the mesh")
    texel = np.asarray(uv_norm, dtype=np.float64) * np.array([w, h])  # atlas texels (x right, y down)
    v_tex = np.stack([texel[:, 0] / T, 1.0 - texel[:, 1] / T], axis=1)
    stats = {
        "charts": charts,
        "utilization": float(atlas.utilization),
        "atlas_width": w,
        "atlas_height": h,
        "texels_per_unit": float(atlas.texels_per_unit) / extent,  # per unit of the mesh's frame
        "attempts": attempts,
        "texture_size": T,
    }
    return v_tex, indices, stats


def unwrap(mesh: Mesh, settings: UVSettings = UVSettings()) -> tuple[Mesh, dict]:
    """UV-unwrap ``mesh`` (positions unchanged, UVs split at seams).

    Returns
    -------
    mesh : Mesh with ``v_tex (T, 2)`` and ``t_tex_idx (F, 3)``; ``v_pos``/``t_pos_idx`` are the
        input's (minus dropped components).
    stats : dict with ``charts``, ``utilization``, ``atlas_width``/``atlas_height`` (texels
        used in the map), ``texels_per_unit``, ``dropped_components``, ``attempts``,
        ``texture_size`` (the map the UVs refer to) and ``requested_texture_size``.
    """
    if len(mesh.t_pos_idx) == 0:
        raise UVError("the mesh has no faces")
    if not np.all(np.isfinite(mesh.v_pos)):
        raise UVError("the mesh has NaN or Inf vertex positions")
    mesh, dropped = drop_small_components(mesh, settings.min_component_faces, settings.min_component_area)
    if dropped:
        log.info("dropped %d small component(s) before unwrapping", dropped)
    v_tex, t_tex_idx, pack = pack_atlas(mesh.v_pos, mesh.t_pos_idx, settings.texture_size, settings.padding,
                                        max_attempts=settings.max_pack_attempts,
                                        max_texture_size=settings.max_texture_size)
    if pack["attempts"] > 1:
        log.info("atlas packed in %d attempts at %.2f texels per unit", pack["attempts"], pack["texels_per_unit"])
    out = Mesh(mesh.v_pos, mesh.t_pos_idx, v_tex, t_tex_idx)
    stats = {
        **pack,
        "requested_texture_size": settings.texture_size,
        "padding": settings.padding,
        "dropped_components": dropped,
        "faces": int(len(out.t_pos_idx)),
        "uv_vertices": int(len(v_tex)),
    }
    return out, stats


def run_uv(mesh_path: str | os.PathLike, out_dir: str | os.PathLike, settings: UVSettings = UVSettings()) -> dict:
    """Write ``out_dir/mesh.obj`` (with UVs) and ``out_dir/uv.json``; ``out_dir`` is replaced atomically."""
    t0 = time.perf_counter()
    try:
        mesh = read_mesh(mesh_path)
    except MeshError as e:
        raise UVError(f"{e}; rerun the init_mesh stage") from e
    try:
        out, stats = unwrap(mesh, settings)
    except UVError as e:
        raise UVError(f"{mesh_path}: {e}") from e
    stats["seconds"] = time.perf_counter() - t0
    stats["settings"] = asdict(settings)
    with atomic_dir(out_dir) as tmp:
        write_obj(Path(tmp) / "mesh.obj", out)
        (Path(tmp) / "uv.json").write_text(json.dumps(stats, indent=1))
    log.info("uv: %d charts, utilization %.1f%%, atlas %dx%d in a %d^2 map, padding %d texels, %.1f s",
             stats["charts"], 100 * stats["utilization"], stats["atlas_width"], stats["atlas_height"],
             stats["texture_size"], stats["padding"], stats["seconds"])
    return stats
