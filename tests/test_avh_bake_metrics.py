"""The bake's per-texel metrics (shared by the evaluation and its ablation): known answers."""

from __future__ import annotations

import math

import numpy as np

from uvatar.avh.bake.metrics import error_summary, pooled_psnr, texel_errors


def test_texel_errors_known_answer():
    points = np.zeros((2, 2, 3))
    gt_surface = np.zeros((2, 2, 3))
    gt_surface[0, 0] = [0.003, 0.004, 0.0]  # 5 mm
    gt_surface[1, 1] = [0.0, 0.0, 0.002]
    texture = np.full((2, 2, 3), 0.5)
    gt_texture = np.full((2, 2, 3), 0.6)
    score = np.array([[True, True], [False, True]])
    ok = np.array([[True, False], [True, True]])
    err, sq = texel_errors(points, texture, score, gt_surface, gt_texture, ok)
    np.testing.assert_allclose(err, [0.005, 0.002])  # texels (0,0) and (1,1): score & ok
    np.testing.assert_allclose(sq, np.full((2, 3), 0.01))


def test_summaries_known_answer():
    s = error_summary([np.array([0.001, 0.003]), np.array([0.002])])
    assert s["texels"] == 3 and math.isclose(s["median"], 2.0) and math.isclose(s["mean"], 2.0)
    assert math.isclose(s["p90"], 2.8)
    assert error_summary([]) == {"median": None, "mean": None, "p90": None, "texels": 0}
    assert math.isclose(pooled_psnr([np.full((4, 3), 0.01)]), 20.0)
    assert pooled_psnr([]) is None and pooled_psnr([np.zeros((2, 3))]) == math.inf
