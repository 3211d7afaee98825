"""A binary graph cut on an image (scipy's max-flow) and colour models for its data term."""

from __future__ import annotations

import numpy as np


def graph_cut(cost_fg: np.ndarray, cost_bg: np.ndarray, guide: np.ndarray, smoothness: float,
              active: np.ndarray | None = None) -> np.ndarray:
    """Minimum of sum(cost) + smoothness * sum over 4-neighbours of exp(-|dI|^2 / (2 <|dI|^2>))
    [labels differ]; returns the (H, W) bool foreground. ``active`` limits the graph to a
    region (pixels outside it are background). Costs are in units of one pairwise weight."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    H, W = cost_fg.shape
    act = np.ones((H, W), bool) if active is None else active.copy()
    fg = np.zeros((H, W), bool)
    if not act.any():
        return fg
    rows, cols = np.nonzero(act)
    i0, i1, j0, j1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    act = act[i0:i1, j0:j1]
    g = guide[i0:i1, j0:j1].astype(np.float32)
    cf, cb = cost_fg[i0:i1, j0:j1], cost_bg[i0:i1, j0:j1]
    h, w = act.shape
    dx = ((g[:, 1:] - g[:, :-1]) ** 2).sum(-1)
    dy = ((g[1:, :] - g[:-1, :]) ** 2).sum(-1)
    beta = 1.0 / (2.0 * max(float(np.concatenate([dx.ravel(), dy.ravel()]).mean()), 1e-6))
    scale = 100.0
    wx = np.rint(scale * smoothness * np.exp(-beta * dx)).astype(np.int64)
    wy = np.rint(scale * smoothness * np.exp(-beta * dy)).astype(np.int64)
    n = h * w
    s, t = n, n + 1
    idx = np.arange(n).reshape(h, w)
    # a pixel outside the active region is tied to the background
    cf = np.where(act, cf, 1e6)
    cb = np.where(act, cb, 0.0)
    cap_s = np.rint(scale * np.clip(cb, 0, 1e6)).astype(np.int64)  # cut s->p: p is background
    cap_t = np.rint(scale * np.clip(cf, 0, 1e6)).astype(np.int64)  # cut p->t: p is foreground
    r = [np.full(n, s), idx.ravel(), idx[:, :-1].ravel(), idx[:, 1:].ravel(), idx[:-1].ravel(), idx[1:].ravel()]
    c = [idx.ravel(), np.full(n, t), idx[:, 1:].ravel(), idx[:, :-1].ravel(), idx[1:].ravel(), idx[:-1].ravel()]
    cap = [cap_s.ravel(), cap_t.ravel(), wx.ravel(), wx.ravel(), wy.ravel(), wy.ravel()]
    r, c, cap = np.concatenate(r), np.concatenate(c), np.concatenate(cap)
    keep = cap > 0
    G = csr_matrix((cap[keep].astype(np.int32), (r[keep], c[keep])), shape=(n + 2, n + 2))
    flow = maximum_flow(G, s, t).flow
    resid = (G - flow).tocsr()
    resid.data = np.maximum(resid.data, 0)
    resid.eliminate_zeros()
    reach = breadth_first_order(resid, s, directed=True, return_predecessors=False)
    side = np.zeros(n + 2, bool)
    side[reach] = True
    fg[i0:i1, j0:j1] = side[:n].reshape(h, w) & act
    return fg


def colour_log_ratio(guide: np.ndarray, sure_fg: np.ndarray, sure_bg: np.ndarray, where: np.ndarray,
                     components: int = 5, samples: int = 1500, seed: int = 0, plain_fg: np.ndarray | None = None,
                     novelty: float = 0.05) -> np.ndarray | None:
    """(H, W) log p(colour | object) - log p(colour | table) at ``where`` (0 elsewhere), from
    Gaussian mixtures (OpenCV EM, CIE Lab) fitted to this view's ``sure_fg`` and ``sure_bg``
    pixels; None when the table or the object has too few pixels or nothing is asked.

    ``plain_fg``: object pixels without evidence of their own (deep inside the silhouette, where
    the plane test says nothing: a plain glaze). Those whose colour the table's model does not
    explain (a log-likelihood under it below the ``novelty`` quantile of its own samples') get
    a second object model, and a pixel's object likelihood is the larger of the two: a plain
    glaze whose colour no pixel with evidence shows (the blue lip of a glazed bell) is the
    object's near the outline too, and a plain colour that the table shows as well (a dark glaze
    and the shadow at the foot, a wood-coloured glaze and the table) changes nothing."""
    import cv2

    if not where.any() or sure_bg.sum() < 10 * components:
        return None
    lab = cv2.cvtColor(guide, cv2.COLOR_RGB2Lab).astype(np.float64)
    rng = np.random.default_rng(seed)

    def sample(x):
        return x[rng.choice(len(x), samples, replace=False)] if len(x) > samples else x

    query = lab[where]
    fg = _em_fit(sample(lab[sure_fg]), components) if sure_fg.sum() >= 10 * components else None
    x_bg = sample(lab[sure_bg])
    bg = _em_fit(x_bg, components)
    logp_fg = [] if fg is None else [_em_loglik(fg, query)]
    if plain_fg is not None and plain_fg.any():
        x = sample(lab[plain_fg])
        x = x[_em_loglik(bg, x) < np.quantile(_em_loglik(bg, x_bg), novelty)]
        if len(x) >= 10 * components:
            logp_fg.append(_em_loglik(_em_fit(x, components), query))
    if not logp_fg:
        return None
    out = np.zeros(guide.shape[:2])
    out[where] = np.clip(np.max(logp_fg, axis=0) - _em_loglik(bg, query), -10.0, 10.0)
    return out


def _em_fit(x: np.ndarray, components: int):
    """An OpenCV EM Gaussian mixture (diagonal covariances) fitted to rows ``x (N, D)``."""
    import cv2

    em = cv2.ml.EM_create()
    em.setClustersNumber(components)
    em.setCovarianceMatrixType(cv2.ml.EM_COV_MAT_DIAGONAL)
    em.setTermCriteria((cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 20, 1e-3))
    em.trainEM(x)
    return em


def _em_loglik(em, x: np.ndarray) -> np.ndarray:
    """Log-likelihood of rows ``x (N, D)`` under a trained OpenCV EM model (diagonal covariances)."""
    means = em.getMeans()
    weights = em.getWeights().ravel()
    covs = em.getCovs()
    ll = []
    for k in range(len(weights)):
        var = np.maximum(np.diag(covs[k]), 1e-6)
        d = (x - means[k]) ** 2 / var
        ll.append(np.log(max(weights[k], 1e-12)) - 0.5 * (d.sum(1) + np.log(2 * np.pi * var).sum()))
    ll = np.stack(ll, 1)
    top = ll.max(1, keepdims=True)
    return (top + np.log(np.exp(ll - top).sum(1, keepdims=True))).ravel()
