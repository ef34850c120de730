"""A frame of the take through the subject tracker (issue 41): :func:`track_frame` judges the crop
observation with :class:`~uvatar.fit.identity.SubjectTracker` (finding everyone in view when it asks),
drops the keypoints that could be another person's (:func:`clear_of_others`) and holds a crowded frame;
:func:`identity_report` says which frames were held and re-associated. The tracker's rules are
:mod:`uvatar.fit.identity`'s."""

from __future__ import annotations

import logging

import numpy as np

from uvatar.fit.identity import (
    _TORSO,
    BEHIND_M,
    CLEAR_MARGIN,
    CLOSE_M,
    MIN_POINTS,
    MIN_VIEW_POINTS,
    MIN_VIEWS_NEAR,
    SLACK_M,
    STATUSES,
    Candidate,
    SubjectTracker,
    body_centre,
)

log = logging.getLogger(__name__)

__all__ = ["frame_ranges", "person_observation", "track_frame", "images_changed", "identity_report",
           "clear_of_others"]


def frame_ranges(frames: list[str], held: list[str]) -> list[str]:
    """Runs of consecutive frames (in ``frames`` order) of ``held``, as "first-last" (or "frame")."""
    idx = sorted(frames.index(f) for f in held)
    out, start = [], None
    for n, i in enumerate(idx):
        if start is None:
            start = i
        if n + 1 == len(idx) or idx[n + 1] != i + 1:
            out.append(frames[start] if start == i else f"{frames[start]}-{frames[i]}")
            start = None
    return out


def person_observation(person, images, cameras, detector, triangulate_config, source: str):
    """A :class:`~uvatar.fit.observe.FrameObservation` from a :class:`~uvatar.fit.person.Person` found
    by :func:`~uvatar.fit.person.find_people` (its own detections, labels resolved, triangulated)."""
    from uvatar.fit.observe import FrameObservation, resolve_left_right
    from uvatar.fit.tracking import image_thumbnail
    from uvatar.fit.triangulate import triangulate

    K = len(detector.keypoint_names)
    xy = np.zeros((len(cameras), K, 2), np.float32)
    conf = np.zeros((len(cameras), K), np.float32)
    for c, (pxy, pconf) in person.detections.items():
        xy[c], conf[c] = pxy, pconf
    xy, conf, _ = resolve_left_right(xy, conf, cameras, triangulate_config, detector.keypoint_names)
    tri = triangulate(xy, conf, cameras, triangulate_config)
    thumbs = np.stack([image_thumbnail(im) for im in images]) if source == "images" else None
    return FrameObservation(source=source, cameras=list(cameras), xy=xy.astype(np.float32),
                            conf=conf.astype(np.float32), points=tri.points.astype(np.float32),
                            points_conf=tri.conf.astype(np.float32),
                            reprojection_px=tri.reprojection_px.astype(np.float32), thumbs=thumbs)


def _person_arrays(person, C: int, K: int) -> tuple[np.ndarray, np.ndarray]:
    xy, conf = np.zeros((C, K, 2)), np.zeros((C, K))
    for c, (pxy, pconf) in person.detections.items():
        xy[c], conf[c] = pxy, pconf
    return xy, conf


def clear_of_others(obs, others: list, config, margin: float = CLEAR_MARGIN):
    """(``obs`` without the keypoints that could be someone else's, views left): in each view, a
    detected keypoint inside the box of another person in front of the subject (their keypoints
    ``others`` [((K, 3), (K,))] projected, the box grown by ``margin`` of its height; their torso
    nearer that camera than ``BEHIND_M`` beyond the subject's) is dropped (where a person in front
    overlaps the subject in a view, the detector mixes them or takes the one in front; one behind is
    hidden by the subject where they overlap), and so is the whole view where
    that takes more than half of its confident keypoints; the rest is triangulated again. Views left:
    those with at least ``MIN_VIEW_POINTS`` confident keypoints."""
    from dataclasses import replace

    from uvatar.fit.projection import project_distorted
    from uvatar.fit.triangulate import triangulate

    conf = np.array(obs.conf, np.float32)
    xy = np.asarray(obs.xy, np.float64)
    centre = body_centre(obs.points, obs.points_conf)
    for c, cam in enumerate(obs.cameras):
        seen = conf[c] >= config.min_conf
        if not seen.any():
            continue
        inside = np.zeros(len(seen), bool)
        depth = np.inf if centre is None else float(cam.world_to_camera(centre[None])[0, 2])
        for points, pconf in others:
            ok = np.asarray(pconf) > 0
            if ok.sum() < 4:
                continue
            theirs = body_centre(points, pconf)
            if theirs is not None and float(cam.world_to_camera(theirs[None])[0, 2]) > depth + BEHIND_M:
                continue   # behind the subject in this view: the subject's pixels there are its own
            pix, z = project_distorted(cam, np.asarray(points, np.float64)[ok])
            pix = pix[z > 0]
            if len(pix) < 4:
                continue
            lo, hi = pix.min(0), pix.max(0)
            pad = margin * (hi[1] - lo[1])
            inside |= np.all((xy[c] >= lo - pad) & (xy[c] <= hi + pad), axis=1)
        drop = seen & inside
        if drop.sum() > 0.5 * seen.sum():
            drop = np.ones_like(seen)
        conf[c, drop] = 0.0
    if np.array_equal(conf, obs.conf):
        return obs, int(((obs.conf >= config.min_conf).sum(1) >= MIN_VIEW_POINTS).sum())
    tri = triangulate(xy, conf, obs.cameras, config)
    views = int(((conf >= config.min_conf).sum(1) >= MIN_VIEW_POINTS).sum())
    return replace(obs, conf=conf, points=tri.points.astype(np.float32), points_conf=tri.conf.astype(np.float32),
                   reprojection_px=tri.reprojection_px.astype(np.float32)), views


