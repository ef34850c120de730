"""The subject as one track (issue 41): the motion gate, other people's tracks, colours, held frames,
and the synthetic crossing scene (known answers on small synthetic inputs; a fake detector)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.fixtures.box_people import BoxPeopleDetector
from uvatar.fit.identity import (
    CLOSE_M,
    HIST_BINS,
    Candidate,
    SubjectTracker,
    body_centre,
    hist_distance,
    torso_histograms,
)
from uvatar.fit.identity_frame import frame_ranges, track_frame
from uvatar.fit.keypoints import BLAZEPOSE_NAMES
from uvatar.fit.observe import observe_frame
from uvatar.fit.triangulate import TriangulateConfig
from uvatar.render.cameras import ring_cameras

STEP = 3.0 / 25   # metres a person can move per frame at 3 m/s, 25 fps
RED, BLUE = np.eye(HIST_BINS ** 3)[HIST_BINS ** 3 - HIST_BINS ** 2], np.eye(HIST_BINS ** 3)[HIST_BINS - 1]


def _cand(x, z=0.0, colour=None):
    return Candidate(centre=np.array([x, 1.0, z]), hists=[colour] * 3 if colour is not None else [None] * 3)


def _crossing(n=40, gap=0.42):
    """Subject drifting slowly along +x; bystander walking from x=-1.5 to +1.5 in front of it at
    ``gap`` metres (z), both as torso centres (n, 3)."""
    t = np.arange(n)
    subject = np.stack([0.005 * t, np.ones(n), np.zeros(n)], 1)
    bystander = np.stack([np.linspace(-1.5, 1.5, n), np.ones(n), np.full(n, gap)], 1)
    return subject, bystander


def test_the_track_never_switches_to_a_bystander_crossing_close_in_front():
    """Within CLOSE_M of another person the frame is held (crowded: a skeleton there may be a mix of
    both), the tracks stand still, and the subject is taken back once the two are seen apart."""
    subject, bystander = _crossing()
    gap = np.linalg.norm((bystander - subject)[:, [0, 2]], axis=1)
    tracker = SubjectTracker(STEP)
    tracker.start(0, subject[0])
    statuses = {}
    for t in range(len(subject)):
        # the crop detector took the bystander whenever it was within 0.6 m (it is in front)
        near = gap[t] < 0.6
        primary = Candidate(bystander[t], [None]) if near else Candidate(subject[t], [None])
        people = [Candidate(subject[t], [None]), Candidate(bystander[t], [None])]
        if not tracker.needs_survey(t, primary):
            people = None
        statuses[t], chosen = tracker.judge(t, primary, people)
        assert chosen is None or np.allclose(chosen.centre, subject[t]), (t, statuses[t])
        if gap[t] < CLOSE_M:
            assert statuses[t] == "crowded", t
    # taken back once seen apart 3 frames in a row (the bystander walks 0.077 m a frame)
    assert all(statuses[t] in ("tracked", "reassociated") for t in range(len(subject)) if gap[t] > CLOSE_M + 0.3)
    assert list(statuses.values()).count("reassociated") == 1 and tracker.others_seen >= 1


def test_a_hidden_subject_is_held_then_reassociated_never_replaced_by_the_one_in_front():
    subject, bystander = _crossing(gap=0.42)
    tracker = SubjectTracker(STEP)
    tracker.start(0, subject[0])
    hidden = range(18, 24)   # the bystander in front hides the subject in every view
    statuses = {}
    for t in range(len(subject)):
        found = [Candidate(bystander[t], [None])] + ([] if t in hidden else [Candidate(subject[t], [None])])
        primary = found[0] if t in hidden else Candidate(subject[t], [None])
        statuses[t], chosen = tracker.judge(t, primary, found)
        if chosen is not None:
            assert np.allclose(chosen.centre, subject[t]), t
    assert all(statuses[t] == "crowded" for t in hidden)
    after = min(t for t in range(24, len(subject)) if statuses[t] != "crowded")
    assert statuses[after] == "reassociated" and all(statuses[t] == "tracked" for t in range(after + 1, len(subject)))


def test_two_people_in_the_gate_alike_are_held_colours_decide_when_they_differ():
    tracker = SubjectTracker(STEP)
    tracker.start(0, np.array([0.0, 1.0, 0.0]), [RED] * 3)
    status, chosen = tracker.judge(1, None, [_cand(0.05), _cand(-0.06)])
    assert status == "crowded" and chosen is None
    tracker = SubjectTracker(STEP)
    tracker.start(0, np.array([0.0, 1.0, 0.0]), [RED] * 3)
    status, chosen = tracker.judge(1, None, [_cand(0.05, colour=BLUE), _cand(-0.06, colour=RED)])
    assert status == "tracked" and chosen.centre[0] == pytest.approx(-0.06)


def test_a_person_beyond_what_a_person_can_run_is_not_the_subject_where_someone_else_was_seen():
    tracker = SubjectTracker(STEP)
    tracker.start(0, np.array([0.0, 1.0, 0.0]))
    status, _ = tracker.judge(0, _cand(0.0), [_cand(0.0), _cand(3.0)])   # someone else, far away
    assert status == "tracked" and tracker.others_seen == 1
    status, chosen = tracker.judge(1, _cand(0.5), [_cand(0.5), _cand(3.0)])   # 0.5 m in 40 ms: 12.5 m/s
    assert status == "lost" and chosen is None
    # lost for 4 frames: the gate has grown to 0.15 + 4 x 0.12 m, no other track explains it: re-associated
    for t in (2, 3):
        tracker.judge(t, None, [_cand(3.0)])
    status, chosen = tracker.judge(4, _cand(0.5), [_cand(0.5), _cand(3.0)])
    assert status == "reassociated" and chosen.centre[0] == pytest.approx(0.5)
    # with nobody else ever seen, one person in view is the subject, wherever it went (a cut)
    alone = SubjectTracker(STEP)
    alone.start(0, np.array([0.0, 1.0, 0.0]))
    assert alone.judge(1, _cand(0.9), [_cand(0.9)])[0] == "tracked"


def test_frame_ranges():
    frames = [f"{i:06d}" for i in range(10)]
    assert frame_ranges(frames, ["000003", "000001", "000002", "000007"]) == ["000001-000003", "000007"]
    assert frame_ranges(frames, []) == []


def test_torso_colours_and_centre():
    img = np.zeros((100, 100, 3), np.float32)
    img[:, :, 2] = 1.0                       # blue everywhere ...
    img[30:70, 30:70] = (1.0, 0.0, 0.0)      # ... but a red torso
    K = len(BLAZEPOSE_NAMES)
    xy, conf = np.zeros((1, K, 2)), np.ones((1, K))
    xy[0, [11, 12, 24, 23]] = [(30, 30), (70, 30), (70, 70), (30, 70)]
    h = torso_histograms([img], xy, conf)[0]
    assert h is not None and h.argmax() == RED.argmax() and h.max() == pytest.approx(1.0)
    assert hist_distance([h], RED) == pytest.approx(0.0, abs=1e-6)
    assert hist_distance([h], BLUE) == pytest.approx(1.0)
    conf[0, 11] = 0.0
    assert torso_histograms([img], xy, conf) == [None]
    pts, pconf = np.zeros((K, 3)), np.zeros(K)
    pts[[11, 12, 23, 24]] = [(0, 1.5, 0), (0.4, 1.5, 0), (0, 1.0, 0), (0.4, 1.0, 0)]
    pconf[[11, 12, 23, 24, 0]] = 1
    np.testing.assert_allclose(body_centre(pts, pconf), [0.2, 1.25, 0.0])
    assert body_centre(pts, np.zeros(K)) is None


def _person(centre, rng):
    pts = rng.normal(size=(33, 3)) * [0.08, 0.4, 0.08] + centre
    for k, name in enumerate(BLAZEPOSE_NAMES):   # left points on +x, so the labels are unambiguous
        if "left" in name:
            pts[k, 0] = centre[0] + abs(pts[k, 0] - centre[0]) + 0.1
        elif "right" in name:
            pts[k, 0] = centre[0] - abs(pts[k, 0] - centre[0]) - 0.1
    return pts


def test_track_frame_takes_the_subject_back_from_a_crop_that_saw_the_person_in_front():
    """The crop around the subject holds the bystander, in front of it in the views looking along z: the
    crop observation is the bystander there; the tracker finds both people, keeps the subject and
    leaves out the views where the two overlap."""
    rng = np.random.default_rng(0)
    cams = ring_cameras((0.0, 1.0, 0.0), 4.0, 4, elevations_deg=(0.0,), width=640, height=480)
    subject0 = _person(np.array([0.0, 1.0, 0.0]), rng)
    tri = TriangulateConfig()
    tracker = SubjectTracker(STEP)
    tracker.start(0, body_centre(subject0, np.ones(33)))
    det = BoxPeopleDetector(cams, [subject0], front_in_crop=True, clip=True)
    images = [det.image(c) for c in range(len(cams))]
    obs0 = observe_frame(images, cams, det, tri, "images")
    obs, status = track_frame(tracker, 0, obs0, images, cams, det, tri, "images")
    assert status == "tracked"
    bystander = _person(np.array([0.0, 1.0, 1.3]), rng)   # 1.3 m in front: beyond CLOSE_M
    det = BoxPeopleDetector(cams, [subject0 + [0.01, 0, 0], bystander], front_in_crop=True, clip=True)
    images = [det.image(c) for c in range(len(cams))]
    crop = observe_frame(images, cams, det, tri, "images", prior=obs)
    obs1, status = track_frame(tracker, 1, crop, images, cams, det, tri, "images")
    assert obs1 is not None, status
    centre = body_centre(obs1.points, obs1.points_conf)
    assert np.linalg.norm(centre - body_centre(subject0, np.ones(33))) < 0.1


def test_crossing_scene_plan():
    """``synth --bystander-path cross``: within 0.5 m for a third of the capture, in front of the
    subject (+z) then behind it (-z), the subject's build; ``--bystander-look subject``: its colours."""
    from uvatar.body import load_body_model
    from uvatar.capture.synth.bystanders import CROSS_GAP, cross_offsets
    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import make_plan

    xz = cross_offsets(50)
    gap = np.linalg.norm(xz, axis=1)
    assert (gap <= 0.5).sum() >= 20 and gap[0] > 1.4 and gap[-1] > 1.3
    close = gap <= CROSS_GAP + 1e-9
    assert (xz[close, 1] > 0.3).any() and (xz[close, 1] < -0.3).any()   # in front, then behind
    np.testing.assert_allclose(cross_offsets(50, mirror=True)[:, 0], -xz[:, 0])
    body = load_body_model("anny")
    cfg = preset("quick", frames=30, cameras=4, bystanders=1, bystander_path="cross")
    plan = make_plan(body, cfg)
    other = plan["bystanders"][0]
    near = np.linalg.norm((other["Th"] - plan["Th"])[:, [0, 2]], axis=1)
    assert (near < 0.5).sum() >= 10
    assert np.abs(other["shape"] - plan["shape"]).max() <= 0.04 + 1e-6          # the subject's build
    assert np.linalg.norm(np.diff(plan["Th"][:, [0, 2]], axis=0), axis=1).max() < 0.1   # one take, no jump
    with pytest.raises(ValueError, match="bystander_path"):
        cfg.replace(bystander_path="zigzag")


