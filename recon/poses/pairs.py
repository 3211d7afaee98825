"""Which view pairs to match: the ``ordered`` matcher's pairs, and the check that they sufficed.

Exhaustive matching costs n (n - 1) / 2 pairs: 3160 for 80 views, most of them views of
opposite sides that share nothing. People photograph an object walking around it, so the
photos in file (capture) order form rings: a view overlaps the few before and after it, the
last view of a ring overlaps its first, and a ring at another height overlaps it at the same
azimuths. The ``ordered`` matcher matches

- each view with its ``ordered_neighbors`` successors in file order, wrapping around (the last
  views neighbour the first: the loop of a single ring closes; :func:`ordered_pairs`);
- each view with its ``retrieval_neighbors`` most similar views by a global image descriptor
  (:func:`retrieval_pairs`: VLAD of the RootSIFT descriptors already extracted, on a small
  vocabulary trained on the capture itself, so no vocabulary-tree file is needed). These are
  the loop closures COLMAP's vocabulary tree would find: the other rings, the views where
  a walk around the object came back, views taken out of order.

That is about n (k + m) pairs instead of n^2 / 2. :func:`ordered_matching_ok` then checks the
assumption on the verified pairs: if the views' consecutive pairs mostly failed to verify (the
photos are not in capture order) or the verified pairs leave the views in separate groups, the
caller matches the remaining pairs exhaustively (COLMAP skips pairs already matched).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np


def ordered_pairs(n: int, neighbors: int, wrap: bool = True) -> set[tuple[int, int]]:
    """Pairs (i, j), i < j, of views at most ``neighbors`` apart in capture order; with
    ``wrap`` the order is a ring (view n - 1 neighbours view 0). All pairs when the ring is
    too short for ``neighbors`` on each side."""
    if n < 2 or neighbors < 1:
        return set()
    pairs = set()
    for i in range(n):
        for d in range(1, neighbors + 1):
            j = i + d
            if j >= n:
                if not wrap:
                    break
                j %= n
            if j != i:
                pairs.add((min(i, j), max(i, j)))
    return pairs


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 12) -> np.ndarray:
    """Plain Lloyd k-means (k-means++-like farthest seeding from a random start); (k, D)."""
    k = min(k, len(x))
    centres = [x[rng.integers(len(x))]]
    d2 = np.full(len(x), np.inf, np.float32)
    for _ in range(1, k):  # k-means++ seeding
        d2 = np.minimum(d2, ((x - centres[-1]) ** 2).sum(1))
        p = d2 / d2.sum() if d2.sum() > 0 else None
        centres.append(x[rng.choice(len(x), p=p)])
    c = np.array(centres, np.float32)
    for _ in range(iters):
        a = _assign(x, c)
        for j in range(k):
            sel = a == j
            if sel.any():
                c[j] = x[sel].mean(0)
    return c


def _assign(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    d = (c * c).sum(1)[None, :] - 2.0 * x @ c.T
    return np.argmin(d, axis=1)


def _rootsift(d: np.ndarray) -> np.ndarray:
    d = np.asarray(d, np.float32)
    d = d / np.maximum(np.abs(d).sum(1, keepdims=True), 1e-12)
    return np.sqrt(np.abs(d))


def vlad(descriptors: Sequence[np.ndarray], words: int = 64, sample: int = 256, seed: int = 0) -> np.ndarray:
    """(n, words * D) global descriptors: VLAD (intra-normalised, signed square root, L2) of
    each view's RootSIFT descriptors on ``words`` centres fitted to ``sample`` descriptors per
    view. Deterministic for a seed. A view without descriptors gets zeros."""
    rng = np.random.default_rng(seed)
    roots = [_rootsift(d) if len(d) else np.zeros((0, 128), np.float32) for d in descriptors]
    dim = next((r.shape[1] for r in roots if len(r)), 128)
    train = [r[rng.choice(len(r), min(len(r), sample), replace=False)] for r in roots if len(r)]
    if not train:
        return np.zeros((len(roots), words * dim), np.float32)
    c = _kmeans(np.concatenate(train), words, rng)
    out = np.zeros((len(roots), len(c), dim), np.float32)
    for i, r in enumerate(roots):
        if not len(r):
            continue
        a = _assign(r, c)
        for j in np.unique(a):
            out[i, j] = (r[a == j] - c[j]).sum(0)
    out /= np.maximum(np.linalg.norm(out, axis=2, keepdims=True), 1e-12)
    out = out.reshape(len(roots), -1)
    out = np.sign(out) * np.sqrt(np.abs(out))
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out


def retrieval_pairs(descriptors: Sequence[np.ndarray], neighbors: int, exclude: Iterable[tuple[int, int]] = (),
                    seed: int = 0) -> set[tuple[int, int]]:
    """Each view paired with its ``neighbors`` most similar other views (VLAD cosine similarity,
    :func:`vlad`), not counting pairs in ``exclude`` (already matched); pairs (i, j), i < j."""
    n = len(descriptors)
    if n < 2 or neighbors < 1:
        return set()
    g = vlad(descriptors, seed=seed)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    for i, j in exclude:
        sim[i, j] = sim[j, i] = -np.inf
    pairs = set()
    for i in range(n):
        order = np.argsort(-sim[i], kind="stable")
        for j in order[:neighbors]:
            if np.isfinite(sim[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return pairs


def ordered_matching_ok(n: int, verified: Iterable[tuple[int, int]], min_consecutive: float = 0.5) -> tuple[bool, str]:
    """Did the ``ordered`` pairs do? ``verified``: the pairs (i, j) whose two-view geometry
    verified. False (with the reason) when fewer than ``min_consecutive`` of the consecutive
    pairs (i, i + 1) verified (the files are not in capture order) or the verified pairs leave
    the views in more than one group."""
    verified = {(min(a, b), max(a, b)) for a, b in verified}
    if n < 2:
        return True, "one view"
    consecutive = sum((i, i + 1) in verified for i in range(n - 1)) / (n - 1)
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in verified:
        parent[find(a)] = find(b)
    groups = len({find(i) for i in range(n)})
    if consecutive < min_consecutive:
        return False, (f"only {consecutive:.0%} of the consecutive views verified a match: the files are not in "
                       "capture order")
    if groups > 1:
        return False, f"the verified pairs leave the views in {groups} separate groups"
    return True, f"{consecutive:.0%} of the consecutive views verified, one group"
