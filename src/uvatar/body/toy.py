"""A tiny skinned body without anny: a UV-mapped tube with a joint chain along +Y.

One builder for every toy use (AVH tests, DVA tests/benches, the viewer's toy avatar): pick the
joints, their heights, the tube's rings/segments/size and the skinning falloff in
:class:`ToyTubeConfig`. The default is AVH's 1.6 m tube with a 6-joint chain whose semantic joints
let :func:`uvatar.body.part_masks` work (the top joint "finger" is a digit, so ``fingers_toes`` is the
tube's top end; the "ankle" branch at the root gets no skin weight).

Rest pose: +Y up, joint rotations identity (local rotvecs are in world axes), joints on the axis.
UV layout: one seam at u = 0 / 1 (seam vertices are split in UV, not in 3D).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from uvatar.body.base import BodyModel, BodyTemplate

__all__ = ["ToyTubeConfig", "ToyTubeBody", "tube_mesh", "tube_skin_weights"]

_AVH_SEMANTIC_JOINTS = {"pelvis": 0, "spine1": 1, "spine2": 1, "spine3": 2, "neck": 2, "head": 3,
                        "l_collar": 2, "l_shoulder": 2, "l_elbow": 2, "l_wrist": 3, "r_collar": 2,
                        "r_shoulder": 2, "r_elbow": 2, "r_wrist": 3, "l_hip": 0, "l_knee": 0,
                        "l_ankle": 5, "l_toe": 5, "r_hip": 0, "r_knee": 0, "r_ankle": 5, "r_toe": 5}


@dataclass(frozen=True)
class ToyTubeConfig:
    """The tube and its rig. Lengths in metres.

    rings: vertex rings along the height; segments: vertices around each ring.
    bulge: ring radius is ``radius * (1 + bulge * cos(3 pi y / height))`` (0: a straight tube).
    u_range / v_range: the UV rectangle the tube unrolls onto (u around, v up).
    joint_heights: (J,) y of each joint (all on the axis); joint_parents: -1 for the root.
    skinning: "hat" (piecewise linear between consecutive ``skinned_joints``), "ramp" (each skinned
        joint after the first takes over linearly across a band ``blend * height`` wide centred on it)
        or "gaussian" (weights ~ exp(-((y - y_j - blend_offset) / blend)^2), ``blend`` in metres).
    skinned_joints: joints that get weight, in increasing height (None: all joints).
    joint_axes: (J, 3, 3) rest-pose world orientation of the axes each joint's rotvec is written in
        (:attr:`BodyModel.rest_joint_rotations`; columns are the axes), as anny's per-joint frames;
        None: world axes.
    """

    rings: int = 17
    segments: int = 16
    height: float = 1.6
    radius: float = 0.15
    bulge: float = 0.0
    u_range: tuple[float, float] = (0.0, 1.0)
    v_range: tuple[float, float] = (0.02, 0.98)
    joint_names: tuple[str, ...] = ("root", "spine", "chest", "wrist", "finger", "ankle")
    joint_parents: tuple[int, ...] = (-1, 0, 1, 2, 3, 0)
    joint_heights: tuple[float, ...] = (0.0, 0.4, 0.8, 1.2, 1.45, 0.0)
    skinning: str = "hat"
    skinned_joints: tuple[int, ...] | None = (0, 1, 2, 3, 4)
    blend: float = 0.3
    blend_offset: float = 0.0
    conditioning_joints: tuple[int, ...] = (1, 2, 3)
    semantic_joints: dict = field(default_factory=lambda: dict(_AVH_SEMANTIC_JOINTS))
    shape_names: tuple[str, ...] = ("height",)
    joint_axes: tuple | None = None


def tube_mesh(rings: int, segments: int, height: float, radius: float, bulge: float = 0.0,
              u_range=(0.0, 1.0), v_range=(0.02, 0.98)):
    """Open tube along +Y from y = 0 to ``height``, vectorized.

    -> vertices (rings*segments, 3) float32, faces (2*(rings-1)*segments, 3) int64, uvs
    (rings*(segments+1), 2) float32, uv_faces like faces. Two triangles per quad, in quad order;
    vertex (ring r, segment s) sits at angle 2 pi s / segments from +Z toward +X.
    """
    y = np.linspace(0.0, height, rings)
    angle = np.arange(segments) * 2 * np.pi / segments
    r = radius * (1.0 + bulge * np.cos(3 * np.pi * y / height))[:, None]
    vertices = np.stack(np.broadcast_arrays(r * np.sin(angle)[None], y[:, None], r * np.cos(angle)[None]), -1)
    u = u_range[0] + (u_range[1] - u_range[0]) * np.arange(segments + 1) / segments
    v = v_range[0] + (v_range[1] - v_range[0]) * y / height
    uvs = np.stack(np.broadcast_arrays(u[None], v[:, None]), -1).reshape(-1, 2)
    ring, seg = (a.ravel() for a in np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij"))

    def quads(row_len, nxt):  # (Q, 2, 3) triangles (a, b, d), (a, d, c) of each quad
        a, b = ring * row_len + seg, ring * row_len + nxt
        c, d = a + row_len, b + row_len
        return np.stack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], 1).reshape(-1, 3)

    faces = quads(segments, (seg + 1) % segments)
    uv_faces = quads(segments + 1, seg + 1)
    return (vertices.reshape(-1, 3).astype(np.float32), faces.astype(np.int64), uvs.astype(np.float32),
            uv_faces.astype(np.int64))


def tube_skin_weights(heights: np.ndarray, config: ToyTubeConfig) -> np.ndarray:
    """(V,) vertex heights (m) -> (V, J) float32 skin weights (rows sum to 1) per ``config.skinning``."""
    J = len(config.joint_names)
    skinned = list(range(J)) if config.skinned_joints is None else list(config.skinned_joints)
    y = np.asarray(heights, np.float64)[:, None]
    jy = np.asarray(config.joint_heights, np.float64)[skinned][None]  # (1, K)
    if config.skinning == "hat":
        left = np.concatenate([jy[:, :1] - 1.0, jy[:, :-1]], 1)
        right = np.concatenate([jy[:, 1:], jy[:, -1:] + 1.0], 1)
        up = np.clip((y - left) / np.maximum(jy - left, 1e-6), 0, 1)
        down = np.clip((right - y) / np.maximum(right - jy, 1e-6), 0, 1)
        w = np.minimum(up, down)
    elif config.skinning == "ramp":
        t, width = y / config.height, config.blend
        takeover = np.clip((t - (jy / config.height - width / 2)) / width, 0, 1)  # (V, K)
        takeover[:, 0] = 1.0
        w = takeover - np.concatenate([takeover[:, 1:], np.zeros_like(y)], 1)
    elif config.skinning == "gaussian":
        w = np.exp(-((np.abs(y - (jy + config.blend_offset))) / config.blend) ** 2)
    else:
        raise ValueError(f"unknown skinning {config.skinning!r} (hat, ramp or gaussian)")
    out = np.zeros((len(y), J), np.float64)
    out[:, skinned] = w
    return (out / out.sum(1, keepdims=True)).astype(np.float32)


class ToyTubeBody(BodyModel):
    """A :class:`BodyModel` tube (default: AVH's 1.6 m tube, joints root-spine-chest-wrist-finger plus
    an unused ankle, conditioning joints 1..3). ``shape`` (1,) scales the body by ``1 + shape[0]``."""

    name = "toy"

    def __init__(self, rings: int | None = None, segments: int | None = None,
                 config: ToyTubeConfig | None = None):
        super().__init__()
        from uvatar.body.kinematics import kinematic_levels

        config = config or ToyTubeConfig()
        if rings is not None or segments is not None:
            config = replace(config, rings=rings or config.rings, segments=segments or config.segments)
        self.config = config
        vertices, faces, uvs, uv_faces = tube_mesh(config.rings, config.segments, config.height, config.radius,
                                                   config.bulge, config.u_range, config.v_range)
        J = len(config.joint_names)
        heights = np.asarray(config.joint_heights, np.float32)
        rest_joints = np.stack([np.zeros(J), heights, np.zeros(J)], 1).astype(np.float32)
        parents = np.asarray(config.joint_parents, np.int64)
        self.template = BodyTemplate(vertices, faces, uvs, uv_faces, tube_skin_weights(vertices[:, 1], config),
                                     tuple(config.joint_names), parents, rest_joints)
        self.shape_names = tuple(config.shape_names)
        self.semantic_joints = dict(config.semantic_joints)
        self.conditioning_joints = tuple(config.conditioning_joints)
        self._levels = kinematic_levels(parents)
        axes = (np.tile(np.eye(3, dtype=np.float32), (J, 1, 1)) if config.joint_axes is None
                else np.asarray(config.joint_axes, np.float32))
        if axes.shape != (J, 3, 3) or not np.allclose(axes @ axes.transpose(0, 2, 1), np.eye(3), atol=1e-5):
            raise ValueError(f"joint_axes must be {J} rotation matrices (J, 3, 3), got shape {axes.shape}")
        self._set_common_buffers(faces, axes)
        offsets = rest_joints - np.where(parents[:, None] >= 0, rest_joints[np.maximum(parents, 0)], 0)
        self.register_buffer("_verts_t", torch.from_numpy(vertices), persistent=False)
        self.register_buffer("_weights_t", torch.from_numpy(self.template.skin_weights), persistent=False)
        self.register_buffer("_joints_t", torch.from_numpy(rest_joints), persistent=False)
        self.register_buffer("_offsets_t", torch.from_numpy(offsets.astype(np.float32)), persistent=False)

    def _pose_local(self, rotvecs: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
        from uvatar.body.kinematics import forward_kinematics, rotvec_to_rotmat, skin, skinning_transforms

        B, J = rotvecs.shape[:2]
        scale = 1.0 if shape is None else torch.as_tensor(shape, dtype=rotvecs.dtype).reshape(-1)[0] + 1.0
        joints = self._joints_t.to(rotvecs) * scale
        local = rotvec_to_rotmat(self.local_to_world_rotvecs(rotvecs))   # each rotvec in its joint's axes
        F, p = forward_kinematics(self._levels_on(rotvecs.device), local, (self._offsets_t.to(rotvecs) * scale)[None])
        vertices = skin((self._verts_t.to(rotvecs) * scale)[None], self._weights_t.to(rotvecs),
                        skinning_transforms(F, p, None, joints[None])).contiguous()
        G = torch.eye(4, dtype=rotvecs.dtype, device=rotvecs.device).repeat(B, J, 1, 1)
        G[..., :3, :3] = F @ self._rest_rot_t.to(rotvecs)   # the joint's frame: its axes at rest, turned
        G[..., :3, 3] = p
        return vertices, G
