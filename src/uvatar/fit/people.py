"""The people of a capture over time (``uvatar fit --person``): who is who at a few frames, the person
found again where their track is lost, and another person's track kept off the subject.

:func:`choose_people` looks at ``SEED_TRIES`` frames (:func:`uvatar.fit.person.find_people` at each),
tells the people apart by build (:func:`uvatar.fit.person.same_body`) and returns the subject (by the
:class:`~uvatar.fit.person.PersonChoice`) and, for ``all``/``ID``, the others with their ids and seed
frames. :func:`lost` and :func:`find_again` are the tracker's loss and re-finding (by build; away from
the subject with ``avoid``); :func:`subject_hider` paints the fitted subject over in the images where
another person is detected (:func:`frame_views`' ``hide``).
"""

from __future__ import annotations

import logging

import numpy as np

from uvatar.capture.layout import Capture
from uvatar.errors import InputError
from uvatar.fit.stages import FitStages

log = logging.getLogger(__name__)

__all__ = ["SEED_TRIES", "frame_views", "choose_people", "lost", "build_so_far", "find_again", "is_at",
           "subject_hider"]


def frame_views(capture: Capture, frame: str, source: str, stages: FitStages, hide=None):
    """(images, cameras) the detector looks at for one frame (``hide(frame, images, cameras) ->
    images``: paints the subject over where another person is detected)."""
    if source == "scans":
        from uvatar.fit.views import render_scan_views, scan_cameras

        mesh = capture.load_scan(frame)
        cameras = scan_cameras(mesh.vertices, stages.views)
        return render_scan_views(mesh, cameras), cameras
    cameras = list(capture.cameras().values())
    images = []
    for cam in cameras:
        path = capture.image_path(cam.name, frame)
        if not path.is_file():
            raise InputError(path, "image is missing")
        images.append(capture.load_image(cam.name, frame))
    return (hide(frame, images, cameras) if hide is not None else images), cameras


SEED_TRIES = 4  # frames tried (from the first on, 1/8 of the capture apart) until one person is seen by every camera


def _find_and_choose(capture: Capture, frame: str, choice, detector, stages: FitStages):
    """(people found at ``frame``, index chosen, why, camera names)."""
    from uvatar.fit.person import choose_person, find_people

    images, cameras = frame_views(capture, frame, "images", stages)
    names = [c.name for c in cameras]
    if choice.camera is not None and choice.camera not in names:
        raise InputError("person", f"camera {choice.camera!r} is not in cameras/ ({', '.join(names)})")
    forced = {names.index(choice.camera): choice.box} if choice.rule == "box" else None
    people = find_people(images, cameras, detector, stages.triangulate, forced=forced)
    i, why = choose_person(people, choice, cameras)
    return people, i, why, names


