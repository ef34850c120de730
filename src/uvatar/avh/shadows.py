"""Cast shadows of the body's own limbs for the light-rig head (``AvhConfig.shading_shadows``, beyond the paper).

A studio's key light is blocked by the body itself: an arm lowered in front of the torso throws its
shadow across the shirt. Which texels it darkens depends on where the *other* limbs are, which the
texel pose map (the rotations of the joints that skin the texel) does not say. This module poses the
skeleton inside the graph and asks, per texel and learned light direction, whether the ray toward
the light passes a limb::

    t_k   = t_parent + G_parent (J_k − J_parent)          posed joint positions (root at its rest place)
    p     = Σ_k W[k, texel] (G_k (x_rest − J_k) + t_k)    posed texel point (linear blend skinning)
    c_s   = the posed joints and the midpoints of their bones (S spheres), learned radii r_s
    w     = c_s − p,  s = w · l̂,  d = |w − s l̂|           along and off the ray
    vis   = Π_s (1 − σ((r_s − d) / τ) · σ(s / τ))          soft visibility of light l̂ (B, K, R, R)

computed on a 32² map (skinning weights and rest points average-pooled) and upsampled bilinearly.

``G_k`` are the conditioning joints' world rotations (:meth:`uvatar.avh.texel_pose.TexelPoseMap.
world_rotations`), ``W`` its texel skinning weights, ``x_rest`` the template's rest surface at the
texel. τ = 1 cm. The light directions are the rig's (:mod:`uvatar.avh.lights`), so the shadow moves
with the light the rig learns. ONNX ops only (MatMul, Mul, Sub, Sqrt, Sigmoid, ReduceProd).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from uvatar.avh.texel_pose import pooled, texel_vertex_map, tree_order

#: Softness of a shadow's edge and of the "in front of the texel" test, metres.
SHADOW_SOFTNESS = 0.01
#: Start radius of every limb sphere, metres (learned).
START_RADIUS = 0.05
#: Side of the map the shadows are computed at (then upsampled bilinearly): cast shadows are smooth,
#: and at 128² every training step would cost 6 s on one CPU thread instead of 0.4.
SHADOW_RESOLUTION = 32


def texel_rest_points(template, resolution: int) -> np.ndarray:
    """(3, R, R) float32 rest-pose surface point of the template at each texel centre (row 0 is v = 1),
    barycentric from the vertices, zero outside the UV charts."""
    return texel_vertex_map(template, np.asarray(template.vertices, np.float64), resolution)


class BodyShadows(nn.Module):
    """(world rotations (B, J_c, 3, 3), texel weights (J_c, R²), light directions (K, 3)) -> soft
    visibility (B, K, R, R). Buffers (zeros until :meth:`set_geometry`): ``rest_joints`` (J_c, 3),
    ``rest_points`` (3, R²), ``parents`` (J_c,); parameter ``log_radius`` (S,), S = 2 J_c − roots."""

    def __init__(self, num_joints: int, resolution: int):
        super().__init__()
        self.resolution = resolution
        self.shadow_resolution = min(resolution, SHADOW_RESOLUTION)
        r = self.shadow_resolution
        self.register_buffer("rest_joints", torch.zeros(num_joints, 3))
        self.register_buffer("rest_points", torch.zeros(3, r * r))
        self.register_buffer("parents", torch.full((num_joints,), -1, dtype=torch.long))
        # spheres: every joint and, while the tree is unknown, a midpoint slot per joint (unused for roots)
        self.log_radius = nn.Parameter(torch.full((2 * num_joints,), float(np.log(START_RADIUS))))

    def set_geometry(self, rest_joints, parents, rest_points) -> None:
        """Rest positions (J_c, 3) of the conditioning joints, their tree (positions or -1) and the
        (3, R, R) rest surface points (:func:`texel_rest_points`)."""
        J, R = self.rest_joints.shape[0], self.resolution
        j = torch.as_tensor(np.asarray(rest_joints, np.float32))
        x = torch.as_tensor(np.asarray(rest_points, np.float32))
        p = [int(q) for q in parents]
        if tuple(j.shape) != (J, 3) or tuple(x.shape) != (3, R, R):
            raise ValueError(f"rest joints must be ({J}, 3) and rest points (3, {R}, {R}), "
                             f"got {tuple(j.shape)} and {tuple(x.shape)}")
        if len(p) != J or tree_order(p) is None:
            raise ValueError(f"parents must be {J} positions in the list or -1, forming a tree, got {p}")
        with torch.no_grad():
            self.rest_joints.copy_(j)
            self.rest_points.copy_(pooled(x[None], self.shadow_resolution)[0].reshape(3, -1))
            self.parents.copy_(torch.tensor(p, dtype=torch.long))

    def joints_and_points(self, world: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(posed joint positions (B, J_c, 3), posed texel points (B, 3, r²) at the shadow resolution).
        ``weights``: (J_c, R²) texel skinning weights at the model's resolution."""
        B, R = world.shape[0], self.resolution
        weights = pooled(weights.reshape(1, -1, R, R), self.shadow_resolution).reshape(weights.shape[0], -1)
        parents = self.parents.tolist()
        rest = self.rest_joints
        posed: dict[int, torch.Tensor] = {}
        for k in tree_order(parents):
            p = parents[k]
            posed[k] = (rest[k].expand(B, 3) if p < 0 else
                        posed[p] + torch.matmul(world[:, p], (rest[k] - rest[p]).reshape(3, 1))[..., 0])
        t = torch.stack([posed[k] for k in range(len(parents))], 1)                       # (B, J, 3)
        offset = t - torch.matmul(world, rest.reshape(1, -1, 3, 1))[..., 0]              # t_k − G_k J_k
        blend = torch.matmul(world.reshape(B, -1, 9).transpose(1, 2), weights).reshape(B, 3, 3, -1)
        points = (blend * self.rest_points[None, None]).sum(2) + torch.matmul(offset.transpose(1, 2), weights)
        return t, points

    def spheres(self, joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(centres (B, S, 3), radii (S,)): the joints, then the midpoints of bones with a parent."""
        children = [k for k, p in enumerate(self.parents.tolist()) if p >= 0]
        parents = [self.parents.tolist()[k] for k in children]
        mids = 0.5 * (joints[:, children] + joints[:, parents])
        radius = torch.exp(self.log_radius)
        return torch.cat([joints, mids], 1), torch.cat([radius[:joints.shape[1]], radius[joints.shape[1]:][children]])

    def forward(self, world: torch.Tensor, weights: torch.Tensor, directions: torch.Tensor,
                normals: torch.Tensor | None = None) -> torch.Tensor:
        """(B, K, R, R) visibility of each light; with ``normals`` (B, 3, R, R) the texels' posed world
        normals, a last channel: the ambient light the limbs leave, ``1 − Σ_s r_s² / (|w|² + r_s²) ·
        max(0, n·w) / |w|`` (each sphere's cosine-weighted solid angle, clamped to [0, 1])."""
        B, r = world.shape[0], self.shadow_resolution
        joints, points = self.joints_and_points(world, weights)
        centres, radius = self.spheres(joints)
        light = directions / torch.sqrt((directions * directions).sum(-1, keepdim=True) + 1e-12)   # (K, 3)
        w = centres[:, :, :, None] - points[:, None]                                       # (B, S, 3, R²)
        along = torch.matmul(light, w)                                                      # (B, S, K, R²)
        off2 = (w * w).sum(2, keepdim=True) - along * along
        off = torch.sqrt(torch.clamp(off2, min=0.0) + 1e-8)
        blocked = torch.sigmoid((radius[None, :, None, None] - off) / SHADOW_SOFTNESS) * \
            torch.sigmoid(along / SHADOW_SOFTNESS)
        vis = torch.prod(1.0 - blocked, 1).reshape(B, -1, r, r)
        if normals is not None:
            n = pooled(normals, self.shadow_resolution).reshape(B, 1, 3, -1)
            dist2 = (w * w).sum(2)                                                          # (B, S, r²)
            r2 = (radius * radius)[None, :, None]
            facing = torch.relu((n * w).sum(2)) / torch.sqrt(dist2 + 1e-8)
            ambient = torch.clamp(1.0 - (r2 / (dist2 + r2) * facing).sum(1), 0.0, 1.0)
            vis = torch.cat([vis, ambient.reshape(B, 1, r, r)], 1)
        return vis if r == self.resolution else F.interpolate(vis, size=(self.resolution, self.resolution),
                                                                mode="bilinear", align_corners=False)

    def reference(self, world: torch.Tensor, weights: torch.Tensor, directions: torch.Tensor,
                  normals: torch.Tensor | None = None) -> torch.Tensor:
        """The same visibility a light, a sphere and a texel at a time (the twin tests compare against)."""
        joints, points = self.joints_and_points(world, weights)
        centres, radius = self.spheres(joints)
        B, K, n = world.shape[0], directions.shape[0], points.shape[-1]
        out = torch.ones(B, K, n)
        for b in range(B):
            for k in range(K):
                light = directions[k] / directions[k].norm()
                for s in range(centres.shape[1]):
                    for i in range(n):
                        w = centres[b, s] - points[b, :, i]
                        along = w @ light
                        off = (w - along * light).norm()
                        out[b, k, i] *= 1 - torch.sigmoid((radius[s] - off) / SHADOW_SOFTNESS) * torch.sigmoid(
                            along / SHADOW_SOFTNESS)
        if normals is not None:
            n = pooled(normals, self.shadow_resolution).reshape(B, 3, -1)
            amb = torch.ones(B, 1, points.shape[-1])
            for b in range(B):
                for i in range(points.shape[-1]):
                    for s in range(centres.shape[1]):
                        w = centres[b, s] - points[b, :, i]
                        d = w.norm()
                        amb[b, 0, i] -= radius[s] ** 2 / (d * d + radius[s] ** 2) * max(float(n[b, :, i] @ w), 0.0) / d
            out = torch.cat([out, amb.clamp(0, 1)], 1)
        out = out.reshape(B, -1, self.shadow_resolution, self.shadow_resolution)
        return F.interpolate(out, size=(self.resolution, self.resolution), mode="bilinear", align_corners=False)
