"""The test-time residual of the decoded primitives (:mod:`uvatar.dva.residual`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.dataset import FrameBank
from uvatar.dva.drive import render_camera
from uvatar.dva.features import voxel_uv_grid
from uvatar.dva.model import preset
from uvatar.dva.residual import FrameResidual, ResidualConfig, fit_residual
from uvatar.dva.train import load_run, train_dva

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def toy(tmp_path):
    """(model, body, bank of frame 0 in cam00-03) of a DVA run trained 2 steps on a 4-camera toy capture."""
    cap = write_toy_capture(tmp_path / "cap", frames=2, cameras=4, size=32)
    train_dva(open_source(cap), tmp_path / "run", preset("tiny"), iters=2, progress=False)
    model, body, _, _ = load_run(tmp_path / "run")
    bank = FrameBank(open_source(cap), body, model.image_raster, model.template, ["000000"],
                     ["cam00", "cam01", "cam02", "cam03"], False)
    return model, body, bank


def _uv(model):
    S = model.cfg.decoder.voxels
    return torch.as_tensor(voxel_uv_grid(model.grid.raster, model.template, S, model.cfg.primitives.scale_factor))


def test_colour_logits_sample_the_uv_texture_at_each_voxel_column(toy):
    """A texture that is a linear ramp in u (logit = u) gives each voxel column its own u, in the
    payload's [k, c, z, y, x] layout (bilinear lookups reproduce a linear function exactly away from the
    texture's border), the same at every depth; a constant texture gives the constant everywhere."""
    model = toy[0]
    uv = _uv(model)
    W, S = model.grid.size, model.cfg.decoder.voxels
    res = FrameResidual(uv, W, 64)
    u = (torch.arange(64, dtype=torch.float32) + 0.5) / 64
    with torch.no_grad():
        res.colour.copy_(u.view(1, 1, 1, 64).expand(1, 3, 64, 64))
    logits = res.colour_logits()
    assert logits.shape == (W * W, 3, 1, S, S)
    # payload layout: primitive wy * W + wx, voxel (y, x) <-> slab row wy * S + y, column wx * S + x
    expected = uv[..., 0].reshape(W, S, W, S).permute(0, 2, 1, 3).reshape(W * W, S, S)
    inside = (expected > 0.5 / 64) & (expected < 1 - 0.5 / 64)
    assert inside.float().mean() > 0.5
    torch.testing.assert_close(logits[:, 0, 0][inside], expected[inside], atol=1e-5, rtol=0)
    torch.testing.assert_close(logits[:, 1], logits[:, 0]) and torch.testing.assert_close(logits[:, 2], logits[:, 0])
    with torch.no_grad():
        res.colour.fill_(0.7)
    torch.testing.assert_close(res.colour_logits(), torch.full_like(logits, 0.7))


def test_a_zero_residual_changes_nothing_and_each_part_moves_its_own_quantity(toy):
    model, body, bank = toy
    cam = bank.cams[3]
    center = torch.as_tensor(cam.center, dtype=torch.float32)[None]
    with torch.no_grad():
        out = model(bank.vertices[:1], bank.rotvecs[:1], bank.image_texture(0, [0, 1, 2])[None], center)
    res = FrameResidual(_uv(model), model.grid.size, 32)
    with torch.no_grad():
        same = res(out)
    torch.testing.assert_close(same.payload[:, :, :3], out.payload[:, :, :3].clamp(1e-4, 1 - 1e-4), atol=1e-5, rtol=0)
    assert torch.equal(same.payload[:, :, 3], out.payload[:, :, 3])
    assert torch.equal(same.positions, out.positions) and torch.equal(same.scales, out.scales)
    with torch.no_grad():
        res.colour.fill_(1.0)
        res.translation[:, 2] = 0.01
        res.log_scale.fill_(np.log(2.0))
        moved = res(out)
    rgb = out.payload[:, :, :3].clamp(1e-4, 1 - 1e-4)
    torch.testing.assert_close(moved.payload[:, :, :3], torch.sigmoid(torch.logit(rgb) + 1.0))
    torch.testing.assert_close(moved.positions - out.positions, torch.tensor([0, 0, 0.01]).expand_as(out.positions))
    torch.testing.assert_close(moved.scales, 2 * out.scales)
    assert torch.equal(moved.rotations, out.rotations)


def _seen_through(model, bank, truth):
    """Driving photos (uint8) and masks (alpha > 0.5) of frame 0 in cam00-02, rendered from the avatar
    with the residual ``truth``."""
    photos, masks = [], []
    tex = bank.image_texture(0, [0, 1, 2])
    for cam, bg in zip(bank.cams[:3], bank.backgrounds[:3], strict=True):
        rgb, alpha = render_camera(model, bank.vertices[0], bank.rotvecs[0], tex, cam, bg, truth)
        photos.append((rgb * 255 + 0.5).astype(np.uint8))
        masks.append(alpha > 0.5)
    assert all(m.sum() > 20 for m in masks)
    return photos, masks


