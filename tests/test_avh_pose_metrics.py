"""UV-space R² of the pose-dependent part, pose distances and distance bins: known answers."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.pose_metrics import R2Sums, distance_bins, pose_distance_deg


def test_pose_distance_is_the_mean_joint_angle_in_degrees():
    a = np.zeros((1, 9), np.float32)
    b = np.zeros((2, 9), np.float32)
    b[0, 3] = np.radians(30)           # joint 1 turned 30 deg about x
    b[1, 6:9] = np.radians(60) * np.array([0.0, 0.6, 0.8])  # joint 2 turned 60 deg about another axis
    d = pose_distance_deg(a, b, [1, 2])
    assert d.shape == (1, 2)
    assert d[0] == pytest.approx([15.0, 30.0], abs=1e-4)
    assert pose_distance_deg(b, b, [1, 2]).diagonal() == pytest.approx([0, 0], abs=1e-4)
    assert pose_distance_deg(a, b, [0])[0] == pytest.approx([0, 0], abs=1e-6)  # joint 0 is the same


def test_r2_is_one_for_the_truth_zero_for_the_mean_and_pooled_over_frames():
    rng = np.random.default_rng(0)
    sums = R2Sums()
    mask = np.ones((4, 4), bool)
    mask[0] = False
    for _ in range(3):
        gt, mean = rng.random((4, 4, 3)), rng.random((4, 4, 3))
        half = 0.5 * (gt + mean)                 # half-way: error / 2 -> squared error / 4 -> R² 0.75
        frame = sums.add({"truth": gt, "mean": mean, "half": half}, mean, gt, mask)
        assert frame["truth"] == 1.0 and frame["mean"] == 0.0 and frame["half"] == pytest.approx(0.75)
    r2 = sums.r2()
    assert r2["truth"] == 1.0 and r2["mean"] == 0.0 and r2["half"] == pytest.approx(0.75)
    gt = np.zeros((4, 4, 3))
    gt[0] = 100.0  # a texel outside the mask does not count
    assert R2Sums().add({"p": np.zeros((4, 4, 3))}, np.ones((4, 4, 3)), gt, mask)["p"] == 1.0


def test_distance_bins_split_at_the_median():
    per_frame = [{"frame": f, "nearest_training_distance_deg": d, "avh_psnr_db": p}
                 for f, d, p in (("a", 30.0, 20.0), ("b", 5.0, 30.0), ("c", 10.0, 28.0), ("d", 40.0, 18.0))]
    bins = distance_bins(per_frame, ["avh"], keys=("psnr_db",))
    assert [b["bin"] for b in bins] == ["near", "far"]
    assert bins[0]["frames"] == ["b", "c"] and bins[1]["frames"] == ["a", "d"]
    assert bins[0]["avh_psnr_db"] == 29.0 and bins[1]["distance_deg_min"] == 30.0
    assert distance_bins(per_frame[:1], ["avh"], keys=("psnr_db",))[0]["bin"] == "all"
    assert distance_bins([], ["avh"]) == []
