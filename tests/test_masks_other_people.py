"""Subject masks where another person overlaps the subject (issue 41): a mask that holds more than the
subject (:func:`~uvatar.fit.masks.crowded_mask`) is written empty and recorded in ``masks/views.json``;
DVA never learns from or scores those views (:func:`~uvatar.fit.masks.unusable_views`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.fit.mask_views import crowded_mask, hidden_mask, record_views, unusable_views
from uvatar.fit.masks import MaskConfig


def test_a_mask_with_more_than_the_share_outside_the_fitted_silhouette_is_crowded():
    sil = np.zeros((40, 40), bool)
    sil[10:30, 10:20] = True                              # 200 px
    mask = sil.copy()
    mask[10:30, 20:22] = True                             # 40 px outside: 0.2 of it (clothes, fit error)
    assert not crowded_mask(mask, sil, 0.3)
    mask[10:30, 22:24] = True                             # 80 px: 0.4 (a person beside or in front)
    assert crowded_mask(mask, sil, 0.3) and not crowded_mask(mask, sil, 0.45)
    assert not crowded_mask(mask, np.zeros_like(sil), 0.3)   # no silhouette: nothing to compare with
    hidden = np.zeros_like(sil)
    hidden[10:11, 10:20] = True                           # 10 px of 200: 0.05 of the silhouette
    hidden[10:30, 20:24] = True                           # and someone's hand beside it
    assert hidden_mask(hidden, sil) and not hidden_mask(mask, sil) and not hidden_mask(hidden, np.zeros_like(sil))
    with pytest.raises(ValueError, match="max_outside must be above 0"):
        MaskConfig(max_outside=0.0)


class _Capture:
    def __init__(self, root):
        self.masks_dir = root / "masks"


def _summary(crowded=None, held=(), partial=None, written=()):
    return {"crowded": crowded or {}, "identity_held": list(held), "partial": partial or {},
            "_subject_written": set(written)}


def test_the_views_record_round_trips_and_a_resumed_run_keeps_the_entries_of_the_masks_it_kept(tmp_path):
    cap = _Capture(tmp_path)
    record_views(cap, _summary({"000001": ["c1", "c2"]}, ["c0/000003"], {"000002": ["c0"]},
                                written=["c1/000001", "c2/000001", "c0/000003", "c0/000002"]), rewritten=False)
    record = json.loads((tmp_path / "masks" / "views.json").read_text())
    assert record == {"crowded": ["c1/000001", "c2/000001"], "identity_held": ["c0/000003"],
                      "partial": ["c0/000002"]}
    assert unusable_views(tmp_path) == {("c1", "000001"), ("c2", "000001"), ("c0", "000003")}   # not partial
    # resumed: c1/000001 written again and no longer crowded; the kept masks keep their entries
    record_views(cap, _summary(written=["c1/000001"]), rewritten=False)
    assert unusable_views(tmp_path) == {("c2", "000001"), ("c0", "000003")}
    record_views(cap, _summary(written=["c2/000001"]), rewritten=True)    # --overwrite: this run's alone
    assert unusable_views(tmp_path) == set() and not (tmp_path / "masks" / "views.json").exists()
    assert unusable_views(tmp_path / "elsewhere") == set()              # masks without a record


def test_dva_never_takes_a_view_without_the_subject_as_a_target_and_skips_a_frame_without_any(tmp_path):
    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset
    from uvatar.dva.train import Trainer

    root = write_toy_capture(tmp_path / "cap", frames=3, cameras=4, size=16)
    (root / "masks" / "views.json").write_text(json.dumps({
        "crowded": ["cam01/000000", "cam02/000000", "cam00/000001", "cam01/000001", "cam02/000001"],
        "identity_held": [], "partial": []}))
    src = open_source(root)
    assert ("cam01", "000000") in src.unusable
    trainer = Trainer(src, tmp_path / "run", preset("tiny"), progress=False)
    bank = trainer.bank
    # cam03 is held out: frame 000001 keeps no training view and is skipped; 000000 keeps cam00 alone
    assert bank.frames == ["000000"] and "000001" in bank.skipped
    assert bank.usable.tolist() == [[True, False, False]]
    for _ in range(20):
        frames, cams, *_ = trainer.sample()
        assert all(bank.usable[f, c] for f, c in zip(frames, cams, strict=True))


def _person(centre, rng=None):
    """(33, 3) BlazePose-ordered keypoints of a 1.7 m person standing at ``centre`` (x, z) metres."""
    from uvatar.fit.keypoints import BLAZEPOSE_NAMES

    heights = {"nose": 1.6, "shoulder": 1.4, "elbow": 1.15, "wrist": 0.9, "hip": 0.95, "knee": 0.5,
               "ankle": 0.08, "heel": 0.05, "foot": 0.03, "eye": 1.65, "ear": 1.62, "mouth": 1.55, "pinky": 0.85,
               "index": 0.85, "thumb": 0.87}
    pts = np.zeros((33, 3))
    for k, name in enumerate(BLAZEPOSE_NAMES):
        part = next(p for p in heights if p in name)
        side = 0.18 if "left" in name else -0.18 if "right" in name else 0.0
        pts[k] = (centre[0] + side, heights[part], centre[1])
    return pts


def test_the_other_people_round_trip_and_are_interpolated_between_sightings(tmp_path):
    from uvatar.fit.others import others_at, read_others, write_others

    frames = [f"{i:06d}" for i in range(12)]
    a, b = _person((0.0, 0.0)), _person((0.4, 0.0))
    conf = np.ones(33)
    write_others(tmp_path, {"000002": [(a, conf)], "000006": [(b, conf)], "000011": [(a, conf)]})
    seen = read_others(tmp_path)
    assert sorted(seen) == ["000002", "000006", "000011"]
    np.testing.assert_allclose(seen["000006"][0][0], b, atol=1e-6)
    assert len(others_at(seen, frames, "000002")) == 1                     # seen there
    mid = others_at(seen, frames, "000004")                                # half-way between 2 and 6
    np.testing.assert_allclose(mid[0][0], 0.5 * (a + b), atol=1e-6)
    assert len(others_at(seen, frames, "000000")) == 1                     # 2 frames before a sighting
    write_others(tmp_path, {})
    assert not (tmp_path / "others.npz").exists()                        # nobody seen: no file
    assert read_others(tmp_path) == {} and read_others(tmp_path / "none") == {}
    far = {"000000": [(a, conf)]}
    assert others_at(far, frames, "000011") == []                          # too far from any sighting


def test_a_person_in_front_is_cut_from_the_subject_mask_one_beside_only_outside_its_silhouette():
    from uvatar.fit.masks import MaskConfig, person_mask
    from uvatar.fit.others import other_regions
    from uvatar.render.cameras import ring_cameras

    cam = ring_cameras([0.0, 1.0, 0.0], 4.0, 1, (0.0,), 50.0, 120, 120)[0]      # on +Z, 4 m away
    subject_centre = np.array([0.0, 1.0, 0.0])
    front = other_regions([(_person((0.25, 1.5)), np.ones(33))], cam, subject_centre, (120, 120))
    behind = other_regions([(_person((0.25, -1.0)), np.ones(33))], cam, subject_centre, (120, 120))
    assert front is not None and front[0].any() and not front[1].any()
    assert behind is not None and behind[1].any() and not behind[0].any()
    assert other_regions([], cam, subject_centre, (120, 120)) is None

    class Everyone:   # a segmenter that takes every pixel of the box it is given
        def segment(self, image, roi=None):
            out = np.zeros(image.shape[:2], np.float32)
            x0, y0, x1, y1 = (int(v) for v in roi)
            out[y0:y1 + 1, x0:x1 + 1] = 1.0
            return out

    prior = np.zeros((120, 120), bool)
    prior[20:100, 50:70] = True                                               # the subject's silhouette
    image = np.zeros((120, 120, 3), np.float32)
    config = MaskConfig(dilate=0.05)
    alone = person_mask(image, Everyone(), prior, config)
    cut = person_mask(image, Everyone(), prior, config, others=front)
    assert not (cut & front[0]).any() and (alone & front[0] & prior).any()   # in front: even over the subject
    kept = person_mask(image, Everyone(), prior, config, others=behind)
    assert kept[prior].all() and not (kept & behind[1] & ~prior).any()       # beside/behind: outside it only
