"""How well a retarget follows its source, and how close two motions of one body are.

Per bone group (:data:`BONE_GROUPS`): **direction error**, the angle between the target's bone
(posed joint → next joint) and the source's; **twist error**, the swing–twist twist angle about
the bone of the rotation between the target's and the source's anatomical frames (the frames of
:mod:`uvatar.motion.retarget`, moved by each skeleton's own world rotations; for the target those
come from posing the body model: this checks the rotation chain, the frames themselves are the
retarget's); **bend-plane error** for the limbs, from joint positions alone (no frames): the angle
between the source's and the target's elbow/knee bend planes where both bend by > 15 degrees. Feet: the **lowest foot height** per frame (lowest vertex of the
posed feet, metres above y = 0); over the source's foot contacts (:mod:`uvatar.motion.feet`)
**foot sliding**, the horizontal speed of each foot's lowest sole point (m/s), and that point's
height; and the share of frames the source itself is airborne. All angles in degrees.
"""

from __future__ import annotations

import numpy as np

from uvatar.motion.rotations import geodesic_angle, twist_angle

# group → (joint whose rotation carries the bone, bone start, bone end)
BONE_GROUPS = {
    "upper_arm": [("l_shoulder", "l_shoulder", "l_elbow"), ("r_shoulder", "r_shoulder", "r_elbow")],
    "forearm": [("l_elbow", "l_elbow", "l_wrist"), ("r_elbow", "r_elbow", "r_wrist")],
    "thigh": [("l_hip", "l_hip", "l_knee"), ("r_hip", "r_hip", "r_knee")],
    "shin": [("l_knee", "l_knee", "l_ankle"), ("r_knee", "r_knee", "r_ankle")],
    "spine": [("spine1", "spine1", "spine2"), ("spine2", "spine2", "spine3"), ("spine3", "spine3", "neck")],
    "head": [("head", "neck", "head")],
}
CONTACT_M = 0.02
HINGE_OF = {"shoulder": ("shoulder", "elbow", "wrist"), "elbow": ("shoulder", "elbow", "wrist"),
            "hip": ("hip", "knee", "ankle"), "knee": ("hip", "knee", "ankle")}
MIN_BEND = np.sin(np.radians(15.0))


def _bend_plane_error(src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """Twist measured from joint positions alone: the angle (degrees) between the source's and the
    target's bend-plane normals (a→b × b→c) of a limb, (N, 3 joints, 3) each, on the frames where
    both limbs bend by more than 15 degrees."""
    def normal(x):
        a, b = x[:, 1] - x[:, 0], x[:, 2] - x[:, 1]
        return np.cross(a / np.linalg.norm(a, axis=-1, keepdims=True), b / np.linalg.norm(b, axis=-1, keepdims=True))

    ns, nt = normal(src), normal(tgt)
    bent = (np.linalg.norm(ns, axis=-1) > MIN_BEND) & (np.linalg.norm(nt, axis=-1) > MIN_BEND)
    return np.degrees(geodesic_angle(ns[bent], nt[bent]))


def _stats(values: list[np.ndarray]) -> dict:
    v = np.abs(np.concatenate([np.ravel(x) for x in values])) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"median": None, "p90": None, "max": None, "n": 0}
    return {"median": round(float(np.median(v)), 3), "p90": round(float(np.percentile(v, 90)), 3),
            "max": round(float(v.max()), 3), "n": int(v.size)}


def pose_frames(body, motion, frames: np.ndarray, batch: int = 32):
    """Posed (world joint rotations (N, J, 3, 3), joints (N, J, 3), vertices' y (N, V)) of ``frames``."""
    import torch

    F, P, Y = [], [], []
    with torch.no_grad():
        for k in range(0, len(frames), batch):
            f = frames[k: k + batch]
            posed = body.pose(motion.joint_rotvecs[f], Rh=motion.Rh[f], Th=motion.Th[f], shape=None)
            T = posed.joint_transforms.double().cpu().numpy()
            F.append(T[..., :3, :3])
            P.append(T[..., :3, 3])
            Y.append(posed.vertices[..., 1].cpu().numpy())
    return np.concatenate(F), np.concatenate(P), np.concatenate(Y)


def _sample(n: int, max_frames: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, max_frames)).astype(int))