def test_a_jump_is_reassociated_only_by_build_and_colours_clearly_the_subjects():
    """A cut to another take moves the subject beyond the gate: taken back where its colours are the
    subject's and clearly not the other person's, held where they are alike."""
    for colour, want in ((RED, "reassociated"), (BLUE, "lost")):
        tracker = SubjectTracker(STEP)
        tracker.start(0, np.array([0.0, 1.0, 0.0]), [RED] * 3)
        assert tracker.judge(0, None, [_cand(0.0, colour=RED), _cand(3.0, colour=BLUE)])[0] == "tracked"
        status, chosen = tracker.judge(1, None, [_cand(0.6, colour=colour), _cand(3.0, colour=BLUE)])
        assert status == want and (chosen is not None) == (want == "reassociated"), colour
    # near another person's track (within JUMP_CLEAR gates): never a jump, whatever the colours
    tracker = SubjectTracker(STEP)
    tracker.start(0, np.array([0.0, 1.0, 0.0]), [RED] * 3)
    tracker.judge(0, None, [_cand(0.0, colour=RED), _cand(1.1, colour=BLUE)])
    assert tracker.judge(1, None, [_cand(0.6, colour=RED), _cand(1.1, colour=BLUE)])[0] == "lost"


def test_a_skeleton_either_person_could_be_teaches_no_track():
    """A candidate inside both people's gates (a mix of their keypoints, half way) is ambiguous, and
    the other person's track does not move onto it."""
    tracker = SubjectTracker(STEP)
    tracker.start(0, np.array([0.0, 1.0, 0.0]))
    tracker.judge(0, None, [_cand(0.0), _cand(0.42)])
    other = tracker.others[0]
    status, chosen = tracker.judge(1, None, [_cand(0.21)])
    assert status == "crowded" and chosen is None   # held: within CLOSE_M of the other person too
    assert other.position[0] == pytest.approx(0.42) and other.frame == 0


