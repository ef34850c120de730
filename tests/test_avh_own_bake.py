"""R² against each frame's own bake and the bake's ceiling: known answers."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.data import BakedFrames
from uvatar.avh.own_bake import OwnBake, clean_displacements, r2_against_own_bake
from uvatar.avh.pose_metrics import R2Sums


def _frames(displacement, valid):
    n, r = displacement.shape[:2]
    ones = np.ones((n, r, r), np.float32)
    return BakedFrames(names=[str(i) for i in range(n)], texture=np.zeros((n, r, r, 3), np.float32),
                       displacement=displacement.astype(np.float32), kappa=ones, w=ones, valid=valid,
                       poses=np.zeros((n, 3), np.float32), Rh=np.zeros((n, 3), np.float32),
                       Th=np.zeros((n, 3), np.float32))


def test_clean_displacements_zeroes_outliers_and_texels_outside_the_charts():
    d = np.full((2, 3, 3, 3), 0.01)
    d[0, 1, 1, 2] = -0.07          # one axis beyond 5 cm: an outlier
    valid = np.ones((2, 3, 3), bool)
    valid[1, 0, 0] = False
    out, kept = clean_displacements(_frames(d, valid), 0.05)
    assert kept.sum() == 16 and not kept[0, 1, 1] and not kept[1, 0, 0]
    assert np.all(out[~kept] == 0) and np.allclose(out[kept], 0.01)


def test_r2_against_own_bake_known_answers_and_masks():
    rng = np.random.default_rng(1)
    R = 4
    mean_t, mean_d = rng.random((R, R, 3)), rng.normal(size=(R, R, 3)) * 0.01
    own_t, own_d = rng.random((R, R, 3)), rng.normal(size=(R, R, 3)) * 0.01
    kappa, kept = np.ones((R, R)), np.ones((R, R), bool)
    kappa[0, 0], kept[1, 1] = 0.2, False
    # a texel the own bake is not confident about does not count, whatever its value
    own_t[0, 0], own_d[1, 1] = 50.0, 50.0
    own = OwnBake(texture=own_t, displacement=own_d, kappa=kappa, kept=kept, valid=np.ones_like(kept))
    base = rng.normal(size=(R, R, 3))

    def surface(d):  # the posed body's texel points plus the displacement, as the runtime re-poses it
        return base + (0.0 if d is None else d)

    maps = {"own": (own_t, own_d), "mean": (mean_t, mean_d),
            "half": (0.5 * (own_t + mean_t), 0.5 * (own_d + mean_d))}
    sums = {"texture": R2Sums(), "displacement": R2Sums()}
    confident = np.ones((R, R), bool)
    confident[3, 3] = False
    frame = r2_against_own_bake(maps, own, mean_t, mean_d, confident, surface, sums)
    for kind in ("texture", "displacement"):
        assert frame[f"own_{kind}_r2_vs_bake"] == pytest.approx(1.0)
        assert frame[f"mean_{kind}_r2_vs_bake"] == pytest.approx(0.0)
        assert frame[f"half_{kind}_r2_vs_bake"] == pytest.approx(0.75)  # half the error: a quarter of the SSE
        assert sums[kind].r2()["half"] == pytest.approx(0.75)
    # a method that is wrong only at the masked-out texels is perfect
    wrong_t, wrong_d = own_t.copy(), own_d.copy()
    wrong_t[3, 3], wrong_d[3, 3] = -9.0, -9.0
    frame = r2_against_own_bake({"w": (wrong_t, wrong_d)}, own, mean_t, mean_d, confident, surface,
                                {"texture": R2Sums(), "displacement": R2Sums()})
    assert frame["w_texture_r2_vs_bake"] == pytest.approx(1.0) and frame["w_displacement_r2_vs_bake"] == pytest.approx(1.0)
