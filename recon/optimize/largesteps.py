"""Large-steps preconditioning (Nicolet, Jacobson, Jakob 2021), on the CPU.

Vertex positions ``v (V, 3)`` are optimized through ``u = M v`` with ``M = I + lambda L`` and
``L = D - A`` the combinatorial (graph) Laplacian. ``v = M^-1 u`` is solved with a sparse
Cholesky factorization (cholespy, float64), and the same solve carries gradients back
(``M`` is symmetric). The matrix is built here with numpy/scipy because the ``largesteps``
package's builder hard-codes CUDA (STACK.md).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch


def combinatorial_laplacian(t_pos_idx: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) ``D - A`` of the mesh's edge graph (each undirected edge once)."""
    f = np.asarray(t_pos_idx, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    i = np.concatenate([e[:, 0], e[:, 1]])
    j = np.concatenate([e[:, 1], e[:, 0]])
    A = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices))
    D = sp.diags(np.asarray(A.sum(axis=1)).ravel())
    return (D - A).tocsr()


class LargeSteps:
    """``M = I + lambda L`` for a fixed mesh connectivity, with differentiable ``M^-1``.

    Parameters
    ----------
    t_pos_idx : (F, 3) int
    n_vertices : int
    lam : float
        lambda > 0; larger diffuses gradients further over the surface.
    """

    def __init__(self, t_pos_idx: np.ndarray, n_vertices: int, lam: float):
        from cholespy import CholeskySolverD, MatrixType

        if not lam > 0:
            raise ValueError(f"lambda must be > 0, got {lam}")
        self.lam = float(lam)
        self.n = int(n_vertices)
        M = (sp.identity(self.n, format="csr") + self.lam * combinatorial_laplacian(t_pos_idx, self.n)).tocoo()
        self.M = M.tocsr()
        self._solver = CholeskySolverD(
            self.n,
            np.ascontiguousarray(M.row, dtype=np.int32),
            np.ascontiguousarray(M.col, dtype=np.int32),
            np.ascontiguousarray(M.data, dtype=np.float64),
            MatrixType.COO,
        )

    def solve_np(self, b: np.ndarray) -> np.ndarray:
        """``M^-1 b`` for ``b (V, k)`` (float64 numpy)."""
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x

    def to_differential(self, v_pos: torch.Tensor) -> torch.Tensor:
        """``u = M v`` (V, 3), same dtype as ``v_pos``; not differentiable (call once per stage)."""
        v = v_pos.detach().cpu().numpy().astype(np.float64)
        return torch.from_numpy(self.M @ v).to(v_pos.dtype)

    def from_differential(self, u: torch.Tensor) -> torch.Tensor:
        """``v = M^-1 u`` (V, 3), differentiable w.r.t. ``u``."""
        if u.shape != (self.n, 3):
            raise ValueError(f"u must be ({self.n}, 3), got {tuple(u.shape)}")
        return _Solve.apply(u, self)


class _Solve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, ls: LargeSteps):
        ctx.ls = ls
        return torch.from_numpy(ls.solve_np(u.detach().cpu().numpy())).to(u.dtype)

    @staticmethod
    def backward(ctx, grad):
        g = torch.from_numpy(ctx.ls.solve_np(grad.detach().cpu().numpy())).to(grad.dtype)
        return g, None


class AdamUniform(torch.optim.Optimizer):
    """Adam whose second moment is the max over all entries of a tensor (Nicolet et al.).

    Keeps the smooth update direction that the large-steps parameterization gives.
    State is the usual ``state_dict`` (checkpointable).
    """

    def __init__(self, params, lr=1e-2, betas=(0.9, 0.999), eps=1e-8):
        super().__init__(params, dict(lr=lr, betas=tuple(betas), eps=eps))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = 0
                    st["m"] = torch.zeros_like(p)
                    st["v"] = torch.zeros_like(p)
                st["step"] += 1
                st["m"].mul_(b1).add_(p.grad, alpha=1 - b1)
                st["v"].mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                m_hat = st["m"] / (1 - b1 ** st["step"])
                v_hat = st["v"] / (1 - b2 ** st["step"])
                p.sub_(group["lr"] * m_hat / (v_hat.max().sqrt() + group["eps"]))
