"""The body fit's silhouette term (``uvatar fit --masks``): inside the mask and out to its outline."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.capture.types import Camera
from uvatar.fit.losses import MaskTerm
from uvatar.fit.projection import camera_tensors

# a camera 2 m above the plane z = 0, looking at it: world (x, y, 0) -> pixel (32 + 50 x, 32 + 50 y)
CAM = Camera(name="top", K=[[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]], T=[0.0, 0.0, 2.0], width=64, height=64)
MASK = np.zeros((64, 64), bool)
MASK[16:48, 16:48] = True                                   # pixels 16..47: world x, y in [-0.33, 0.31]


def _square(half: float, n: int = 25, shift=(0.0, 0.0)) -> torch.Tensor:
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g + shift[0], g + shift[1])
    return torch.tensor(np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1), dtype=torch.float32)[None]


def _term(frames: int = 1) -> MaskTerm:
    return MaskTerm([[MASK]] * frames, camera_tensors([CAM]), np.arange(25 * 25), "cpu", outline_points=64)


def test_a_body_that_fills_its_mask_costs_nothing_both_ways():
    term = _term()
    full = _square(0.31)                                    # up to half a pixel (1 cm) from the outline pixels
    cost = float(term(full, 0.05))
    assert cost < 3e-4 and float(term(_square(0.15), 0.05)) > 10 * cost


def test_a_body_short_of_the_outline_costs_only_with_the_outline_half():
    term = _term()
    small = _square(0.15)                                   # well inside: the inside half is exactly 0
    assert float(term(small, 0.05, outline_weight=0.0)) == 0.0
    assert float(term(small, 0.05)) > 1e-3
    outside = _square(0.31, shift=(0.2, 0.0))               # 10 px out of the mask
    assert float(term(outside, 0.05, outline_weight=0.0)) > 3e-4


def test_the_outline_half_grows_a_shrunken_body_to_its_mask():
    term = _term()
    base = _square(0.15)
    for outline, want in ((1.0, 0.31 / 0.15), (0.0, 1.0)):
        scale = torch.ones(1, requires_grad=True)
        opt = torch.optim.Adam([scale], lr=0.02)
        for _ in range(300):
            opt.zero_grad()
            term(base * scale, 0.5, outline_weight=outline).sum().backward()
            opt.step()
        assert scale.item() == pytest.approx(want, rel=0.05), outline


def test_frames_without_a_mask_cost_nothing():
    term = MaskTerm([[MASK], [None]], camera_tensors([CAM]), np.arange(25 * 25), "cpu", outline_points=64)
    cost = term(torch.cat([_square(0.15), _square(0.15)]), 0.05)
    assert cost.shape == (2,) and float(cost[0]) > 1e-3 and float(cost[1]) == 0.0


def test_cameras_of_different_sizes_all_count():
    """A real rig mixes sizes (Pose2Sim's cameras decode 1080 and 1088 wide): every camera's mask counts,
    in its own pixel coordinates."""
    from dataclasses import replace

    wide = replace(CAM, name="wide", width=80)
    mask_wide = np.zeros((64, 80), bool)
    mask_wide[16:48, 16:48] = True                           # the same square: the same world extent
    term = MaskTerm([[MASK, mask_wide]], camera_tensors([CAM, wide]), np.arange(25 * 25), "cpu", outline_points=64)
    assert term.valid.tolist() == [[1.0, 1.0]]
    assert float(term(_square(0.31), 0.05)) < 3e-4          # fills both masks
    only_wide = MaskTerm([[None, mask_wide]], camera_tensors([CAM, wide]), np.arange(25 * 25), "cpu",
                         outline_points=64)
    assert float(only_wide(_square(0.15), 0.05)) > 1e-3      # the wider camera alone still pulls
