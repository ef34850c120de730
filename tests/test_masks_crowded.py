"""Subject masks where another person overlaps the subject (issue 41): a mask that holds more than the
subject (:func:`~uvatar.fit.masks.crowded_mask`) is written empty and recorded in ``masks/views.json``;
DVA never learns from or scores those views (:func:`~uvatar.fit.masks.unusable_views`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.fit.masks import MaskConfig, _record_views, crowded_mask, unusable_views


def test_a_mask_with_more_than_the_share_outside_the_fitted_silhouette_is_crowded():
    sil = np.zeros((40, 40), bool)
    sil[10:30, 10:20] = True                              # 200 px
    mask = sil.copy()
    mask[10:30, 20:22] = True                             # 40 px outside: 0.2 of it (clothes, fit error)
    assert not crowded_mask(mask, sil, 0.3)
    mask[10:30, 22:24] = True                             # 80 px: 0.4 (a person beside or in front)
    assert crowded_mask(mask, sil, 0.3) and not crowded_mask(mask, sil, 0.45)
    assert not crowded_mask(mask, np.zeros_like(sil), 0.3)   # no silhouette: nothing to compare with
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
    _record_views(cap, _summary({"000001": ["c1", "c2"]}, ["c0/000003"], {"000002": ["c0"]},
                                written=["c1/000001", "c2/000001", "c0/000003", "c0/000002"]), rewritten=False)
    record = json.loads((tmp_path / "masks" / "views.json").read_text())
    assert record == {"crowded": ["c1/000001", "c2/000001"], "identity_held": ["c0/000003"],
                      "partial": ["c0/000002"]}
    assert unusable_views(tmp_path) == {("c1", "000001"), ("c2", "000001"), ("c0", "000003")}   # not partial
    # resumed: c1/000001 written again and no longer crowded; the kept masks keep their entries
    _record_views(cap, _summary(written=["c1/000001"]), rewritten=False)
    assert unusable_views(tmp_path) == {("c2", "000001"), ("c0", "000003")}
    _record_views(cap, _summary(written=["c2/000001"]), rewritten=True)   # --overwrite: this run's alone
    assert unusable_views(tmp_path) == set()
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
