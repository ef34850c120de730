"""SMPL / SMPL-X backends through the ``smplx`` package, from model files the user supplies.

The licence of SMPL and SMPL-X forbids redistribution, so uvatar ships neither: get SMPL from
https://smpl.is.tue.mpg.de and SMPL-X from https://smpl-x.is.tue.mpg.de, and point
``load_body_model("smpl", model_dir=...)`` (or the ``UVATAR_SMPL_DIR`` environment variable) at the
folder holding them. The UV layout comes from an OBJ with ``vt`` lines whose faces index the model's
vertices (``uv_obj=``, or ``smpl_uv.obj`` / ``smplx_uv.obj`` found in that folder).

Posing is the model's own LBS (shape blend shapes, pose blend shapes, skinning) written on the
shared kinematics, in the model's axes (+Y up, facing +Z: uvatar's). ``joint_rotvecs[:, j]`` are the
usual SMPL local axis-angles (rest joint frames are the world axes, so ``rest_joint_rotations`` is
the identity). SMPL has 24 joints; SMPL-X 55 (body 22, jaw, eyes, 2 x 15 finger joints; hands
flat at zero). ``shape`` is ``betas``; SMPL-X expressions are zero.
``conditioning_joints``: SMPL the 23 body joints 1..23; SMPL-X the 21 body joints 1..21.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

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
from uvatar.devices import to_device_async
from uvatar.errors import InputError, require

__all__ = ["SmplxConfig", "SmplxBody", "find_model_file", "read_obj_uvs", "SMPL_JOINT_NAMES"]

SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand")
_FINGERS = [f"{f}{i}" for f in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3)]
SMPLX_JOINT_NAMES = (SMPL_JOINT_NAMES[:22] + ("jaw", "left_eye_smplhf", "right_eye_smplhf")
                     + tuple(f"left_{f}" for f in _FINGERS) + tuple(f"right_{f}" for f in _FINGERS))
_SEMANTIC = {
    "pelvis": "pelvis", "spine1": "spine1", "spine2": "spine2", "spine3": "spine3", "neck": "neck",
    "head": "head", "l_collar": "left_collar", "l_shoulder": "left_shoulder", "l_elbow": "left_elbow",
    "l_wrist": "left_wrist", "r_collar": "right_collar", "r_shoulder": "right_shoulder",
    "r_elbow": "right_elbow", "r_wrist": "right_wrist", "l_hip": "left_hip", "l_knee": "left_knee",
    "l_ankle": "left_ankle", "l_toe": "left_foot", "r_hip": "right_hip", "r_knee": "right_knee",
    "r_ankle": "right_ankle", "r_toe": "right_foot", "l_eye": "left_eye_smplhf", "r_eye": "right_eye_smplhf",
    "jaw": "jaw",
}
_WHERE = {"smpl": "https://smpl.is.tue.mpg.de", "smplx": "https://smpl-x.is.tue.mpg.de"}
_FILES = {
    "smpl": ["SMPL_{G}.npz", "SMPL_{G}.pkl", "basicModel_{g}_lbs_10_207_0_v1.0.0.pkl",
             "basicmodel_{g}_lbs_10_207_0_v1.1.0.pkl", "basicmodel_{g}_lbs_10_207_0_v1.0.0.pkl"],
    "smplx": ["SMPLX_{G}.npz", "SMPLX_{G}.pkl"],
}


@dataclass
class SmplxConfig:
    """model_type "smpl" | "smplx"; model_dir: folder or model file (None: $UVATAR_SMPL_DIR);
    gender "neutral" | "male" | "female"; num_betas; uv_obj: OBJ with the UV layout (None: look for
    smpl_uv.obj / smplx_uv.obj beside the model); device; dtype."""

    model_type: str = "smpl"
    model_dir: str | None = None
    gender: str = "neutral"
    num_betas: int = 10
    uv_obj: str | None = None
    device: str = "cpu"
    dtype: torch.dtype = torch.float32


def find_model_file(model_type: str, model_dir: str | os.PathLike | None, gender: str = "neutral") -> Path:
    """The SMPL/SMPL-X model file, or an InputError saying what to download and where to put it."""
    where = _WHERE[model_type]
    if model_dir is None:
        model_dir = os.environ.get("UVATAR_SMPL_DIR")
    names = [n.format(G=gender.upper(), g=gender.lower()[:1] if gender != "neutral" else "neutral")
             for n in _FILES[model_type]]
    if model_dir is None:
        raise InputError("UVATAR_SMPL_DIR", f"no {model_type.upper()} model folder given: download the model "
                         f"from {where}, put {names[0]} in a folder and pass model_dir or set "
                         "UVATAR_SMPL_DIR to it")
    root = Path(model_dir).expanduser()
    if root.is_file():
        return root
    for folder in (root, root / model_type):
        for name in names:
            if (folder / name).is_file():
                return folder / name
    raise InputError(root, f"no {model_type.upper()} model file found (looked for {', '.join(names)} here "
                     f"and in {model_type}/): download it from {where} and put it in this folder")


def read_obj_uvs(path: str | os.PathLike, num_faces: int | None = None):
    """(faces (F, 3) int64, uvs (U, 2) float32, uv_faces (F, 3) int64) from an OBJ's v/vt/f lines.

    Polygons are fan-triangulated. Raises InputError when the file has no UVs or faces."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "UV layout OBJ not found")
    uvs, faces, uv_faces = [], [], []
    with open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("vt "):
                uvs.append([float(x) for x in line.split()[1:3]])
            elif line.startswith("f "):
                corners = [c.split("/") for c in line.split()[1:]]
                if any(len(c) < 2 or not c[1] for c in corners):
                    raise InputError(path, "a face has no texture coordinate index (expected f v/vt ...)")
                v = [int(c[0]) - 1 for c in corners]
                t = [int(c[1]) - 1 for c in corners]
                for k in range(1, len(v) - 1):
                    faces.append([v[0], v[k], v[k + 1]])
                    uv_faces.append([t[0], t[k], t[k + 1]])
    if not uvs or not faces:
        raise InputError(path, "no texture coordinates (vt) or faces (f) in the OBJ")
    faces_a, uvs_a, uv_faces_a = np.asarray(faces, np.int64), np.asarray(uvs, np.float32), np.asarray(uv_faces, np.int64)
    if num_faces is not None and len(faces_a) != num_faces:
        raise InputError(path, f"the OBJ has {len(faces_a)} triangles, the body model {num_faces}")
    if uv_faces_a.min() < 0 or uv_faces_a.max() >= len(uvs_a):
        raise InputError(path, "a face references a texture coordinate that does not exist")
    return faces_a, uvs_a, uv_faces_a


