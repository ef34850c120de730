"""Retarget a named source skeleton (BVH, AMASS, body-model fits) onto any body model, by full
joint rotations (twist included) for any rest pose.

Each semantic joint (:mod:`uvatar.motion.rigs`) gets an *anatomical frame* in each skeleton: its
bone direction ``u`` plus a second axis ``v`` that fixes the twist (:func:`bone_axes`): the hinge
axis of the limb (shoulder–elbow–wrist, hip–knee–ankle, knee–ankle–toe) for limb bones, the hip
line for the pelvis and the low spine, the shoulder line for the chest, neck and head, the trunk
for the collars. The target's frames come from its rest pose, hinge axes from the flexion
direction where the rest limb is straight (elbows and ankles bend forward, knees backward). The
source's come from the clip itself: every frame's world ``u``, ``v`` (from joint positions) is
turned back into the joint's rest frame by its world rotation and averaged. That is exact for
rigid parts and does not depend on the source's rest pose or on how its joint axes are twisted;
a bone whose hinge never bends in the clip falls back to the rest-pose rule (``info`` says which).
With ``A_s``, ``A_t`` the frames (columns u, v, u×v) the target joint's world rotation relative to
its rest pose is ``G_t(t) = G_s(t) @ A_s @ A_t^T``; unmapped target joints follow their parent.

Root: ``root="floor"`` (mocap) scales the source pelvis path by the ratio of leg lengths and sets
the height so that the target's lowest sole point is as high above y = 0 as the source's feet are
above their own contact heights (each foot joint's 5th percentile over the clip), never below it;
``root="pelvis"`` (body-model fits) keeps the source pelvis where it is.

Feet: ``feet="clean"`` then finds the source's foot contacts (:func:`uvatar.motion.feet.source_contacts`)
and pins each standing foot's sole to the floor by a two-bone IK of its leg
(:mod:`uvatar.motion.footlock`), lowering the body only where a leg cannot reach.

Shape: the target is the body model at ``shape`` (its shape parameters; None: the model's default),
so a retarget for an avatar (``uvatar animate``, ``uvatar motion convert --avatar``, the viewer) puts
*that* body's soles on the floor and scales the path by *its* legs; the motion records the shape.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uvatar.errors import UvatarError, check_values
from uvatar.motion.feet import (
    FootContactConfig,
    foot_landmarks,
    segments,
    sole_points,
    source_clearance,
    source_contacts,
)
from uvatar.motion.footlock import pin_feet
from uvatar.motion.record import Motion
from uvatar.motion.rigs import LIMB, RigMatch, match_rig
from uvatar.motion.rotations import matrix_to_rotvec, rotation_between, rotvec_to_matrix
from uvatar.motion.skeleton import SkeletonMotion

UP_CHAIN = ("pelvis", "spine1", "spine2", "spine3", "neck", "head")
HINGES = {"shoulder": ("shoulder", "elbow", "wrist", 1.0), "elbow": ("shoulder", "elbow", "wrist", 1.0),
          "wrist": ("shoulder", "elbow", "wrist", 1.0), "hip": ("hip", "knee", "ankle", -1.0),
          "knee": ("hip", "knee", "ankle", -1.0), "ankle": ("knee", "ankle", "toe", 1.0),
          "toe": ("knee", "ankle", "toe", 1.0)}  # joints of the hinge, flexion toward +-forward
LIMB_BONE = {"collar": ("collar", "shoulder"), "shoulder": ("shoulder", "elbow"), "elbow": ("elbow", "wrist"),
             "wrist": ("elbow", "wrist"), "hip": ("hip", "knee"), "knee": ("knee", "ankle"),
             "ankle": ("ankle", "toe"), "toe": ("ankle", "toe")}


@dataclass
class RetargetConfig:
    """name_map: source joint → semantic joint (or target joint name), merged over the automatic
    rig match (None/"" drops a joint); twist: where the source's bone frames come from ("auto":
    the clip, the rest pose where the clip has no evidence; "motion"; "rest": the rest pose, right
    for T/A-pose body models); root: "floor" or "pelvis" (module docstring); source_floor: floor
    height in source units; min_evidence: mean sine of the hinge bend (or length of the averaged
    second axis) below which "auto" uses the rest pose; feet: "floor" (the root height alone) or
    "clean" (also pin each foot in the source's contacts, found by ``contacts``)."""

    name_map: dict[str, str | None] | None = None
    twist: str = "auto"
    root: str = "floor"
    source_floor: float = 0.0
    min_evidence: float = 0.05
    feet: str = "floor"
    contacts: FootContactConfig = field(default_factory=FootContactConfig)

    def __post_init__(self) -> None:
        check_values([(self.twist in ("auto", "motion", "rest"), f"twist must be auto|motion|rest, got {self.twist!r}"),
                      (self.root in ("floor", "pelvis"), f"root must be floor|pelvis, got {self.root!r}"),
                      (np.isfinite(self.source_floor), "source_floor must be finite"),
                      (0 <= self.min_evidence < 1, "min_evidence must be in [0, 1)"),
                      (self.feet in ("floor", "clean"), f"feet must be floor|clean, got {self.feet!r}")])


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def _first(P: dict, names, origin: np.ndarray | None = None) -> np.ndarray | None:
    """The first of ``names`` in P (away from ``origin``, when given: joints at the same place,
    like CMU's neck and collars on the chest, give no direction)."""
    for n in names:
        if n in P and (origin is None or np.mean(np.linalg.norm(P[n] - origin, axis=-1)) > 1e-6):
            return P[n]
    return None


def _lateral(P: dict, upper: bool) -> np.ndarray | None:
    pairs = [("l_shoulder", "r_shoulder"), ("l_collar", "r_collar")] if upper else []
    for a, b in [*pairs, ("l_hip", "r_hip")]:
        if a in P and b in P:
            return P[a] - P[b]
    return None


def _bone_vectors(sem: str, P: dict) -> tuple[np.ndarray | None, np.ndarray | None, bool]:
    """(u, v, is_hinge) world vectors (..., 3) of semantic joint ``sem`` from positions P."""
    if sem in UP_CHAIN:
        k = UP_CHAIN.index(sem)
        if sem == "pelvis":
            top = _first(P, UP_CHAIN[:0:-1], P[sem])
            return _lateral(P, False), None if top is None else top - P[sem], False
        above, below = _first(P, UP_CHAIN[k + 1:], P[sem]), _first(P, UP_CHAIN[k - 1::-1], P[sem])
        u = above - P[sem] if above is not None else (P[sem] - below if below is not None else None)
        return u, _lateral(P, sem in ("spine3", "neck", "head")), False
    side, kind = sem[:2], sem[2:]
    a, b = (side + n for n in LIMB_BONE[kind])
    u = P[b] - P[a] if a in P and b in P else None
    if kind == "collar":
        top, low = _first(P, ("head", "neck")), _first(P, ("pelvis", "spine1", "spine2", "spine3"))
        return u, None if top is None or low is None else top - low, False
    h = HINGES[kind]
    names = [side + n for n in h[:3]]
    if not all(n in P for n in names):
        return u, None, True
    x, y, z = (P[n] for n in names)
    return u, np.cross(_unit(y - x), _unit(z - y)), True


def _frame(u: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """Columns (u, v ⊥ u, u × v), unit; None when degenerate."""
    if np.linalg.norm(u) < 1e-9:
        return None
    e1 = _unit(u)
    v = v - np.dot(v, e1) * e1
    if np.linalg.norm(v) < 1e-6:
        return None
    e2 = _unit(v)
    return np.stack([e1, e2, np.cross(e1, e2)], 1)


def body_forward(P: dict) -> np.ndarray:
    """Facing direction of a skeleton from its joint positions: left × up (+Z for uvatar bodies)."""
    left = _lateral(P, False)
    top = _first(P, UP_CHAIN[:0:-1])
    if left is None or top is None or "pelvis" not in P:
        return np.array([0.0, 0.0, 1.0])
    return _unit(np.cross(_unit(left), _unit(top - P["pelvis"])))


def rest_frame(sem: str, P: dict, min_bend: float = 0.05) -> np.ndarray | None:
    """Anatomical frame (3, 3) of ``sem`` in a rest pose P (semantic name → (3,)): hinges bent less
    than ``min_bend`` (sine) or backwards take the flexion convention (elbow and ankle forward,
    knee backward)."""
    u, v, hinge = _bone_vectors(sem, P)
    if u is None:
        return None
    if hinge:
        side, h = sem[:2], HINGES[sem[2:]]
        a, b = side + h[0], side + h[1]
        if a in P and b in P:
            convention = np.cross(_unit(P[b] - P[a]), h[3] * body_forward(P))
            if v is None or np.linalg.norm(v) < min_bend or np.dot(v, convention) <= 0:
                v = convention
    return None if v is None else _frame(u, v)


def motion_frame(sem: str, P: dict, G: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Anatomical frame of ``sem`` in the source's rest frame, averaged over the clip: P semantic
    name → (T, 3) world positions, G (T, 3, 3) the joint's world rotations relative to rest.
    → (frame or None, evidence = length of the averaged second axis ⊥ u)."""
    u, v, hinge = _bone_vectors(sem, P)
    if u is None or v is None:
        return None, 0.0
    Gt = np.swapaxes(G, -1, -2)
    u_rest = (Gt @ _unit(u)[..., None])[..., 0].mean(0)
    v_rest = (Gt @ (v if hinge else _unit(v))[..., None])[..., 0].mean(0)
    e1 = _unit(u_rest)
    evidence = float(np.linalg.norm(v_rest - np.dot(v_rest, e1) * e1))
    return _frame(u_rest, v_rest), evidence


@dataclass
class RetargetPlan:
    """match: the rig match; src_index / tgt_index: semantic → joint index; shared: semantic
    joints in both; alignment: semantic → A_s @ A_t^T (3, 3); source_frames / target_frames:
    semantic → A (3, 3) (when known); twist_from: semantic → "motion" | "rest" | "direction" |
    "none"; scale: metres per source unit."""

    match: RigMatch
    src_index: dict[str, int]
    tgt_index: dict[str, int]
    shared: list[str]
    alignment: dict[str, np.ndarray]
    source_frames: dict[str, np.ndarray] = field(default_factory=dict)
    target_frames: dict[str, np.ndarray] = field(default_factory=dict)
    twist_from: dict[str, str] = field(default_factory=dict)
    scale: float = 1.0
    rest: object = None  # the target's BodyTemplate at the plan's shape (body_rest)
    shape: np.ndarray | None = None  # (S,) the target's shape parameters, None: the model's default


def body_rest(body, shape=None):
    """The rest :class:`~uvatar.body.base.BodyTemplate` of ``body`` at ``shape`` ((S,) or None: its
    default, ``body.template``)."""
    return body.template if shape is None else body.rest_template(shape)


def _leg_length(index: dict[str, int], rest: np.ndarray) -> float | None:
    lengths = []
    for p in ("l_", "r_"):
        if all(f"{p}{k}" in index for k in ("hip", "knee", "ankle")):
            h, k, a = (rest[index[f"{p}{n}"]] for n in ("hip", "knee", "ankle"))
            lengths.append(np.linalg.norm(k - h) + np.linalg.norm(a - k))
    return float(np.mean(lengths)) if lengths and np.mean(lengths) > 0 else None


def plan_retarget(source: SkeletonMotion, body, config: RetargetConfig | None = None,
                  shape=None) -> RetargetPlan:
    """Match the joints and align the rest frames of ``body`` at ``shape`` (see the module docstring)."""
    config = config or RetargetConfig()
    shape = None if shape is None else np.asarray(shape, np.float32).reshape(-1)
    target_names = {body.joint_names[i]: s for s, i in body.semantic_joints.items()}
    try:
        match = match_rig(source.names, source.parents, config.name_map, target_names)
    except ValueError as exc:
        raise UvatarError(f"{source.source or 'source skeleton'}: {exc}") from None
    if match.missing_required:
        raise UvatarError(f"{source.source or 'source skeleton'}: rig '{match.rig}': no joint maps to "
                          f"{', '.join(match.missing_required)}; unmapped joints: {', '.join(match.unmapped[:12]) or 'none'}"
                          f"{' ...' if len(match.unmapped) > 12 else ''}; give them in a joint map "
                          "(name_map, {source joint: semantic joint})")
    src_index = {s: source.index(n) for n, s in match.mapping.items()}
    tgt_index = dict(body.semantic_joints)
    shared = [s for s in src_index if s in tgt_index]
    rest = body_rest(body, shape)
    t_rest = np.asarray(rest.rest_joints, np.float64)
    P_t = {s: t_rest[i] for s, i in tgt_index.items()}
    P_rest = {s: source.rest_positions[i] for s, i in src_index.items()}
    P_src = {s: source.positions[:, i] for s, i in src_index.items()}
    plan = RetargetPlan(match, src_index, tgt_index, shared, {}, rest=rest, shape=shape)
    for sem in shared:
        A_t = rest_frame(sem, {k: P_t[k] for k in P_t if k in src_index}, config.min_evidence)
        A_s, how = None, "rest"
        if config.twist != "rest":
            A_s, evidence = motion_frame(sem, P_src, source.world_rotations[:, src_index[sem]])
            how = "motion"
            if A_s is not None and config.twist == "auto" and evidence < config.min_evidence:
                A_s = None
        if A_s is None and config.twist != "motion":
            A_s, how = rest_frame(sem, P_rest, config.min_evidence), "rest"
        if A_s is not None and A_t is not None:
            plan.alignment[sem] = A_s @ A_t.T
            plan.source_frames[sem], plan.target_frames[sem] = A_s, A_t
            plan.twist_from[sem] = how
            continue
        u_s, _, _ = _bone_vectors(sem, P_rest)
        u_t, _, _ = _bone_vectors(sem, P_t)
        ok = u_s is not None and u_t is not None and min(np.linalg.norm(u_s), np.linalg.norm(u_t)) > 1e-9
        plan.alignment[sem] = rotation_between(u_t, u_s) if ok else np.eye(3)
        plan.twist_from[sem] = "direction" if ok else "none"
    if config.root == "floor":
        ls, lt = _leg_length(src_index, source.rest_positions), _leg_length(tgt_index, t_rest)
        if ls is None or lt is None:
            raise UvatarError(f"{source.source or 'source skeleton'}: cannot scale the root translation: "
                              "the legs have no length")
        plan.scale = lt / ls
    else:
        plan.scale = float(source.units_to_metres or 1.0)
    return plan


def target_world_rotations(source: SkeletonMotion, body, plan: RetargetPlan) -> np.ndarray:
    """(T, J, 3, 3) every target joint's world rotation relative to its rest pose."""
    T, J = source.num_frames, body.num_joints
    parents = np.asarray(body.template.joint_parents)
    by_joint = {plan.tgt_index[s]: s for s in plan.shared}
    G = np.empty((T, J, 3, 3))
    for j in range(J):  # parents precede children
        if j in by_joint:
            sem = by_joint[j]
            G[:, j] = source.world_rotations[:, plan.src_index[sem]] @ plan.alignment[sem]
        elif parents[j] >= 0:
            G[:, j] = G[:, parents[j]]
        else:
            G[:, j] = source.world_rotations[:, plan.src_index["pelvis"]] @ plan.alignment["pelvis"]
    return G


def posed_joint_positions(G: np.ndarray, rest: np.ndarray, parents) -> np.ndarray:
    """Joint positions (T, J, 3) from world rotations G (T, J, 3, 3) relative to a rest pose whose
    joint frames are world-aligned (rest joints (J, 3)), the root kept at its rest position."""
    from uvatar.body.kinematics import forward_kinematics_numpy

    parents = np.asarray(parents)
    parent_G = G[:, np.maximum(parents, 0)]
    local = np.where((parents >= 0)[None, :, None, None], np.swapaxes(parent_G, -1, -2) @ G, G)
    offsets = rest - rest[np.maximum(parents, 0)]
    offsets[parents < 0] = rest[parents < 0]
    return forward_kinematics_numpy(parents, local, offsets)[1]


def motion_world(motion: Motion, body) -> tuple[np.ndarray, np.ndarray]:
    """A motion of ``body`` (at the motion's shape) in world space by the same kinematics as
    :func:`posed_joint_positions`: (G (T, J, 3, 3) world rotations relative to the rest pose, Rh
    included; joint positions (T, J, 3) metres, ``V = R(Rh) X + Th`` applied)."""
    from uvatar.body.kinematics import forward_kinematics_numpy

    rest = np.asarray(body_rest(body, motion.shape).rest_joints, np.float64)
    parents = np.asarray(body.template.joint_parents)
    local = rotvec_to_matrix(body.local_to_world_rotvecs(np.asarray(motion.joint_rotvecs, np.float64)))
    R = rotvec_to_matrix(motion.Rh)
    roots = np.flatnonzero(parents < 0)
    local[:, roots] = R[:, None] @ local[:, roots]
    offsets = rest - rest[np.maximum(parents, 0)]
    offsets[roots] = rest[roots]
    G, p = forward_kinematics_numpy(parents, local, offsets)
    root = rest[roots[0]]
    return G, p + ((R @ root) + motion.Th.astype(np.float64) - root)[:, None]


def _same_shape(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.shape(a) == np.shape(b)
                                         and np.allclose(a, b, atol=1e-6))


def _lowest_sole_and_pelvis(motion: Motion, body, rest, index: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """(each frame's lowest sole point height (T,), the pelvis (T, 3)) of ``motion`` posed at ``rest``."""
    G, positions = motion_world(motion, body)
    sole = sole_points(G, positions, np.asarray(rest.rest_joints, np.float64), foot_landmarks(body, index, rest=rest))
    return sole[..., 1].min(1), positions[:, index["pelvis"]]


def motion_at_shape(motion: Motion, body, shape) -> Motion:
    """``motion`` (of ``body`` at ``motion.shape``) played by ``body`` at ``shape`` ((S,) or None: the
    model's default): the joint rotations and Rh kept, the root moved so that each frame's lowest sole
    point is as high as at the motion's own shape (feet stay on the floor, a jump stays a jump) and the
    pelvis's horizontal path from the first frame scaled by the ratio of leg lengths (strides fit the
    legs). The same shape: the motion unchanged. This is how another person's fits drive an avatar."""
    from dataclasses import replace

    shape = None if shape is None else np.asarray(shape, np.float32).reshape(-1)
    if _same_shape(motion.shape, shape):
        return motion
    index = dict(body.semantic_joints)
    rest_from, rest_to = body_rest(body, motion.shape), body_rest(body, shape)
    moved = replace(motion, shape=shape, info=dict(motion.info, reshaped_from=None if motion.shape is None
                                                   else np.asarray(motion.shape).tolist()))
    lowest_from, pelvis_from = _lowest_sole_and_pelvis(motion, body, rest_from, index)
    lowest_to, pelvis_to = _lowest_sole_and_pelvis(moved, body, rest_to, index)
    legs_from = _leg_length(index, np.asarray(rest_from.rest_joints, np.float64))
    legs_to = _leg_length(index, np.asarray(rest_to.rest_joints, np.float64))
    ratio = legs_to / legs_from if legs_from and legs_to else 1.0
    delta = np.zeros_like(pelvis_to)
    delta[:, 1] = lowest_from - lowest_to
    wanted = pelvis_from[0, [0, 2]] + ratio * (pelvis_from[:, [0, 2]] - pelvis_from[0, [0, 2]])
    delta[:, [0, 2]] = wanted - pelvis_to[:, [0, 2]]
    moved.Th = (np.asarray(motion.Th, np.float64) + delta).astype(np.float32)
    return moved


def _motion(G: np.ndarray, P: np.ndarray, body, plan: RetargetPlan, fps: float, source: str, info: dict) -> Motion:
    """World rotations G (T, J, 3, 3) relative to the rest pose and the pelvis path P (T, 3) →
    Motion (the pelvis's rotation becomes Rh) of ``body`` at the plan's shape."""
    pelvis = plan.tgt_index["pelvis"]
    t_rest = np.asarray(plan.rest.rest_joints, np.float64)
    parents = np.asarray(body.template.joint_parents)
    Rh_mat = G[:, pelvis].copy()
    Gp = np.swapaxes(Rh_mat, -1, -2)[:, None] @ G  # without the global rotation
    parent_G = np.where((parents >= 0)[None, :, None, None], Gp[:, np.maximum(parents, 0)], np.eye(3))
    world_rotvecs = matrix_to_rotvec(np.swapaxes(parent_G, -1, -2) @ Gp)
    joint_rotvecs = np.asarray(body.world_to_local_rotvecs(world_rotvecs.astype(np.float32)), np.float32)
    joint_rotvecs[:, parents < 0] = 0.0  # the root's rotation is Rh
    Th = P - (Rh_mat @ t_rest[pelvis])  # V = R(Rh) X + Th puts the pelvis at P
    return Motion(joint_rotvecs=joint_rotvecs, Rh=matrix_to_rotvec(Rh_mat).astype(np.float32),
                  Th=Th.astype(np.float32), fps=fps, body=body.name, source=source,
                  joint_names=tuple(body.joint_names), shape=plan.shape, info=info)


def retarget(source: SkeletonMotion, body, config: RetargetConfig | None = None, plan: RetargetPlan | None = None,
             shape=None):
    """Retarget ``source`` onto ``body`` at ``shape`` ((S,) shape parameters, None: the model's default;
    a given ``plan`` brings its own) → :class:`~uvatar.motion.record.Motion` for that body:
    joint_rotvecs (T, J, 3) local axis-angles, Rh (T, 3), Th (T, 3) metres, shape. ``config.feet ==
    "clean"`` then pins the feet in the source's contacts (:mod:`uvatar.motion.footlock`)."""
    config = config or RetargetConfig()
    plan = plan or plan_retarget(source, body, config, shape)
    t_rest = np.asarray(plan.rest.rest_joints, np.float64)
    parents = np.asarray(body.template.joint_parents)
    G = target_world_rotations(source, body, plan)
    pelvis = plan.tgt_index["pelvis"]
    P = source.positions[:, plan.src_index["pelvis"]] * plan.scale
    info = {"rig": plan.match.rig, "mapping": dict(plan.match.mapping), "mapped_joints": sorted(plan.shared),
            "twist_from": dict(plan.twist_from), "scale_m_per_unit": plan.scale,
            "units_to_metres_hint": source.units_to_metres, "root": config.root, "feet": config.feet}
    if config.root == "floor" or config.feet == "clean":
        pos = posed_joint_positions(G, t_rest, parents)
        rel = pos - pos[:, pelvis: pelvis + 1]
        landmarks = foot_landmarks(body, plan.tgt_index, rest=plan.rest)
        sole = sole_points(G, rel, t_rest, landmarks)  # (T, K, 3) relative to the pelvis
    if config.root == "floor":
        clearance = source_clearance(source, plan, config.source_floor)
        P[:, 1] = clearance * plan.scale - sole[..., 1].min(1)  # lowest sole point at the clearance
    if config.feet == "clean":
        contacts = source_contacts(source, plan, config.contacts)
        forward = body_forward({s: t_rest[i] for s, i in plan.tgt_index.items()})
        G, pos, out = pin_feet(G, rel + P[:, None], sole + P[:, None], landmarks[2], contacts, plan.tgt_index,
                               parents, int(round(config.contacts.blend_s * source.fps)), forward,
                               config.contacts.max_drop_m)
        P = pos[:, pelvis]
        info["foot_contacts"] = {"frames": contacts.sum(0).tolist(),
                                 "segments": [len(segments(c)) for c in contacts.T],
                                 "max_drop_m": round(float(out["drop"].max()), 4),
                                 "max_miss_m": round(float(out["miss"].max()), 4)}
    return _motion(G, P, body, plan, source.fps, source.source, info)


def semantic_map(names, parents=None) -> dict[str, str]:
    """Source joint name → semantic name by the rig registry (parents: the tree, for the spine;
    without it the names are taken as a chain in order)."""
    names = tuple(names)
    parents = np.arange(-1, len(names) - 1) if parents is None else parents
    return match_rig(names, parents).mapping


__all__ = ["LIMB", "RetargetConfig", "RetargetPlan", "body_rest", "motion_at_shape", "plan_retarget", "retarget", "semantic_map", "rest_frame",
           "motion_frame", "target_world_rotations", "posed_joint_positions", "motion_world", "foot_landmarks",
           "source_clearance"]
