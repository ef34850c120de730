"""``uvatar bake --report``: shares of confident, matched and inpainted texels (known answers on a
hand-made frame), rejected frames with their reasons and a picture of their previews."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.fixtures.fake_baked import make_fake_baked_dataset
from uvatar.avh.bake.report import bake_report, frame_report, rejected_sheet
from uvatar.errors import InputError
from uvatar.io_utils import write_image, write_npz


def test_frame_report_known_shares(tmp_path):
    valid = np.zeros((4, 4), bool)
    valid[:2] = True                     # 8 body texels
    kappa = np.zeros((4, 4), np.float32)
    kappa[0] = 0.9                       # 4 of them confident
    matched = valid.copy()
    matched[1, :2] = False               # 6 matched
    write_npz(tmp_path / "f.npz", kappa=kappa.astype(np.float16), valid=valid, matched=matched)
    r = frame_report(tmp_path / "f.npz")
    assert r["confident_share"] == 0.5 and r["inpainted_share"] == 0.5 and r["matched_share"] == 0.75
    assert r["kappa_mean"] == pytest.approx(0.45, abs=1e-3)


def test_bake_report_lists_rejections_with_pictures(tmp_path):
    root = make_fake_baked_dataset(tmp_path / "baked", num_frames=4)
    info = json.loads((root / "dataset.json").read_text())
    info["frames_baked"] = info["frames_baked"][:3]
    rejected = "000003"
    info["rejected"] = {rejected: "mean kappa 0.31 < 0.51"}
    (root / "rejected").mkdir()
    (root / "frames" / f"{rejected}.npz").rename(root / "rejected" / f"{rejected}.npz")
    write_image(root / "preview" / f"{rejected}.png", np.full((8, 24, 3), 0.5, np.float32))
    (root / "dataset.json").write_text(json.dumps(info))
    report = bake_report(root)
    assert report["frames_baked"] == 3 and report["frames_rejected"] == 1
    assert report["rejected"] == {rejected: "mean kappa 0.31 < 0.51"}
    assert report["frames"][rejected]["status"] == "rejected" and "confident_share" in report["frames"][rejected]
    assert 0.0 <= report["accepted_mean"]["confident_share"] <= 1.0
    sheet = rejected_sheet(report, tmp_path / "r_rejected.png")
    assert sheet and (tmp_path / "r_rejected.png").is_file()
    json.dumps(report)


def test_bake_report_of_nothing_is_one_line(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"texels": 8, "frames_baked": [], "rejected": {}}))
    with pytest.raises(InputError, match="lists no baked or rejected frame"):
        bake_report(tmp_path)