def choose_people(capture: Capture, frames: list[str], choice, detector, stages: FitStages) -> list[tuple]:
    """[(id, seed frame, the chosen :class:`~uvatar.fit.person.Person`, a report dict)]: the subject
    first (id None), then, for ``all``/``id``, every other person (ids "1", "2", ... by the views that
    see them over the frames looked at; seeded at their best-seen frame).

    Without a frame in the choice, ``SEED_TRIES`` frames (1/8 of the capture apart) are looked at and
    the people found are told apart across them by their build (:func:`~uvatar.fit.person.same_body`);
    for ``most-views`` the person seen by the most cameras over those frames wins (one frame can hide
    the subject behind a bystander in a view); for the other rules, the rule at the frame where the
    person it picks is seen by the most cameras. The seed is that person's best-seen frame."""
    from uvatar.fit.person import SAME_BODY, body_signature, same_body

    if choice.frame is not None and choice.frame not in frames:
        raise InputError("person", f"frame {choice.frame!r} is not one of the capture's frames being fitted")
    step = max(1, len(frames) // 8)
    tries = [choice.frame] if choice.frame is not None else frames[: SEED_TRIES * step: step]
    found = []   # (frame, people, chosen index, why, names)
    for seed in tries:
        try:
            found.append((seed, *_find_and_choose(capture, seed, choice, detector, stages)))
        except InputError:
            if seed == tries[-1] and not found:
                if choice.rule not in ("most-views", "all"):
                    raise
                log.warning("person: nobody seen by two views at frames %s; detecting without a subject",
                            ", ".join(tries))
                return [(None, frames[0], None, {"rule": choice.rule, "frame": None, "people_found": 0,
                                                 "chosen": None, "why": "nobody found", "people": [],
                                                 "chosen_again_after_cuts": []})]
    clusters = []   # [signature, total views, best (views, -frame index, person index)]
    for f, (_, people, _, _, _) in enumerate(found):
        for k, p in enumerate(people):
            sig = body_signature(p.points, p.points_conf)
            near = [c for c in clusters if same_body(sig, c[0]) < SAME_BODY]
            if near:
                near[0][1] += len(p.members)
                near[0][2] = max(near[0][2], (len(p.members), -f, k))
            else:
                clusters.append([sig, len(p.members), (len(p.members), -f, k)])
    clusters.sort(key=lambda c: (c[1], c[2]), reverse=True)
    if choice.rule in ("most-views", "all", "id") and len(found) > 1:
        total, (_, f, k) = clusters[0][1], clusters[0][2]
        seed, people, _, _, names = found[-f]
        i, why = k, f"seen by the most cameras over frames {', '.join(t[0] for t in found)} ({total} views)"
    else:
        seed, people, i, why, names = max(found, key=lambda t: len(t[1][t[2]].members))
    report = {"rule": choice.rule, "frame": seed, "people_found": len(people), "chosen": i, "why": why,
              "people": [{"cameras": [names[c] for c in sorted(p.members)],
                          "position_m": np.round(np.median(p.points[p.points_conf > 0], axis=0), 3).tolist()}
                         for p in people], "chosen_again_after_cuts": []}
    log.info("person: %d found at frame %s; fitting #%d, %s", len(people), seed, i, why)
    out = [(None, seed, people[i], report)]
    if not choice.several:
        return out
    subject_sig = body_signature(people[i].points, people[i].points_conf)
    subject = min(clusters, key=lambda c: same_body(c[0], subject_sig))
    others = [c for c in clusters if c is not subject]
    report["others"] = []
    for n, (_, total, (views, f, k)) in enumerate(others, start=1):
        frame, found_people = found[-f][0], found[-f][1]
        p = found_people[k]
        pid = str(n)
        position = np.round(np.median(p.points[p.points_conf > 0], axis=0), 3).tolist()
        report["others"].append({"id": pid, "views": total, "frame": frame, "position_m": position})
        if choice.rule == "all" or choice.person_id == pid:
            out.append((pid, frame, p, {"rule": choice.rule, "id": pid, "frame": frame, "why":
                                        f"another person, seen {total} times over frames "
                                        f"{', '.join(t[0] for t in found)}; seeded at frame {frame} "
                                        f"({views} cameras)", "position_m": position,
                                        "chosen_again_after_cuts": []}))
    log.info("person: %d other(s) found: %s", len(others), ", ".join(o["id"] for o in report["others"]) or "-")
    if choice.rule == "id" and len(out) == 1:
        raise InputError("person", f"person {choice.person_id} is not found: {len(others)} other "
                                   f"{'person' if len(others) == 1 else 'people'} seen by two views "
                                   f"({', '.join(o['id'] for o in report['others']) or 'none'})")
    return out


def lost(prior, obs, cut_distance: float) -> bool:
    """True when ``obs`` does not continue the subject ``prior`` (too few keypoints, or every keypoint
    jumped at once: a cut to another take, where the subject may be anywhere)."""
    from uvatar.fit.tracking import continuity

    if (obs.points_conf > 0).sum() < 6:
        return True
    pts = np.stack([prior.points, obs.points]).astype(np.float64)
    conf = np.stack([prior.points_conf, obs.points_conf])
    return not bool(continuity(pts, conf, cut_distance)[0])


def build_so_far(observations: dict, seed) -> np.ndarray:
    """(B,) the subject's build so far: the median bone lengths over the frames tracked."""
    import warnings

    from uvatar.fit.person import body_signature

    sigs = [body_signature(o.points, o.points_conf) for o in observations.values()]
    if seed is not None:
        sigs.append(body_signature(seed.points, seed.points_conf))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a bone never seen stays nan
        return np.nanmedian(np.stack(sigs), axis=0)


def find_again(capture, frame, detector, stages, signature, avoid=None, hide=None):
    """The person found again at ``frame`` after the track was lost: the person whose build
    (:func:`~uvatar.fit.person.body_signature`) is theirs (``signature``, the median over the
    frames tracked so far), if one is within ``SAME_BODY`` and is not where ``avoid`` (the subject's
    observation of that frame, when another person is tracked) is; else None (the frame keeps what
    the tracking found, and its views are judged as usual)."""
    from uvatar.fit.person import SAME_BODY, body_signature, find_people, same_body

    images, cameras = frame_views(capture, frame, "images", stages, hide)
    people = [p for p in find_people(images, cameras, detector, stages.triangulate) if not is_at(p, avoid)]
    scored = [(same_body(body_signature(p.points, p.points_conf), signature), -len(p.members), k)
              for k, p in enumerate(people)]
    if not scored or min(scored)[0] > SAME_BODY:
        return None
    return people[min(scored)[2]]


def is_at(obs, avoid) -> bool:
    """True when the observation (or Person) ``obs`` is where ``avoid`` (the subject's observation of
    the same frame) is: the same person (:func:`~uvatar.fit.person.same_place`)."""
    from uvatar.fit.person import same_place

    return avoid is not None and same_place(obs.points, obs.points_conf, avoid.points, avoid.points_conf)


def subject_hider(subject: Capture, body):
    """``hide(frame, images, cameras) -> images`` for :func:`frame_views`: the subject's fitted body
    (``fits/``, written before anyone else is fitted) painted over in each view (its silhouette grown
    as for its masks), so that the detector, looking for another person, never finds the subject."""
    from uvatar.fit.masks import MaskConfig, hide_body, posed_vertices

    def hide(frame, images, cameras):
        if not subject.has_fit(frame):
            return images
        return hide_body(images, cameras, posed_vertices(body, subject, frame), body.template.faces,
                         MaskConfig().dilate)

    return hide
