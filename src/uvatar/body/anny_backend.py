"""The anny body model (default backend): 13,718 vertices, 27,420 triangles, 104 bones, MakeHuman UVs.

Posing reproduces anny's own forward pass (pose parameterization "local-ref") in uvatar's axes:

- ``joint_rotvecs[:, c]`` is anny's local-ref delta of bone c: a rotation about the bone head in
  anny's world axes (+Z up), carried along by the parent bones. In uvatar's axes that frame is
  ``ANNY_TO_WORLD`` for every joint, which is what ``rest_joint_rotations`` holds.
- Zero rotations give anny's reference pose (its zero pose, root at the origin); that is the rest
  template ``template.vertices``. Skinning is anny's exact LBS from its bind mesh, so
  ``pose(0) == template.vertices`` and ``pose(θ) == anny.forward(θ)`` (to float32 round-off).
  Re-skinning ``template.vertices`` with ``rest_to_posed_transforms`` and ``template.skin_weights``
  instead is off by ~0.1 mm on average (< 4 mm at worst for 0.3 rad random poses).
- ``shape`` is anny's phenotype vector (``shape_names``: gender, age, muscle, weight, height,
  proportions, each in [0, 1], default 0.5). The shape-dependent bind state is cached (LRU), so
  posing a fixed shape many times costs only kinematics and skinning.

``conditioning_joints``: every bone except the root (its rotation is ``Rh``), the fingers and
metacarpals (``finger*``, ``metacarpal*``), the toes (``toe*``), the eyes (``eye.*``) and the tongue
(none in this rig): 35 bones (pelvis, legs, feet, spine, clavicles, arms, wrists, neck, head).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from uvatar.body.anny_data import ANNY_TO_WORLD, anny_data, anny_rest_state, load_anny
from uvatar.body.base import BodyModel, BodyTemplate
from uvatar.body.kinematics import (
    forward_kinematics,
    homogeneous,
    kinematic_levels,
    rotvec_to_rotmat,
    skin,
    skinning_transforms,
    sparse_weights,
)

__all__ = ["AnnyConfig", "AnnyBody", "ANNY_SEMANTIC_BONES", "anny_conditioning_bones"]

ANNY_SEMANTIC_BONES = {
    "pelvis": "root", "spine1": "spine05", "spine2": "spine03", "spine3": "spine01",
    "neck": "neck01", "head": "head",
    "l_collar": "clavicle.L", "l_shoulder": "upperarm01.L", "l_elbow": "lowerarm01.L", "l_wrist": "wrist.L",
    "r_collar": "clavicle.R", "r_shoulder": "upperarm01.R", "r_elbow": "lowerarm01.R", "r_wrist": "wrist.R",
    "l_hip": "upperleg01.L", "l_knee": "lowerleg01.L", "l_ankle": "foot.L", "l_toe": "toe3-1.L",
    "r_hip": "upperleg01.R", "r_knee": "lowerleg01.R", "r_ankle": "foot.R", "r_toe": "toe3-1.R",
    "l_eye": "eye.L", "r_eye": "eye.R",
}
_EXCLUDED_PREFIXES = ("finger", "metacarpal", "toe", "eye", "tongue")


def anny_conditioning_bones(bone_labels) -> tuple[int, ...]:
    """Indices of the bones used for pose conditioning (see the module docstring)."""
    return tuple(i for i, n in enumerate(bone_labels) if i > 0 and not n.startswith(_EXCLUDED_PREFIXES))


@dataclass
class AnnyConfig:
    """device: torch device; dtype: posing precision; shape_cache_size: bind states kept (LRU)."""

    device: str = "cpu"
    dtype: torch.dtype = torch.float32
    shape_cache_size: int = 8


class AnnyBody(BodyModel):
    """anny behind the :class:`BodyModel` interface. Build with ``load_body_model("anny")``."""

    name = "anny"

    def __init__(self, config: AnnyConfig | None = None):
        super().__init__()
        self.config = config or AnnyConfig()
        self.anny = load_anny("cpu")
        data = anny_data(self.anny)
        self._data = data
        self.shape_names = data.phenotype_labels
        self._levels = kinematic_levels(data.parents)
        self._cache: OrderedDict = OrderedDict()
        dt = self.config.dtype
        self.register_buffer("_weights", torch.as_tensor(data.weights, dtype=dt), persistent=False)
        self.register_buffer("_weights_csr", sparse_weights(self._weights), persistent=False)
        self.register_buffer("_to_world", torch.as_tensor(ANNY_TO_WORLD, dtype=dt), persistent=False)
        self.register_buffer("_reference_rotations", torch.as_tensor(data.reference_rotations),
                             persistent=False)
        J = len(data.bone_labels)
        self._set_common_buffers(data.faces, np.repeat(ANNY_TO_WORLD[None], J, 0))
        index = {n: i for i, n in enumerate(data.bone_labels)}
        self.semantic_joints = {k: index[v] for k, v in ANNY_SEMANTIC_BONES.items() if v in index}
        self.conditioning_joints = anny_conditioning_bones(data.bone_labels)
        self.template = self._build_template()
        self.to(self.config.device)

    # -- shape ---------------------------------------------------------------------------------
    def default_shape(self, device=None) -> torch.Tensor:
        return torch.full((len(self.shape_names),), 0.5, device=self.device if device is None else device)

    def _bind_state(self, shape) -> dict[str, torch.Tensor]:
        """Bind state for shape (S,) or (B, S) (None: :meth:`default_shape`): bind vertices, heads,
        rotations (U R^T), offsets. A shape without a gradient and the same in every row is cached
        (LRU); the cache looks at the shape where it is given, so a shape on the host (and the default)
        finds its state on a GPU body without a read-back from the device."""
        shape = self.default_shape(device="cpu") if shape is None else torch.as_tensor(shape)
        if shape.dim() == 1:
            shape = shape[None]
        if shape.shape[-1] != len(self.shape_names):
            raise ValueError(f"shape must have {len(self.shape_names)} values {self.shape_names}, "
                             f"got {tuple(shape.shape)}")
        cacheable = not shape.requires_grad and bool((shape == shape[:1]).all())
        if cacheable:
            shape = shape[:1]
            key = (str(self.device), self._weights.dtype, tuple(shape[0].tolist()))
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        with torch.set_grad_enabled(torch.is_grad_enabled() and shape.requires_grad):
            state = self._compute_bind_state(shape.to(self.device))
        if cacheable:
            self._cache[key] = state
            while len(self._cache) > self.config.shape_cache_size:
                self._cache.popitem(last=False)
        return state

    def _compute_bind_state(self, shape: torch.Tensor) -> dict[str, torch.Tensor]:
        rest = anny_rest_state(self.anny, shape)
        R, h = rest["bind_rotations"], rest["bind_heads"]
        U = self._reference_rotations.to(R)
        parents = torch.as_tensor(self._data.parents, device=R.device).clamp_min(0)
        # Reference head offsets q_c - q_p = A_p (h_c - h_p), A_p = U_p R_p^T (A_root = I).
        A = U[None] @ R.transpose(-1, -2)
        A[:, 0] = torch.eye(3, dtype=R.dtype, device=R.device)
        offsets = (A[:, parents] @ (h - h[:, parents])[..., None])[..., 0]
        dt = self._weights.dtype
        return {"bind_vertices": rest["bind_vertices"].to(dt), "bind_heads": h.to(dt),
                "bind_rotations": (U[None] @ R.transpose(-1, -2)).to(dt), "offsets": offsets.to(dt)}

    # -- posing --------------------------------------------------------------------------------
    def _kinematics(self, rotvecs: torch.Tensor, shape):
        """Bind state, joint frames F (B, J, 3, 3) and heads p (B, J, 3) in anny axes."""
        state = self._bind_state(shape)
        D = rotvec_to_rotmat(rotvecs.to(self._weights.dtype))  # anny local-ref deltas, anny axes
        F, p = forward_kinematics(self._levels_on(D.device), D, state["offsets"])
        return state, F, p

    def _world_transforms(self, F, p):
        C = self._to_world
        return homogeneous(C @ F, (C @ p[..., None])[..., 0])

    def _pose_local(self, rotvecs: torch.Tensor, shape):
        state, F, p = self._kinematics(rotvecs, shape)
        T = skinning_transforms(F, p, state["bind_rotations"], state["bind_heads"])
        vertices = skin(state["bind_vertices"], self._skin_weights_for(F.device), T)
        return vertices @ self._to_world.T, self._world_transforms(F, p)

    def _joints_local(self, rotvecs: torch.Tensor, shape):
        _, F, p = self._kinematics(rotvecs, shape)
        return self._world_transforms(F, p)

    def _build_template(self) -> BodyTemplate:
        d = self._data
        with torch.no_grad():
            posed = self.pose(torch.zeros(1, len(d.bone_labels), 3))
        return BodyTemplate(
            vertices=posed.vertices[0].cpu().numpy().astype(np.float32),
            faces=d.faces,
            uvs=d.uvs.astype(np.float32),
            uv_faces=d.uv_faces,
            skin_weights=d.weights.astype(np.float32),
            joint_names=d.bone_labels,
            joint_parents=d.parents,
            rest_joints=posed.joints[0].cpu().numpy().astype(np.float32),
        )

    def _apply(self, fn, *args, **kwargs):
        self._cache.clear()
        return super()._apply(fn, *args, **kwargs)
