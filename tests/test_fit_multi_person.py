"""More than one person in view, the subject over time: left/right tracking, cuts, views that disagree,
choosing the person (known answers on small synthetic inputs; a fake detector where one is needed)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.fixtures.box_people import BoxPeopleDetector
from uvatar.errors import InputError
from uvatar.fit.keypoints import BLAZEPOSE_NAMES
from uvatar.fit.observe import FrameObservation, disagreeing_views, left_right_swap, reject_views
from uvatar.fit.person import (
    Person,
    PersonChoice,
    choose_person,
    find_people,
    parse_person,
    volume_centre,
)
from uvatar.fit.projection import project_distorted
from uvatar.fit.tracking import continuity, image_change, image_thumbnail, track_left_right
from uvatar.fit.triangulate import TriangulateConfig, triangulate
from uvatar.render.cameras import ring_cameras

PERM = left_right_swap(BLAZEPOSE_NAMES)


def _body(rng, centre=(0.0, 1.0, 0.0)):
    """(33, 3) a person-like point set: every left point 0.2-0.5 m from its right twin."""
    pts = rng.normal(size=(33, 3)) * [0.1, 0.5, 0.1] + centre
    for k, m in enumerate(PERM):
        if "left" in BLAZEPOSE_NAMES[k]:
            pts[k, 0] = pts[m, 0] + rng.uniform(0.2, 0.5)
    return pts


def test_mirrored_frames_are_relabelled_fast_limbs_and_flips_are_no_cut_a_new_take_is():
    rng = np.random.default_rng(0)
    T = 14
    base = _body(rng)
    pts = np.repeat(base[None], T, axis=0)
    limbs = [BLAZEPOSE_NAMES.index(n) for n in ("left_wrist", "right_wrist", "left_ankle", "right_ankle")]
    pts[:, limbs] += (np.arange(T) % 2)[:, None, None] * 0.35        # limbs swing 35 cm a frame
    pts[10:] += [2.0, 0.0, 1.0]                                          # frame 10: another take
    conf = np.ones((T, 33))
    flipped = [4, 5, 8]
    pts[flipped] = pts[flipped][:, PERM]                                  # mirrored labels
    swap = track_left_right(pts, conf, PERM, 0.1)
    assert np.flatnonzero(swap).tolist() == flipped
    fixed = np.where(swap[:, None, None], pts[:, PERM], pts)
    cont = continuity(fixed, conf, 0.1)
    assert np.flatnonzero(~cont).tolist() == [9]                         # only the new take
    # without the relabelling every flip moves (nearly) every keypoint: a cut into and out of each flip
    assert np.flatnonzero(~continuity(pts, conf, 0.1)).tolist() == [3, 5, 7, 8, 9]


def test_majority_decides_the_labelling_of_a_stretch():
    rng = np.random.default_rng(1)
    pts = np.repeat(_body(rng)[None], 5, axis=0)
    pts[[1, 2, 3]] = pts[[1, 2, 3]][:, PERM]      # most frames say the other labelling
    swap = track_left_right(pts, np.ones((5, 33)), PERM, 0.1)
    assert np.flatnonzero(swap).tolist() == [0, 4]


def test_a_cut_needs_the_images_to_change_where_thumbnails_exist():
    img = np.zeros((48, 72, 3), np.float32)
    img[:, :36] = 1.0
    th = image_thumbnail(img, side=4)
    assert th.shape == (4, 4) and np.allclose(th[:, :2], 1.0) and np.allclose(th[:, 2:], 0.0)
    pts = np.zeros((3, 10, 3))
    pts[2] += 1.0                                   # every keypoint jumps between frames 1 and 2
    conf = np.ones((3, 10))
    same = np.zeros((3, 2, 4, 4), np.float32)
    other = same.copy()
    other[2] = 1.0                                  # both views change content at frame 2
    assert image_change(same).tolist() == [False, False]
    assert image_change(other).tolist() == [False, True]
    assert continuity(pts, conf, 0.1, image_change(same)).tolist() == [True, True]
    assert continuity(pts, conf, 0.1, image_change(other)).tolist() == [True, False]
    unknown = other.copy()
    unknown[1] = np.nan                             # no thumbnails: the keypoints decide alone
    assert image_change(unknown).tolist() == [True, True]


def _cams(count=4, size=(640, 480)):
    cams = ring_cameras([0.0, 1.0, 0.0], 3.5, count, (0.0,), 50.0, *size)
    for c in cams:
        c.dist = np.zeros(5)
    return cams


def _observation(cams, views_xy):
    xy = np.stack(views_xy).astype(np.float32)
    conf = np.ones(xy.shape[:2], np.float32)
    tri = triangulate(xy, conf, cams, TriangulateConfig())
    return FrameObservation("images", cams, xy, conf, tri.points, tri.conf, tri.reprojection_px)


def test_a_view_of_another_person_is_named_and_rejected():
    rng = np.random.default_rng(2)
    cams = _cams()
    subject, other = _body(rng), _body(rng, centre=(0.9, 1.0, 0.4))
    views = [project_distorted(c, subject)[0] for c in cams]
    views[2] = project_distorted(cams[2], other)[0]           # camera 02 sees the bystander
    obs = _observation(cams, views)
    assert disagreeing_views(obs) == (cams[2].name,)
    out = reject_views(obs, disagreeing_views(obs))
    assert out.rejected == (cams[2].name,) and (out.conf[2] == 0).all() and (out.conf[[0, 1, 3]] == 1).all()
    assert disagreeing_views(out) == (cams[2].name,)         # stays named once rejected
    agree = _observation(cams, [project_distorted(c, subject)[0] for c in cams])
    assert disagreeing_views(agree) == () and reject_views(agree, ()) is agree


@pytest.mark.parametrize("spec, expected", [
    ("most-views", PersonChoice()),
    ("centre", PersonChoice(rule="centre")), ("center", PersonChoice(rule="centre")),
    ("largest", PersonChoice(rule="largest")),
    ("nearest-to:1,0,-2.5", PersonChoice(rule="nearest-to", target=(1.0, 0.0, -2.5))),
    ("box:cam01:000012:10,20,110,220", PersonChoice("box", "cam01", "000012", (10.0, 20.0, 110.0, 220.0))),
    ("point:cam01:000000:50,60", PersonChoice("point", "cam01", "000000", (50.0, 60.0, 50.0, 60.0))),
])
def test_parse_person(spec, expected):
    assert parse_person(spec) == expected


@pytest.mark.parametrize("spec", ["tallest", "nearest-to:1,2", "box:cam01:10,20,30,40", "box:c:f:5,5,1,1",
                                  "point:c:f:x,y", "largest:3"])
def test_parse_person_bad_specs_are_one_line(spec):
    with pytest.raises(InputError, match="^person: ") as err:
        parse_person(spec)
    assert "\n" not in str(err.value)


def test_find_and_choose_people_with_a_fake_detector():
    rng = np.random.default_rng(3)
    cams = _cams(4, (1280, 960))
    subject = _body(rng, centre=(0.0, 1.0, 0.0))
    near = _body(rng, centre=(0.8, 1.0, 1.3))
    near = (near - near.mean(0)) * 1.5 + near.mean(0)   # a bigger person, nearer the cameras: the largest
    det = BoxPeopleDetector(cams, [subject, near])
    images = [det.image(c) for c in range(len(cams))]
    people = find_people(images, cams, det, TriangulateConfig())
    assert len(people) == 2
    at = [np.median(p.points[p.points_conf > 0], axis=0) for p in people]
    which = {i: int(np.linalg.norm(a - near.mean(0)) < 0.3) for i, a in enumerate(at)}   # 1: the near person
    assert sorted(which.values()) == [0, 1]
    i, why = choose_person(people, PersonChoice(), cams)
    assert which[i] == 0 and "most cameras" in why
    i, _ = choose_person(people, PersonChoice(rule="centre"), cams)
    assert which[i] == 0
    i, _ = choose_person(people, PersonChoice(rule="nearest-to", target=(0.8, 1.0, 1.4)), cams)
    assert which[i] == 1
    i, _ = choose_person(people, PersonChoice(rule="largest"), cams)
    assert which[i] == 1
    c = min(next(p for k, p in enumerate(people) if which[k] == 1).members)   # a view that sees the near one
    xy = project_distorted(cams[c], near)[0]
    i, _ = choose_person(people, PersonChoice("point", cams[c].name, "0", (*xy.mean(0), *xy.mean(0))), cams)
    assert which[i] == 1
    with pytest.raises(InputError, match="^person: "):
        choose_person([], PersonChoice(), cams)


def test_volume_centre_is_where_the_cameras_look():
    cams = _cams(5)
    np.testing.assert_allclose(volume_centre(cams), [0.0, 1.0, 0.0], atol=1e-9)
    assert isinstance(Person(np.zeros((33, 3)), np.zeros(33)).members, dict)


def test_build_tells_people_apart_whatever_the_pose():
    from uvatar.fit.person import SAME_BODY, body_signature, same_body

    rng = np.random.default_rng(4)
    body = _body(rng)
    conf = np.ones(33)
    moved = body.copy()
    elbow, wrist = BLAZEPOSE_NAMES.index("left_elbow"), BLAZEPOSE_NAMES.index("left_wrist")
    forearm = moved[wrist] - moved[elbow]
    c, s_ = np.cos(1.0), np.sin(1.0)
    moved[wrist] = moved[elbow] + np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ forearm   # another pose
    moved += [1.0, 0.0, -2.0]                                                                 # elsewhere
    sig = body_signature(body, conf)
    assert same_body(body_signature(moved, conf), sig) < 1e-9
    other = (body - body.mean(0)) * 1.2 + body.mean(0)                                       # a bigger build
    assert same_body(body_signature(other, conf), sig) > SAME_BODY
    hidden = conf.copy()
    hidden[11:] = 0
    assert same_body(body_signature(body, hidden), sig) == np.inf                             # too few bones



def test_a_view_mixed_with_a_person_in_front_is_rejected():
    """The detector took the subject and a bystander in front of it together (nearer camera 02,
    0.2 m aside): its keypoints lie half-way between both, 0.09 of the subject's height off (the
    synthetic crossing: 0.10-0.12); views that agree stay below 0.063 there."""
    rng = np.random.default_rng(3)
    cams = _cams()
    subject = _body(rng)
    views = [project_distorted(c, subject)[0] for c in cams]
    ahead = subject.mean(0) - cams[2].center
    ahead /= np.linalg.norm(ahead)
    aside = np.cross(ahead, [0.0, 1.0, 0.0])
    other = cams[2].center + 0.55 * (subject - cams[2].center) + 0.2 * aside / np.linalg.norm(aside)
    views[2] = 0.5 * (views[2] + project_distorted(cams[2], other)[0])
    obs = _observation(cams, views)
    assert disagreeing_views(obs) == (cams[2].name,)


def test_a_right_view_cut_off_by_the_border_agrees():
    """A right view whose legs are cut off (its detection half the subject's height there), 5.5 % of
    the subject's height off (noise), agrees: scaled by its own height it would lie 0.106 off, beyond
    ``DISAGREE_FRACTION``."""
    rng = np.random.default_rng(4)
    cams = _cams()
    subject = _body(rng)
    views = [project_distorted(c, subject)[0] for c in cams]
    height = float(np.ptp(views[1][:, 1]))
    angle = rng.uniform(0, 2 * np.pi, len(subject))
    views[1] = views[1] + 0.055 * height * np.stack([np.cos(angle), np.sin(angle)], 1)
    obs = _observation(cams, views)
    obs.conf[1, views[1][:, 1] > np.median(views[1][:, 1])] = 0.0     # the lower half: out of the image
    assert disagreeing_views(obs) == ()


def test_a_view_whose_one_detection_mixes_two_people_does_not_hide_the_second(monkeypatch):
    """Camera 02 sees the bystander in front of the subject and finds one skeleton between both; it
    matches both people's 3D keypoints, the subject's hypothesis takes it, and the bystander (seen
    alone by cameras 00, 01, 03) is still found from their other views. Pairs of one person's view
    and the other's are no person (they reproject far from both)."""
    import uvatar.fit.person as person

    rng = np.random.default_rng(5)
    cams = _cams()
    subject = _body(rng)
    ahead = subject.mean(0) - cams[2].center
    ahead /= np.linalg.norm(ahead)
    aside = np.cross(ahead, [0.0, 1.0, 0.0])
    bystander = subject - 0.6 * ahead + 0.2 * aside / np.linalg.norm(aside)   # alike, 0.6 m nearer camera 02
    ones = np.ones(33)
    dets = [[(project_distorted(c, subject)[0], ones), (project_distorted(c, bystander)[0], ones)] for c in cams]
    dets[2] = [(0.5 * (dets[2][0][0] + dets[2][1][0]), ones)]               # one skeleton of both
    monkeypatch.setattr(person, "_view_detections", lambda image, *a, **k: dets[int(image)])
    people = find_people(list(range(4)), cams, BoxPeopleDetector(cams, []), TriangulateConfig())
    centres = [np.median(p.points[p.points_conf > 0], axis=0) for p in people]
    assert len(people) == 2, [sorted(p.members) for p in people]
    assert min(np.linalg.norm(c - np.median(bystander, 0)) for c in centres) < 0.1
    assert min(np.linalg.norm(c - np.median(subject, 0)) for c in centres) < 0.1