def test_a_colour_seen_in_the_driving_views_carries_to_the_held_out_view(toy):
    """Driving views rendered from the avatar with its colour brightened (logits + 1 everywhere): the
    colour residual fitted to them (positions and sizes frozen) lowers their loss, is kept, and brings
    the held-out cam03's render most of the way to the brightened one; the model's weights are
    untouched and train again afterwards; iters 0 fits nothing."""
    model, body, bank = toy
    before = {k: v.clone() for k, v in model.state_dict().items()}
    truth = FrameResidual(_uv(model), model.grid.size, 8)
    with torch.no_grad():
        truth.colour.fill_(1.0)
    photos, masks = _seen_through(model, bank, truth)
    tex = bank.image_texture(0, [0, 1, 2])
    args = (model, bank.vertices[0], bank.rotvecs[0], tex, bank.cams[:3], photos, masks, list(bank.backgrounds[:3]))
    colour_only = ResidualConfig(iters=60, stride=1, uv_resolution=16, lr_position=0.0, lr_scale=0.0, colour_l2=0.0)
    residual, summary = fit_residual(*args, colour_only)
    assert summary["kept"] and summary["loss_after"] < 0.3 * summary["loss_before"]
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert all(p.requires_grad for p in model.parameters())
    assert not any(p.requires_grad for p in residual.parameters())
    cam, bg = bank.cams[3], bank.backgrounds[3]
    plain, alpha = render_camera(model, bank.vertices[0], bank.rotvecs[0], tex, cam, bg)
    fitted, _ = render_camera(model, bank.vertices[0], bank.rotvecs[0], tex, cam, bg, residual)
    target, _ = render_camera(model, bank.vertices[0], bank.rotvecs[0], tex, cam, bg, truth)
    person = alpha > 0.5
    assert person.sum() > 20
    gap_before = np.abs(target[person] - plain[person]).mean()
    assert gap_before > 0.03 and np.abs(target[person] - fitted[person]).mean() < 0.4 * gap_before
    none, nothing = fit_residual(*args, ResidualConfig(iters=0))
    assert none is None and nothing == {"kept": False}


def test_the_primitives_move_to_where_the_driving_views_see_them(toy):
    """Driving views rendered from the avatar itself with every primitive 2 cm along +x (and their
    alpha > 0.5 as the masks): fitted from zero (no prior), the translation moves along +x, not across."""
    model, body, bank = toy
    tex = bank.image_texture(0, [0, 1, 2])
    shift = FrameResidual(_uv(model), model.grid.size, 8)
    with torch.no_grad():
        shift.translation[:, 0] = 0.02
    photos, masks = _seen_through(model, bank, shift)
    args = (model, bank.vertices[0], bank.rotvecs[0], tex, bank.cams[:3], photos, masks, list(bank.backgrounds[:3]))
    cfg = ResidualConfig(iters=100, stride=1, uv_resolution=8, lr_colour=0.0, lr_scale=0.0, lr_position=1e-3,
                          position_weight=0.0)
    residual, summary = fit_residual(*args, cfg)
    assert summary["kept"] and summary["loss_after"] < 0.5 * summary["loss_before"]
    moved = residual.translation.mean(0)
    # half the 2 cm or more for the median primitive (those no view sees stay near zero), little across
    assert 0.006 < float(moved[0]) < 0.03 and float(residual.translation[:, 0].median()) > 0.008
    assert abs(float(moved[1])) < 0.005 and abs(float(moved[2])) < 0.005


def test_a_residual_that_does_not_help_is_not_kept(toy):
    """Steps far too large (a log scale step of 5 per iteration) leave the driving views worse: None."""
    model, body, bank = toy
    args = (model, bank.vertices[0], bank.rotvecs[0], bank.image_texture(0, [0, 1, 2]), bank.cams[:3],
            bank.images[0][:3], bank.masks[0][:3], list(bank.backgrounds[:3]))
    residual, summary = fit_residual(*args, ResidualConfig(iters=3, lr_scale=5.0, lr_position=0.5, lr_colour=0.0))
    assert residual is None and not summary["kept"] and summary["loss_after"] >= summary["loss_before"]


def test_the_prior_on_one_primitive_s_log_scale():
    """Zero residual: zero prior. One corner primitive's log scale 1 on all axes: the quadratic prior
    (mean square 1/K) plus its two grid neighbours' differences (one per axis and channel)."""
    W, S = 4, 2
    uv = torch.rand(W * S, W * S, 2)
    res = FrameResidual(uv, W, 8)
    cfg = ResidualConfig(scale_weight=0.5, smoothness=0.25)
    with torch.no_grad():
        assert float(res.prior(cfg)) == 0.0
        res.log_scale[0] = 1.0
        expected = 0.5 / (W * W) + 0.25 * 2 / ((W - 1) * W)
        assert float(res.prior(cfg)) == pytest.approx(expected, rel=1e-6)


def test_drive_sequence_fits_a_residual_only_when_asked(tmp_path):
    """render dva's driving: refine_residual = 0 renders as before the option; a few steps change it."""
    from uvatar.dva.drive import drive_sequence

    cap = write_toy_capture(tmp_path / "cap", frames=1, cameras=4, size=24)
    train_dva(open_source(cap), tmp_path / "run", preset("tiny"), iters=2, progress=False)
    model, body, _, _ = load_run(tmp_path / "run")
    src = open_source(cap)
    args = (model, body, src, ["000000"], ["cam00", "cam01"], src.cameras["cam03"])
    plain = drive_sequence(*args, progress=False)
    again = drive_sequence(*args, progress=False, refine_residual=0)
    fitted = drive_sequence(*args, progress=False, refine_residual=10)
    assert np.array_equal(plain[0], again[0]) and np.abs(fitted[0] - plain[0]).max() > 1e-3
