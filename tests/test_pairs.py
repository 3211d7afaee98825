"""The ordered matcher's pairs (recon.poses.pairs) and the auto choice of matcher."""

import numpy as np
import pytest

from recon import poses as rp
from recon.poses.features import matcher_kind
from recon.poses.pairs import (bridge_pairs, cross_group_pairs, groups, in_capture_order, ordered_matching_ok,
                               ordered_pairs, retrieval_pairs, similarity, vlad)


def test_ordered_pairs_wrap_around_the_ring():
    pairs = ordered_pairs(10, 2)
    assert len(pairs) == 20 and all(i < j for i, j in pairs)
    assert {(0, 1), (0, 2), (8, 9), (0, 9), (1, 9), (0, 8)} <= pairs  # the last views neighbour the first
    assert (0, 3) not in pairs and (4, 7) not in pairs
    assert ordered_pairs(10, 2, wrap=False) == {(i, j) for i in range(10) for j in (i + 1, i + 2) if j < 10}


def test_ordered_pairs_of_a_short_ring_are_all_pairs():
    assert ordered_pairs(5, 5) == {(i, j) for i in range(5) for j in range(i + 1, 5)}
    assert ordered_pairs(1, 3) == set() and ordered_pairs(2, 3) == {(0, 1)}


def _views_of_groups(groups, per_view=150, seed=0):
    """Descriptor sets: the views of a group share most descriptors (they see the same side)."""
    rng = np.random.default_rng(seed)
    pools = [rng.integers(0, 120, (400, 128)).astype(np.uint8) for _ in set(groups)]
    out = []
    for g in groups:
        pick = pools[g][rng.choice(400, per_view, replace=False)]
        noise = rng.integers(0, 120, (per_view // 5, 128)).astype(np.uint8)
        out.append(np.concatenate([pick, noise]))
    return out


def test_retrieval_pairs_find_the_views_of_the_same_side():
    groups = [0, 1, 2, 0, 1, 2, 0, 1, 2, 0, 1, 2]  # shuffled: file order says nothing
    descs = _views_of_groups(groups)
    pairs = retrieval_pairs(descs, 3)
    assert pairs and all(groups[i] == groups[j] for i, j in pairs)
    assert all(any(i in p for p in pairs) for i in range(len(groups)))
    # pairs already matched are not proposed again; deterministic for a seed
    assert not retrieval_pairs(descs, 3, exclude=pairs) & pairs
    assert retrieval_pairs(descs, 3) == pairs
    g = vlad(descs)
    assert np.allclose(np.linalg.norm(g, axis=1), 1.0)
    # views without descriptors: no pairs for them, no NaN
    assert np.all(np.isfinite(vlad([np.zeros((0, 128), np.uint8)] + descs[:3])))


def test_ordered_matching_check():
    chain = {(i, i + 1) for i in range(19)} | {(0, 19)}
    assert ordered_matching_ok(20, chain)[0]
    # two rings of 10 in order: the step between the rings fails, retrieval links them
    rings = ({(i, i + 1) for i in range(19)} - {(9, 10)}) | {(0, 10), (5, 15)}
    assert ordered_matching_ok(20, rings)[0]
    ok, why = ordered_matching_ok(20, {(i, i + 2) for i in range(18)} | {(0, 1)})
    assert not ok and "capture order" in why
    ok, why = ordered_matching_ok(20, chain - {(9, 10), (0, 19)})
    assert not ok and "2 separate groups" in why


def test_groups_of_verified_pairs():
    chain = {(i, i + 1) for i in range(19)}
    assert groups(20, chain) == [list(range(20))]
    parts = groups(20, chain - {(6, 7), (13, 14)} | {(2, 15)})  # 0-6 with 14-19, 7-13 apart
    assert parts == [[0, 1, 2, 3, 4, 5, 6, 14, 15, 16, 17, 18, 19], [7, 8, 9, 10, 11, 12, 13]]
    assert groups(3, set()) == [[0], [1], [2]]
    assert in_capture_order(20, chain - {(6, 7)}) and not in_capture_order(20, {(i, i + 2) for i in range(18)})


def test_bridge_pairs_join_groups_at_their_ends_and_by_similarity():
    """A walk of 24 views whose step 7 -> 8 failed (two groups in capture order, 0-7 and 8-23,
    the ring closing 23 -> 0): the bridges are the views around the failed step (a window of 2
    on each side) and the groups' most similar cross pairs, never a pair inside a group or one
    already matched."""
    chain = {(i, i + 1) for i in range(23)} - {(7, 8)}
    parts = groups(24, chain)
    assert [len(g) for g in parts] == [16, 8]
    sim = np.zeros((24, 24))
    sim[3, 20] = sim[20, 3] = 0.9  # the other ring at the same azimuth
    sim[1, 12] = sim[12, 1] = 0.8
    np.fill_diagonal(sim, -np.inf)
    matched = {(6, 8), (7, 8)}  # ordered pairs that failed to verify: not proposed again
    pairs = bridge_pairs(parts, sim, exclude=matched, per_group_pair=2, window=2)
    ends = {(6, 9), (7, 9)} | {(0, 23), (1, 23), (0, 22), (1, 22)}  # the failed step; the ring's wrap
    assert pairs == ends | {(3, 20), (1, 12)}
    label = {i: k for k, g in enumerate(parts) for i in g}
    assert all(label[i] != label[j] for i, j in pairs)
    # without a similarity: the ends alone; one group: nothing to bridge
    assert bridge_pairs(parts, None, exclude=matched, window=2) == ends
    assert bridge_pairs([list(range(24))], sim) == set()
    # the last resort: every pair between the groups, none inside one
    rest = cross_group_pairs(parts, exclude=matched | pairs)
    assert len(rest) == 16 * 8 - len(matched | pairs) and all(label[i] != label[j] for i, j in rest)


def test_similarity_is_the_retrieval_order():
    descs = _views_of_groups([0, 1, 0, 1, 0, 1])
    sim = similarity(descs)
    assert np.all(np.isneginf(np.diag(sim)))
    assert retrieval_pairs(descs, 2) == retrieval_pairs(descs, 2, sim=sim)
    assert all(sim[i, j] > sim[i, k] for i in range(6) for j in range(6) for k in range(6)
               if i != j and i != k and i % 2 == j % 2 and i % 2 != k % 2)


def test_auto_matcher_choice():
    s = rp.PoseSettings()
    assert matcher_kind(s, 32) == "exhaustive"  # the demo: every pair is cheap insurance
    assert matcher_kind(s, s.matching.exhaustive_max_views) == "exhaustive"
    assert matcher_kind(s, 80) == "ordered"
    assert matcher_kind(rp.PoseSettings(matching={"matcher": "exhaustive"}), 80) == "exhaustive"  # still selectable
    assert matcher_kind(rp.PoseSettings(matching={"matcher": "ordered"}), 10) == "ordered"
    with pytest.raises(ValueError, match="ordered_neighbors"):
        rp.PoseSettings(matching={"ordered_neighbors": 0})
    with pytest.raises(ValueError, match="bridge_window"):
        rp.PoseSettings(matching={"bridge_window": 0})


@pytest.fixture(scope="module")
def ordered_capture(tmp_path_factory):
    """The SfM test capture (40 views of a blob on a Fibonacci sphere, whose file order jumps
    137 degrees between views) renamed into capture order: two rings, low then high, each by
    azimuth, as a person walking around the object twice would take them."""
    import json
    import os

    from _geometry_scene import linearize_and_mask, synth_capture

    from recon.io.cameras import load_cameras

    capture = synth_capture(tmp_path_factory.getbasetemp())
    linear, masks = linearize_and_mask(capture, tmp_path_factory.mktemp("pairs_src"))
    true = load_cameras(capture / "gt" / "cameras.json")
    c = np.array([cam.center for cam in true])
    ring = (c[:, 2] > np.median(c[:, 2])).astype(int)
    order = sorted(range(len(true)), key=lambda i: (ring[i], np.arctan2(c[i, 1], c[i, 0])))
    new = {true.frames[i].stem: f"r{k:03d}" for k, i in enumerate(order)}
    out = tmp_path_factory.mktemp("pairs_ordered")
    (out / "linear").mkdir()
    (out / "masks").mkdir()
    for old, stem in new.items():
        for src, dst in ((linear / f"{old}.exr", out / "linear" / f"{stem}.exr"),
                         (linear / f"{old}.sat.png", out / "linear" / f"{stem}.sat.png"),
                         (masks / f"{old}.png", out / "masks" / f"{stem}.png")):
            if src.is_file():
                os.symlink(src, dst)
    data = json.loads((linear / "linear.json").read_text())
    text = json.dumps(data)
    for old, stem in new.items():  # per-view entries keyed by stem or by image name
        text = text.replace(f'"{old}"', f'"{stem}"').replace(f"/{old}.", f"/{stem}.")
    (out / "linear" / "linear.json").write_text(text)
    (out / "masks" / "masks.json").write_text((masks / "masks.json").read_text())
    return capture, out, {v: k for k, v in new.items()}


def test_ordered_matching_poses_a_capture_in_order(ordered_capture):
    """Views in capture order: the ordered pairs (a fraction of the exhaustive ones) register
    every view as accurately as the SfM test's exhaustive run (< 0.5 degrees)."""
    from recon import metrics
    from recon.io.cameras import Camera, CameraSet, load_cameras

    capture, folder, old_of = ordered_capture
    settings = rp.PoseSettings(matching={"matcher": "ordered"}, num_threads=1)
    diag = rp.run_poses(folder / "linear", folder / "poses", settings, masks_dir=folder / "masks",
                        linear_json=folder / "linear" / "linear.json")
    n = diag["views"]
    m = diag["matching"]
    assert diag["matcher"] == "ordered" and not m["exhaustive_fallback"], m
    assert m["pairs"] < 0.5 * n * (n - 1) / 2
    assert diag["registered"] >= 0.95 * n, diag["unregistered"]
    est = load_cameras(folder / "poses" / "cameras.json")
    est = CameraSet(tuple(Camera(f"images/{old_of[c.stem]}.exr", c.width, c.height, c.K, c.world_to_camera)
                          for c in est), est.light_intensity)
    err = metrics.pose_errors(est, load_cameras(capture / "gt" / "cameras.json"))
    print(f"\nordered: {m['pairs']} pairs ({m['order_check']}), {diag['registered']}/{n} registered, "  # noqa: T201
          f"mean rotation {err['mean_rotation_deg']:.3f} deg, match {diag['timings']['match_s']:.1f} s")
    assert err["mean_rotation_deg"] < 0.5, err["mean_rotation_deg"]


class _Rot:
    def __init__(self, R):
        self._R = R

    def matrix(self):
        return self._R


class _Pose:
    def __init__(self, R):
        self.rotation = _Rot(R)


class _Image:
    def __init__(self, name, R):
        self.name, self._R = name, R

    def cam_from_world(self):
        return _Pose(self._R)


class _Model:
    """The part of a pycolmap.Reconstruction relative_rotations_agree reads."""

    def __init__(self, rotations):
        self.images = {i + 1: _Image(f"{i:04d}.png", R) for i, R in enumerate(rotations)}

    def reg_image_ids(self):
        return list(self.images)


def test_two_mappers_agree_up_to_the_gauge_but_not_when_mirrored():
    from scipy.spatial.transform import Rotation

    from recon.poses.mapping import relative_rotations_agree

    rng = np.random.default_rng(0)
    Rs = Rotation.random(12, random_state=1).as_matrix()
    G = Rotation.random(random_state=2).as_matrix()  # another model's frame: R_i -> R_i G^T
    noisy = [R @ Rotation.from_rotvec(rng.normal(0, 0.002, 3)).as_matrix() @ G.T for R in Rs]
    assert relative_rotations_agree(_Model(Rs), _Model(noisy)) < 1.0
    F = np.diag([1.0, 1.0, -1.0])  # a mirrored model: every rotation conjugated by a reflection
    mirrored = [F @ R @ F for R in Rs]
    assert relative_rotations_agree(_Model(Rs), _Model(mirrored)) > 10
    assert relative_rotations_agree(_Model(Rs[:2]), _Model(Rs[:2])) is None
