"""Foot contacts and their clean-up: contact detection with hysteresis, the two-bone IK and the
body lowering (known answers), a synthetic clip on anny's own skeleton whose standing feet slide
with the pelvis (pinned after the clean-up, everything else unchanged), and the CMU clip."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.motion.feet import FootContactConfig, detect_contacts, segments
from uvatar.motion.footlock import needed_drop, spread_drop, two_bone_ik
from uvatar.motion.retarget import (
    RetargetConfig,
    motion_world,
    plan_retarget,
    posed_joint_positions,
    retarget,
)
from uvatar.motion.rotations import rotvec_to_matrix
from uvatar.motion.skeleton import SkeletonMotion


@pytest.fixture(scope="module")
def anny():
    from uvatar.body.registry import load_body_model

    return load_body_model("anny")


def test_contact_detection_hysteresis_and_minimum_length():
    T, fps = 40, 20.0
    clear, speed = np.full((T, 2), 0.1), np.zeros((T, 2))
    clear[10:20, 0] = 0.025  # loose (below 1.5 x 2 cm) ...
    clear[14, 0] = 0.01      # ... around one strict frame: the whole loose run is a contact
    clear[25:30, 0] = 0.025  # loose only: never a contact
    clear[5:25, 1] = 0.0
    speed[12, 1] = 0.4       # loose speed inside: the contact goes on
    speed[18, 1] = 1.0       # too fast: splits it into [5, 18) and [19, 25)
    clear[33, 1] = 0.0       # one frame: shorter than min_s
    c = detect_contacts(clear, speed, fps, FootContactConfig(min_s=0.1))
    assert segments(c[:, 0]).tolist() == [[10, 20]]
    assert segments(c[:, 1]).tolist() == [[5, 18], [19, 25]]
    assert segments(np.array([True, True, False, True])).tolist() == [[0, 2], [3, 4]]
    assert segments(np.zeros(3, bool)).shape == (0, 2)
    with pytest.raises(ValueError, match="release must be >= 1"):
        FootContactConfig(release=0.5)
    with pytest.raises(ValueError, match="feet must be floor|clean"):
        RetargetConfig(feet="glue")


def test_two_bone_ik_and_lowering_known_answers():
    hip, knee, ankle = np.zeros((1, 3)), np.array([[0, -0.5, 0.0]]), np.array([[0, -1.0, 0.0]])
    pole = np.array([[0, 0, 1.0]])
    new_knee, new_ankle = two_bone_ik(hip, knee, ankle, np.array([[0, -0.8, 0.0]]), pole)
    np.testing.assert_allclose(new_ankle, [[0, -0.8, 0]], atol=1e-12)
    np.testing.assert_allclose(new_knee, [[0, -0.4, 0.3]], atol=1e-12)  # 0.3-0.4-0.5, toward the pole
    bent_knee = np.array([[0.0, -0.4, 0.3]])
    same = two_bone_ik(hip, bent_knee, np.array([[0, -0.8, 0.0]]), np.array([[0, -0.8, 0.0]]), -pole)
    np.testing.assert_allclose(same[0], bent_knee, atol=1e-12)  # target = ankle: unchanged (pole unused)
    far = two_bone_ik(hip, knee, ankle, np.array([[0, -3.0, 0.0]]), pole)
    np.testing.assert_allclose(far[1], [[0, -1.0, 0]], atol=1e-12)  # out of reach: straight toward it
    # hip at 1 m, target 0.6 m sideways on the floor, reach 1 m: lower by 1 - 0.8
    drop = needed_drop(np.array([[0, 1.0, 0], [0, 1.0, 0]]), np.array([[0.6, 0, 0], [0, 0.5, 0]]), np.ones(2))
    np.testing.assert_allclose(drop, [0.2, 0.0], atol=1e-12)
    d = np.zeros(30)
    d[14] = 0.05
    smooth = spread_drop(d, 4)
    assert (smooth >= d).all() and smooth[14] == pytest.approx(0.05) and smooth[:6].max() == 0
    assert np.abs(np.diff(smooth)).max() <= 0.05 / 9 + 1e-12  # a ramp over 9 frames, no step


def _leg_rotations(body, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """(T, J, 3, 3) world rotations relative to rest: per side (T, 2) hip flexion and knee bend
    (radians) of that leg, the feet kept flat; anny faces +Z with its left along +X."""
    from uvatar.motion.feet import below

    parents, sj = np.asarray(body.template.joint_parents), body.semantic_joints
    G = np.broadcast_to(np.eye(3), (len(left), body.num_joints, 3, 3)).copy()
    for side, angles in (("l_", left), ("r_", right)):
        foot = below(parents, [sj[side + "ankle"]])
        shin = below(parents, [sj[side + "knee"]]) & ~foot
        thigh = below(parents, [sj[side + "hip"]]) & ~shin & ~foot
        for mask, angle in ((thigh, -angles[:, 0]), (shin, angles[:, 1] - angles[:, 0])):
            G[:, mask] = rotvec_to_matrix(np.outer(angle, [1.0, 0, 0]))[:, None]
    return G


def _sliding_clip(body, stand=(0.26, 0.52), fps=30.0, speed=0.12):
    """anny's own skeleton as a source: the pelvis glides forward at ``speed`` m/s, so standing feet
    slide with it; the left foot stands on frames [30, 60), the right one on [0, 25) and [65, 90),
    each lifted (hip 50 deg, knee 80 deg) otherwise. ``stand``: hip flexion and knee bend standing."""
    T = 90
    left, right = np.tile([0.87, 1.4], (T, 1)), np.tile([0.87, 1.4], (T, 1))
    left[30:60] = stand
    right[:25] = right[65:] = stand
    G = _leg_rotations(body, left, right)
    rest = np.asarray(body.template.rest_joints, np.float64)
    pos = posed_joint_positions(G, rest, body.template.joint_parents)
    pos[..., 2] += speed * np.arange(T)[:, None] / fps
    return SkeletonMotion(names=tuple(body.joint_names), parents=np.asarray(body.template.joint_parents),
                          rest_positions=rest, world_rotations=G, positions=pos, fps=fps, units_to_metres=1.0,
                          source="sliding")


def _soles(body, motion, plan):
    from uvatar.motion.feet import foot_landmarks, lowest_point_tracks, sole_points

    G, pos = motion_world(motion, body)
    landmarks = foot_landmarks(body, plan.tgt_index)
    sole = sole_points(G, pos, np.asarray(body.template.rest_joints, np.float64), landmarks)
    return {f: point for f, point, _ in lowest_point_tracks(sole, landmarks[2])}, pos


def test_sliding_feet_are_pinned_and_nothing_else_moves(anny):
    from uvatar.motion.feet import source_contacts

    src = _sliding_clip(anny)
    plan = plan_retarget(src, anny)
    contacts = source_contacts(src, plan)
    left, right = segments(contacts[:, 0]).tolist(), segments(contacts[:, 1]).tolist()
    assert len(left) == 1 and 30 <= left[0][0] <= 32 and 58 <= left[0][1] <= 60, left  # pose switches: fast frames
    assert len(right) == 2 and right[0][0] == 0 and 23 <= right[0][1] <= 25 and right[1][1] == 90, right
    floor = retarget(src, anny, RetargetConfig(), plan)
    clean = retarget(src, anny, RetargetConfig(feet="clean"), plan)
    assert clean.info["foot_contacts"]["max_drop_m"] == 0.0 and clean.info["foot_contacts"]["segments"] == [1, 2]
    before, _ = _soles(anny, floor, plan)
    after, pos = _soles(anny, clean, plan)
    for f in (0, 1):
        c = contacts[:, f]
        both = c[1:] & c[:-1]
        step_before = np.linalg.norm(np.diff(before[f][:, [0, 2]], axis=0), axis=1)[both] * src.fps
        step_after = np.linalg.norm(np.diff(after[f][:, [0, 2]], axis=0), axis=1)[both] * src.fps
        assert np.median(step_before) == pytest.approx(0.12, abs=0.01)  # the source slides ...
        assert step_after.max() < 1e-3  # ... the clean-up holds the sole (m/s)
        assert np.abs(after[f][c, 1]).max() < 0.005
    # bone lengths of the whole body unchanged
    parents = np.asarray(anny.template.joint_parents)
    rest = np.asarray(anny.template.rest_joints, np.float64)
    bones = np.linalg.norm(pos[:, 1:] - pos[:, parents[1:]], axis=-1)
    np.testing.assert_allclose(bones, np.broadcast_to(np.linalg.norm(rest[1:] - rest[parents[1:]], axis=-1), bones.shape),
                               atol=1e-5)
    # far from its contacts (fade 3 frames) each leg is unchanged; the rest of the body and the root everywhere
    from uvatar.motion.feet import below

    sj = anny.semantic_joints
    blend = round(FootContactConfig().blend_s * src.fps)
    legs = {f: below(parents, [sj[s + "hip"]]) for f, s in ((0, "l_"), (1, "r_"))}
    for f, leg in legs.items():
        near = np.convolve(contacts[:, f].astype(float), np.ones(2 * blend + 1), mode="same") > 0
        assert (~near).sum() >= 20
        np.testing.assert_allclose(clean.joint_rotvecs[~near][:, leg], floor.joint_rotvecs[~near][:, leg], atol=1e-5)
        assert np.abs(clean.joint_rotvecs[near][:, leg] - floor.joint_rotvecs[near][:, leg]).max() > 0.01
    others = ~(legs[0] | legs[1])
    np.testing.assert_allclose(clean.joint_rotvecs[:, others], floor.joint_rotvecs[:, others], atol=1e-5)
    np.testing.assert_allclose(clean.Th, floor.Th, atol=1e-6)
    np.testing.assert_allclose(clean.Rh, floor.Rh, atol=1e-6)
    # the ankles keep their world orientation
    G_floor, _ = motion_world(floor, anny)
    G_clean, _ = motion_world(clean, anny)
    for s in ("l_ankle", "r_ankle", "l_toe"):
        np.testing.assert_allclose(G_clean[:, sj[s]], G_floor[:, sj[s]], atol=1e-5)


def test_straight_legs_lower_the_body_smoothly(anny):
    """Standing with straight knees, a foot held in place needs a longer leg: the body goes down,
    by at most a few centimetres and without a step; the feet still reach their targets."""
    src = _sliding_clip(anny, stand=(0.0, 0.0), speed=0.3)
    plan = plan_retarget(src, anny)
    config = RetargetConfig(feet="clean", contacts=FootContactConfig(speed_m_s=0.5))
    clean = retarget(src, anny, config, plan)
    floor = retarget(src, anny, RetargetConfig(), plan)
    info = clean.info["foot_contacts"]
    assert 0.001 < info["max_drop_m"] < 0.05 and info["max_miss_m"] < 1e-6, info
    drop = floor.Th[:, 1] - clean.Th[:, 1]
    assert drop.min() >= -1e-6 and drop.max() == pytest.approx(info["max_drop_m"], abs=1e-4)
    assert np.abs(np.diff(drop)).max() < 0.4 * drop.max()  # spread over frames, no step
    capped = retarget(src, anny, RetargetConfig(feet="clean", contacts=FootContactConfig(speed_m_s=0.5, max_drop_m=0.002)),
                      plan)
    info = capped.info["foot_contacts"]
    assert info["max_drop_m"] == pytest.approx(0.002, abs=1e-6) and info["max_miss_m"] > 0.001, info  # short of it


def test_cmu_clip_clean_feet(anny, shared_data):
    """On CMU 01_01 (jumps) the clean-up stops the standing feet sliding and puts their soles on
    the floor; the share of frames with a foot on the floor cannot pass the source's own."""
    from uvatar.motion.bvh import read_bvh
    from uvatar.motion.feet import source_contacts
    from uvatar.motion.report import feet_in_contact
    from uvatar.motion.skeleton import skeleton_motion_from_bvh

    src = skeleton_motion_from_bvh(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), "cmu")
    plan = plan_retarget(src, anny)
    contacts = source_contacts(src, plan)
    assert 0.7 < contacts[:, 0].mean() < 0.85 and 0.7 < contacts[:, 1].mean() < 0.85  # measured 0.77, 0.75
    before = feet_in_contact(retarget(src, anny, RetargetConfig(), plan), anny, plan, contacts)
    after = feet_in_contact(retarget(src, anny, RetargetConfig(feet="clean"), plan), anny, plan, contacts)
    # measured: median 0.088 -> 4e-6 m/s, p90 0.25 -> 1e-5 m/s; sole height max 6 cm -> 0
    assert before["sliding_m_per_s"]["median"] > 0.05 and before["sole_height_abs_m"]["max"] > 0.03
    for stat in ("median", "p90"):  # sliding drops by more than 1000x (measured ~2e4x)
        assert after["sliding_m_per_s"][stat] < before["sliding_m_per_s"][stat] / 1000
    assert after["sole_height_abs_m"]["max"] < 1e-4