def track_frame(tracker: SubjectTracker, t: int, obs, images, cameras, detector, triangulate_config,
                source: str):
    """(the subject's observation at frame index ``t`` or None where it is held, status): ``obs`` (the
    crop observation of :func:`~uvatar.fit.observe.observe_frame`) judged by ``tracker``; everyone
    in view is found (:func:`~uvatar.fit.person.find_people`) when the tracker asks; a person other
    than ``obs`` taken as the subject is observed again from its own keypoints. The keypoints that
    could be another person's are dropped (:func:`clear_of_others`) and the views that disagree
    rejected; where fewer than ``MIN_VIEWS_NEAR`` views or ``MIN_POINTS`` triangulated keypoints (the torso among them) are left, the frame is held: status
    "crowded" (the subject is known, but its keypoints cannot be told from the other person's).
    Status "nobody" (``obs`` returned as it is): nobody at all in view, a missed detection, not a
    question of identity."""
    from uvatar.fit.observe import disagreeing_views, observe_frame, reject_views
    from uvatar.fit.person import find_people

    primary = (Candidate.of(images, obs.points, obs.points_conf, obs.xy, obs.conf)
               if (obs.points_conf > 0).sum() >= 6 else None)
    people = None
    if tracker.needs_survey(t, primary):
        K = obs.conf.shape[1]
        people = []
        for p in find_people(images, cameras, detector, triangulate_config):
            cand = Candidate.of(images, p.points, p.points_conf, *_person_arrays(p, len(cameras), K), person=p)
            if cand is not None:
                people.append(cand)
    status, chosen = tracker.judge(t, primary, people)
    if chosen is None and primary is None and people == []:
        tracker.held = False   # nobody in view: nobody to confuse the subject with (a plain missed detection)
        return obs, "nobody"
    if chosen is None:
        return None, status
    if chosen is not primary:
        again = observe_frame(images, cameras, detector, triangulate_config, source, prior=chosen.person)
        centre = body_centre(again.points, again.points_conf)
        if centre is not None and np.linalg.norm(centre - chosen.centre) < SLACK_M:
            obs = again
        else:
            obs = person_observation(chosen.person, images, cameras, detector, triangulate_config, source)
    centre = body_centre(obs.points, obs.points_conf)
    near = [float(np.linalg.norm((c - centre)[[0, 2]])) for c in tracker.others_close(t, exclude=chosen)
            if centre is not None]
    if min(near, default=np.inf) < CLOSE_M:
        log.debug("frame %d: crowded (another person %.2f m away)", t, min(near))
        return None, "crowded"
    others = tracker.others_near(t, exclude=chosen)
    if not others:
        return obs, status
    obs, _ = clear_of_others(obs, others, triangulate_config)
    obs = reject_views(obs, disagreeing_views(obs, triangulate_config), triangulate_config)
    views = int(((obs.conf >= triangulate_config.min_conf).sum(1) >= MIN_VIEW_POINTS).sum())
    torso = sum(obs.points_conf[k] > 0 for k in _TORSO if k < len(obs.points_conf))
    if views < MIN_VIEWS_NEAR or (obs.points_conf > 0).sum() < MIN_POINTS or torso < 3:
        log.debug("frame %d: crowded (%d views clear of the others, %d keypoints)", t, views,
                  int((obs.points_conf > 0).sum()))
        return None, "crowded"
    return obs, status


def images_changed(prior, obs) -> bool:
    """True where both frames have image thumbnails and the content changed (a cut to another take,
    :func:`~uvatar.fit.tracking.image_change`); False where either has none."""
    from uvatar.fit.tracking import image_change

    a, b = getattr(prior, "thumbs", None), getattr(obs, "thumbs", None)
    if a is None or b is None or np.shape(a) != np.shape(b):
        return False
    return bool(image_change(np.stack([a, b]))[0])


def identity_report(frames: list[str], statuses: dict, tracker, max_speed: float) -> dict:
    """``person["identity"]``: the frames held (lost, ambiguous, crowded: no fit) and re-associated,
    as frame ranges."""
    held = sorted(set().union(*(statuses.get(k, ()) for k in STATUSES)), key=frames.index)
    return {"max_speed_m_s": max_speed, "held": frame_ranges(frames, held), "held_frames": len(held),
            **{k: frame_ranges(frames, statuses.get(k, [])) for k in STATUSES},
            "reassociated": sorted(statuses["reassociated"], key=frames.index),
            "people_looked_for": tracker.surveys if tracker is not None else 0,
            "other_people_seen": tracker.others_seen if tracker is not None else 0}
