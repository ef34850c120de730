"""DVA evaluation protocols: the source protocol plus the full-image and union-of-masks scores shared
with ``uvatar eval avh``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.eval import EDGE_KEYS, METRIC_KEYS, image_scores
from uvatar.dva.model import preset
from uvatar.dva.train import train_dva


def _pair():
    gt = np.ones((8, 8, 3), np.float32)
    pred = gt.copy()
    pred[:2] = 0.5  # the top 16 pixels are off by 0.5
    alpha = np.zeros((8, 8), np.float32)
    alpha[:2] = 0.9
    return pred, gt, alpha


def test_image_scores_analytic():
    pred, gt, alpha = _pair()
    s = image_scores(pred, gt, alpha, np.zeros((8, 8), bool))
    assert s["psnr_db"] == s["psnr_db_full"] == pytest.approx(10 * np.log10(16), rel=1e-6)  # MSE 16*0.25/64
    assert s["psnr_db_union_mask"] == pytest.approx(10 * np.log10(4), rel=1e-6)  # MSE 0.25 over the union
    assert s["ssim"] == s["ssim_full"] and s["ssim_union_mask"] < s["ssim_full"] < 1


def test_image_scores_union_uses_alpha_threshold_and_gt_mask():
    pred, gt, alpha = _pair()
    alpha[:2] = 0.4  # below 0.5: not predicted foreground
    gt_mask = np.zeros((8, 8), bool)
    gt_mask[:4] = True  # union = top 4 rows, 16 of 32 pixels off by 0.5 -> MSE 0.125
    s = image_scores(pred, gt, alpha, gt_mask)
    assert s["psnr_db_union_mask"] == pytest.approx(10 * np.log10(8), rel=1e-6)
    empty = image_scores(pred, gt, alpha, np.zeros((8, 8), bool))
    assert np.isnan(empty["psnr_db_union_mask"]) and np.isnan(empty["ssim_union_mask"])


def test_image_scores_box_protocol_keeps_psnr_db_inside_the_box():
    pred, gt, alpha = _pair()
    box = np.zeros((8, 8), bool)
    box[:4] = True
    s = image_scores(pred, gt, alpha, np.zeros((8, 8), bool), box)
    assert s["psnr_db"] == pytest.approx(10 * np.log10(8), rel=1e-6)
    assert s["psnr_db_full"] == pytest.approx(10 * np.log10(16), rel=1e-6)


def test_evaluate_dva_reports_both_protocols(tmp_path):
    from uvatar.cli.main import main

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cap = write_toy_capture(tmp_path / "cap", frames=3, cameras=4, size=24)
        run = tmp_path / "run"
        train_dva(open_source(cap), run, preset("tiny"), iters=2, progress=False)
        assert main(["eval", "dva", str(run), str(cap), "--json", str(tmp_path / "m.json")]) == 0
        assert main(["eval", "dva", str(run), str(cap), "--json", str(tmp_path / "m0.json"), "--refine-pose", "0",
                     "--refine-residual", "0", "--report", str(tmp_path / "r" / "eval.html")]) == 0
    finally:
        torch.set_num_threads(n)
    m = json.loads((tmp_path / "m.json").read_text())
    for key in METRIC_KEYS:
        assert np.isfinite(m[key]) and all(key in r for r in m["per_image"])
        assert m[key] == pytest.approx(np.mean([r[key] for r in m["per_image"]]))
    for key in EDGE_KEYS:  # the person-mask scores split at the outline, for the baselines too
        assert all(key in r for r in m["per_image"]) and key in m["baseline_mean_colour"]
        finite = [r[key] for r in m["per_image"] if np.isfinite(r[key])]  # the toy's masks may have no interior
        assert m[key] == pytest.approx(np.mean(finite)) if finite else np.isnan(m[key])
    assert m["psnr_db"] == m["psnr_db_full"] and m["ssim"] == m["ssim_full"]
    assert "union" in m["protocol"] and "alpha > 0.5" in m["protocol"] and "full-image" in m["protocol"]
    # by default each test frame's fit is refined against its driving views first; --refine-pose 0: as it is
    assert m["refine_pose"]["iters"] == 40 and "refined against its driving views (40 steps)" in m["protocol"]
    assert set(m["refine_pose"]["frames"]) == set(m["frames"])
    m0 = json.loads((tmp_path / "m0.json").read_text())
    assert m0["refine_pose"] is None and "the fits as they are" in m0["protocol"]
    # and then a residual of the decoded primitives is fitted to the driving views; --refine-residual 0: none
    assert m["refine_residual"]["iters"] == 60 and "residual of the decoded primitives fitted" in m["protocol"]
    assert set(m["refine_residual"]["frames"]) == set(m["frames"])
    assert all({"loss_before", "loss_after", "kept"} <= set(v) for v in m["refine_residual"]["frames"].values())
    assert m0["refine_residual"] is None and "residual" not in m0["protocol"]
    # the report: the avatar beside its baselines with the JSON's figures, one row an image, its images linked
    page = (tmp_path / "r" / "eval.html").read_text()
    assert "<td>DVA</td>" in page and "<td>mean-colour body</td>" in page and "<td>projective texture</td>" in page
    assert f"<td>{round(m0['psnr_db_person_mask'], 4):.4g}</td>" in page
    assert page.count("<tr><td>0000") == len(m0["per_image"])
    assert all(f'src="../{Path(m0["images"]).name}/{p.name}"' in page for p in Path(m0["images"]).glob("*.png"))
    assert "baseline_projective_texture" in m and np.isfinite(m["baseline_projective_texture"]["psnr_db_full"])


def test_evaluate_dva_named_frames_and_cameras(tmp_path):
    from uvatar.dva.eval import evaluate_dva
    from uvatar.errors import InputError

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cap = write_toy_capture(tmp_path / "cap", frames=3, cameras=4, size=16)
        src = open_source(cap)
        run = tmp_path / "run"
        train_dva(src, run, preset("tiny"), iters=1, progress=False)
        r = evaluate_dva(run, src, None, frames=["000001"], cameras=["cam03"], progress=False)
        assert r["frames"] == ["000001"] and r["cameras"] == ["cam03"] and len(r["per_image"]) == 1
        with pytest.raises(InputError, match="nope"):
            evaluate_dva(run, src, None, cameras=["nope"], progress=False)
    finally:
        torch.set_num_threads(n)


def test_edge_scores_split_the_person_mask_at_its_outline():
    from uvatar.dva.eval import edge_scores
    from uvatar.render.metrics import ssim_map

    gt = np.random.default_rng(0).uniform(0, 1, (40, 40, 3))
    mask = np.zeros((40, 40), bool)
    mask[8:32, 8:32] = True  # 24 px square: a 6 px edge band around a 12 x 12 interior
    alpha = np.where(mask, 1.0, 0.0)
    alpha[mask & ~np.pad(np.ones((12, 12), bool), 14)] = 0.25  # the band half transparent
    s = edge_scores(ssim_map(gt, gt), alpha, mask)
    assert s["ssim_person_edge"] == pytest.approx(1) and s["ssim_person_interior"] == pytest.approx(1)
    assert s["opacity_person_edge"] == pytest.approx(0.25) and s["opacity_person_interior"] == pytest.approx(1)
    worse = gt.copy()
    worse[mask] = 1 - worse[mask]  # the person's colours inverted: structure anti-correlated everywhere inside
    w = edge_scores(ssim_map(worse, gt), alpha, mask)
    assert w["ssim_person_edge"] < 0.5 and w["ssim_person_interior"] < 0
    thin = np.zeros((40, 40), bool)
    thin[10:30, 18:22] = True  # 4 px wide: all edge, no interior
    t = edge_scores(ssim_map(gt, gt), alpha, thin)
    assert np.isnan(t["ssim_person_interior"]) and np.isnan(t["opacity_person_interior"])
    assert t["ssim_person_edge"] == pytest.approx(1)
