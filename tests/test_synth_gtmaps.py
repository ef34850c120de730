"""Exact gt maps at any resolution: a round trip of the stored gt, the config round trip, and the
eval's reference protocol (exact / native / resampled)."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.synth.config import preset
from uvatar.capture.synth.gtmaps import GtRenderer, config_from_dict
from uvatar.capture.synth.pipeline import synthesize

TINY = dict(frames=2, cameras=0, scan_texture=64, gt_texels=64, seed=3, preview=False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("gtmaps") / "cap"
    synthesize(root, preset("quick", **TINY), progress=False)
    return root


def test_config_round_trip():
    cfg = preset("quick", seed=7, face_count=(1000, 2000))
    assert config_from_dict(cfg.to_dict()) == cfg


def test_render_at_the_gt_resolution_reproduces_the_stored_gt(capture):
    g = GtRenderer(capture, 64).render("000001")
    with np.load(capture / "gt" / "frames" / "000001.npz") as z:
        m = z["mask"]
        assert np.array_equal(g["mask"], m)
        np.testing.assert_allclose(g["texture"][m], z["texture"][m], atol=1e-5)
        np.testing.assert_allclose(g["surface"][m], z["surface"][m], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(g["normal"][m], axis=-1), 1.0, atol=1e-6)
    assert GtRenderer(capture, 64).render("999999") is None


def test_render_at_twice_the_resolution_agrees_with_the_resample_on_smooth_maps(capture):
    from uvatar.avh.bake.evaluate import resample_gt_map

    g = GtRenderer(capture, 128).render("000000")
    with np.load(capture / "gt" / "frames" / "000000.npz") as z:
        surface, ok = resample_gt_map(z["surface"], z["mask"], 128)
    ok &= g["mask"]
    assert ok.sum() > 1000
    err = np.linalg.norm(g["surface"][ok] - surface[ok], axis=-1)
    assert np.median(err) < 0.003                    # the surface is smooth: a few mm at most


def test_gt_source_protocol(capture):
    from uvatar.avh.bake.evaluate import GtSource

    assert GtSource(capture, 128).protocol["reference"] == "exact"
    assert GtSource(capture, 64).protocol["reference"] == "native"
    src = GtSource(capture, 128, "resampled")
    assert src.protocol["reference"] == "resampled" and src.protocol["gt_texels"] == 64
    surface, texture, ok = src.get("000000")
    assert surface.shape == texture.shape == (128, 128, 3) and ok.shape == (128, 128)
    with pytest.raises(ValueError):
        GtSource(capture, 128, "blurry")
