"""Person masks restricted to the fitted body, the per-frame keypoint files, surface sampling."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.types import Camera
from uvatar.errors import InputError
from uvatar.fit.masks import MaskConfig, person_mask
from uvatar.fit.observe import FrameObservation, load_observation, person_roi, save_observation
from uvatar.geometry.sampling import sample_surface


class BlobSegmenter:
    """Two 'people': a blob at the left (the captured person) and one at the right (a bystander)."""

    def __init__(self, h=60, w=100):
        self.prob = np.zeros((h, w), np.float32)
        self.prob[10:50, 10:30] = 0.9
        self.prob[10:50, 70:90] = 0.95
        self.rois = []

    def segment(self, image, roi=None):
        self.rois.append(roi)
        out = np.zeros_like(self.prob)
        if roi is None:
            return self.prob.copy()
        x0, y0, x1, y1 = (int(v) for v in roi)
        out[y0:y1 + 1, x0:x1 + 1] = self.prob[y0:y1 + 1, x0:x1 + 1]
        return out


def test_person_mask_keeps_the_fitted_person_and_drops_the_bystander():
    seg = BlobSegmenter()
    image = np.zeros((60, 100, 3), np.float32)
    prior = np.zeros((60, 100), bool)
    prior[14:46, 13:27] = True  # the fitted body: a little inside the person's outline
    mask = person_mask(image, seg, prior, MaskConfig(dilate=0.1))
    assert mask[10:50, 10:30].all()            # the whole person, clothes beyond the body included
    assert not mask[:, 60:].any()              # never the bystander
    assert mask.sum() == 40 * 20
    x0, y0, x1, y1 = seg.rois[-1]
    assert x1 < 70                             # the segmenter only searched around the person


class TouchingDetector:
    """A second person standing right against the first one (x 30..50): BlazePose-like keypoints,
    found only where the image was not painted over."""

    def detect(self, image, roi=None):
        from uvatar.fit.keypoints import Keypoints2D

        xy = np.zeros((33, 2), np.float32)
        conf = np.zeros(33, np.float32)
        for k, (x, y) in {0: (40, 12), 11: (33, 18), 12: (45, 18), 23: (33, 32), 24: (45, 32), 25: (33, 40),
                          26: (45, 40), 27: (33, 48), 28: (45, 48)}.items():
            xy[k], conf[k] = (x, y), 0.9
        return Keypoints2D(xy, conf)


def test_another_person_in_the_grown_band_is_dropped_the_fitted_body_kept():
    seg = BlobSegmenter()
    seg.prob[10:50, 30:50] = 0.9                       # the second person touches the first one
    image = np.zeros((60, 100, 3), np.float32)
    prior = np.zeros((60, 100), bool)
    prior[14:46, 13:29] = True
    config = MaskConfig(dilate=0.1)
    leaky = person_mask(image, seg, prior, config)
    assert leaky[20:40, 30:34].all()                  # without the detector: the band takes them in
    mask = person_mask(image, seg, prior, config, TouchingDetector())
    assert not mask[20:40, 30:34].any() and mask[prior].all() and mask[10:50, 10:13].all()


def test_person_mask_without_prior_takes_the_largest_person_and_empty_prior_gives_empty():
    seg = BlobSegmenter()
    image = np.zeros((60, 100, 3), np.float32)
    mask = person_mask(image, seg, None, MaskConfig())
    assert mask.sum() == 40 * 20 and mask[20, 15]  # both blobs are the same size: one of them, whole
    assert not person_mask(image, seg, np.zeros((60, 100), bool), MaskConfig()).any()


@pytest.mark.parametrize("kwargs", [{"threshold": 0.0}, {"threshold": 1.0}, {"dilate": -0.1}, {"render_width": 8}])
def test_mask_config_bounds(kwargs):
    with pytest.raises(ValueError):
        MaskConfig(**kwargs)


def _camera(name="c0"):
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    return Camera(name=name, K=K, R=np.eye(3), T=np.array([0.0, 0.0, 3.0]), width=100, height=80,
                  dist=np.array([0.01, -0.002, 0.0, 0.0, 0.0]))


def test_person_roi_boxes_the_projected_keypoints():
    cam = _camera()
    pts = np.array([[-0.3, -0.6, 0.0], [0.3, -0.6, 0.0], [-0.3, 0.6, 0.0], [0.3, 0.6, 0.0], [0, 0, 0]])
    conf = np.ones(5, np.float32)
    dist0 = Camera(name="c", K=cam.K, R=cam.R, T=cam.T, width=100, height=80)
    x0, y0, x1, y1 = person_roi(pts, conf, dist0, margin=0.0)
    # x = 49.5 +- 100 * 0.3 / 3, y = 39.5 +- 100 * 0.6 / 3
    assert np.allclose([x0, y0, x1, y1], [39.5, 19.5, 59.5, 59.5], atol=1e-6)
    assert person_roi(pts, np.zeros(5, np.float32), cam) is None  # nothing confident


def test_observation_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    cams = [_camera("a"), _camera("b")]
    obs = FrameObservation(source="images", cameras=cams, xy=rng.random((2, 33, 2), dtype=np.float32),
                           conf=rng.random((2, 33), dtype=np.float32), points=rng.random((33, 3), dtype=np.float32),
                           points_conf=rng.random(33, dtype=np.float32),
                           reprojection_px=rng.random((2, 33), dtype=np.float32), redetected=("b",))
    path = tmp_path / "k" / "000000.npz"
    save_observation(path, obs)
    back = load_observation(path)
    assert back.source == "images" and back.redetected == ("b",)
    assert [c.name for c in back.cameras] == ["a", "b"]
    for c0, c1 in zip(cams, back.cameras, strict=True):
        assert np.allclose(c0.K, c1.K) and np.allclose(c0.dist, c1.dist) and (c0.width, c0.height) == (c1.width, c1.height)
    for key in ("xy", "conf", "points", "points_conf", "reprojection_px"):
        assert np.array_equal(getattr(obs, key), getattr(back, key))
    with pytest.raises(InputError, match="missing"):
        load_observation(tmp_path / "nope.npz")
    np.savez(tmp_path / "bad.npz", xy=np.zeros(3))
    with pytest.raises(InputError, match="missing array"):
        load_observation(tmp_path / "bad.npz")


def test_sample_surface_is_on_the_mesh_and_uniform_by_area():
    # two triangles in the z = 0 plane with areas 1.5 and 0.5 (ratio 3)
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 1.5, 0], [0, 1, 0]], float)
    v[3] = [0, 0.5, 0]
    f = np.array([[0, 1, 2], [0, 2, 3]])
    a0 = 0.5 * 2 * 1.5
    a1 = 0.5 * np.linalg.norm(np.cross(v[2] - v[0], v[3] - v[0]))
    pts, normals = sample_surface(v, f, 20000, seed=1)
    assert np.allclose(pts[:, 2], 0) and np.allclose(normals, [0, 0, 1])
    in_first = pts[:, 1] <= 0.75 * pts[:, 0] + 1e-6  # below the diagonal (0,0)-(2,1.5)
    assert abs(in_first.mean() - a0 / (a0 + a1)) < 0.01
    assert np.array_equal(pts, sample_surface(v, f, 20000, seed=1)[0])  # deterministic
    with pytest.raises(InputError):
        sample_surface(v, np.zeros((0, 3), int), 10)


def test_continuity_cuts_where_the_person_jumps():
    from uvatar.fit.sequence import continuity

    T, K = 6, 10
    pts = np.zeros((T, K, 3))
    pts[:, :, 0] = np.arange(T)[:, None] * 0.05           # walking 5 cm per frame
    pts[4:, :, 2] += 2.0                                  # frame 4 is another take, 2 m away
    conf = np.ones((T, K))
    conf[2] = 0                                           # frame 2 undetected: bridged
    assert continuity(pts, conf, 0.2).tolist() == [True, True, True, False, True]
