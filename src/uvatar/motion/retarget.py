"""Retarget a named source skeleton (BVH, AMASS) onto any :class:`~uvatar.body.base.BodyModel`.

For each source joint mapped to a semantic name (``pelvis``, ``l_elbow``, ...; tables below) the
source's world rotation relative to its rest pose ``G_s(t)`` is carried over as the target joint's
world-axis rotation ``G_j(t) = G_s(t) @ C_j``. ``C_j`` aligns the rest poses: the smallest rotation
taking the target's rest bone direction (joint → next mapped joint) onto the source's, so a T-pose
source drives an A-pose target. Unmapped target joints (fingers, twist bones) follow their parent.
Global rotation goes to ``Rh``; each joint's rotation relative to its parent, in rest-pose world
axes, is turned into the body's local axis-angles with ``body.world_to_local_rotvecs``.

The root translation is the source pelvis trajectory scaled by the ratio of leg lengths
(hip→knee→ankle, source units → metres). Its height is set so that the target's lowest ankle is
at its rest height above a floor at y = 0 whenever the source's lowest ankle is at its contact
height (5th percentile over the clip), and rises by the scaled amount when the source's does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import UvatarError
from uvatar.motion.skeleton import SkeletonMotion

SIDES = {"Left": "l_", "Right": "r_"}

# CMU BVH (and close variants) → semantic joint names
CMU_TO_SEMANTIC = {"Hips": "pelvis", "LowerBack": "spine1", "Spine": "spine2", "Spine1": "spine3",
                   "Neck": "neck", "Head": "head"}
MIXAMO_TO_SEMANTIC = {"Hips": "pelvis", "Spine": "spine1", "Spine1": "spine2", "Spine2": "spine3",
                      "Neck": "neck", "Head": "head"}
for _side, _p in SIDES.items():
    for _table in (CMU_TO_SEMANTIC, MIXAMO_TO_SEMANTIC):
        _table.update({f"{_side}Shoulder": f"{_p}collar", f"{_side}Arm": f"{_p}shoulder",
                       f"{_side}ForeArm": f"{_p}elbow", f"{_side}Hand": f"{_p}wrist",
                       f"{_side}UpLeg": f"{_p}hip", f"{_side}Leg": f"{_p}knee", f"{_side}Foot": f"{_p}ankle",
                       f"{_side}ToeBase": f"{_p}toe"})

SMPL_TO_SEMANTIC = {"pelvis": "pelvis", "spine1": "spine1", "spine2": "spine2", "spine3": "spine3",
                    "neck": "neck", "head": "head"}
for _side, _p in (("left", "l_"), ("right", "r_")):
    SMPL_TO_SEMANTIC.update({f"{_side}_collar": f"{_p}collar", f"{_side}_shoulder": f"{_p}shoulder",
                             f"{_side}_elbow": f"{_p}elbow", f"{_side}_wrist": f"{_p}wrist",
                             f"{_side}_hip": f"{_p}hip", f"{_side}_knee": f"{_p}knee",
                             f"{_side}_ankle": f"{_p}ankle", f"{_side}_foot": f"{_p}toe"})

# the joint whose rest position gives each semantic joint's bone direction
BONE_CHILD = {"spine1": "spine2", "spine2": "spine3", "spine3": "neck", "neck": "head"}
for _p in ("l_", "r_"):
    BONE_CHILD.update({f"{_p}collar": f"{_p}shoulder", f"{_p}shoulder": f"{_p}elbow", f"{_p}elbow": f"{_p}wrist",
                       f"{_p}hip": f"{_p}knee", f"{_p}knee": f"{_p}ankle", f"{_p}ankle": f"{_p}toe"})
NO_ALIGNMENT = ("pelvis", "head", "l_toe", "r_toe")  # keep the rest frames as they are


def semantic_map(names) -> dict[str, str]:
    """Source joint name → semantic name, picking the table that fits the skeleton."""
    stripped = {n: n.split(":")[-1] for n in names}  # "mixamorig:Hips" → "Hips"
    base = set(stripped.values())
    if "pelvis" in base and "left_hip" in base:
        table = SMPL_TO_SEMANTIC
    elif "LowerBack" in base or "Spine2" not in base:
        table = CMU_TO_SEMANTIC
    else:
        table = MIXAMO_TO_SEMANTIC
    out = {n: table[s] for n, s in stripped.items() if s in table}
    semantic = set(CMU_TO_SEMANTIC.values())
    out.update({n: s for n, s in stripped.items() if s in semantic and n not in out})
    return out


@dataclass
class RetargetConfig:
    """name_map: source joint name → semantic name (None → :func:`semantic_map`); source_floor:
    the floor height in source units (BVH and AMASS: 0)."""

    name_map: dict[str, str] | None = None
    source_floor: float = 0.0


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking direction a onto direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1 + 1e-8:  # opposite: rotate pi about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _descendants(parents: np.ndarray, j: int) -> np.ndarray:
    inside = np.zeros(len(parents), bool)
    inside[j] = True
    for k in range(j + 1, len(parents)):  # parents precede children
        if parents[k] >= 0 and inside[parents[k]]:
            inside[k] = True
    inside[j] = False
    return np.flatnonzero(inside)


def _bone_direction(semantic: str, joint: int, index: dict[str, int], rest: np.ndarray, parents) -> np.ndarray | None:
    child = BONE_CHILD.get(semantic)
    if child in index:
        d = rest[index[child]] - rest[joint]
        if np.linalg.norm(d) > 1e-6:
            return d
    desc = _descendants(np.asarray(parents), joint)
    if len(desc):
        d = rest[desc].mean(0) - rest[joint]
        if np.linalg.norm(d) > 1e-6:
            return d
    return None


def _leg_length(index: dict[str, int], rest: np.ndarray) -> float:
    lengths = []
    for p in ("l_", "r_"):
        if all(f"{p}{k}" in index for k in ("hip", "knee", "ankle")):
            h, k, a = (rest[index[f"{p}{n}"]] for n in ("hip", "knee", "ankle"))
            lengths.append(np.linalg.norm(k - h) + np.linalg.norm(a - k))
    if not lengths:
        raise UvatarError("cannot scale the root translation: hip, knee and ankle are not all mapped")
    return float(np.mean(lengths))


def _positions_from_pelvis(G: np.ndarray, rest: np.ndarray, parents: np.ndarray, pelvis: int) -> np.ndarray:
    """Joint positions (T, J, 3) relative to the pelvis, from world-axis rotations G (T, J, 3, 3):
    each bone's rest offset turned by its parent's G."""
    T, J = G.shape[:2]
    pos = np.zeros((T, J, 3))
    for j in range(J):
        p = parents[j]
        if p >= 0:
            pos[:, j] = pos[:, p] + G[:, p] @ (rest[j] - rest[p])
    return pos - pos[:, pelvis: pelvis + 1]


def retarget(source: SkeletonMotion, body, config: RetargetConfig | None = None):
    """Retarget ``source`` onto ``body`` → :class:`~uvatar.motion.sequences.Motion` for that body.

    Returns joint_rotvecs (T, J, 3) local axis-angles, Rh (T, 3), Th (T, 3) metres (floor y = 0).
    """
    from scipy.spatial.transform import Rotation

    from uvatar.motion.sequences import Motion

    config = config or RetargetConfig()
    name_map = config.name_map or semantic_map(source.names)
    src_index = {sem: source.index(n) for n, sem in name_map.items() if n in source.names}
    tgt_index = dict(body.semantic_joints)
    shared = [s for s in src_index if s in tgt_index]
    if "pelvis" not in shared:
        raise UvatarError(f"retargeting needs a 'pelvis' joint in both skeletons (source {source.source})")
    template = body.template
    t_rest = np.asarray(template.rest_joints, np.float64)
    t_parents = np.asarray(template.joint_parents)
    s_rest = np.asarray(source.rest_positions, np.float64)
    T, J = source.num_frames, body.num_joints
    # world-axis rotation of every target joint: mapped ones from the source (rest-aligned), the
    # others follow their parent
    G = np.empty((T, J, 3, 3))
    mapped = {tgt_index[s]: s for s in shared}
    for j in range(J):
        if j in mapped:
            sem = mapped[j]
            C = np.eye(3)
            if sem not in NO_ALIGNMENT:
                d_src = _bone_direction(sem, src_index[sem], src_index, s_rest, source.parents)
                d_tgt = _bone_direction(sem, j, tgt_index, t_rest, t_parents)
                if d_src is not None and d_tgt is not None:
                    C = _rotation_between(d_tgt, d_src)
            G[:, j] = source.world_rotations[:, src_index[sem]] @ C
        elif t_parents[j] >= 0:
            G[:, j] = G[:, t_parents[j]]
        else:
            G[:, j] = source.world_rotations[:, src_index["pelvis"]]
    pelvis = tgt_index["pelvis"]
    Rh_mat = G[:, pelvis].copy()
    Gp = np.swapaxes(Rh_mat, -1, -2)[:, None] @ G  # without the global rotation
    parent_G = np.where((t_parents >= 0)[None, :, None, None], Gp[:, np.maximum(t_parents, 0)], np.eye(3))
    local_world = np.swapaxes(parent_G, -1, -2) @ Gp
    world_rotvecs = Rotation.from_matrix(local_world.reshape(-1, 3, 3)).as_rotvec().reshape(T, J, 3)
    joint_rotvecs = np.asarray(body.world_to_local_rotvecs(world_rotvecs.astype(np.float32)), np.float32)
    joint_rotvecs[:, t_parents < 0] = 0.0  # the root's rotation is Rh
    # root translation
    scale = _leg_length(tgt_index, t_rest) / _leg_length(src_index, s_rest)  # metres per source unit
    floor_t = float(template.vertices[:, 1].min())
    ankles_s = [src_index[a] for a in ("l_ankle", "r_ankle") if a in src_index]
    ankles_t = [tgt_index[a] for a in ("l_ankle", "r_ankle") if a in src_index and a in tgt_index]
    if not ankles_s or not ankles_t:
        raise UvatarError("cannot place the body on the floor: no ankle is mapped")
    # feet touch the floor when the source's do: the lowest target ankle sits at its rest height
    # above the floor plus the scaled height of the lowest source ankle above its contact height
    src_ankle = source.positions[:, ankles_s, 1].min(1) - config.source_floor
    contact_s = float(np.percentile(src_ankle, 5))
    ankle_rest_t = float(t_rest[ankles_t, 1].mean()) - floor_t
    relative = _positions_from_pelvis(G, t_rest, t_parents, pelvis)  # (T, J, 3), pelvis at 0
    P = source.positions[:, src_index["pelvis"]] * scale
    P[:, 1] = ankle_rest_t + (src_ankle - contact_s) * scale - relative[:, ankles_t, 1].min(1)
    Th = P - (Rh_mat @ t_rest[pelvis])  # V = R(Rh) X + Th puts the pelvis at P
    return Motion(joint_rotvecs=joint_rotvecs, Rh=Rotation.from_matrix(Rh_mat).as_rotvec().astype(np.float32),
                  Th=Th.astype(np.float32), fps=source.fps, body=body.name, source=source.source,
                  joint_names=tuple(body.joint_names),
                  info={"scale_m_per_unit": scale, "units_to_metres_hint": source.units_to_metres,
                        "mapped_joints": sorted(shared)})