def _load_smplx_module(cfg: SmplxConfig, path: Path):
    smplx = require("smplx", "smpl", "SMPL/SMPL-X body models")
    try:
        if path.suffix == ".npz":
            data = dict(np.load(path, allow_pickle=True))
        else:
            with open(path, "rb") as fh:
                data = pickle.load(fh, encoding="latin1")
    except ModuleNotFoundError as exc:
        raise InputError(path, f"unpickling needs the '{exc.name}' package (pip install {exc.name}), or "
                         "convert the model to .npz") from exc
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error
        raise InputError(path, f"cannot read the model file: {exc}") from exc
    if not isinstance(data, dict):
        raise InputError(path, "the model file does not hold a dictionary of arrays")
    required = ["v_template", "shapedirs", "posedirs", "J_regressor", "kintree_table", "weights", "f"]
    missing = [k for k in required if k not in data]
    if missing:
        raise InputError(path, f"not a {cfg.model_type.upper()} model: missing {', '.join(missing)}")
    data = {k: (v.item() if isinstance(v, np.ndarray) and v.dtype == object and v.shape == () else v)
            for k, v in data.items()}
    Struct = smplx.utils.Struct
    try:
        if cfg.model_type == "smpl":
            return smplx.SMPL(model_path=str(path), data_struct=Struct(**data), num_betas=cfg.num_betas,
                              gender=cfg.gender)
        return smplx.SMPLX(model_path=str(path), num_betas=cfg.num_betas, gender=cfg.gender,
                           use_pca=False, flat_hand_mean=True, ext=path.suffix.lstrip("."))
    except Exception as exc:  # noqa: BLE001
        raise InputError(path, f"smplx could not build the model: {exc}") from exc


