"""The bake's fast paths against the computation they replace (issue 27): the scan visibility cast
only where kappa's other factors are not zero, the Warp ray backend (CPU here, CUDA when a GPU is
present) against Embree, and scans read once per worker across the colour rounds and the bake."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_avh_bake_helpers import body, frame_pose, make_capture, offset_scan

import uvatar.avh.bake.frame as frame_module
from uvatar.avh.bake.config import BakeConfig, PoseRefineConfig
from uvatar.avh.bake.frame import BodyLayout, bake_frame, shadow_vertices
from uvatar.capture import BodyFit

R = 48
FAST = BakeConfig(texels=R, visibility_rays=16, refine_pose=False, pose_refine=PoseRefineConfig(iterations=2))


@pytest.fixture(scope="module")
def setup():
    model = body()
    layout = BodyLayout.from_template(model.template, R)
    fit = BodyFit(poses=frame_pose(model, 3), Rh=[0.0, 0.4, 0.0])
    # a scan that leaves part of the body uncovered (cut above the hips): texels without a match,
    # and matches beyond the distance clip, so kappa's other factors are zero on some texels
    scan = offset_scan(model, fit, cut_above=0.9)
    return model, layout, shadow_vertices(model, fit), scan


@pytest.fixture(scope="module")
def baked(setup):
    _, layout, shadow, scan = setup
    return bake_frame(shadow, layout, scan, FAST)


def _assert_same_maps(a, b, atol=0.0):
    for name in ("texture", "displacement", "kappa", "w", "matched", "valid"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=atol, rtol=0, err_msg=name)


def test_scan_visibility_is_cast_only_where_it_changes_kappa(setup, baked, monkeypatch):
    """Reference twin: the scan's visibility on every face (the computation before issue 27)."""
    _, layout, shadow, scan = setup
    culled = baked.stats["rays"]["visibility_scan"]
    every = frame_module.vertex_visibility

    def all_faces(vertices, faces, caster=None, n_rays=64, offset=1e-4, needed=None, stratified=False):
        return every(vertices, faces, caster, n_rays, offset, stratified=stratified)

    monkeypatch.setattr(frame_module, "vertex_visibility", all_faces)
    reference = bake_frame(shadow, layout, scan, FAST)
    _assert_same_maps(baked, reference)
    assert reference.stats["rays"]["visibility_scan"] == len(scan.faces) * FAST.visibility_rays
    assert 0 < culled < 0.8 * reference.stats["rays"]["visibility_scan"]
    assert baked.stats["rays"]["correspond"] == 2 * layout.raster.mask.sum()     # two rays per texel


def test_warp_backend_bakes_the_embree_maps_on_the_cpu(setup, baked):
    pytest.importorskip("warp")
    _, layout, shadow, scan = setup
    warp = bake_frame(shadow, layout, scan, replace(FAST, ray_backend="warp"))
    _assert_warp_parity(baked, warp)


def _assert_warp_parity(embree, warp):
    """float32 BVHs that differ: a texel ray grazing an edge may pick the neighbouring face (same
    point, same colour), and a hemisphere ray grazing a fold may flip (1/16 of one face's visibility)."""
    assert (warp.matched == embree.matched).mean() > 0.999
    both = warp.matched & embree.matched
    assert np.abs(warp.displacement[both] - embree.displacement[both]).max() < 1e-5          # metres
    assert np.abs(warp.texture[both] - embree.texture[both]).mean() < 1e-4
    assert np.abs(warp.kappa - embree.kappa).mean() < 2e-3
    assert np.abs(warp.w - embree.w).mean() < 2e-3


@pytest.mark.gpu
def test_cuda_bake_matches_the_cpu_bake(setup, baked):
    pytest.importorskip("warp")
    _, layout, shadow, scan = setup
    _assert_warp_parity(baked, bake_frame(shadow, layout, scan, replace(FAST, device="cuda")))


@pytest.mark.slow
def test_scans_are_read_once_per_frame_and_bake_the_same_maps(tmp_path, monkeypatch):
    from uvatar.avh.bake.pipeline import bake_capture
    from uvatar.capture import Capture

    cap = make_capture(tmp_path / "cap", n_frames=3, broken=(), fit_noise_deg=1.0)
    cfg = BakeConfig().with_updates(texels=32, visibility_rays=8, pose_refine_iterations=2,
                                    pose_refine_photometric_radii=(0.004, 0.003),
                                    pose_refine_photometric_iterations=2)
    reads: list[str] = []
    load = Capture.load_scan
    monkeypatch.setattr(Capture, "load_scan", lambda self, frame: reads.append(frame) or load(self, frame))
    bake_capture(cap, tmp_path / "kept", cfg, progress=False)
    assert sorted(reads) == ["000000", "000001", "000002"]                 # once each: 3 rounds + bake
    reads.clear()
    bake_capture(cap, tmp_path / "reread", replace(cfg, scan_cache_mb=0), progress=False)
    assert len(reads) == 3 * 4                                             # the reference: every time
    bake_capture(cap, tmp_path / "pool", cfg, workers=2, progress=False)   # one kept pool of 2 workers
    for frame in ("000000", "000001", "000002"):
        with np.load(tmp_path / "kept" / "frames" / f"{frame}.npz") as a, \
                np.load(tmp_path / "reread" / "frames" / f"{frame}.npz") as b, \
                np.load(tmp_path / "pool" / "frames" / f"{frame}.npz") as c:
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
                np.testing.assert_array_equal(a[key], c[key], err_msg=key)


@pytest.mark.slow
@pytest.mark.parametrize("device, backend", [("cpu", "warp"), pytest.param("cuda", "auto", marks=pytest.mark.gpu)])
def test_whole_bake_through_warp_matches_embree(tmp_path, device, backend):
    """The whole bake (geometry round, colour rounds, per-frame bake) with every ray through Warp:
    on the CPU here (the same code as on CUDA but the device), on the GPU where one is present."""
    pytest.importorskip("warp")
    from uvatar.avh.bake.pipeline import bake_capture

    cap = make_capture(tmp_path / "cap", n_frames=3, broken=(), fit_noise_deg=1.0)
    cfg = BakeConfig().with_updates(texels=32, visibility_rays=8, pose_refine_iterations=2,
                                    pose_refine_photometric_radii=(0.004,), pose_refine_photometric_iterations=2)
    bake_capture(cap, tmp_path / "embree", cfg, progress=False)
    bake_capture(cap, tmp_path / "warp", replace(cfg, device=device, ray_backend=backend), progress=False)
    for frame in ("000000", "000001", "000002"):
        with np.load(tmp_path / "embree" / "frames" / f"{frame}.npz") as a, \
                np.load(tmp_path / "warp" / "frames" / f"{frame}.npz") as b:
            np.testing.assert_allclose(b["pose"], a["pose"], atol=1e-3)                 # radians
            assert np.abs(b["kappa"].astype(float) - a["kappa"]).mean() < 5e-3
            assert np.abs(b["displacement"].astype(float) - a["displacement"]).mean() < 1e-4   # metres
            assert np.abs(b["texture"].astype(float) - a["texture"]).mean() < 5e-3
