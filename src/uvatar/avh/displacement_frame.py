"""Displacement frames: the body frame the bake stores and the rest frame the generator learns.

The bake stores ``d = x - s`` in the *body frame*: world axes of the posed frame with the global
rotation Rh removed (:mod:`uvatar.avh.data`). A body-frame vector still turns with every limb: the
same 1 cm of sleeve on a forearm points another way when the elbow bends. A generator trained on
body-frame maps must learn those directions from the pose, and for a pose unlike its training poses
it falls back towards their average direction, which is shorter and points elsewhere: the clothed
surface shrinks towards the body (thin silhouettes).

The *rest frame* undoes the skinning rotation at each texel first::

    M(texel, pose) = sum_j w_j(texel) · A_j[:3, :3]      A_j = posed joint j ∘ (rest joint j)^-1 (LBS, Rh = 0)
    d_rest = M^-1 d_body         d_body = M d_rest

with the body's skinning weights ``w`` interpolated to the texel. ``d_rest`` of a garment is then
nearly the same for every pose (it is what the rest-pose body would wear), so the generator only
learns what really changes with pose (folds, bulges), and a runtime re-poses it with the same
blended rotations as the body's own vertices; in a game engine that is "add the displacement to the
rest vertex, then skin" (glTF/three.js skinning does the rotation).

``DISPLACEMENT_FRAMES``: ``"rest"`` (default for training) and ``"body"`` (the paper's maps as baked).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["DISPLACEMENT_FRAMES", "DISPLACEMENT_SPACES", "SkinningRotations", "vertex_skinning_rotations",
           "texel_skinning_rotations", "body_to_rest", "rest_to_body", "maps_body_to_rest", "displacements_to_frame",
           "frame_of_space"]

DISPLACEMENT_FRAMES = ("rest", "body")

#: The text written to run.json / avatar.json ``displacement_space`` for each frame.
DISPLACEMENT_SPACES = {
    "body": "body frame: world axes of the posed body with the global rotation Rh removed; d_world = R(Rh) @ d",
    "rest": "rest frame: the body's rest-pose axes at each texel; d_world = R(Rh) @ M @ d with "
            "M = sum_j w_j A_j[:3, :3] the texel's blended LBS rotation (add to the rest vertex, then skin)",
}


def frame_of_space(space: str | None) -> str:
    """``"rest"`` or ``"body"`` from a ``displacement_space`` text (older avatars: body frame)."""
    return "rest" if str(space or "").startswith("rest frame") else "body"


class SkinningRotations:
    """Blended LBS rotations of a body: ``M_v = sum_j w_vj A_j[:3, :3]`` per vertex for local poses.

    The rest-pose joint transforms (for ``shape``) are computed once; each call poses the body
    without global rotation, translation or scale.
    """

    def __init__(self, body, shape=None):
        self.body = body
        self.shape = None if shape is None else torch.as_tensor(np.asarray(shape, np.float32))
        with torch.no_grad():
            rest = body.pose(torch.zeros(1, body.num_joints, 3, device=body.device), shape=self.shape)
            self._rest_inverse = torch.linalg.inv(rest.joint_transforms[0, :, :3, :3].double().cpu())
        self._weights = torch.as_tensor(np.asarray(body.template.skin_weights, np.float64))

    def joint_rotations(self, poses) -> torch.Tensor:
        """(T, J·3) local axis-angles -> (T, J, 3, 3) float64 ``A_j[:3, :3]`` (rest -> posed)."""
        p = torch.as_tensor(np.asarray(poses, np.float32)).reshape(len(poses), -1, 3).to(self.body.device)
        with torch.no_grad():
            posed = self.body.pose(p, shape=self.shape)
        return posed.joint_transforms[..., :3, :3].double().cpu() @ self._rest_inverse

    def vertices(self, poses) -> np.ndarray:
        """(T, J·3) -> (T, V, 3, 3) float32 blended rotation per template vertex."""
        A = self.joint_rotations(poses)
        return torch.einsum("vj,tjab->tvab", self._weights, A).float().numpy()


def vertex_skinning_rotations(body, poses, shape=None) -> np.ndarray:
    """(T, J·3) local axis-angles -> (T, V, 3, 3) float32 blended LBS rotation per template vertex."""
    return SkinningRotations(body, shape).vertices(poses)


def texel_skinning_rotations(raster, faces, vertex_rotations: np.ndarray) -> np.ndarray:
    """Per-texel blended rotations (R, R, 3, 3) from per-vertex ones (V, 3, 3), barycentric inside the
    charts, identity outside (so conversions leave uncovered texels unchanged)."""
    from uvatar.geometry import sample_vertex_attribute

    V = vertex_rotations.shape[-3]
    m = np.asarray(sample_vertex_attribute(raster, faces, vertex_rotations.reshape(V, 9)), np.float32)
    m = m.reshape(*m.shape[:2], 3, 3)
    m[~raster.mask] = np.eye(3, dtype=np.float32)
    return m


def body_to_rest(d_body: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(…, 3) body-frame displacements and (…, 3, 3) blended rotations -> (…, 3) rest frame (M^-1 d)."""
    d = np.linalg.solve(rotations.astype(np.float64), np.asarray(d_body, np.float64)[..., None])[..., 0]
    return d.astype(np.float32)


def rest_to_body(d_rest: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(…, 3) rest-frame displacements and (…, 3, 3) blended rotations -> (…, 3) body frame (M d)."""
    return np.einsum("...ab,...b->...a", rotations, np.asarray(d_rest, np.float32)).astype(np.float32)


def maps_body_to_rest(body, raster, faces, displacement: np.ndarray, poses: np.ndarray, shape=None,
                      chunk: int = 16) -> np.ndarray:
    """(N, R, R, 3) body-frame displacement maps of poses (N, J·3) -> rest frame, in chunks of frames."""
    skin = SkinningRotations(body, shape)
    out = np.empty_like(np.asarray(displacement, np.float32))
    for s in range(0, len(poses), chunk):
        Mv = skin.vertices(poses[s:s + chunk])
        for k, mv in enumerate(Mv):
            out[s + k] = body_to_rest(displacement[s + k], texel_skinning_rotations(raster, faces, mv))
    return out


def displacements_to_frame(frames, frame: str, body, shape=None):
    """:class:`uvatar.avh.data.BakedFrames` with their body-frame displacements converted to ``frame``
    ("body": returned unchanged)."""
    if frame == "body" or len(frames) == 0:
        return frames
    from dataclasses import replace

    from uvatar.geometry import rasterize_uv

    t = body.template
    raster = rasterize_uv(t.uvs, t.uv_faces, frames.resolution)
    return replace(frames, displacement=maps_body_to_rest(body, raster, t.faces, frames.displacement,
                                                          frames.poses, shape))
