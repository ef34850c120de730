"""Skin only the vertices a fit looks at (keypoint support, scan and silhouette samples).

A sequence fit poses every frame hundreds of times; skinning anny's 13.7k vertices and their
normals each time dominates the cost. Linear blend skinning is linear in the rest vertices, so a
subset of N vertices is posed exactly as the full mesh would pose it when re-skinned from the rest
template (``BodyModel.rest_to_posed_transforms``; for anny within ~0.1 mm of its own LBS, see
:mod:`uvatar.body.anny_backend`)::

    v_i = sum_j W_ij G_j [x_i; 1],   G_j = joint_transforms_j @ inverse(rest joint_transforms_j)

Normals are the rest normals turned by the blended rotation (exact for rigid parts, the usual LBS
normal approximation elsewhere). Joint transforms come from ``BodyModel.pose_joints`` (kinematics
only).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["SubsetSkinner", "RestState"]


class RestState:
    """Rest pose for one shape: vertices (N, 3) and normals (N, 3) of the subset, inverse rest joint
    transforms (J, 4, 4)."""

    def __init__(self, vertices, normals, inverse):
        self.vertices, self.normals, self.inverse = vertices, normals, inverse


class SubsetSkinner:
    """Pose template vertices ``ids`` (N,) of ``body`` from joint transforms (torch, differentiable
    in the transforms and, through :meth:`rest`, in the shape)."""

    def __init__(self, body, ids):
        self.body = body
        self.ids = torch.as_tensor(np.asarray(ids, np.int64), device=body.device)
        w = np.asarray(body.template.skin_weights, np.float32)[np.asarray(ids, np.int64)]
        self.weights = torch.as_tensor(w, device=body.device)            # (N, J)

    def rest(self, shape=None) -> RestState:
        """Rest state for ``shape`` (S,) (differentiable when it requires grad)."""
        body = self.body
        posed = body.pose(torch.zeros(1, body.num_joints, 3, device=body.device), shape=shape)
        return RestState(posed.vertices[0, self.ids], posed.normals[0, self.ids],
                         torch.linalg.inv(posed.joint_transforms[0]))

    def __call__(self, joint_transforms: torch.Tensor, rest: RestState):
        """joint_transforms (B, J, 4, 4) from ``pose_joints`` -> (vertices (B, N, 3), normals (B, N, 3))."""
        G = joint_transforms[..., :3, :] @ rest.inverse                  # (B, J, 3, 4)
        B, J = G.shape[:2]
        blended = (self.weights @ G.permute(1, 0, 2, 3).reshape(J, B * 12)).reshape(-1, B, 3, 4)
        blended = blended.permute(1, 0, 2, 3)                            # (B, N, 3, 4)
        v = (blended[..., :3] @ rest.vertices[None, :, :, None])[..., 0] + blended[..., 3]
        n = (blended[..., :3] @ rest.normals[None, :, :, None])[..., 0]
        return v, torch.nn.functional.normalize(n, dim=-1)
