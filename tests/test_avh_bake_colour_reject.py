"""The bake's colour check across frames: a frame whose scan texture does not belong to its mesh
(as a volumetric video frame decoded wrong) keeps a normal κ, so the paper's κ rejection passes it;
its colours at the body's refinement points disagree with the other frames' median and it is
rejected (baked into rejected/ with the reason, for its preview). Known answers for the measure."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.bake.photometric import PhotoTarget
from uvatar.avh.bake.refine_together import colour_disagreement, colour_outliers


def test_disagreement_is_the_median_error_over_points_both_know():
    target = PhotoTarget(np.full((5, 3), 0.5), np.array([True, True, True, True, False]), 0.01)
    colours = np.array([[0.6, 0.6, 0.6], [0.5, 0.5, 0.5], [0.8, 0.2, 0.5], [np.nan] * 3, [0.0, 0.0, 0.0]])
    # seen and known: rows 0-2, errors 0.1, 0, 0.2 -> median 0.1 (row 4 is unknown, row 3 unseen)
    assert colour_disagreement(colours, target) == pytest.approx(0.1)
    assert np.isnan(colour_disagreement(np.full((5, 3), np.nan), target))


def test_outliers_are_ratio_times_the_median():
    d = {"000000": 0.02, "000001": 0.025, "000002": 0.03, "000003": 0.2}
    out = colour_outliers(d, 4.0)
    assert list(out) == ["000003"] and "0.200" in out["000003"] and "4 x" in out["000003"]
    assert colour_outliers(d, 0.0) == {} and colour_outliers(dict(list(d.items())[:2]), 4.0) == {}


@pytest.mark.slow
def test_a_frame_with_a_foreign_texture_is_rejected_with_its_reason(tmp_path):
    import imageio.v3 as iio
    from test_avh_bake_helpers import make_capture

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.dataset import read_dataset_info
    from uvatar.avh.bake.pipeline import bake_capture

    cap = make_capture(tmp_path / "cap", n_frames=5, broken=(), fit_noise_deg=1.0)
    images = sorted((cap / "scans").glob("000002*.png"))
    assert images, "the synthetic scan's texture image"
    texture = iio.imread(images[0])
    h, w = texture.shape[:2]
    iio.imwrite(images[0], 255 - np.roll(texture, (h // 3, w // 2), axis=(0, 1)))   # another texture's charts
    cfg = BakeConfig().with_updates(texels=32, visibility_rays=8, pose_refine_iterations=2,
                                    pose_refine_photometric_radii=(0.004,))
    results = bake_capture(cap, tmp_path / "out", cfg, progress=False)
    assert results["000002"].status == "rejected" and results["000002"].reason.startswith("colours disagree")
    assert [f for f, r in results.items() if r.status == "baked"] == ["000000", "000001", "000003", "000004"]
    assert (tmp_path / "out" / "rejected" / "000002.npz").is_file()
    info = read_dataset_info(tmp_path / "out")
    assert "000002" in info["rejected"] and "000002" not in info["frames_baked"]
    # off: the κ rejection alone passes the frame (its κ is normal)
    again = bake_capture(cap, tmp_path / "out", cfg.with_updates(reject_colour_ratio=0.0), progress=False)
    assert again["000002"].status == "baked"
    assert not (tmp_path / "out" / "rejected" / "000002.npz").exists()
