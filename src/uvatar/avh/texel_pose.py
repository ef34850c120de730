"""Texel-aligned pose conditioning for the AVH generator (``AvhConfig.conditioning = "texel"``).

The paper's generator sees the pose only through one global latent vector (the feature cuboid).
Texel conditioning adds, at every decoder level, a UV-space map of the rotations of the joints that
skin each texel::

    r_j   = rot6d(R(a_j)) - rot6d(I)               (B, J_c, 6)   a_j: local axis-angle of conditioning joint j
    P     = sum_j W[j, texel] · r_j                 (B, 6, R, R)  W: skinning weights of the texel (a constant)

``rot6d`` is the first two columns of the rotation matrix (Zhou et al. 2019), made zero at rest, so a
texel's map changes only when a joint that skins it turns. ``W`` is the body's vertex skinning weights
interpolated to the texel (barycentric), with the weight of every joint that is not a conditioning
joint (fingers, toes, eyes) given to its nearest conditioning ancestor, zero outside the UV charts.
The map is computed inside the network from the same ``pose_angles`` input (a matmul with the
constant ``W``), so the exported ONNX graph keeps its one input and runtimes need no change.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["rotvec_to_rot6d", "conditioning_skin_weights", "texel_skin_weights", "TexelPoseMap"]


def rotvec_to_rot6d(rotvecs: torch.Tensor) -> torch.Tensor:
    """(…, 3) axis-angle (radians) -> (…, 6) first two columns of the rotation matrix minus those of I.

    Rodrigues ``R = I + a K + b K²`` with ``a = sin θ / θ``, ``b = 2 sin²(θ/2) / θ²`` (stable near
    θ = 0), written with ONNX-portable ops only (no atan2, no branches). Output order: column 0
    (x, y, z) then column 1 (x, y, z).
    """
    x, y, z = rotvecs.unbind(-1)
    theta2 = x * x + y * y + z * z
    theta = torch.sqrt(theta2 + 1e-12)
    a = torch.sin(theta) / theta
    half = torch.sin(0.5 * theta)
    b = 2.0 * half * half / (theta2 + 1e-12)
    # K² = v vᵀ − θ² I; R − I = a K + b K²
    c0 = torch.stack([b * (x * x - theta2), a * z + b * x * y, -a * y + b * x * z], -1)
    c1 = torch.stack([-a * z + b * x * y, b * (y * y - theta2), a * x + b * y * z], -1)
    return torch.cat([c0, c1], -1)


def conditioning_skin_weights(skin_weights: np.ndarray, joint_parents, conditioning_joints) -> np.ndarray:
    """(V, J) vertex skinning weights -> (V, J_c) over the conditioning joints (in their order).

    A joint outside the conditioning set gives its weight to its nearest conditioning ancestor (a
    finger's to the wrist); a joint with none (the root, whose rotation is the global Rh) drops it.
    """
    cond = [int(j) for j in conditioning_joints]
    column = {j: k for k, j in enumerate(cond)}
    parents = np.asarray(joint_parents, np.int64)
    w = np.asarray(skin_weights, np.float32)
    out = np.zeros((w.shape[0], len(cond)), np.float32)
    for j in range(w.shape[1]):
        a = j
        while a >= 0 and a not in column:
            a = int(parents[a])
        if a >= 0:
            out[:, column[a]] += w[:, j]
    return out


def texel_skin_weights(template, conditioning_joints, resolution: int) -> np.ndarray:
    """(J_c, R, R) float32 skinning weight of each conditioning joint at each texel centre (row 0 is
    v = 1), barycentric from the template's vertices, zero outside the UV charts."""
    from uvatar.geometry import rasterize_uv, sample_vertex_attribute

    raster = rasterize_uv(template.uvs, template.uv_faces, resolution)
    wv = conditioning_skin_weights(template.skin_weights, template.joint_parents, conditioning_joints)
    w = np.asarray(sample_vertex_attribute(raster, template.faces, wv), np.float32)
    w[~raster.mask] = 0.0
    return np.ascontiguousarray(w.transpose(2, 0, 1))


class TexelPoseMap(nn.Module):
    """Conditioning angles (B, 3·J_c) radians -> texel pose map (B, 6, R, R); ``weights`` (J_c, R, R)
    is a persistent buffer (zeros until :meth:`set_weights`; saved with the model's state)."""

    channels = 6

    def __init__(self, num_joints: int, resolution: int):
        super().__init__()
        self.register_buffer("weights", torch.zeros(num_joints, resolution * resolution))
        self.resolution = resolution

    def set_weights(self, weights) -> None:
        """Fill the buffer from (J_c, R, R) skinning weights (:func:`texel_skin_weights`)."""
        w = torch.as_tensor(np.asarray(weights, np.float32))
        if tuple(w.shape) != (self.weights.shape[0], self.resolution, self.resolution):
            raise ValueError(f"texel weights must be ({self.weights.shape[0]}, {self.resolution}, "
                             f"{self.resolution}), got {tuple(w.shape)}")
        with torch.no_grad():
            self.weights.copy_(w.reshape(w.shape[0], -1))

    def forward(self, pose_angles: torch.Tensor) -> torch.Tensor:
        r6 = rotvec_to_rot6d(pose_angles.reshape(pose_angles.shape[0], -1, 3))      # (B, J_c, 6)
        m = torch.matmul(r6.transpose(1, 2), self.weights)                           # (B, 6, R²)
        return m.reshape(pose_angles.shape[0], self.channels, self.resolution, self.resolution)


def pooled(pose_map: torch.Tensor, resolution: int) -> torch.Tensor:
    """(B, C, R, R) -> (B, C, r, r) by average pooling (R / r an integer)."""
    factor = pose_map.shape[-1] // resolution
    return pose_map if factor == 1 else F.avg_pool2d(pose_map, factor)
