"""The regularizers of sec. 3.3 (mesh and material priors), in torch.

The paper writes plain sums; here every term is a mean (over vertices, edges, face pairs or
texels) and lengths are divided by the stage's target edge length ``h``, so a weight means the
same at every mesh and texture resolution and for every object size:

- Laplacian   ``mean_i |(L V)_i / h|^2`` with the uniform Laplacian
  ``(L V)_i = v_i - mean_{j ~ i} v_j``, or ``mean_i |h/4 (L_cot V)_i|^2`` with the cotangent
  Laplacian ``(L_cot V)_i = 1/(2 A_i) sum_j (cot a_ij + cot b_ij)(v_i - v_j)`` (A_i: one third
  of the incident face areas; the cotangent weights are held constant within an evaluation).
  On a regular mesh both approximate ``(h/2 H)^2`` (H: mean curvature), so one weight fits both.
- normal consistency ``mean_(i,j) (1 - n_i . n_j)^2`` over face pairs sharing an edge.
- edge length ``sqrt(mean_e |e|^2) / h`` over the unique edges (the paper's (sum e^2)^(1/2)).
- specular/diffuse correlation (eq. 9) ``mean_p |a_s[p] - sum_q mu_pq a_s[q] / sum_q mu_pq|``
  with ``mu_pq = exp(-|p - q|^2 / (2 s1^2) - |a_d[p] - a_d[q]|^2 / (2 s2^2))`` over a
  (2r+1)^2 window; a_d enters mu without gradient (it says where a_s should be smooth).
- roughness total variation ``(sum |r[i+1,j] - r[i,j]| + |r[i,j+1] - r[i,j]|) / n_texels``.

The texture terms skip texels outside the atlas charts when a ``valid`` mask is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


# ---- Mesh connectivity (computed once per stage) ----
@dataclass
class MeshTopology:
    """Index tensors derived from ``t_pos_idx (F, 3)`` for the mesh terms.

    faces : (F, 3) long
    edges : (E, 2) long, unique undirected edges (i < j)
    face_pairs : (P, 2) long, faces sharing an edge
    degree : (V,) float, number of neighbours of each vertex
    """

    n_vertices: int
    faces: torch.Tensor
    edges: torch.Tensor
    face_pairs: torch.Tensor
    degree: torch.Tensor

    @staticmethod
    def from_faces(t_pos_idx: np.ndarray, n_vertices: int) -> "MeshTopology":
        f = np.asarray(t_pos_idx, dtype=np.int64).reshape(-1, 3)
        if f.size == 0:
            raise ValueError("a mesh without faces has no topology")
        if f.min() < 0 or f.max() >= n_vertices:
            raise ValueError(f"face indices must be in [0, {n_vertices}), got [{f.min()}, {f.max()}]")
        he = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # (3F, 2) half-edges
        face_of = np.tile(np.arange(len(f)), 3)
        und = np.sort(he, axis=1)
        edges, inv = np.unique(und, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        # face pairs: faces grouped by edge; all pairs within each group
        order = np.argsort(inv, kind="stable")
        inv_s, face_s = inv[order], face_of[order]
        starts = np.flatnonzero(np.r_[True, inv_s[1:] != inv_s[:-1]])
        counts = np.diff(np.r_[starts, len(inv_s)])
        pairs = []
        for c in np.unique(counts):
            if c < 2:
                continue
            grp = starts[counts == c]
            for a in range(c):
                for b in range(a + 1, c):
                    pairs.append(np.stack([face_s[grp + a], face_s[grp + b]], axis=1))
        face_pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
        degree = np.bincount(edges.reshape(-1), minlength=n_vertices).astype(np.float32)
        return MeshTopology(
            n_vertices=int(n_vertices),
            faces=torch.from_numpy(f),
            edges=torch.from_numpy(edges.astype(np.int64)),
            face_pairs=torch.from_numpy(face_pairs.astype(np.int64)),
            degree=torch.from_numpy(degree),
        )


def _check_v(v_pos: torch.Tensor, topo: MeshTopology) -> None:
    if v_pos.ndim != 2 or v_pos.shape[1] != 3 or v_pos.shape[0] != topo.n_vertices:
        raise ValueError(f"v_pos must be ({topo.n_vertices}, 3), got {tuple(v_pos.shape)}")


# ---- Mesh terms ----
def uniform_laplacian(v_pos: torch.Tensor, topo: MeshTopology) -> torch.Tensor:
    """(V, 3) ``v_i - mean of the neighbours of i`` (0 for isolated vertices)."""
    _check_v(v_pos, topo)
    i, j = topo.edges[:, 0], topo.edges[:, 1]
    s = torch.zeros_like(v_pos)
    s = s.index_add(0, i, v_pos[j]).index_add(0, j, v_pos[i])
    deg = topo.degree.to(v_pos.dtype).clamp(min=1.0)[:, None]
    lap = v_pos - s / deg
    return torch.where(topo.degree[:, None] > 0, lap, torch.zeros_like(lap))


def cotangent_laplacian(v_pos: torch.Tensor, topo: MeshTopology) -> torch.Tensor:
    """(V, 3) ``1/(2 A_i) sum_j (cot a + cot b)(v_i - v_j)`` (approx. 2 H n, H mean curvature).

    Cotangent weights and areas are evaluated without gradient (constant per evaluation).
    """
    _check_v(v_pos, topo)
    f = topo.faces
    with torch.no_grad():
        p = v_pos.detach()[f]  # (F, 3, 3)
        area2 = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).norm(dim=1).clamp(min=1e-20)
        cots = []
        for k in range(3):  # angle at corner k, opposite edge (k+1, k+2)
            a = p[:, (k + 1) % 3] - p[:, k]
            b = p[:, (k + 2) % 3] - p[:, k]
            cots.append((a * b).sum(1) / area2)
        mass = torch.zeros(topo.n_vertices, dtype=v_pos.dtype)
        for k in range(3):
            mass.index_add_(0, f[:, k], area2 / 6.0)
        mass = mass.clamp(min=1e-20)
    out = torch.zeros_like(v_pos)
    for k in range(3):
        i, j = f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        w = cots[k][:, None]
        d = v_pos[i] - v_pos[j]
        out = out.index_add(0, i, w * d).index_add(0, j, -w * d)
    return out / (2.0 * mass[:, None])


def laplacian_loss(v_pos: torch.Tensor, topo: MeshTopology, h: float, kind: str = "uniform") -> torch.Tensor:
    """Scalar ``mean_i |(L V)_i / h|^2`` (uniform) or ``mean_i |h/4 (L_cot V)_i|^2`` (cotangent)."""
    if not h > 0:
        raise ValueError(f"h must be > 0, got {h}")
    if kind == "uniform":
        lv = uniform_laplacian(v_pos, topo) / h
    elif kind == "cotangent":
        lv = cotangent_laplacian(v_pos, topo) * (h / 4.0)
    else:
        raise ValueError(f"kind must be 'uniform' or 'cotangent', got {kind!r}")
    return (lv * lv).sum(1).mean()


def face_normals(v_pos: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) unit face normals (zero-area faces give a finite, arbitrary unit-ish vector)."""
    p = v_pos[faces]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / torch.sqrt((n * n).sum(1, keepdim=True) + 1e-30)


