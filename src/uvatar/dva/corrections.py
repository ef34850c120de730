"""Corrections learned beside a DVA avatar during training: per-frame body pose and per-camera colour.

Real captures have body fits a few pixels off (about 8 px on the Pose2Sim recording, ``docs/real.md``)
and cameras whose colour response differs. An avatar trained on them averages the misplaced photos
into a blur. As Animatable Gaussians, 3DGS-Avatar and GauHuman do, training therefore also learns:

* **pose**: for every training frame, a rotation offset (axis-angle, radians) of each conditioning
  joint, added to the fit's local rotation, a global rotation offset composed before the fit's ``Rh``
  and a translation offset (metres) added to ``Th``. The body is re-posed through the body model's LBS
  each step (the gradient reaches the offsets through the primitives' positions and through the pose
  features). A quadratic prior (``pose_weight`` on radians², ``translation_weight`` on metres²) keeps
  them small; they start learning after the primitive correctives' warm-up.
* **colour**: for every training camera, a gain (3,) and bias (3,) applied to the rendered foreground
  (premultiplied: ``gain * rgb + bias * alpha``) before it is composited over the background, with a
  quadratic prior toward the identity (``colour_weight``).

Both are training-time only: a frame or camera the avatar did not train on (held-out poses, a held-out
camera, driving at run time) is rendered with the fit as it is and the identity colour response, so
evaluation never sees anything fitted to its own images.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn


@dataclass
class CorrectionConfig:
    """pose: learn per-frame pose/translation offsets. colour: learn per-camera gain and bias.
    pose_weight / translation_weight / colour_weight: the quadratic priors' weights (on mean squared
    radians, metres and colour-response deviation). lr: their Adam learning rate."""

    pose: bool = True
    colour: bool = True
    pose_weight: float = 1.0
    translation_weight: float = 100.0
    colour_weight: float = 1.0
    lr: float = 1e-3


@dataclass
class FitParams:
    """A bank of body fits as tensors: rotvecs (F, J, 3) local axis-angles, Rh (F, 3), Th (F, 3) metres,
    scale (F,), shape (F, S) or None."""

    rotvecs: torch.Tensor
    Rh: torch.Tensor
    Th: torch.Tensor
    scale: torch.Tensor
    shape: torch.Tensor | None


class TrainingCorrections(nn.Module):
    """Per-frame pose offsets for ``num_frames`` frames (over ``joints``, the conditioning joints) and
    per-camera colour responses for ``num_cameras`` cameras; all start at the identity."""

    def __init__(self, cfg: CorrectionConfig, num_frames: int, num_cameras: int, joints):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("joints", torch.as_tensor(list(joints), dtype=torch.long))
        J = len(self.joints)
        self.joint_rotvecs = nn.Parameter(torch.zeros(num_frames, J, 3))
        self.root_rotvecs = nn.Parameter(torch.zeros(num_frames, 3))
        self.translations = nn.Parameter(torch.zeros(num_frames, 3))
        self.gains = nn.Parameter(torch.ones(num_cameras, 3))
        self.biases = nn.Parameter(torch.zeros(num_cameras, 3))

    def pose_inputs(self, fits: FitParams, frames: torch.Tensor, active: bool):
        """(rotvecs (B, J, 3), Rh, Th (B, 3)) of ``frames`` (B,) with the offsets applied when ``active``
        and ``cfg.pose`` (otherwise the fits' own, without a graph to the offsets). ``Rh``: the fits' (B, 3)
        axis-angles, or with the offsets applied (B, 3, 3) the composed rotations ``R(offset) R(Rh)`` as
        matrices (what the body's posing takes either way: two conversions and a product, where composing
        axis-angles took ~70 operators a step and as many in the backward, issue 39)."""
        from uvatar.body.kinematics import rotvec_to_rotmat

        dev = self.translations.device
        rot, Rh, Th = (x[frames.to(x.device)].to(dev) for x in (fits.rotvecs, fits.Rh, fits.Th))
        frames = frames.to(dev)
        if not (active and self.cfg.pose):
            return rot, Rh, Th
        rot = rot.index_add(1, self.joints, self.joint_rotvecs[frames])
        Rh = rotvec_to_rotmat(self.root_rotvecs[frames]) @ rotvec_to_rotmat(Rh)
        return rot, Rh, Th + self.translations[frames]

    def colour(self, rgb: torch.Tensor, alpha: torch.Tensor, camera: int) -> torch.Tensor:
        """Premultiplied foreground rgb (N, 3) and alpha (N,) of training camera ``camera`` (a (1,) index
        tensor) -> (N, 3) with that camera's response (unchanged when ``cfg.colour`` is off). A batch:
        rgb (B, N, 3), alpha (B, N) and ``camera`` (B, 1), sample b through camera ``camera[b]``."""
        if not self.cfg.colour:
            return rgb
        return rgb * self.gains[camera] + alpha[..., None] * self.biases[camera]

    def prior(self, frames: torch.Tensor, cameras: torch.Tensor) -> dict[str, torch.Tensor]:
        """The quadratic priors of the offsets in use this step (frames (B,), cameras (B,))."""
        c, terms = self.cfg, {}
        if c.pose:
            terms["pose_prior"] = c.pose_weight * (self.joint_rotvecs[frames].square().mean()
                                                   + self.root_rotvecs[frames].square().mean())
            terms["translation_prior"] = c.translation_weight * self.translations[frames].square().mean()
        if c.colour:
            terms["colour_prior"] = c.colour_weight * ((self.gains[cameras] - 1).square().mean()
                                                       + self.biases[cameras].square().mean())
        return terms

    def summary(self) -> dict:
        """Sizes of what was learned: RMS joint / root rotation (degrees), RMS translation (mm),
        the gains and biases per camera."""
        deg = 180.0 / torch.pi
        with torch.no_grad():
            return {"joint_rotation_rms_deg": float(self.joint_rotvecs.square().mean().sqrt() * deg),
                    "root_rotation_rms_deg": float(self.root_rotvecs.square().mean().sqrt() * deg),
                    "translation_rms_mm": float(self.translations.square().mean().sqrt() * 1000),
                    "gains": self.gains.tolist(), "biases": self.biases.tolist()}
