"""What a body fit sees, how it is weighted, and what it returns (:mod:`uvatar.fit.body_fit` runs it).

The stage names, the joints a fit rotates (:func:`fitted_joints`), :class:`FitObservations`,
:class:`BodyFitConfig` and :class:`SequenceFit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uvatar.errors import check_values

__all__ = ["STAGES", "PHOTO_STAGE", "FITTED_JOINTS", "STIFF_JOINTS", "ARM_KEYPOINTS", "fitted_joints",
           "FitObservations", "BodyFitConfig", "SequenceFit", "hip_chain_joints", "HIP_CHAIN"]

STAGES = ("global", "torso", "limbs", "full")
HIP_CHAIN = ("auto", "free", "rest")
PHOTO_STAGE = "texture"  # after "full", where photometric views exist
FITTED_JOINTS = ("semantic", "conditioning")
# joints whose rotation keypoints barely see (a collar moves the shoulder point as an arm does; a wrist
# turns a hand whose finger points are weak): their pose prior is ``stiff_prior`` times stronger, as
# is that of the hip chain (hip_chain_joints: a pelvis bone moves the hip point as the thigh does)
STIFF_JOINTS = ("l_collar", "r_collar", "l_wrist", "r_wrist")
# keypoints the ``torso`` stage leaves out: the arms are still at rest then, and the only torso joints
# that move a hanging arm are the collars, so a raised arm's elbow and wrist would be reached by
# turning the collar, which the later stages never fully undo. (The legs' keypoints stay: they hang
# from the root, which the torso stage turns, and they place the hip line.) Measured on the 60-frame
# studio capture (``uvatar fit``, 2026-11-23): from scans, the right collar's world angle error
# 14.7 -> 8.9 deg, left 7.1 -> 4.0 deg, and the bake from those fits 27.5 -> 29.1 dB; from the 4
# images alone MPJPE 24.4 -> 22.6 mm. Leaving out the legs' too: the real recording's hip line
# 4.0 -> 7.8 deg off the triangulated hips
ARM_KEYPOINTS = ("left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky",
                 "left_index", "right_index", "left_thumb", "right_thumb")
# semantic joints that keypoints cannot turn: toes and eyes stay at rest, as in EasyMocap's body fits
_AT_REST = ("l_toe", "r_toe", "l_eye", "r_eye")


def hip_chain_joints(body) -> set[int]:
    """The bones between the root and each semantic hip (anny's ``pelvis.L`` / ``pelvis.R``; none in
    SMPL, whose hips hang from the root)."""
    parents = body.template.joint_parents
    out: set[int] = set()
    for hip in ("l_hip", "r_hip"):
        j = int(parents[body.semantic_joints[hip]]) if hip in body.semantic_joints else -1
        while j >= 0 and parents[j] >= 0:
            out.add(j)
            j = int(parents[j])
    return out


def fitted_joints(body, which: str = "semantic", hip_chain: bool = False) -> list[int]:
    """Indices of the joints a fit rotates. "semantic": the body's semantic skeleton (pelvis, spine,
    neck, head, collars, shoulders, elbows, wrists, hips, knees, ankles; the joints of an EasyMocap /
    SMPL body fit), so that helper and twist bones a keypoint cannot see (anny's upperarm02,
    lowerarm02, shoulder01, ...) stay at rest instead of soaking up twist; "conditioning": every
    pose-conditioning joint. The root is left out (Rh turns the body). ``hip_chain``: the semantic
    set also turns the bones between the root and each hip (:func:`hip_chain_joints`)."""
    conditioning = [int(j) for j in body.conditioning_joints]
    if which == "conditioning":
        return conditioning
    keep = {int(j) for name, j in body.semantic_joints.items() if name not in _AT_REST}
    if hip_chain:
        keep |= hip_chain_joints(body)
    root = [j for j, p in enumerate(body.template.joint_parents) if p < 0]
    return [j for j in conditioning if j in keep and j not in root] or conditioning


@dataclass
class FitObservations:
    """What a sequence fit sees (T frames, K = len(BLAZEPOSE_NAMES) keypoints, C cameras).

    keypoints3d (T, K, 3) metres and keypoints3d_conf (T, K) in [0, 1] (from triangulation);
    keypoints2d (T, C, K, 2) distorted pixels, keypoints2d_conf (T, C, K), with ``cameras``;
    scans: per frame (points (P, 3), normals (P, 3)) or None; masks: per frame, per camera (H, W)
    bool or None; continuous: (T-1,) bool, False where frame t+1 does not follow frame t in time (a cut
    between takes): no smoothness across it (None: all continuous); photo: per frame
    :class:`~uvatar.fit.photometric.PhotoViews` (views with depth for the photometric term) or None."""

    keypoints3d: np.ndarray | None
    keypoints3d_conf: np.ndarray | None
    keypoints2d: np.ndarray | None = None
    keypoints2d_conf: np.ndarray | None = None
    cameras: list | None = None
    scans: list | None = None
    masks: list | None = None
    continuous: np.ndarray | None = None
    photo: list | None = None

    @property
    def num_frames(self) -> int:
        for x in (self.keypoints3d, self.keypoints2d, self.scans, self.masks):
            if x is not None:
                return len(x)
        return 0


@dataclass
class BodyFitConfig:
    """Weights (dimensionless, on metres^2 terms), robust scales (metres / pixels), stages.

    iterations: Adam steps per stage (global, torso, limbs, full); lr: rotation step (rad) /
    translation step (m) / shape step; sigmas: Geman-McClure scales; scan_*: see
    :class:`~uvatar.fit.losses.ScanTerm` and :func:`~uvatar.fit.losses.signed_scan_cost`;
    refresh_every: scan nearest neighbours are refreshed every this many steps.

    ``scan_inside_tolerance`` is the clothing layer a body may sit under the scan for free: the
    thinner it is, the more the scan (not the detector's landmarks, which are not the body's joints)
    sets the shape. Measured on the 60-frame studio capture (``uvatar fit --from scans``, mean vertex
    error of the shared shape): 3.2 mm with a 2 cm layer, 1.2 mm with 1 cm (also 1.2 mm with 0.5
    cm); moving the shape only in the full stage gave 2.1 / 1.0 mm but needs more steps from a shape
    far from the mean.

    ``w_photo`` / ``photo_iterations``: the ``texture`` stage (observations with photometric views:
    ``uvatar fit`` renders them where scans exist). Same capture, colour residual Geman-McClure
    ``photo_sigma`` 0.1, views at 256 px blurred by 1 px: world angle error of the joints 9.2 deg
    without it, 8.0 with w_photo 0.2 x 60 steps, 6.4 with 1.0 x 120 (3.0 x 200: 6.8; 512 px: 6.8);
    the bake from those fits: texture 25.2 -> 25.7 -> 26.3 dB, correspondence 2.49 -> 2.35 mm.

    ``hip_chain``: whether the bones between the root and the hips (:func:`hip_chain_joints`, anny's
    ``pelvis.L`` / ``pelvis.R``) turn, under the stiff prior: "free", "rest", or "auto" (free where
    no scan constrains the surface). Held at rest, a real person's pelvis cannot turn against the
    legs: on the real 4-camera recording (``uvatar fit --from images``, 100 frames) the fitted hip
    line's yaw was off the triangulated hips' by 13.3 deg mean / 32 deg max (right hip 33 mm off);
    free, 4.0 / 15 deg (15 mm). ``uvatar synth``
    moves the semantic joints alone, so freeing them costs a little there: from scans MPJPE 12.3 ->
    12.5 mm, angle 6.4 -> 7.1 deg, shape 1.2 -> 2.4 mm; from images 23.2 -> 24.4 mm. Where scans
    exist the surface places the hips, hence "auto"."""

    device: str = "cpu"
    iterations: tuple[int, int, int, int] = (40, 40, 80, 100)
    lr_rotation: float = 0.03
    lr_translation: float = 0.01
    lr_shape: float = 0.1
    fit_shape: bool = True
    shape_from_stage: int = 2
    shape_every: int = 4
    w_keypoints3d: float = 1.0
    keypoint_sigma: float = 0.05
    keypoint_sigma_coarse: float = 0.3
    w_keypoints2d: float = 1.0
    keypoint2d_sigma_px: float = 15.0
    w_scan: float = 3.0
    scan_sigma: float = 0.05
    scan_inside_tolerance: float = 0.01
    scan_inside_weight: float = 0.5
    scan_max_distance: float = 0.15
    scan_body_vertices: int = 1000
    scan_samples: int = 1000
    refresh_every: int = 10
    w_photo: float = 1.0
    photo_iterations: int = 120
    photo_sigma: float = 0.1
    photo_vertices: int = 2000
    photo_clothing: float = 0.03
    photo_blur_px: float = 1.0
    w_mask: float = 2.0
    mask_sigma: float = 0.05
    mask_vertices: int = 2000
    mask_outline: float = 1.0
    mask_outline_points: int = 200
    w_pose_prior: float = 2e-4
    w_smooth: float = 0.5
    smooth_sigma: float = 0.03
    w_shape_prior: float = 1e-3
    max_untracked_weight: float = 0.5
    min_torso_keypoints: int = 3
    joints: str = "semantic"  # which joints move: "semantic" (an EasyMocap body) or "conditioning"
    stiff_prior: float = 20.0  # pose-prior weight of STIFF_JOINTS (and the hip chain) relative to the others
    hip_chain: str = "auto"

    def __post_init__(self) -> None:
        self.iterations = tuple(int(i) for i in self.iterations)
        weights = [self.w_keypoints3d, self.w_keypoints2d, self.w_scan, self.w_mask, self.w_pose_prior,
                   self.w_smooth, self.w_shape_prior, self.w_photo]
        check_values([
            (self.photo_iterations >= 0 and self.photo_sigma > 0 and self.photo_vertices >= 1 and self.photo_clothing > 0
             and self.photo_blur_px >= 0, "photo_sigma, photo_vertices, photo_clothing must be > 0, "
                                          "photo_blur_px >= 0"),
            (len(self.iterations) == 4 and min(self.iterations) >= 0, "iterations: four counts >= 0"),
            (min(self.lr_rotation, self.lr_translation, self.lr_shape) > 0, "learning rates must be > 0"),
            (min(weights) >= 0 and self.mask_outline >= 0, "loss weights must be >= 0"),
            (min(self.keypoint_sigma, self.keypoint_sigma_coarse, self.smooth_sigma, self.keypoint2d_sigma_px, self.scan_sigma, self.mask_sigma) > 0,
             "robust scales (sigmas) must be > 0"),
            (self.scan_inside_tolerance >= 0 and 0 <= self.scan_inside_weight <= 1,
             "scan_inside_tolerance >= 0 and scan_inside_weight in [0, 1]"),
            (self.scan_max_distance > 0, "scan_max_distance must be > 0"),
            (min(self.scan_body_vertices, self.scan_samples, self.mask_vertices, self.mask_outline_points,
                 self.refresh_every) >= 1,
             "vertex/sample counts and refresh_every must be >= 1"),
            (0 < self.max_untracked_weight <= 1, "max_untracked_weight must be in (0, 1]"),
            (self.stiff_prior >= 0, f"stiff_prior must be >= 0, got {self.stiff_prior}"),
            (self.hip_chain in HIP_CHAIN, f"hip_chain must be one of {', '.join(HIP_CHAIN)}, got {self.hip_chain!r}"),
            (self.joints in FITTED_JOINTS, f"joints must be one of {', '.join(FITTED_JOINTS)}, got {self.joints!r}"),
            (0 <= self.shape_from_stage <= 3, "shape_from_stage must be 0..3"),
            (self.shape_every >= 1, "shape_every must be >= 1"),
            (self.min_torso_keypoints >= 3, "min_torso_keypoints must be >= 3"),
        ])


@dataclass
class SequenceFit:
    """poses (T, J, 3) local axis-angles (root zero); Rh, Th (T, 3); shape (S,) shared; scale (T,);
    frame_loss (T,) final total loss per frame; observed (T,) False for frames nothing constrained
    (their pose comes from the temporal term alone); losses: final mean of each term."""

    poses: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    shape: np.ndarray
    scale: np.ndarray
    frame_loss: np.ndarray
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    losses: dict = field(default_factory=dict)

    def body_fits(self):
        """list[BodyFit] in the EasyMocap convention, one per frame."""
        from uvatar.capture.types import BodyFit

        return [BodyFit(poses=p.reshape(-1), Rh=r, Th=t, shapes=self.shape, scale=float(s))
                for p, r, t, s in zip(self.poses, self.Rh, self.Th, self.scale, strict=True)]