def normal_consistency_loss(v_pos: torch.Tensor, topo: MeshTopology) -> torch.Tensor:
    """Scalar ``mean over face pairs sharing an edge of (1 - n_i . n_j)^2``."""
    _check_v(v_pos, topo)
    if len(topo.face_pairs) == 0:
        return v_pos.sum() * 0.0
    n = face_normals(v_pos, topo.faces)
    c = (n[topo.face_pairs[:, 0]] * n[topo.face_pairs[:, 1]]).sum(1)
    return ((1.0 - c) ** 2).mean()


def edge_length_loss(v_pos: torch.Tensor, topo: MeshTopology, h: float) -> torch.Tensor:
    """Scalar ``sqrt(mean_e |e|^2) / h`` over the unique edges."""
    _check_v(v_pos, topo)
    if not h > 0:
        raise ValueError(f"h must be > 0, got {h}")
    d = v_pos[topo.edges[:, 0]] - v_pos[topo.edges[:, 1]]
    return torch.sqrt((d * d).sum(1).mean() + 1e-30) / h


# ---- Material terms ----
def _check_map(x: torch.Tensor, name: str) -> None:
    if x.ndim != 3:
        raise ValueError(f"{name} must be (H, W, C), got {tuple(x.shape)}")


def specular_bilateral_loss(
    specular: torch.Tensor,
    diffuse: torch.Tensor,
    sigma_space: float = 1.0,
    sigma_color: float = 0.1,
    radius: int = 2,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. 9: L1 distance of ``specular (H, W, Cs)`` to its diffuse-guided bilateral average.

    ``diffuse (H, W, 3)`` sets the weights (no gradient through it); ``valid (H, W)`` bool
    restricts both p and q to texels inside the atlas charts.
    """
    _check_map(specular, "specular")
    _check_map(diffuse, "diffuse")
    if specular.shape[:2] != diffuse.shape[:2]:
        raise ValueError(f"specular {tuple(specular.shape)} and diffuse {tuple(diffuse.shape)} differ in size")
    if not (sigma_space > 0 and sigma_color > 0 and radius >= 1):
        raise ValueError("need sigma_space > 0, sigma_color > 0, radius >= 1")
    H, W = specular.shape[:2]
    r = int(radius)
    pad = torch.nn.functional.pad
    vq = torch.ones((H, W), dtype=specular.dtype) if valid is None else valid.to(specular.dtype)
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    # ---- weights mu_pq / sum_q mu_pq (constant: no gradient); contiguous channels-first maps ----
    with torch.no_grad():
        d = diffuse.detach().to(specular.dtype).permute(2, 0, 1).contiguous()
        dp = pad(d, (r, r, r, r))
        vp = pad(vq, (r, r, r, r))
        weights = []
        den = torch.zeros((H, W), dtype=specular.dtype)
        for dy, dx in offsets:
            w = (d - dp[:, r + dy:r + dy + H, r + dx:r + dx + W]).square_().sum(0)
            w.mul_(-1.0 / (2 * sigma_color**2)).add_(-(dy * dy + dx * dx) / (2 * sigma_space**2)).exp_()
            w.mul_(vp[r + dy:r + dy + H, r + dx:r + dx + W])
            den.add_(w)
            weights.append(w)
        den.clamp_(min=1e-12)
        for w in weights:
            w.div_(den)
    # ---- the weighted average of specular and the L1 distance to it ----
    s_cf = specular.permute(2, 0, 1).contiguous()
    sp = pad(s_cf, (r, r, r, r))
    avg = sum(w * sp[:, r + dy:r + dy + H, r + dx:r + dx + W] for w, (dy, dx) in zip(weights, offsets, strict=True))
    err = (s_cf - avg).abs().mean(0) * vq
    return err.sum() / vq.sum().clamp(min=1.0)


def roughness_tv_loss(roughness: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Anisotropic total variation of ``roughness (H, W, C)`` per texel (pairs inside ``valid``)."""
    _check_map(roughness, "roughness")
    r = roughness
    dy = (r[1:] - r[:-1]).abs().mean(-1)
    dx = (r[:, 1:] - r[:, :-1]).abs().mean(-1)
    if valid is None:
        n = r.shape[0] * r.shape[1]
        return (dy.sum() + dx.sum()) / n
    v = valid.to(r.dtype)
    vy = v[1:] * v[:-1]
    vx = v[:, 1:] * v[:, :-1]
    return ((dy * vy).sum() + (dx * vx).sum()) / v.sum().clamp(min=1.0)
