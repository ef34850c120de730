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

With the body's orientation in the studio as an input (``AvhConfig.orientation = "studio"``: the
last conditioning "joint" is the root, whose slot carries ``Rh``), the map gets three more channels,
the texel's **posed normal in the capture's world**::

    G_j   = G_parent(j) · R(a_j)                    (B, J_c, 3, 3)  world rotation (forward kinematics
                                                                    over the conditioning joints, root = R(Rh))
    n     = sum_j W[j, texel] · G_j · n_rest(texel)  (B, 3, R, R)

A studio's lights are fixed in its world, so the shading it bakes into every frame is a function of
this normal (and of what occludes the texel); the decoders and the shading head of
:class:`uvatar.avh.model.AvhGenerator` read it. ``n_rest`` is the template's rest-pose vertex normal
interpolated to the texel (a constant buffer, like ``W``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["standardize", "input_statistics", "rotation_minus_identity", "rotvec_to_rot6d", "rotvec_to_rotmat", "conditioning_skin_weights", "conditioning_parents",
           "texel_skin_weights", "texel_rest_normals", "texel_vertex_map", "TexelPoseMap"]


def rotation_minus_identity(rotvecs: torch.Tensor) -> torch.Tensor:
    """(…, 3) axis-angle (radians) -> (…, 3, 3) ``R − I`` (rows are the matrix's rows).

    Rodrigues ``R = I + a K + b K²`` with ``a = sin θ / θ``, ``b = 2 sin²(θ/2) / θ²`` (stable near
    θ = 0), written with ONNX-portable ops only (no atan2, no branches); ``R − I`` is kept apart from
    the identity so that small rotations keep their precision. ``K² = v vᵀ − θ² I``.
    """
    x, y, z = rotvecs.unbind(-1)
    theta2 = x * x + y * y + z * z
    theta = torch.sqrt(theta2 + 1e-12)
    a = torch.sin(theta) / theta
    half = torch.sin(0.5 * theta)
    b = 2.0 * half * half / (theta2 + 1e-12)
    rows = [torch.stack([b * (x * x - theta2), -a * z + b * x * y, a * y + b * x * z], -1),
            torch.stack([a * z + b * x * y, b * (y * y - theta2), -a * x + b * y * z], -1),
            torch.stack([-a * y + b * x * z, a * x + b * y * z, b * (z * z - theta2)], -1)]
    return torch.stack(rows, -2)


def input_statistics(x: torch.Tensor, floor: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, std floored at ``floor``) over the first axis of training inputs ``x`` (N, ...): what
    :func:`standardize` divides by (``AvhConfig.pose_normalization``)."""
    return x.mean(0), x.std(0, unbiased=False).clamp_min(floor)


def standardize(x: torch.Tensor, mean: torch.Tensor, scale: torch.Tensor, clip: float) -> torch.Tensor:
    """(x - mean) / scale, clipped to ±``clip`` (ONNX: Sub, Div, Clip)."""
    return torch.clamp((x - mean) / scale, -clip, clip)


def rotvec_to_rot6d(rotvecs: torch.Tensor) -> torch.Tensor:
    """(…, 3) axis-angle (radians) -> (…, 6) first two columns of the rotation matrix minus those of I.
    Output order: column 0 (x, y, z) then column 1 (x, y, z)."""
    d = rotation_minus_identity(rotvecs)
    return torch.cat([d[..., :, 0], d[..., :, 1]], -1)


def rotvec_to_rotmat(rotvecs: torch.Tensor) -> torch.Tensor:
    """(…, 3) axis-angle (radians) -> (…, 3, 3) rotation matrices (ONNX-portable ops only)."""
    eye = torch.eye(3, dtype=rotvecs.dtype, device=rotvecs.device)
    return rotation_minus_identity(rotvecs) + eye


def conditioning_parents(joint_parents, conditioning_joints) -> list[int]:
    """For each conditioning joint, the position (in ``conditioning_joints``) of its nearest conditioning
    ancestor, -1 where it has none. The forward kinematics of :class:`TexelPoseMap` walks this tree."""
    cond = [int(j) for j in conditioning_joints]
    column = {j: k for k, j in enumerate(cond)}
    parents = np.asarray(joint_parents, np.int64)
    out = []
    for j in cond:
        a = int(parents[j])
        while a >= 0 and a not in column:
            a = int(parents[a])
        out.append(column[a] if a >= 0 else -1)
    return out


def tree_order(parents: list[int]) -> list[int] | None:
    """Positions ordered so that every parent comes before its children; None if ``parents`` (positions
    or -1) is not a tree (out of range, or a cycle)."""
    n = len(parents)
    if any(not -1 <= q < n for q in parents):
        return None
    order, placed = [], set()
    while len(order) < n:
        ready = [k for k in range(n) if k not in placed and (parents[k] < 0 or parents[k] in placed)]
        if not ready:
            return None
        order += ready
        placed.update(ready)
    return order


def texel_vertex_map(template, vertex_values, resolution: int, dtype=np.float32) -> np.ndarray:
    """(C, R, R) ``dtype``: per-vertex ``vertex_values`` (V, C) of the template at each texel centre
    (row 0 is v = 1), barycentric from the vertices, zero outside the UV charts."""
    from uvatar.geometry import rasterize_uv, sample_vertex_attribute

    raster = rasterize_uv(template.uvs, template.uv_faces, resolution)
    x = np.asarray(sample_vertex_attribute(raster, template.faces, vertex_values), np.float64)
    x[~raster.mask] = 0.0
    return np.ascontiguousarray(x.transpose(2, 0, 1).astype(dtype))


def texel_rest_normals(template, resolution: int) -> np.ndarray:
    """(3, R, R) float32 unit rest-pose normal of the template at each texel centre (row 0 is v = 1),
    barycentric from the vertex normals and normalized, zero outside the UV charts."""
    from uvatar.geometry.frames import vertex_normals

    n = texel_vertex_map(template, vertex_normals(template.vertices, template.faces), resolution, np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=0, keepdims=True), 1e-12)
    return np.ascontiguousarray(n.astype(np.float32))


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


def conditioning_axes(body, conditioning_joints, orientation_root: int | None = None) -> np.ndarray:
    """(J_c, 3, 3) float32: the rest-pose world orientation of the axes each conditioning joint's
    rotation is written in (``body.rest_joint_rotations``), identity at the slot of
    ``orientation_root`` (the joint whose slot carries the body's Rh, a world rotation), if given."""
    cond = [int(j) for j in conditioning_joints]
    axes = np.asarray(body.rest_joint_rotations, np.float32)[cond].copy()
    if orientation_root is not None:
        axes[cond.index(int(orientation_root))] = np.eye(3, dtype=np.float32)
    return axes


def texel_skin_weights(template, conditioning_joints, resolution: int) -> np.ndarray:
    """(J_c, R, R) float32 skinning weight of each conditioning joint at each texel centre (row 0 is
    v = 1), barycentric from the template's vertices, zero outside the UV charts."""
    wv = conditioning_skin_weights(template.skin_weights, template.joint_parents, conditioning_joints)
    return texel_vertex_map(template, wv, resolution)


class TexelPoseMap(nn.Module):
    """Conditioning angles (B, 3·J_c) radians -> texel pose map (B, C, R, R): C = 6 (local rotations)
    or, with ``world_normals``, 9 (also the posed world normal; the last conditioning joint is then the
    root, carrying Rh). Buffers (saved with the model's state, zeros until :meth:`set_weights`):
    ``weights`` (J_c, R²), ``parents`` (J_c,), ``rest_normals`` (3, R²) and ``axes`` (J_c, 3, 3): the
    rest-pose world orientation of the axes each joint's rotation is written in
    (:attr:`uvatar.body.base.BodyModel.rest_joint_rotations`; identity for the root slot carrying Rh,
    which is in world axes already). A joint's rotation in world axes is ``axes · R · axesᵀ``: anny
    writes its rotations in per-joint frames, and composing them as if they were world rotations
    turned the posed normals 19° off the posed mesh's (median; 55° p90) on the demo's frames (0.6°
    with the axes)."""

    def __init__(self, num_joints: int, resolution: int, world_normals: bool = False,
                 normalization: tuple[float, float] | None = None):
        super().__init__()
        self.register_buffer("weights", torch.zeros(num_joints, resolution * resolution))
        # (scale floor, clip): each joint's rot6d standardized by the training frames' statistics
        # (AvhConfig.pose_normalization; identity until set_statistics) before it is blended
        self.normalization = normalization
        if normalization is not None:
            self.register_buffer("r6_mean", torch.zeros(num_joints, 6))
            self.register_buffer("r6_scale", torch.ones(num_joints, 6))
        self.resolution = resolution
        self.world_normals = bool(world_normals)
        self.channels = 9 if self.world_normals else 6
        if self.world_normals:
            self.register_buffer("parents", torch.full((num_joints,), -1, dtype=torch.long))
            self.register_buffer("rest_normals", torch.zeros(3, resolution * resolution))
            self.register_buffer("axes", torch.eye(3).repeat(num_joints, 1, 1))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a model saved before the axes were kept composed its rotations in world axes: identity
        if self.world_normals and prefix + "axes" not in state_dict:
            state_dict[prefix + "axes"] = torch.eye(3).repeat(self.weights.shape[0], 1, 1)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def set_weights(self, weights, parents=None, rest_normals=None, axes=None) -> None:
        """Fill the buffers from (J_c, R, R) skinning weights (:func:`texel_skin_weights`) and, with
        world normals, the conditioning tree (:func:`conditioning_parents`), (3, R, R) rest normals
        (:func:`texel_rest_normals`) and the (J_c, 3, 3) rotation axes (:func:`conditioning_axes`;
        None: world axes)."""
        J, R = self.weights.shape[0], self.resolution
        w = torch.as_tensor(np.asarray(weights, np.float32))
        if tuple(w.shape) != (J, R, R):
            raise ValueError(f"texel weights must be ({J}, {R}, {R}), got {tuple(w.shape)}")
        with torch.no_grad():
            self.weights.copy_(w.reshape(J, -1))
        if not self.world_normals:
            return
        if parents is None or rest_normals is None:
            raise ValueError("world normals need the conditioning joints' parents and the rest normals")
        p = [int(x) for x in parents]
        if len(p) != J or tree_order(p) is None:
            raise ValueError(f"parents must be {J} positions in the list or -1, forming a tree, got {p}")
        n = torch.as_tensor(np.asarray(rest_normals, np.float32))
        if tuple(n.shape) != (3, R, R):
            raise ValueError(f"rest normals must be (3, {R}, {R}), got {tuple(n.shape)}")
        a = torch.eye(3).repeat(J, 1, 1) if axes is None else torch.as_tensor(np.asarray(axes, np.float32))
        if tuple(a.shape) != (J, 3, 3):
            raise ValueError(f"rotation axes must be ({J}, 3, 3), got {tuple(a.shape)}")
        with torch.no_grad():
            self.parents.copy_(torch.tensor(p, dtype=torch.long))
            self.rest_normals.copy_(n.reshape(3, -1))
            self.axes.copy_(a)

    def set_statistics(self, pose_angles: torch.Tensor) -> None:
        """Mean and std (floored) of each joint's rot6d over (N, 3·J_c) training angles (radians)."""
        if self.normalization is None:
            raise ValueError("set_statistics needs a TexelPoseMap made with normalization")
        r6 = rotvec_to_rot6d(torch.as_tensor(pose_angles, dtype=torch.float32).reshape(len(pose_angles), -1, 3))
        mean, scale = input_statistics(r6, self.normalization[0])
        with torch.no_grad():
            self.r6_mean.copy_(mean)
            self.r6_scale.copy_(scale)

    def world_rotations(self, rotvecs: torch.Tensor) -> torch.Tensor:
        """(B, J_c, 3) local axis-angles -> (B, J_c, 3, 3) world rotations (forward kinematics over
        ``parents``; a joint without a conditioning parent is turned by its own rotation alone), each
        local rotation first turned into world axes (its axis-angle by ``axes``: ``axes · R · axesᵀ``)."""
        local = rotvec_to_rotmat(torch.matmul(self.axes, rotvecs[..., None])[..., 0])
        parents = self.parents.tolist()
        world: dict[int, torch.Tensor] = {}
        for k in tree_order(parents):
            p = parents[k]
            world[k] = local[:, k] if p < 0 else torch.matmul(world[p], local[:, k])
        return torch.stack([world[k] for k in range(len(parents))], 1)

    def forward(self, pose_angles: torch.Tensor) -> torch.Tensor:
        B, R = pose_angles.shape[0], self.resolution
        rotvecs = pose_angles.reshape(B, -1, 3)
        r6 = rotvec_to_rot6d(rotvecs)                                                 # (B, J_c, 6)
        if self.normalization is not None:
            r6 = standardize(r6, self.r6_mean, self.r6_scale, self.normalization[1])
        m = torch.matmul(r6.transpose(1, 2), self.weights)                            # (B, 6, R²)
        if self.world_normals:
            g = self.world_rotations(rotvecs).reshape(B, -1, 9)                       # (B, J_c, 9)
            blend = torch.matmul(g.transpose(1, 2), self.weights).reshape(B, 3, 3, -1)  # (B, 3, 3, R²)
            normal = (blend * self.rest_normals[None, None]).sum(2)                   # (B, 3, R²)
            m = torch.cat([m, normal], 1)
        return m.reshape(B, self.channels, R, R)


def pooled(pose_map: torch.Tensor, resolution: int) -> torch.Tensor:
    """(B, C, R, R) -> (B, C, r, r) by average pooling (R / r an integer)."""
    factor = pose_map.shape[-1] // resolution
    return pose_map if factor == 1 else F.avg_pool2d(pose_map, factor)
