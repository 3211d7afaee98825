"""Robust surface evolution: every accepted vertex update keeps the mesh free of new defects.

The paper moves vertices with El Topo; here the same guarantee comes from checking each
proposed update and backing off where it fails. A step from a valid mesh ``v_old`` towards
``v_new`` is checked for three defects (each only counts when the old mesh did not already
have it, so an imperfect initial mesh does not freeze the optimization):

- self-intersections between non-adjacent faces (pymeshlab's per-face test, a uniform grid
  in C++: ~25 ms for 20k faces on one core),
- folds: two faces sharing an edge whose normals point against each other
  (``n_i . n_j < fold_cos``; pymeshlab skips adjacent faces, so this catches flipped faces),
- degenerate faces (area below ``1e-10`` of the squared mean edge length).

The displacement of the vertices of offending faces is halved until the step passes
(at most ``max_halvings`` times), then those vertices stay where they were (up to three rounds),
then (it makes the guarantee unconditional) the whole step is undone.
Connectivity never changes during a stage, so manifoldness is preserved by construction.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from recon.optimize.regularizers import MeshTopology

log = logging.getLogger(__name__)


def self_intersecting_faces(v_pos: np.ndarray, t_pos_idx: np.ndarray) -> np.ndarray:
    """(F,) bool: faces that intersect a non-adjacent face (pymeshlab)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(v_pos, dtype=np.float64), np.asarray(t_pos_idx, dtype=np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return np.asarray(ms.current_mesh().face_selection_array(), dtype=bool)


def _face_geometry(v_pos: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = v_pos[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    a2 = np.linalg.norm(n, axis=1)
    return n / np.maximum(a2, 1e-300)[:, None], a2


@dataclass
class DefectState:
    """Per-face/per-pair defects of one vertex configuration."""

    intersecting: np.ndarray  # (F,) bool
    folded_pairs: np.ndarray  # (P,) bool
    degenerate: np.ndarray  # (F,) bool

    @property
    def n_defects(self) -> int:
        return int(self.intersecting.sum() + self.folded_pairs.sum() + self.degenerate.sum())


@dataclass
class GuardStats:
    checks: int = 0
    halved_steps: int = 0
    frozen_vertices: int = 0
    reverted_steps: int = 0
    history: list = field(default_factory=list)


class SurfaceGuard:
    """Accepts vertex updates that add no self-intersection, fold or degenerate face.

    Parameters
    ----------
    t_pos_idx : (F, 3) int
    topo : MeshTopology of the same faces (for the edge-adjacent face pairs)
    v_init : (V, 3) the current (accepted) positions; its own defects are tolerated
    max_halvings : int
    fold_cos : float
        Adjacent faces with ``n_i . n_j`` below this are folded (-0.5: a 120 degree turn).
    """

    def __init__(self, t_pos_idx: np.ndarray, topo: MeshTopology, v_init: np.ndarray,
                 max_halvings: int = 8, fold_cos: float = -0.5):
        self.faces = np.asarray(t_pos_idx, dtype=np.int64)
        self.pairs = topo.face_pairs.numpy()
        self.max_halvings = int(max_halvings)
        self.fold_cos = float(fold_cos)
        e = topo.edges.numpy()
        v = np.asarray(v_init, dtype=np.float64)
        self.area_eps = 1e-10 * float(np.mean(np.sum((v[e[:, 0]] - v[e[:, 1]]) ** 2, axis=1)))
        self.baseline = self.defects(v)
        self.stats = GuardStats()
        if self.baseline.n_defects:
            log.warning(
                "the mesh already has %d self-intersecting faces, %d folded face pairs and %d degenerate "
                "faces; the guard only prevents new ones",
                self.baseline.intersecting.sum(), self.baseline.folded_pairs.sum(), self.baseline.degenerate.sum(),
            )

    def defects(self, v_pos: np.ndarray) -> DefectState:
        n, a2 = _face_geometry(v_pos, self.faces)
        folded = (n[self.pairs[:, 0]] * n[self.pairs[:, 1]]).sum(1) < self.fold_cos if len(self.pairs) else np.zeros(0, bool)
        return DefectState(self_intersecting_faces(v_pos, self.faces), folded, a2 < self.area_eps)

    def new_bad_faces(self, v_pos: np.ndarray) -> np.ndarray:
        """(F,) bool: faces with a defect the baseline did not have."""
        self.stats.checks += 1
        d = self.defects(v_pos)
        bad = (d.intersecting & ~self.baseline.intersecting) | (d.degenerate & ~self.baseline.degenerate)
        fold_new = d.folded_pairs & ~self.baseline.folded_pairs
        if fold_new.any():
            bad[self.pairs[fold_new].ravel()] = True
        return bad

    def accept(self, v_old: np.ndarray, v_new: np.ndarray, first_bad: np.ndarray | None = None
               ) -> tuple[np.ndarray, dict]:
        """The accepted positions (V, 3) for a proposed step ``v_old -> v_new`` and a report.

        ``v_old`` must be the last accepted positions (defect-free relative to the baseline);
        ``first_bad`` is :meth:`new_bad_faces` of ``v_new`` when it was already computed.
        """
        v_old = np.asarray(v_old, dtype=np.float64)
        disp = np.asarray(v_new, dtype=np.float64) - v_old
        scale = np.ones(len(v_old))
        info = {"halvings": 0, "frozen": 0, "reverted": False}
        freeze_rounds = 0
        v = v_old + disp
        bad = self.new_bad_faces(v) if first_bad is None else first_bad
        while bad.any():
            verts = np.unique(self.faces[bad])
            if info["halvings"] < self.max_halvings:
                scale[verts] *= 0.5
                info["halvings"] += 1
            elif freeze_rounds < 3:
                scale[verts] = 0.0
                info["frozen"] += int(len(verts))
                freeze_rounds += 1
            else:
                info["reverted"] = True
                scale[:] = 0.0
                v = v_old.copy()
                break
            v = v_old + disp * scale[:, None]
            bad = self.new_bad_faces(v)
        self.stats.halved_steps += info["halvings"] > 0
        self.stats.frozen_vertices += info["frozen"]
        self.stats.reverted_steps += info["reverted"]
        return v, info
