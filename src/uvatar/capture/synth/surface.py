"""Points on the body surface and the rest-pose features that appearance and clothing read.

Every synthetic quantity (texture, clothing offset, fold, crease) is a function of a surface point's
*rest-pose features*: its rest position ``p`` (metres) and its soft membership in body parts
(``groups``, from the skinning weights). A set of surface points is a sparse matrix ``W`` (N, V)
over the template vertices (barycentric weights), so the same functions serve body texels
(``W`` from the UV raster), scan vertices (``W`` from subdivision) and scan-atlas texels (a
product of the two), and posed positions are ``W @ posed_vertices``.

Landmarks (:class:`BodyLandmarks`) are the rest joint positions the recipes need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["GROUPS", "BodyLandmarks", "SurfaceFeatures", "vertex_groups", "landmarks", "features",
           "raster_matrix", "bary_matrix", "posed_points"]

GROUPS = ("torso", "neck", "head", "eye",
          "upperarm_l", "forearm_l", "hand_l", "upperarm_r", "forearm_r", "hand_r",
          "thigh_l", "shin_l", "foot_l", "thigh_r", "shin_r", "foot_r")

# joint (semantic name) that starts each group; joints inherit the group of their nearest start
_GROUP_STARTS = {"neck": "neck", "head": "head", "l_eye": "eye", "r_eye": "eye",
                 "l_shoulder": "upperarm_l", "l_elbow": "forearm_l", "l_wrist": "hand_l",
                 "r_shoulder": "upperarm_r", "r_elbow": "forearm_r", "r_wrist": "hand_r",
                 "l_hip": "thigh_l", "l_knee": "shin_l", "l_ankle": "foot_l",
                 "r_hip": "thigh_r", "r_knee": "shin_r", "r_ankle": "foot_r"}


@dataclass(frozen=True)
class BodyLandmarks:
    """Rest-pose joint positions (3,) in metres by semantic name, plus derived levels."""

    joints: dict[str, np.ndarray]
    floor_y: float       # lowest rest vertex
    top_y: float         # highest rest vertex

    def __getitem__(self, name: str) -> np.ndarray:
        return self.joints[name]


@dataclass
class SurfaceFeatures:
    """Rest features of N surface points: p (N, 3) rest position (m); groups (N, G) part
    memberships in [0, 1] (columns in ``GROUPS`` order, rows sum to 1)."""

    p: np.ndarray
    groups: np.ndarray

    def g(self, *names: str) -> np.ndarray:
        """(N,) summed membership of the named groups."""
        return self.groups[:, [GROUPS.index(n) for n in names]].sum(1)

    def __len__(self) -> int:
        return int(self.p.shape[0])


def joint_groups(body) -> np.ndarray:
    """(J,) group index (into GROUPS) of every joint of ``body``."""
    from uvatar.body.kinematics import nearest_ancestor

    starts = {body.semantic_joints[k]: GROUPS.index(g) for k, g in _GROUP_STARTS.items()
              if k in body.semantic_joints}
    heads = list(starts)
    below = nearest_ancestor(body.template.joint_parents, heads)
    return np.where(below >= 0, np.array([starts[j] for j in heads] + [0])[below], 0).astype(np.int64)


def vertex_groups(body) -> np.ndarray:
    """(V, G) float32 part memberships: skinning weights summed per group."""
    w = np.asarray(body.template.skin_weights, dtype=np.float64)
    onehot = np.eye(len(GROUPS))[joint_groups(body)]  # (J, G)
    g = w @ onehot
    return (g / np.maximum(g.sum(1, keepdims=True), 1e-12)).astype(np.float32)


def landmarks(body) -> BodyLandmarks:
    t = body.template
    joints = {k: np.asarray(t.rest_joints[j], dtype=np.float64) for k, j in body.semantic_joints.items()}
    if "l_eye" not in joints:  # bodies without eye joints: a guess from the head joint
        head = joints["head"]
        for s, x in (("l", 0.032), ("r", -0.032)):
            joints[f"{s}_eye"] = head + np.array([x, 0.04, 0.08])
    return BodyLandmarks(joints=joints, floor_y=float(t.vertices[:, 1].min()), top_y=float(t.vertices[:, 1].max()))


def features(W: sp.spmatrix, rest_vertices: np.ndarray, groups: np.ndarray) -> SurfaceFeatures:
    """Features of the points ``W`` (N, V) from per-vertex rest positions (V, 3) and groups (V, G)."""
    return SurfaceFeatures(p=np.asarray(W @ rest_vertices, dtype=np.float64),
                           groups=np.asarray(W @ groups, dtype=np.float32))


def bary_matrix(faces: np.ndarray, face_index: np.ndarray, bary: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """(N, V) sparse barycentric weights of N points given by a face index (N,) and barycentrics (N, 3)."""
    face_index = np.asarray(face_index, dtype=np.int64)
    rows = np.repeat(np.arange(len(face_index)), 3)
    cols = np.asarray(faces, dtype=np.int64)[face_index].ravel()
    return sp.csr_matrix((np.asarray(bary, dtype=np.float64).ravel(), (rows, cols)),
                         shape=(len(face_index), int(num_vertices)))


def raster_matrix(raster, faces: np.ndarray, num_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """(W (N, V), flat texel indices (N,)) of the covered texels of a :class:`UVRaster`
    (row-major, row 0 = v 1)."""
    flat = np.flatnonzero(raster.mask.ravel())
    W = bary_matrix(faces, raster.face_index.ravel()[flat], raster.bary.reshape(-1, 3)[flat], num_vertices)
    return W, flat


def posed_points(W: sp.spmatrix, vertices: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posed positions (N, 3) and unit normals (N, 3) of the points ``W`` from posed vertices and
    vertex normals (V, 3) (float64)."""
    pos = np.asarray(W @ np.asarray(vertices, dtype=np.float64))
    nrm = np.asarray(W @ np.asarray(normals, dtype=np.float64))
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return pos, nrm
