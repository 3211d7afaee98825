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
photos are not in capture order), the caller matches the remaining pairs exhaustively (COLMAP
skips pairs already matched). If the verified pairs leave the views in separate groups
(:func:`groups`; sparse captures whose steps of 10-15 degrees sometimes fail to match), the
caller first matches the pairs most likely to join them (:func:`bridge_pairs`: the groups'
ends in capture order and their most similar cross pairs), and only if groups remain, every
pair between the groups (:func:`cross_group_pairs`), never the pairs inside a group again.
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


def similarity(descriptors: Sequence[np.ndarray], seed: int = 0) -> np.ndarray:
    """(n, n) cosine similarity of the views' VLAD vectors (:func:`vlad`), -inf on the diagonal."""
    g = vlad(descriptors, seed=seed)
    sim = (g @ g.T).astype(np.float64)
    np.fill_diagonal(sim, -np.inf)
    return sim


def retrieval_pairs(descriptors: Sequence[np.ndarray], neighbors: int, exclude: Iterable[tuple[int, int]] = (),
                    seed: int = 0, sim: np.ndarray | None = None) -> set[tuple[int, int]]:
    """Each view paired with its ``neighbors`` most similar other views (VLAD cosine similarity,
    :func:`similarity`, or ``sim`` when given), not counting pairs in ``exclude`` (already
    matched); pairs (i, j), i < j."""
    n = len(descriptors) if sim is None else len(sim)
    if n < 2 or neighbors < 1:
        return set()
    sim = similarity(descriptors, seed) if sim is None else np.array(sim, dtype=np.float64)
    for i, j in exclude:
        sim[i, j] = sim[j, i] = -np.inf
    pairs = set()
    for i in range(n):
        order = np.argsort(-sim[i], kind="stable")
        for j in order[:neighbors]:
            if np.isfinite(sim[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return pairs


def groups(n: int, verified: Iterable[tuple[int, int]]) -> list[list[int]]:
    """The views 0..n-1 in groups connected by ``verified`` pairs, largest first (ties: by
    their first view)."""
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in verified:
        parent[find(a)] = find(b)
    out: dict[int, list[int]] = {}
    for i in range(n):
        out.setdefault(find(i), []).append(i)
    return sorted(out.values(), key=lambda g: (-len(g), g[0]))


def bridge_pairs(parts: Sequence[Sequence[int]], sim: np.ndarray | None, exclude: Iterable[tuple[int, int]] = (),
                 per_group_pair: int = 10, window: int = 3) -> set[tuple[int, int]]:
    """Pairs between the separate groups ``parts`` of an ordered matching (:func:`groups`) that
    are likely to join them, not counting ``exclude`` (already matched):

    - the groups' ends in capture order: where view i and view i + 1 (wrapping around) lie in
      different groups, the ``window`` views up to i with the ``window`` views from i + 1 that
      lie in another group (the walk went on, but the match across that step failed: its
      neighbours one or two steps further often share enough);
    - for every two groups, their ``per_group_pair`` most similar cross pairs by the global
      descriptor ``sim`` (:func:`similarity`; the other rings, a walk that came back).

    About (boundaries x window^2 + groups^2 / 2 x per_group_pair) pairs: tens, where matching
    the rest exhaustively costs n^2 / 2."""
    n = sum(len(g) for g in parts)
    label = np.empty(n, np.int64)
    for k, g in enumerate(parts):
        label[list(g)] = k
    exclude = {(min(a, b), max(a, b)) for a, b in exclude}
    pairs = set()
    for i in range(n):
        j = (i + 1) % n
        if n < 2 or label[i] == label[j]:
            continue
        before = [(i - d) % n for d in range(window)]
        after = [(j + d) % n for d in range(window)]
        for a in before:
            for b in after:
                if a != b and label[a] != label[b]:
                    pairs.add((min(a, b), max(a, b)))
    if sim is not None and per_group_pair > 0:
        for ka in range(len(parts)):
            for kb in range(ka + 1, len(parts)):
                a, b = np.asarray(parts[ka]), np.asarray(parts[kb])
                block = np.asarray(sim, dtype=np.float64)[np.ix_(a, b)]
                order = np.argsort(-block, axis=None, kind="stable")
                taken = 0
                for flat in order:
                    i, j = int(a[flat // len(b)]), int(b[flat % len(b)])
                    pair = (min(i, j), max(i, j))
                    if pair in exclude or pair in pairs or not np.isfinite(block.flat[flat]):
                        continue
                    pairs.add(pair)
                    taken += 1
                    if taken >= per_group_pair:
                        break
    return pairs - exclude


def cross_group_pairs(parts: Sequence[Sequence[int]], exclude: Iterable[tuple[int, int]] = ()) -> set[tuple[int, int]]:
    """Every pair of views in different groups, not counting ``exclude``: what joins the groups
    if anything does, without the pairs inside a group (the ordered pairs already tie it)."""
    exclude = {(min(a, b), max(a, b)) for a, b in exclude}
    pairs = set()
    for ka in range(len(parts)):
        for kb in range(ka + 1, len(parts)):
            for i in parts[ka]:
                for j in parts[kb]:
                    pairs.add((min(i, j), max(i, j)))
    return pairs - exclude


def ordered_matching_ok(n: int, verified: Iterable[tuple[int, int]], min_consecutive: float = 0.5) -> tuple[bool, str]:
    """Did the ``ordered`` pairs do? ``verified``: the pairs (i, j) whose two-view geometry
    verified. False (with the reason) when fewer than ``min_consecutive`` of the consecutive
    pairs (i, i + 1) verified (the files are not in capture order) or the verified pairs leave
    the views in more than one group."""
    verified = {(min(a, b), max(a, b)) for a, b in verified}
    if n < 2:
        return True, "one view"
    consecutive = sum((i, i + 1) in verified for i in range(n - 1)) / (n - 1)
    count = len(groups(n, verified))
    if consecutive < min_consecutive:
        return False, (f"only {consecutive:.0%} of the consecutive views verified a match: the files are not in "
                       "capture order")
    if count > 1:
        return False, f"the verified pairs leave the views in {count} separate groups"
    return True, f"{consecutive:.0%} of the consecutive views verified, one group"


def in_capture_order(n: int, verified: Iterable[tuple[int, int]], min_consecutive: float = 0.5) -> bool:
    """Did at least ``min_consecutive`` of the consecutive views (i, i + 1) verify a match?"""
    verified = {(min(a, b), max(a, b)) for a, b in verified}
    return n < 2 or sum((i, i + 1) in verified for i in range(n - 1)) / (n - 1) >= min_consecutive