def compare_motions(body, a, b, max_frames: int = 200) -> dict:
    """Per bone group, direction and twist differences (degrees) between motions ``a`` and ``b`` of
    the same body (same frame count), on up to ``max_frames`` evenly spaced frames."""
    if a.num_frames != b.num_frames:
        raise ValueError(f"the motions have {a.num_frames} and {b.num_frames} frames")
    frames = _sample(a.num_frames, max_frames)
    Fa, Pa, _ = pose_frames(body, a, frames)
    Fb, Pb, _ = pose_frames(body, b, frames)
    sj = body.semantic_joints
    out = {}
    for group, bones in BONE_GROUPS.items():
        dirs, twists = [], []
        for joint, start, end in bones:
            if not all(k in sj for k in (joint, start, end)):
                continue
            da, db = Pa[:, sj[end]] - Pa[:, sj[start]], Pb[:, sj[end]] - Pb[:, sj[start]]
            dirs.append(np.degrees(geodesic_angle(da, db)))
            E = Fa[:, sj[joint]] @ np.swapaxes(Fb[:, sj[joint]], -1, -2)
            twists.append(np.degrees(twist_angle(E, db)))
        out[group] = {"direction_deg": _stats(dirs), "twist_deg": _stats(twists)}
    return {"frames_compared": int(len(frames)), "bones": out}


def _foot_vertices(body, tgt_index: dict) -> dict[str, np.ndarray]:
    from uvatar.motion.feet import SIDES, below

    main = np.asarray(body.template.skin_weights).argmax(1)
    return {side: np.flatnonzero(below(body.template.joint_parents, [tgt_index[side + "ankle"]])[main])
            for side in SIDES if side + "ankle" in tgt_index}


def feet_in_contact(motion, body, plan, contacts: np.ndarray) -> dict:
    """Foot sliding (m/s, :func:`uvatar.motion.feet.sliding_speeds`) and each standing foot's lowest
    sole point height (metres) of ``motion`` over the source's contact frames ``contacts`` (T, F)."""
    from uvatar.motion.feet import foot_landmarks, lowest_point_tracks, sliding_speeds, sole_points
    from uvatar.motion.retarget import body_rest, motion_world

    G, pos = motion_world(motion, body)
    rest = body_rest(body, motion.shape)
    landmarks = foot_landmarks(body, plan.tgt_index, rest=rest)
    sole = sole_points(G, pos, np.asarray(rest.rest_joints, np.float64), landmarks)
    speed = sliding_speeds(sole, landmarks[2], contacts, motion.fps)
    heights = [point[contacts[:, f], 1] for f, point, _ in lowest_point_tracks(sole, landmarks[2])]
    height = np.concatenate(heights) if heights else np.zeros(0)
    return {"sliding_m_per_s": {"median": round(float(np.median(speed)), 5) if speed.size else None,
                                "p90": round(float(np.percentile(speed, 90)), 5) if speed.size else None,
                                "contact_frame_pairs": int(speed.size)},
            "sole_height_abs_m": {"median": round(float(np.median(np.abs(height))), 5) if height.size else None,
                                  "max": round(float(np.abs(height).max()), 5) if height.size else None}}


