"""Body model interface: a rest template with a UV layout, and batched differentiable posing.

Conventions (see docs/ARCHITECTURE.md): metres, +Y up; the rest pose faces +Z with the body's left
toward +X. Posing follows EasyMocap::

    V = R(Rh) @ (LBS(joint_rotvecs, shape) * scale) + Th

rotation about the model origin (not the pelvis). ``joint_rotvecs`` are per-joint local axis-angles
(radians) in the backend's joint order; the root's is normally zero (global rotation is ``Rh``).

Each backend says in which axes a joint's local rotation is expressed through
``rest_joint_rotations`` (J, 3, 3): column k is that frame's k-th axis in world coordinates in the
rest pose. ``world_to_local_rotvecs`` turns a rotation written in rest-pose world axes ("bend the left
elbow 60 degrees about world +X") into the backend's local axis-angle: ``local = R_j^T @ world``.
``PosedBody.joint_transforms[b, j]`` maps that same joint frame to world (so at the rest pose its
3x3 block is ``rest_joint_rotations[j]`` and its translation the joint position).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.errors import InputError
from uvatar.geometry.frames import vertex_face_adjacency, vertex_normals
from uvatar.geometry.mesh import MeshCounts

__all__ = ["BodyTemplate", "PosedBody", "BodyModel", "apply_global_transform"]


@dataclass(frozen=True)
class BodyTemplate(MeshCounts):
    """Rest-pose template in numpy (metres).

    vertices: (V, 3) float32 rest-pose positions (what ``pose`` gives for zero rotations)
    faces: (F, 3) int64 triangles into ``vertices``
    uvs: (U, 2) float32 in [0, 1], v up (image row 0 is v = 1)
    uv_faces: (F, 3) int64 triangles into ``uvs`` (seams split UVs, not vertices)
    skin_weights: (V, J) float32, rows sum to 1
    joint_names: J names in the backend's order
    joint_parents: (J,) int64, -1 for the root
    rest_joints: (J, 3) float32 joint (bone head) positions in the rest pose
    joint_world_rest: (J, 4, 4) float64 rest-pose world transform of each joint frame (rotation = the
        frame's rest orientation, translation = its position), or None (not known: axis-aligned frames
        at ``rest_joints``); the engine export's skeleton
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    skin_weights: np.ndarray
    joint_names: tuple[str, ...]
    joint_parents: np.ndarray
    rest_joints: np.ndarray
    joint_world_rest: np.ndarray | None = None


@dataclass
class PosedBody:
    """Output of :meth:`BodyModel.pose` (torch, on the model's device).

    vertices: (B, V, 3) world positions (metres)
    joint_transforms: (B, J, 4, 4) world transform of each joint frame (the 3x3 block is
        ``scale * R`` when a scale is given)
    normals: (B, V, 3) unit vertex normals (area weighted)
    """

    vertices: torch.Tensor
    joint_transforms: torch.Tensor
    normals: torch.Tensor

    @property
    def joints(self) -> torch.Tensor:
        """(B, J, 3) world joint positions."""
        return self.joint_transforms[..., :3, 3]


def apply_global_transform(vertices, joint_transforms, Rh=None, Th=None, scale=None):
    """EasyMocap global transform about the model origin.

    vertices (B, V, 3), joint_transforms (B, J, 4, 4), Rh (B, 3) axis-angle or (B, 3, 3) the rotations
    themselves, Th (B, 3) metres, scale (B,) -> (vertices, joint_transforms) with
    ``x -> R(Rh) @ (x * scale) + Th``.
    """
    if scale is not None:
        s = scale.to(vertices).reshape(-1, 1, 1)
        vertices = vertices * s
        joint_transforms = torch.cat([joint_transforms[..., :3, :] * s[..., None], joint_transforms[..., 3:, :]], -2)
    if Rh is not None:
        from uvatar.body.kinematics import rotvec_to_rotmat

        R = Rh.to(vertices) if Rh.dim() == 3 else rotvec_to_rotmat(Rh.to(vertices))  # (B, 3, 3)
        vertices = vertices @ R.transpose(-1, -2)
        top = R[:, None] @ joint_transforms[..., :3, :]
        joint_transforms = torch.cat([top, joint_transforms[..., 3:, :].expand_as(joint_transforms[..., 3:, :])], -2)
    if Th is not None:
        t = Th.to(vertices)
        vertices = vertices + t[:, None, :]
        joint_transforms = joint_transforms.clone()
        joint_transforms[..., :3, 3] = joint_transforms[..., :3, 3] + t[:, None, :]
    return vertices, joint_transforms


