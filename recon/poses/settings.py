"""Settings and the error of the poses stage.

:class:`PoseSettings` has a section per step of the SfM path (``recon.poses``'s docstring) and
three settings of its own; ``capture.yaml`` gives them the same way::

    poses:
      features: {max_image_size: 2400, sift_upsample: 2}
      matching: {matcher: ordered}
      mapping: {mapping_trials: 6}
      camera: {focal_px: 3300}
      frame: {margin: 0.15}
      seed: 1

A flat key of an older capture.yaml (``poses: {sift_upsample: 2}``) still works, with a warning
naming its place (:mod:`recon.sections`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from recon.sections import sectioned


class PoseError(ValueError):
    """Cameras that cannot be recovered or used; the message lists the views and what to try."""


def _positive_number(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class FeatureSettings:
    """Step 1-2: the SIFT images and features."""

    SIGNED_SETTINGS = ("max_image_size",)  # -1: full size

    max_image_size: int = 1600  # SIFT runs on images downscaled to this long side (-1: full)
    max_num_features: int = 8192
    sift_encoding: str = "srgb"  # srgb | log: what SIFT sees (see sift_image)
    sift_upsample: int = 1  # enlarge the SIFT images by this factor; 0: auto (see sift_upsample_factor)
    max_num_features_upsampled: int = 2048  # feature cap on enlarged images (matching cost)
    # small photos (sift_upsample_factor would enlarge them) whose first SfM pass leaves more than
    # 1 - mapping.accept_fraction of the views out: SfM once more on enlarged images, kept if it
    # registers more
    sift_upsample_retry: bool = False  # measured both ways: config/README.md
    # SIFT's peak threshold; 0: by the SIFT images' long side (features.peak_threshold): 0.001 on small
    # images (COLMAP's 0.0067 finds too few on smooth objects there), 0.0067 from peak_threshold_size px
    # (real photos: the features below it are mostly noise that does not match; docs/sfm_speed.md)
    peak_threshold: float = 0.0
    peak_threshold_size: int = 1000
    highlight_factor: float = 4.0  # no features where luminance > this x the object's median (0: off)
    affine_features: bool = False  # affine-covariant SIFT + domain-size pooling (wide baselines)

    def __post_init__(self):
        if self.sift_encoding not in ("log", "srgb"):
            raise ValueError(f"sift_encoding must be log or srgb, got {self.sift_encoding!r}")
        if self.peak_threshold < 0:
            raise ValueError(f"peak_threshold must be >= 0 (0: by image size), got {self.peak_threshold}")


@dataclass(frozen=True)
class MatchingSettings:
    """Step 3: which pairs are matched and verified (recon.poses.pairs)."""

    max_ratio: float = 0.8  # SIFT ratio test
    # re-match each verified pair along its epipolar geometry: the sparse skull photos' weak pairs
    # gained the inliers that registered 32 instead of 20 of 33 views (docs/sfm_speed.md)
    guided_matching: bool = True
    matcher: str = "auto"  # auto | exhaustive | ordered | sequential (see recon.poses.pairs)
    exhaustive_max_views: int = 40  # auto: exhaustive up to this many views, ordered beyond
    ordered_neighbors: int = 5  # ordered: each view with its next k in capture order (wrapping around)
    retrieval_neighbors: int = 5  # ordered: and with its m most similar views (loop closure)
    # ordered, views left in separate groups: rounds of bridging pairs (the groups' ends in capture
    # order, bridge_window views on each side; each two groups' bridge_pairs most similar cross
    # pairs), then every pair between the groups left (never the exhaustive n^2 / 2)
    bridge_rounds: int = 2
    bridge_pairs: int = 10
    bridge_window: int = 3
    sequential_overlap: int = 15
    min_num_inliers: int = 12  # verified two-view geometry
    verify_max_error: float = 0.0  # RANSAC epipolar threshold, pixels; 0: 0.4% of the long side in [1, 4]

    def __post_init__(self):
        if self.matcher not in ("auto", "exhaustive", "ordered", "sequential"):
            raise ValueError(f"matcher must be auto, exhaustive, ordered or sequential, got {self.matcher!r}")
        if self.ordered_neighbors < 1 or self.retrieval_neighbors < 0:
            raise ValueError("ordered_neighbors must be >= 1 and retrieval_neighbors >= 0")
        if self.bridge_rounds < 0 or self.bridge_pairs < 0 or self.bridge_window < 1:
            raise ValueError("bridge_rounds and bridge_pairs must be >= 0 and bridge_window >= 1")


@dataclass(frozen=True)
class MappingSettings:
    """Step 4: the mapping trials and what a trial must register (recon.poses.mapping)."""

    mapper: str = "auto"  # auto (see mapping.mapper_sequence) | incremental | incremental_fixed | global
    init_min_num_inliers: int = 50
    abs_pose_min_num_inliers: int = 15
    mapping_trials: int = 4  # retries (other mapper, other seed) while too many views are left out
    accept_fraction: float = 0.95  # a trial registering this fraction of the views ends the retries
    # ... or, when the masks disagree, two mappers' rotations all within this, in degrees (0: off): wrong
    # (mirrored, folded) models differ by tens; right ones of sparse photos by up to 0.9 on their weakest views
    agree_deg: float = 2.0
    max_mapping_seconds: float = 600.0  # per incremental trial
    min_registered: int = 3
    min_view_points: int = 15  # views posed from fewer 3D points are dropped (unreliable)
    min_registered_fraction: float = 0.5  # fewer than this (largest model / views): error
    min_silhouette_consistency: float = 0.9  # with masks: see silhouette_consistency (0: off)

    def __post_init__(self):
        if self.mapper not in ("auto", "incremental", "incremental_fixed", "global"):
            raise ValueError(f"mapper must be auto, incremental, incremental_fixed or global, got {self.mapper!r}")
        if self.min_registered < 3:
            raise ValueError(f"min_registered must be >= 3, got {self.min_registered}")
        if self.mapping_trials < 1:
            raise ValueError(f"mapping_trials must be >= 1, got {self.mapping_trials}")


@dataclass(frozen=True)
class CameraSettings:
    """The shared camera: its model, its focal length prior and the final bundle adjustment."""

    SIGNED_SETTINGS = ("distortion_gain",)  # -1: always keep the distortion

    camera_model: str = "SIMPLE_RADIAL"  # shared camera; PINHOLE-like models skip distortion
    refine: bool = True  # a final robust bundle adjustment
    refine_loss_scale: float = 0.5  # Cauchy loss scale, pixels
    distortion_gain: float = 0.05  # keep lens distortion only if it cuts the error by more (-1: always)
    # the focal length with a prior (EXIF): auto (the bundle adjustment's estimate and the prior
    # weighted by their variances), fixed (held at the prior), free (the prior only starts it)
    focal_refine: str = "auto"
    # a known focal length in pixels of the photos in images/ (their full size), e.g. from a
    # calibration: the prior instead of EXIF's (weight: focal_prior_sigma; fixed holds it)
    focal_px: float | None = None
    focal_prior_sigma: float = 0.01  # the prior's relative standard deviation (auto): focal_px, a 35 mm equivalent
    # ... of EXIF FocalLength x FocalPlaneXResolution (DSLRs without a 35 mm equivalent): a few percent
    # (the Canon EOS Rebel T3's 10,221 px at 4272 px wide; SfM found 4.6 % less)
    focal_plane_prior_sigma: float = 0.05
    focal_sigma_scale: float = 2.0  # the adjustment's standard deviation times this (auto; see mapping)

    def __post_init__(self):
        if self.focal_refine not in ("auto", "fixed", "free"):
            raise ValueError(f"focal_refine must be auto, fixed or free, got {self.focal_refine!r}")
        if self.focal_px is not None:
            try:
                object.__setattr__(self, "focal_px", _positive_number("focal_px", self.focal_px))
            except ValueError:
                raise ValueError(f"focal_px must be a positive number of pixels (the photos' focal length), "
                                 f"got {self.focal_px!r}") from None
        for key in ("focal_prior_sigma", "focal_plane_prior_sigma"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and 0 < value < 1):
                raise ValueError(f"{key} must be in (0, 1), got {value!r}")
        if not (isinstance(self.focal_sigma_scale, (int, float)) and 0 < self.focal_sigma_scale < 1e6):
            raise ValueError(f"focal_sigma_scale must be positive, got {self.focal_sigma_scale!r}")


@dataclass(frozen=True)
class FrameSettings:
    """Step 6: the object frame."""

    bbox_percentile: float = 1.0  # robust box of the sparse points: [p, 100 - p] percentiles
    margin: float = 0.1  # the object fills [-(1 - margin), 1 - margin]
    hull_resolution: int = 64  # coarse visual hull for the object's extent (0: sparse points only)

    def __post_init__(self):
        if not 0 <= self.margin < 1 or not 0 <= self.bbox_percentile < 50:
            raise ValueError("margin must be in [0, 1) and bbox_percentile in [0, 50)")


@sectioned
@dataclass(frozen=True)
class PoseSettings:
    """Settings of the SfM path (ignored when the capture gives cameras.json) and the light."""

    SIGNED_SETTINGS = ("num_threads",)  # -1: every core

    features: FeatureSettings = field(default_factory=FeatureSettings)
    matching: MatchingSettings = field(default_factory=MatchingSettings)
    mapping: MappingSettings = field(default_factory=MappingSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    frame: FrameSettings = field(default_factory=FrameSettings)
    seed: int = 0  # every random choice of the stage derives from it (trial_seed)
    num_threads: int = -1
    # I_e written to cameras.json's light.intensity: capture.yaml's ``light_intensity`` (merged
    # here by recon.config). None: a given cameras.json keeps its own, SfM writes 1.
    light_intensity: float | None = None

    def __post_init__(self):
        if self.light_intensity is not None:
            object.__setattr__(self, "light_intensity", _positive_number("light_intensity", self.light_intensity))

    def trial_seed(self, trial: int = 0) -> int:
        """The seed of mapping trial ``trial``; trial 0's (``seed``) also seeds the two-view
        RANSAC and the retrieval's k-means (recon.poses.features)."""
        return self.seed + trial