def test_keypoints_over_another_person_are_left_out_and_a_frame_without_two_clear_views_is_held():
    from uvatar.fit.identity_frame import clear_of_others

    rng = np.random.default_rng(1)
    cams = ring_cameras((0.0, 1.0, 0.0), 4.0, 4, elevations_deg=(0.0,), width=640, height=480)
    subject = _person(np.array([0.0, 1.0, 0.0]), rng)
    det = BoxPeopleDetector(cams, [subject], front_in_crop=True, clip=True)
    images = [det.image(c) for c in range(len(cams))]
    tri = TriangulateConfig()
    obs = observe_frame(images, cams, det, tri, "images")
    far = _person(np.array([2.5, 1.0, 2.5]), rng)
    kept, views = clear_of_others(obs, [(far, np.ones(33))], tri)
    assert views == 4 and (kept.points_conf > 0).sum() == (obs.points_conf > 0).sum()
    # another person 1 m along +z: the views looking along z see them overlap, those along x apart; the
    # one on the +z side sees it in front of the subject (left out), the one on the -z side behind (kept)
    kept, views = clear_of_others(obs, [(subject + [0.0, 0.0, 1.0], np.ones(33))], tri)
    front = np.array([cam.R[2] @ [0.0, 0.0, 1.0] < -0.9 for cam in cams])   # looking along -z: on the +z side
    assert front.sum() == 1 and views == 3
    assert not (kept.conf[front] > 0).any() and (kept.conf[~front] > 0).all()
    ok = kept.points_conf > 0
    assert ok.sum() >= 20 and np.abs(kept.points[ok] - obs.points[ok]).max() < 1e-3
    kept, views = clear_of_others(obs, [(subject + [0.05, 0.0, 0.0], np.ones(33))], tri)   # the same place
    assert views == 0 and not (kept.conf > 0).any()