class BodyModel(torch.nn.Module):
    """Common interface of all body model backends (a ``torch.nn.Module``; ``.to(device)`` moves it).

    Subclasses set ``name``, ``template``, ``shape_names``, ``semantic_joints``,
    ``conditioning_joints`` and ``_rest_joint_rotations`` and implement ``_pose_local``.
    """

    name: str = "body"
    template: BodyTemplate
    shape_names: tuple[str, ...] = ()
    semantic_joints: dict[str, int]
    conditioning_joints: tuple[int, ...]

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("_faces_t", torch.zeros(0, 3, dtype=torch.int64), persistent=False)
        self.register_buffer("_rest_rot_t", torch.zeros(0, 3, 3), persistent=False)

    # -- metadata -----------------------------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return int(self._rest_rot_t.shape[0])

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.template.joint_names

    @property
    def device(self) -> torch.device:
        return self._faces_t.device

    @property
    def faces_torch(self) -> torch.Tensor:
        """(F, 3) int64 triangles on the model's device."""
        return self._faces_t

    @property
    def rest_joint_rotations(self) -> np.ndarray:
        """(J, 3, 3) float32: rest-pose world orientation of the axes each joint's rotvec is in."""
        return self._rest_rot_t.detach().cpu().numpy().astype(np.float32)

    def default_shape(self, device=None) -> torch.Tensor:
        """(S,) the backend's neutral shape parameters (float32, on ``device``; None: the model's)."""
        return torch.zeros(len(self.shape_names), device=self.device if device is None else device)

    # -- rotations in world axes <-> local -----------------------------------------------------
    def world_to_local_rotvecs(self, world_rotvecs):
        """(..., J, 3) rotations in rest-pose world axes -> (..., J, 3) backend local axis-angles.

        numpy in -> numpy out, torch in -> torch out (differentiable)."""
        return self._change_axes(world_rotvecs, transpose=True)

    def local_to_world_rotvecs(self, local_rotvecs):
        """Inverse of :meth:`world_to_local_rotvecs`."""
        return self._change_axes(local_rotvecs, transpose=False)

    def _change_axes(self, rotvecs, transpose: bool):
        is_numpy = not isinstance(rotvecs, torch.Tensor)
        r = torch.as_tensor(np.asarray(rotvecs)) if is_numpy else rotvecs
        if r.shape[-2:] != (self.num_joints, 3):
            raise ValueError(f"rotvecs must have shape (..., {self.num_joints}, 3), got {tuple(r.shape)}")
        R = self._rest_rot_t.to(device=r.device, dtype=r.dtype if r.is_floating_point() else torch.float32)
        if transpose:
            R = R.transpose(-1, -2)
        out = (R @ r.to(R.dtype)[..., None])[..., 0]
        return out.numpy() if is_numpy else out

    # -- posing ---------------------------------------------------------------------------------
    def pose(self, joint_rotvecs, Rh=None, Th=None, scale=None, shape=None) -> PosedBody:
        """Pose the body.

        joint_rotvecs: (B, J, 3) local axis-angles (radians); (J, 3) is taken as B = 1
        Rh: (B, 3) global axis-angle about the model origin (or (B, 3, 3): those rotations as matrices);
        Th: (B, 3) metres; scale: (B,)
        shape: (S,) or (B, S) backend shape parameters (default :meth:`default_shape`)
        -> :class:`PosedBody` with vertices (B, V, 3), joint_transforms (B, J, 4, 4), normals.
        """
        rotvecs, (Rh, Th, scale) = self._pose_args(joint_rotvecs, Rh, Th, scale)
        vertices, transforms = self._pose_local(rotvecs, shape)
        vertices, transforms = apply_global_transform(vertices, transforms, Rh, Th, scale)
        vertices = vertices.contiguous()
        # sparse products on CPU; plain index_add_ (atomics) on GPUs, where it is fast already
        adjacency = self._adjacency(vertices.shape[-2]) if vertices.device.type == "cpu" else None
        return PosedBody(vertices=vertices, joint_transforms=transforms,
                         normals=vertex_normals(vertices, self._faces_t, adjacency))

    def pose_joints(self, joint_rotvecs, Rh=None, Th=None, scale=None, shape=None) -> torch.Tensor:
        """(B, J, 4, 4) ``pose(...).joint_transforms`` without skinning the mesh (kinematics only:
        much cheaper, for fits that skin only a few vertices themselves)."""
        rotvecs, (Rh, Th, scale) = self._pose_args(joint_rotvecs, Rh, Th, scale)
        transforms = self._joints_local(rotvecs, shape)
        empty = transforms.new_zeros(transforms.shape[0], 0, 3)
        return apply_global_transform(empty, transforms, Rh, Th, scale)[1]

    def _pose_args(self, joint_rotvecs, Rh, Th, scale):
        rotvecs = torch.as_tensor(joint_rotvecs, device=self.device)
        if not rotvecs.is_floating_point():
            rotvecs = rotvecs.float()
        if rotvecs.dim() == 2:
            rotvecs = rotvecs[None]
        if rotvecs.dim() != 3 or rotvecs.shape[1:] != (self.num_joints, 3):
            raise ValueError(f"joint_rotvecs must have shape (B, {self.num_joints}, 3), got {tuple(rotvecs.shape)}")
        B = rotvecs.shape[0]

        def batch(x, tail):
            if x is None:
                return None
            x = torch.as_tensor(x, device=self.device, dtype=rotvecs.dtype)
            return x.reshape(-1, *tail).expand(B, *tail)

        matrix = Rh is not None and np.ndim(Rh) == 3  # (B, 3, 3) rotation matrices, not B = 3 axis-angles
        return rotvecs, (batch(Rh, (3, 3) if matrix else (3,)), batch(Th, (3,)), batch(scale, ()))

    def _skin_weights_for(self, device: torch.device) -> torch.Tensor:
        """Skinning weights for :func:`~uvatar.body.kinematics.skin`: sparse CSR on CPU (~4x faster),
        dense elsewhere. Subclasses register ``_weights`` (V, J) and ``_weights_csr``."""
        return self._weights_csr if device.type == "cpu" else self._weights

    def _levels_on(self, device: torch.device):
        """The backend's kinematic levels (``self._levels``, :func:`~uvatar.body.kinematics.kinematic_levels`)
        on ``device``, copied there once (not a copy per pose)."""
        cache = self.__dict__.setdefault("_levels_by_device", {})
        key = str(device)
        if key not in cache:
            cache[key] = self._levels.to(device)
        return cache[key]

    def _adjacency(self, num_vertices: int) -> torch.Tensor:
        """(V, F) vertex-face CSR on the model's device (built once per device)."""
        cache = self.__dict__.setdefault("_adjacency_by_device", {})
        key = str(self._faces_t.device)
        if key not in cache:
            cache[key] = vertex_face_adjacency(self._faces_t, num_vertices)
        return cache[key]

    def _pose_local(self, rotvecs: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, J, 3) -> vertices (B, V, 3), joint transforms (B, J, 4, 4) in model space."""
        raise NotImplementedError

    def _joints_local(self, rotvecs: torch.Tensor, shape) -> torch.Tensor:
        """(B, J, 3) -> joint transforms (B, J, 4, 4) in model space (backends override this with
        kinematics alone)."""
        return self._pose_local(rotvecs, shape)[1]

    def rest_to_posed_transforms(self, posed: PosedBody, shape=None) -> torch.Tensor:
        """(B, J, 4, 4) per-joint transforms taking rest-pose points (``template.vertices`` space, for
        ``shape``) to the posed world: ``joint_transforms @ inverse(rest joint_transforms)``.

        Blending them with ``template.skin_weights`` re-skins any rest-space point; for anny this
        approximates ``pose`` (its exact LBS starts from anny's bind mesh) to a few millimetres."""
        rest = self.pose(torch.zeros(1, self.num_joints, 3, device=self.device), shape=shape).joint_transforms
        return posed.joint_transforms @ torch.linalg.inv(rest.to(posed.joint_transforms))

    def rest_pose(self, batch_size: int = 1) -> PosedBody:
        """The body with all joint rotations zero and the default shape."""
        return self.pose(torch.zeros(batch_size, self.num_joints, 3, device=self.device))

    def rest_template(self, shape=None) -> BodyTemplate:
        """The rest pose (zero rotations) at ``shape`` ((S,) shape parameters; None: the model's
        default) as a :class:`BodyTemplate`: its vertices, the joints where that shape puts them and
        each joint frame's rest transform (``joint_world_rest``). ``template`` is this at the default
        shape; retargeting (:mod:`uvatar.motion.retarget`) and the engine export use it at an avatar's."""
        t = self.template
        J = len(t.joint_names)
        with torch.no_grad():
            shape_t = None if shape is None else torch.as_tensor(np.asarray(shape, np.float32), device=self.device)
            posed = self.pose(torch.zeros(1, J, 3, device=self.device), shape=shape_t)
        vertices = posed.vertices[0].detach().cpu().numpy().astype(np.float32)
        transforms = posed.joint_transforms[0].detach().cpu().numpy().astype(np.float64)
        world = np.tile(np.eye(4), (J, 1, 1))
        world[:, :3, :3] = self.rest_joint_rotations
        if np.abs(transforms[:, :3, 3]).max() > 1e-6:  # world joint frames at rest (orientation and position)
            world = transforms
        else:  # skinning transforms (identity at rest): joints from the template
            world[:, :3, 3] = t.rest_joints
        return BodyTemplate(vertices, np.asarray(t.faces, np.int64), np.asarray(t.uvs, np.float32),
                            np.asarray(t.uv_faces, np.int64), np.asarray(t.skin_weights, np.float32),
                            tuple(t.joint_names), np.asarray(t.joint_parents, np.int64),
                            world[:, :3, 3].astype(np.float32), world)

    def joint_rotvecs_from_fit(self, fit) -> np.ndarray:
        """(J, 3) float32 local axis-angles from a ``BodyFit`` (``poses`` holds J*3 values)."""
        poses = np.asarray(fit.poses, dtype=np.float32).reshape(-1)
        if poses.size != 3 * self.num_joints:
            raise InputError(f"fit {getattr(fit, 'id', 0)}",
                             f"poses has {poses.size} values, body model '{self.name}' expects "
                             f"{3 * self.num_joints} ({self.num_joints} joints x 3)")
        if not np.isfinite(poses).all():
            raise InputError(f"fit {getattr(fit, 'id', 0)}", "poses contains NaN or inf")
        return poses.reshape(self.num_joints, 3)

    def _set_common_buffers(self, faces: np.ndarray, rest_rotations: np.ndarray) -> None:
        self._faces_t = torch.as_tensor(np.asarray(faces, dtype=np.int64), device=self.device)
        self._rest_rot_t = torch.as_tensor(np.asarray(rest_rotations, dtype=np.float32), device=self.device)

    def extra_repr(self) -> str:
        t = self.template
        return f"name={self.name}, vertices={t.num_vertices}, faces={t.num_faces}, joints={self.num_joints}"
