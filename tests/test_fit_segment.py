"""Person masks: IoU against the studio's true masks, roi and prior restriction, the real bystander."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from uvatar.capture import Capture
from uvatar.errors import InputError, MissingDependencyError
from uvatar.fit.keypoints import load_detector
from uvatar.fit.segment import SegmenterConfig, load_segmenter, mask_iou, prior_roi

IOU_MIN = 0.93       # every studio view (issue 14's bar is 0.9; measured 0.956 worst, 0.978 mean)
IOU_MEAN = 0.95


@pytest.fixture(scope="module")
def segmenter():
    seg = load_segmenter("mediapipe")
    yield seg
    seg.close()


def _true_mask(cap, cam, frame="000000"):
    return np.asarray(cap.load_mask(cam, frame)) > 0.5


def test_iou_against_true_masks(fit_studio, segmenter):
    root, _ = fit_studio
    cap = Capture(root)
    ious = []
    for cam in sorted(cap.cameras()):
        image = cap.load_image(cam, "000000")
        prob = segmenter.segment(image)
        assert prob.shape == image.shape[:2] and prob.dtype == np.float32 and 0 <= prob.min() <= prob.max() <= 1
        ious.append(mask_iou(segmenter.mask(image), _true_mask(cap, cam)))
    assert min(ious) >= IOU_MIN and np.mean(ious) >= IOU_MEAN, ious


def test_selfie_model_runs(fit_studio):
    root, _ = fit_studio
    cap = Capture(root)
    with load_segmenter("mediapipe", SegmenterConfig(model="selfie")) as seg:
        iou = mask_iou(seg.mask(cap.load_image("00", "000000")), _true_mask(cap, "00"))
    assert iou > 0.8, iou       # measured 0.947 mean: the pose model (default) is better


def test_prior_and_roi_pick_one_person(fit_studio, segmenter):
    """Two studio people side by side: a prior (or roi) on the right one masks only her."""
    root, _ = fit_studio
    cap = Capture(root)
    pair = np.concatenate([cap.load_image("00", "000000"), cap.load_image("02", "000000")], axis=1)
    truth = np.zeros((256, 512), bool)
    truth[:, 256:] = _true_mask(cap, "02")
    prior = np.zeros_like(truth)
    prior[:, 256:] = _true_mask(cap, "02")
    with load_segmenter("mediapipe", SegmenterConfig(prior_dilate_px=6)) as seg:
        right = seg.mask(pair, prior=prior)
    assert not right[:, :256].any() and mask_iou(right, truth) >= IOU_MIN
    by_roi = segmenter.mask(pair, roi=(256, 0, 512, 256))
    assert not by_roi[:, :256].any() and mask_iou(by_roi, truth) >= IOU_MIN
    # the prior restricts: outside it the probability is 0
    tight = np.zeros_like(prior)
    tight[:128, 256:] = True
    assert not segmenter.mask(pair, prior=tight)[128:].any()


def test_empty_inputs_and_bad_prior(segmenter):
    assert not segmenter.mask(np.ones((200, 160, 3), np.float32)).any()
    assert not segmenter.mask(np.ones((64, 64, 3), np.float32), prior=np.zeros((64, 64), bool)).any()
    with pytest.raises(InputError, match="prior mask: shape"):
        segmenter.segment(np.ones((64, 64, 3), np.float32), prior=np.zeros((32, 64), bool))
    assert prior_roi(np.zeros((8, 8), bool), 0.1) is None
    box = np.zeros((100, 200), bool)
    box[10:20, 50:150] = True
    assert prior_roi(box, 0.5) == (0, 5, 200, 25)
    with pytest.raises(ValueError, match="model"):
        SegmenterConfig(model="sam")
    with pytest.raises(ValueError, match="unknown person segmenter"):
        load_segmenter("sam")


def test_missing_extra_names_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)
    with pytest.raises(MissingDependencyError, match=r"uvatar\[fit\]"):
        load_segmenter("mediapipe")


def test_real_recording_bystander(shared_data, segmenter):
    """cam01 of the shared recording: the athlete (centre) and a bystander (left edge). The detector
    picks the athlete; a roi on the bystander finds her instead; a prior from the athlete's keypoints
    keeps the bystander out of the mask."""
    import imageio.v3 as iio

    video = shared_data / "pose2sim_single" / "videos" / "cam01.mp4"
    if not video.is_file():
        pytest.skip(f"{video} not found")
    frame = next(iter(iio.imiter(video))).astype(np.float32) / 255.0      # (1920, 1080, 3)
    with load_detector("mediapipe") as det:
        athlete = det.detect(frame)
        bystander = det.detect(frame, roi=(0, 150, 200, 800))
    hips = athlete.xy[[23, 24]].mean(axis=0)
    assert athlete.conf[[11, 12, 23, 24]].min() > 0.5 and 300 < hips[0] < 600, hips
    seen = bystander.xy[bystander.conf > 0.5]
    assert len(seen) >= 5 and seen[:, 0].max() < 200          # her keypoints, inside the roi
    sure = athlete.xy[athlete.conf > 0.5]
    prior = np.zeros(frame.shape[:2], bool)
    (x0, y0), (x1, y1) = sure.min(0).astype(int) - 60, sure.max(0).astype(int) + 60
    prior[max(y0, 0):y1, max(x0, 0):x1] = True
    mask = segmenter.mask(frame, prior=prior)
    assert mask.sum() > 50_000 and not mask[:, :200].any()   # the athlete, and no bystander pixel
