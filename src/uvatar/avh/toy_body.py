"""A tiny skinned body (a UV-mapped tube with a 6-joint chain) for AVH tests and benchmarks.

It implements the :class:`uvatar.body.BodyModel` interface without anny: ~300 vertices, a UV
layout with one seam (u = 0 / 1), skinning weights along the chain, and the semantic joints that
:func:`uvatar.body.part_masks` needs (the top joint "finger" is a digit, so ``fingers_toes`` is the
tube's top end). Rest pose: +Y up, radius 0.15 m, 1.6 m tall, joint rotations identity.
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.body.base import BodyModel, BodyTemplate

JOINT_NAMES = ("root", "spine", "chest", "wrist", "finger", "ankle")
JOINT_PARENTS = np.array([-1, 0, 1, 2, 3, 0])
JOINT_HEIGHTS = np.array([0.0, 0.4, 0.8, 1.2, 1.45, 0.0])


def _tube(rings: int, segments: int, height: float, radius: float):
    """Open tube: vertices (rings·segments, 3), faces, uvs (rings·(segments+1), 2), uv_faces."""
    y = np.linspace(0.0, height, rings)
    a = np.arange(segments) * 2 * np.pi / segments
    vertices = np.stack(np.broadcast_arrays(radius * np.sin(a)[None], y[:, None], radius * np.cos(a)[None]), -1)
    u = np.arange(segments + 1) / segments
    v = 0.02 + 0.96 * y / height
    uvs = np.stack(np.broadcast_arrays(u[None], v[:, None]), -1).reshape(-1, 2)
    r, s = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    r, s = r.ravel(), s.ravel()
    s1 = (s + 1) % segments

    def vid(ri, si):
        return ri * segments + si

    def uid(ri, si):
        return ri * (segments + 1) + si

    faces = np.concatenate([np.stack([vid(r, s), vid(r, s1), vid(r + 1, s1)], 1),
                            np.stack([vid(r, s), vid(r + 1, s1), vid(r + 1, s)], 1)])
    uv_faces = np.concatenate([np.stack([uid(r, s), uid(r, s + 1), uid(r + 1, s + 1)], 1),
                               np.stack([uid(r, s), uid(r + 1, s + 1), uid(r + 1, s)], 1)])
    return (vertices.reshape(-1, 3).astype(np.float32), faces.astype(np.int64), uvs.astype(np.float32),
            uv_faces.astype(np.int64))


def _skin_weights(heights: np.ndarray) -> np.ndarray:
    """(V,) heights -> (V, J) hat-function weights over the chain root..finger (ankle gets none)."""
    chain = JOINT_HEIGHTS[:5]
    w = np.zeros((len(heights), len(JOINT_NAMES)), np.float32)
    for j in range(5):  # 5 joints, vectorized over vertices
        left = chain[j - 1] if j > 0 else chain[0] - 1.0
        right = chain[j + 1] if j < 4 else chain[4] + 1.0
        up = np.clip((heights - left) / max(chain[j] - left, 1e-6), 0, 1)
        down = np.clip((right - heights) / max(right - chain[j], 1e-6), 0, 1)
        w[:, j] = np.minimum(up, down)
    return w / w.sum(1, keepdims=True)


class ToyTubeBody(BodyModel):
    """A 1.6 m tube with joints root-spine-chest-wrist-finger (+ an unused ankle); conditioning joints 1..3."""

    name = "toy"

    def __init__(self, rings: int = 17, segments: int = 16):
        super().__init__()
        vertices, faces, uvs, uv_faces = _tube(rings, segments, 1.6, 0.15)
        rest_joints = np.stack([np.zeros(6), JOINT_HEIGHTS, np.zeros(6)], 1).astype(np.float32)
        self.template = BodyTemplate(vertices, faces, uvs, uv_faces, _skin_weights(vertices[:, 1]), JOINT_NAMES,
                                     JOINT_PARENTS.copy(), rest_joints)
        self.shape_names = ("height",)
        self.semantic_joints = {"pelvis": 0, "spine1": 1, "spine2": 1, "spine3": 2, "neck": 2, "head": 3,
                                "l_collar": 2, "l_shoulder": 2, "l_elbow": 2, "l_wrist": 3, "r_collar": 2,
                                "r_shoulder": 2, "r_elbow": 2, "r_wrist": 3, "l_hip": 0, "l_knee": 0,
                                "l_ankle": 5, "l_toe": 5, "r_hip": 0, "r_knee": 0, "r_ankle": 5, "r_toe": 5}
        self.conditioning_joints = (1, 2, 3)
        self._set_common_buffers(faces, np.tile(np.eye(3, dtype=np.float32), (6, 1, 1)))
        self.register_buffer("_verts_t", torch.from_numpy(vertices), persistent=False)
        self.register_buffer("_weights_t", torch.from_numpy(self.template.skin_weights), persistent=False)
        self.register_buffer("_joints_t", torch.from_numpy(rest_joints), persistent=False)

    def _pose_local(self, rotvecs: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
        import roma

        B, J = rotvecs.shape[:2]
        scale = 1.0 if shape is None else torch.as_tensor(shape, dtype=rotvecs.dtype).reshape(-1)[0] + 1.0
        rot = roma.rotvec_to_rotmat(rotvecs)  # (B, J, 3, 3)
        joints = self._joints_t.to(rotvecs) * scale
        world = [None] * J
        for j in range(J):  # 6 joints, parents first
            local = torch.eye(4, dtype=rotvecs.dtype, device=rotvecs.device).repeat(B, 1, 1)
            local[:, :3, :3] = rot[:, j]
            p = int(JOINT_PARENTS[j])
            local[:, :3, 3] = joints[j] - (joints[p] if p >= 0 else 0.0)
            world[j] = local if p < 0 else world[p] @ local
        G = torch.stack(world, 1)  # (B, J, 4, 4) world joint frames
        skinning = G.clone()
        skinning[..., :3, 3] = G[..., :3, 3] - (G[..., :3, :3] @ joints[None, :, :, None])[..., 0]
        blended = torch.einsum("vj,bjik->bvik", self._weights_t.to(rotvecs), skinning[..., :3, :])
        v = self._verts_t.to(rotvecs) * scale
        vertices = (blended[..., :3] @ v[None, :, :, None])[..., 0] + blended[..., 3]
        return vertices, G