class SmplxBody(BodyModel):
    """SMPL or SMPL-X behind the :class:`BodyModel` interface (``load_body_model("smpl", ...)``)."""

    def __init__(self, config: SmplxConfig | None = None):
        super().__init__()
        cfg = self.config = config or SmplxConfig()
        if cfg.model_type not in _WHERE:
            raise ValueError(f"model_type must be 'smpl' or 'smplx', got {cfg.model_type!r}")
        self.name = cfg.model_type
        model_path = find_model_file(cfg.model_type, cfg.model_dir, cfg.gender)
        uv_obj = Path(cfg.uv_obj) if cfg.uv_obj else None
        if uv_obj is None:
            candidates = [model_path.parent / f"{cfg.model_type}_uv.obj", model_path.parent / "uv.obj"]
            uv_obj = next((c for c in candidates if c.is_file()), None)
            if uv_obj is None:
                raise InputError(candidates[0], f"no UV layout for {cfg.model_type.upper()}: get the UV OBJ from "
                                 f"{_WHERE[cfg.model_type]} and put it here or pass uv_obj=")
        m = _load_smplx_module(cfg, model_path)
        dt = cfg.dtype
        parents = m.parents.detach().cpu().numpy().astype(np.int64).copy()
        parents[0] = -1
        J = len(parents)
        names = SMPL_JOINT_NAMES if cfg.model_type == "smpl" else SMPLX_JOINT_NAMES
        if len(names) != J:
            names = tuple(f"joint{j}" for j in range(J))
        model_faces = np.asarray(m.faces, dtype=np.int64)
        faces, uvs, uv_faces = read_obj_uvs(uv_obj, num_faces=len(model_faces))
        V = m.v_template.shape[0]
        if faces.max() >= V:
            raise InputError(uv_obj, f"faces reference vertex {faces.max()}, the model has {V} vertices")
        self.register_buffer("_v_template", m.v_template.detach().to(dt), persistent=False)
        self.register_buffer("_shapedirs", m.shapedirs.detach().to(dt), persistent=False)
        self.register_buffer("_posedirs", m.posedirs.detach().to(dt), persistent=False)
        self.register_buffer("_J_regressor", m.J_regressor.detach().to(dt), persistent=False)
        self.register_buffer("_weights", m.lbs_weights.detach().to(dt), persistent=False)
        self.register_buffer("_weights_csr", sparse_weights(self._weights), persistent=False)
        self._levels = kinematic_levels(parents)
        self._parents = torch.as_tensor(parents).clamp_min(0)
        self._set_common_buffers(faces, np.repeat(np.eye(3)[None], J, 0))
        self.shape_names = tuple(f"beta{i}" for i in range(self._shapedirs.shape[-1]))
        index = {n: i for i, n in enumerate(names)}
        self.semantic_joints = {k: index[v] for k, v in _SEMANTIC.items() if v in index}
        n_body = 24 if cfg.model_type == "smpl" else 22
        self.conditioning_joints = tuple(range(1, min(n_body, J)))
        with torch.no_grad():
            v = self._v_template
            joints = self._J_regressor @ v
        self.template = BodyTemplate(
            vertices=v.cpu().numpy().astype(np.float32), faces=faces, uvs=uvs, uv_faces=uv_faces,
            skin_weights=self._weights.cpu().numpy().astype(np.float32), joint_names=tuple(names),
            joint_parents=parents, rest_joints=joints.cpu().numpy().astype(np.float32))
        self.to(cfg.device)

    def _pose_local(self, rotvecs: torch.Tensor, shape):
        return self._forward(rotvecs, shape, with_vertices=True)

    def _joints_local(self, rotvecs: torch.Tensor, shape):
        return self._forward(rotvecs, shape, with_vertices=False)[1]

    def _forward(self, rotvecs: torch.Tensor, shape, with_vertices: bool):
        dt = self._v_template.dtype
        B, J = rotvecs.shape[:2]
        # a host shape goes over without making the host wait (a trainer keeps the fits' shapes there)
        betas = torch.zeros(len(self.shape_names), device=self.device, dtype=dt) if shape is None else \
            to_device_async(shape, self.device, dt)
        if betas.dim() == 1:
            betas = betas[None]
        if betas.shape[-1] != len(self.shape_names):
            raise ValueError(f"shape must have {len(self.shape_names)} betas, got {tuple(betas.shape)}")
        v_shaped = self._v_template + torch.einsum("bl,vkl->bvk", betas, self._shapedirs)  # (Bs, V, 3)
        joints = self._J_regressor @ v_shaped  # (Bs, J, 3)
        R = rotvec_to_rotmat(rotvecs.to(dt))
        parents = self._parents.to(R.device)
        offsets = joints - joints[:, parents]
        offsets[:, 0] = joints[:, 0]
        F, p = forward_kinematics(self._levels_on(R.device), R, offsets)
        transforms = homogeneous(F, p)
        if not with_vertices:
            return None, transforms
        eye = torch.eye(3, dtype=dt, device=R.device)
        pose_feature = (R[:, 1:] - eye).reshape(B, -1)
        v_posed = v_shaped + (pose_feature @ self._posedirs).reshape(B, -1, 3)
        T = skinning_transforms(F, p, None, joints.expand(B, -1, -1))
        vertices = skin(v_posed, self._skin_weights_for(R.device), T)
        return vertices, transforms