def retarget_report(source, motion, body, plan, max_frames: int = 200, contacts_config=None, before=None) -> dict:
    """Direction/twist errors against ``source`` (a SkeletonMotion), lowest foot height and foot
    sliding of ``motion`` (its retarget onto ``body`` by ``plan``). Feet: the source's contacts
    (:func:`uvatar.motion.feet.source_contacts` with ``contacts_config``), the share of frames the
    source is airborne (its lower foot more than 2 cm, scaled to the target, above its contact
    height), and :func:`feet_in_contact` of ``motion`` and of ``before`` (the same retarget
    without the foot clean-up) when given."""
    from uvatar.motion.feet import segments, source_clearance, source_contacts

    T = motion.num_frames
    frames = _sample(T, max_frames)
    F, P, Y = pose_frames(body, motion, frames)
    import torch

    with torch.no_grad():
        F_rest = body.rest_pose().joint_transforms[..., :3, :3].double().cpu().numpy()
    G_t = F @ np.swapaxes(F_rest, -1, -2)  # world rotation relative to the rest pose
    sj, si = plan.tgt_index, plan.src_index
    bones = {}
    for group, members in BONE_GROUPS.items():
        dirs, twists, planes = [], [], []
        for joint, start, end in members:
            hinge = HINGE_OF.get(joint[2:]) if joint[:2] in ("l_", "r_") else None
            names = [joint[:2] + n for n in hinge] if hinge else []
            if names and all(n in si and n in sj for n in names):
                planes.append(_bend_plane_error(source.positions[frames][:, [si[n] for n in names]],
                                                P[:, [sj[n] for n in names]]))
            if not all(k in si and k in sj for k in (joint, start, end)):
                continue
            ds = source.positions[frames, si[end]] - source.positions[frames, si[start]]
            if np.linalg.norm(ds, axis=-1).min() < 1e-9:
                continue
            dirs.append(np.degrees(geodesic_angle(P[:, sj[end]] - P[:, sj[start]], ds)))
            if joint in plan.source_frames:
                S = source.world_rotations[frames, si[joint]] @ plan.source_frames[joint]
                Tf = G_t[:, sj[joint]] @ plan.target_frames[joint]
                twists.append(np.degrees(twist_angle(Tf @ np.swapaxes(S, -1, -2), S[..., 0])))
        bones[group] = {"direction_deg": _stats(dirs), "twist_deg": _stats(twists)}
        if planes:
            bones[group]["bend_plane_deg"] = _stats(planes)
    feet = _foot_vertices(body, sj)
    lowest = np.min([Y[:, v].min(1) for v in feet.values()], 0)  # (N,) metres
    clearance = source_clearance(source, plan) * plan.scale
    contact = clearance[frames] < CONTACT_M
    contacts = source_contacts(source, plan, contacts_config)
    after = feet_in_contact(motion, body, plan, contacts)
    return {
        "frames": T, "frames_posed": int(len(frames)), "rig": plan.match.rig, "twist_from": dict(plan.twist_from),
        "feet_mode": motion.info.get("feet", "floor"),
        "bones": bones,
        "lowest_foot_m": {"per_frame": [round(float(x), 4) for x in lowest], "frames": frames.tolist(),
                          "min": round(float(lowest.min()), 4), "median": round(float(np.median(lowest)), 4),
                          "within_2cm_all_frames": round(float(np.mean(np.abs(lowest) <= CONTACT_M)), 4),
                          "within_2cm_source_contact_frames": round(float(np.mean(np.abs(lowest[contact]) <= CONTACT_M)), 4)
                          if contact.any() else None,
                          "source_contact_frames": int(contact.sum()),
                          "source_airborne_share": round(float(np.mean(clearance >= CONTACT_M)), 4)},
        "foot_contacts": {"frames_per_foot": contacts.sum(0).tolist(),
                          "segments_per_foot": [len(segments(c)) for c in contacts.T],
                          "any_foot_share": round(float(contacts.any(1).mean()), 4),
                          "after": after, "before": None if before is None else feet_in_contact(before, body, plan, contacts)},
        "foot_sliding_m_per_s": after["sliding_m_per_s"],
    }


def summary_lines(report: dict) -> list[str]:
    """Short human-readable lines of a report from :func:`retarget_report` or :func:`compare_motions`."""
    lines = []
    for group, r in report["bones"].items():
        d, t = r["direction_deg"], r["twist_deg"]
        plane = r.get("bend_plane_deg")
        lines.append(f"{group:>10}: direction median {d['median']} deg (p90 {d['p90']}), "
                     f"twist median {t['median']} deg (p90 {t['p90']})"
                     + (f", bend plane median {plane['median']} deg (p90 {plane['p90']})" if plane else ""))
    if "lowest_foot_m" in report:
        f = report["lowest_foot_m"]
        lines.append(f"lowest foot: min {f['min']} m, median {f['median']} m, within 2 cm on "
                     f"{100 * f['within_2cm_all_frames']:.1f}% of frames"
                     + (f" ({100 * f['within_2cm_source_contact_frames']:.1f}% of the source's contact frames)"
                        if f["within_2cm_source_contact_frames"] is not None else ""))
        lines.append(f"source airborne (lower foot > 2 cm above its contact height) on "
                     f"{100 * f['source_airborne_share']:.1f}% of frames: at most "
                     f"{100 * (1 - f['source_airborne_share']):.1f}% of frames can have a foot on the floor")
    if "foot_contacts" in report:
        c = report["foot_contacts"]
        for when in ("before", "after"):
            r = c[when]
            if r is not None:
                s, h = r["sliding_m_per_s"], r["sole_height_abs_m"]
                label = f" ({when} clean-up)" if c["before"] is not None else ""
                lines.append(f"feet in the source's contacts{label}: sliding median {s['median']} m/s "
                             f"(p90 {s['p90']}), sole height |median| {h['median']} m (max {h['max']})")
    return lines
