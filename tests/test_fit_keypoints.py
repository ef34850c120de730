"""The keypoint detector: BlazePose really runs on a studio image and lands on the true joints."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from uvatar.capture import Capture
from uvatar.errors import InputError, MissingDependencyError, UvatarError
from uvatar.fit.keypoints import (
    BLAZEPOSE_NAMES,
    DETECTORS,
    DetectorConfig,
    Keypoints2D,
    load_detector,
)
from uvatar.render.cameras import project_points

# BlazePose landmark -> the anny body's semantic joint (joint centres; BlazePose marks the same joints)
PAIRS = {"left_shoulder": "l_shoulder", "right_shoulder": "r_shoulder", "left_hip": "l_hip",
         "right_hip": "r_hip", "left_knee": "l_knee", "right_knee": "r_knee"}
TOL_PX = 15.0      # any of them, on a 256^2 image where the body is ~180 px tall
MEDIAN_PX = 6.0    # median over the 4 views x 6 joints (measured: ~3.5 px)


@pytest.fixture(scope="module")
def detector():
    det = load_detector("mediapipe")
    yield det
    det.close()


def _true_pixels(root, joints, cam_name, frame="000000", offset=(0.0, 0.0)):
    cam = Capture(root).cameras()[cam_name]
    sem = joints["semantic"]
    pts = np.stack([joints[frame][sem[j]] for j in PAIRS.values()])
    return project_points(cam, pts)[0] + np.asarray(offset)


def _detected(kp: Keypoints2D):
    idx = [BLAZEPOSE_NAMES.index(n) for n in PAIRS]
    return kp.xy[idx], kp.conf[idx]


def test_blazepose_lands_on_true_joints(fit_studio, detector):
    root, joints = fit_studio
    cap = Capture(root)
    errors = []
    for cam in sorted(cap.cameras()):
        kp = detector.detect(cap.load_image(cam, "000000"))
        assert kp.xy.shape == (33, 2) and kp.conf.shape == (33,) and kp.xy.dtype == np.float32
        xy, conf = _detected(kp)
        assert (conf[:4] > 0.5).all(), (cam, conf)   # hips, shoulders (a knee may be hidden in a side view)
        errors.append(np.linalg.norm(xy - _true_pixels(root, joints, cam), axis=1))
    errors = np.concatenate(errors)
    assert errors.max() < TOL_PX and np.median(errors) < MEDIAN_PX, errors


def test_roi_picks_one_of_two_people(fit_studio, detector):
    """Two studio views side by side: the roi picks the right-hand person, coordinates in the full image."""
    root, joints = fit_studio
    cap = Capture(root)
    pair = np.concatenate([cap.load_image("00", "000000"), cap.load_image("02", "000000")], axis=1)
    kp = detector.detect(pair, roi=(256, 0, 512, 256))
    xy, conf = _detected(kp)
    assert (conf[:4] > 0.5).all()
    err = np.linalg.norm(xy - _true_pixels(root, joints, "02", offset=(256.0, 0.0)), axis=1)
    assert err.max() < TOL_PX, err
    left = detector.detect(pair, roi=(0.0, 0.0, 255.5, 256.0))
    err = np.linalg.norm(_detected(left)[0] - _true_pixels(root, joints, "00"), axis=1)
    assert err.max() < TOL_PX, err


def test_no_person_gives_zero_confidence(detector):
    for image in (np.ones((256, 256, 3), np.float32), np.zeros((128, 96, 3), np.float32)):
        kp = detector.detect(image)
        assert not kp.detected and (kp.conf == 0).all() and (kp.xy == 0).all()
    kp = detector.detect(np.ones((64, 64, 3), np.float32), roi=(100, 100, 200, 200))  # roi outside
    assert kp.conf.shape == (33,) and not kp.detected


def test_bad_roi_is_one_line(detector):
    with pytest.raises(InputError, match=r"roi: expected 4 finite numbers"):
        detector.detect(np.zeros((32, 32, 3), np.float32), roi=(0, 0, 10))


def test_missing_extra_names_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)       # import mediapipe -> ImportError
    with pytest.raises(MissingDependencyError, match=r"uvatar\[fit\]"):
        load_detector("mediapipe")


def test_registry_and_config():
    assert "mediapipe" in DETECTORS.names()

    class Fixed:
        name, version, keypoint_names = "fixed", "1", ("a", "b")

        def __init__(self, config):
            self.config = config

        def detect(self, image, roi=None):
            return Keypoints2D(np.ones((2, 2), np.float32), np.ones(2, np.float32))

    DETECTORS.register("fixed-test", Fixed)
    det = load_detector("fixed-test", DetectorConfig(upsample_to=0))
    assert det.config.upsample_to == 0 and det.detect(np.zeros((4, 4, 3))).detected
    with pytest.raises(ValueError, match="unknown keypoint detector"):
        load_detector("nope")
    with pytest.raises(ValueError, match="min_detection_confidence"):
        DetectorConfig(min_detection_confidence=1.5)
    with pytest.raises(ValueError, match="model_complexity"):
        DetectorConfig(model_complexity=3)
    with pytest.raises(UvatarError, match="model_complexity=1"):
        load_detector("mediapipe", DetectorConfig(model_complexity=2))   # heavy: not in the wheel