def test_held_frames_are_reported_and_strict_exits_1(tmp_path, monkeypatch, capsys):
    """``uvatar fit``: the frames where the subject's identity is held are named by range, and
    ``--strict`` fails on them (the fit itself stubbed: its summary as fit_capture returns it)."""
    import uvatar.fit.pipeline as pipeline
    from uvatar.cli.main import main
    from uvatar.fit.identity_frame import identity_report

    frames = [f"{i:06d}" for i in range(10)]
    identity = identity_report(frames, {"lost": ["000002"], "ambiguous": ["000005", "000006"],
                                        "crowded": ["000007"], "reassociated": ["000008"]}, None, 3.0)
    summary = {"frames": 10, "frames_fitted": 6, "source": "images", "frames_without_detection": {},
               "identity": identity}
    monkeypatch.setattr(pipeline, "fit_capture", lambda *a, **k: dict(summary))
    assert identity["held"] == ["000002", "000005-000007"] and identity["held_frames"] == 4
    assert main(["fit", str(tmp_path), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "held in 4 frame(s)" in err and "ambiguous 000005-000006" in err and "crowded" in err and "000007" in err
    assert "re-associated after a gap at frame(s) 000008" in err
    assert main(["fit", str(tmp_path), "--no-progress", "--strict"]) == 1
    assert "--strict: the subject's identity is held" in capsys.readouterr().err
    summary["identity"] = identity_report(frames, {"lost": [], "ambiguous": [], "crowded": [], "reassociated": []},
                                          None, 3.0)
    assert main(["fit", str(tmp_path), "--no-progress", "--strict"]) == 0


def test_a_resumed_fit_holds_the_frames_held_before_and_keeps_their_statuses(tmp_path):
    """A resumed ``uvatar fit`` (its keypoints kept) never re-tracks a frame the run it resumes held
    (its tracker would not know the other people yet) and reports the statuses of the frames it reads
    back; a run under other settings starts over (``identity.json`` is stale with the keypoints)."""
    from uvatar.capture.layout import Capture, write_capture_info
    from uvatar.fit.observe import FrameObservation, observation_path, save_observation
    from uvatar.fit.person import Person
    from uvatar.fit.pipeline import _detect_all
    from uvatar.fit.records import read_identity_record, write_identity_record
    from uvatar.fit.stages import FitStages
    from uvatar.render.cameras import ring_cameras

    frames = [f"{i:06d}" for i in range(4)]
    write_capture_info(tmp_path, frames)
    capture = Capture(tmp_path)
    cams = ring_cameras([0.0, 1.0, 0.0], 3.0, 3, (0.0,), 50.0, 64, 64)
    points = np.random.default_rng(0).normal(size=(33, 3)) * [0.1, 0.5, 0.1] + [0.0, 1.0, 0.0]
    obs = FrameObservation("images", cams, np.zeros((3, 33, 2), np.float32), np.ones((3, 33), np.float32),
                           points.astype(np.float32), np.ones(33, np.float32), np.zeros((3, 33), np.float32))
    for frame in ("000000", "000003"):
        save_observation(observation_path(tmp_path, frame), obs)
    keypoints = observation_path(tmp_path, "-").parent
    write_identity_record(keypoints, {"000001": "crowded", "000002": "lost", "000003": "reassociated"}, 2)
    assert read_identity_record(keypoints)["other_people_seen"] == 2
    chosen = ("000000", Person(points=points, points_conf=np.ones(33)), {"people_found": 2})

    class NoDetector:   # nothing may be detected: every frame is read back or held
        keypoint_names = ()

        def detect(self, *a, **k):
            raise AssertionError("a resumed run detected again")

    observations, failures, person = _detect_all(capture, frames, "images", NoDetector(), FitStages(), False,
                                                 chosen=chosen)
    assert sorted(observations) == ["000000", "000003"]
    assert failures["000001"].startswith("identity crowded") and failures["000002"].startswith("identity lost")
    identity = person["identity"]
    assert identity["held"] == ["000001-000002"] and identity["crowded"] == ["000001"]
    assert identity["reassociated"] == ["000003"] and identity["other_people_seen"] == 2
    assert read_identity_record(tmp_path / "elsewhere") == {"statuses": {}, "other_people_seen": 0}
