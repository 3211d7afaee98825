"""Stage ``poses``: cameras in the object frame (DESIGN sections 1 and 2).

Known cameras (the capture's ``cameras.json``) pass through after validation: no SfM runs.
Otherwise COLMAP (pycolmap 4.2.1, CPU) recovers them. In both cases the light intensity of
the settings (capture.yaml's ``light_intensity``) is written into ``cameras.json``; a given
``cameras.json`` that states another one is an error naming both files.

1. The linear images are encoded to 8-bit PNGs for SIFT (``poses/work/images``), each scaled
   by its own 99.5th percentile (SIFT needs contrast, not radiometry; see
   :func:`~recon.poses.features.sift_image`).
   Specular highlights get no features (``poses/work/feature_masks``): they move with the
   flash, so their matches belong to no fixed surface point.
2. SIFT features (peak threshold 0.001 on small images: smooth, flash-lit objects have little
   contrast; COLMAP's 0.0067 from 1000 px, where the finer features of real photos are noise:
   :func:`~recon.poses.features.peak_threshold`) with one shared camera
   (``CameraMode.SINGLE``: one photo camera, one zoom) and the focal length prior from
   ``linear.json`` when the linearize stage found one (EXIF: a 35 mm equivalent, or a DSLR's
   FocalLength x FocalPlaneXResolution, a prior of 5 % (``focal_plane_prior_sigma``): the
   Canon EOS Rebel T3's is 4.6 % long); ``poses.json`` records its source.
3. Matching: exhaustive up to ``exhaustive_max_views`` (40) views; beyond, ``ordered``
   (:mod:`~recon.poses.pairs`): people walk around the object, so each view is matched with
   its next ``ordered_neighbors`` views in file order, wrapping around (the loop closes), and
   with its ``retrieval_neighbors`` most similar views by a global descriptor of the SIFT
   features already extracted (the other rings, other loop closures; no vocabulary tree
   file). When the verified pairs leave the views in separate groups, the pairs most likely to
   join them are matched (the groups' ends in capture order, their most similar cross pairs:
   :func:`~recon.poses.pairs.bridge_pairs`), then, if groups remain, the pairs between the
   groups; only files not in capture order are matched exhaustively. Every verified pair is
   matched again along its epipolar geometry (``guided_matching``): on the 33 sparse skull
   photos that registered 32 views instead of 20. On an 80-view phone
   capture: 670 pairs instead of 3160, matching 5x faster, the stage's CPU time 0.41x, 80/80
   registered either way (docs/sfm_speed.md). The
   two-view RANSAC threshold scales with the image (0.4% of the long side,
   1 to 4 px): COLMAP's fixed 4 px lets chance matches of repeated texture pass as verified
   pairs on small images, and those wrong pairs broke the mapping in tests.
4. Mapping: global (rotation averaging, robust on orbits around an object) then incremental,
   alternating with new seeds while a trial registers fewer than ``accept_fraction`` of the
   views or ends with drifted intrinsics; the trial with most views wins. Views posed from
   fewer than ``min_view_points`` 3D points are dropped (global mapping places a view from
   rotations alone), and so are views that share fewer than that with the rest of the model
   (a pair seeing mostly each other's points can sit anywhere along its rays). A final
   bundle adjustment with a Cauchy loss lowers the pull of wrong matches (about 20% smaller
   pose errors in tests). With a focal length prior (EXIF) its focal length is held at the
   prior and its own estimate weighted by their variances (``focal_refine``,
   :func:`~recon.poses.mapping.focal_with_prior`).
   Small photos (long side under 400 px) whose first pass leaves more than 1 -
   ``accept_fraction`` of the views out get a second pass of steps 1-4 on 2x enlarged SIFT
   images (``sift_upsample_retry``), kept when it registers more views: at 192 x 144 SIFT
   finds 200-300 features on some views of a smooth object, too few to place them.
5. Undistortion of the linear EXRs, the masks and the clipped-pixel masks to the pinhole
   camera COLMAP derives (``pycolmap.undistort_camera``), by ``cv2.remap`` in float: the
   8-bit route of ``pycolmap.undistort_images`` would lose the linear data. A distortion that
   moves no pixel by more than 0.01 px keeps the photo's size (COLMAP's crop of 1-2 pixels
   was a knife edge between runs).
6. The object frame: z up (the mean of the cameras' up vectors: photographers hold the camera
   roughly upright), x and y along the principal axes of the sparse points that project
   inside the masks; then a coarse visual hull (64^3) of the undistorted masks around those
   points gives the object's extent (sparse points miss untextured parts, the hull never
   misses object); the object is centered and scaled to fill ``1 - margin`` of [-1, 1]^3.
   The similarity from COLMAP's frame is written to ``frame.json`` and to the
   ``colmap_to_object`` key of ``cameras.json``.

Outputs (``results/<capture>/poses/``, replaced atomically, nothing partial on error):
``cameras.json`` (pinhole, undistorted sizes, object frame), ``frame.json``, ``poses.json``
(diagnostics: registered and unregistered views with reasons, reprojection error, timings),
``points.ply`` (sparse points, object frame), ``sparse/`` (the COLMAP model, COLMAP frame,
original distorted camera), ``undistorted/<stem>.exr``, ``undistorted/<stem>.sat.png`` and
``undistorted/masks/<stem>.png`` (the pinhole views every later stage reads), ``work/`` (the
SIFT images and COLMAP database).

Modules: :mod:`~recon.poses.settings` (:class:`PoseSettings`, :class:`PoseError`),
:mod:`~recon.poses.inputs` (the linearize and masks stages' files), :mod:`~recon.poses.features`
(steps 1-3), :mod:`~recon.poses.pairs` (the ordered matcher's pairs), :mod:`~recon.poses.mapping` (step 4), :mod:`~recon.poses.undistort` (step 5),
:mod:`~recon.poses.frame` (step 6), :mod:`~recon.poses.stage` (:func:`run_poses`: the given
cameras' pass-through, the SfM sequence and the outputs).
"""

from recon.poses.features import sift_image, sift_upsample_factor, verify_max_error
from recon.poses.frame import object_frame
from recon.poses.inputs import focal_prior
from recon.poses.mapping import silhouette_consistency
from recon.poses.settings import PoseError, PoseSettings
from recon.poses.stage import run_poses

__all__ = ["PoseError", "PoseSettings", "focal_prior", "object_frame", "run_poses", "sift_image",
           "sift_upsample_factor", "silhouette_consistency", "verify_max_error"]
