"""``uvatar synth --bystanders N``: other people in the images, the subject's truth unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.synth.config import SynthConfig, preset

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    from uvatar.capture.synth.pipeline import synthesize

    root = tmp_path_factory.mktemp("bystanders") / "cap"
    cfg = preset("quick", frames=3, cameras=4, image_size=96, seed=0, preview=False, bystanders=1)
    synthesize(root, cfg, progress=False)
    return root, cfg


def test_bystanders_change_the_images_not_the_subject(crowd):
    from uvatar.body import load_body_model
    from uvatar.capture.synth.pipeline import make_plan

    root, cfg = crowd
    body = load_body_model("anny")
    alone, with_others = make_plan(body, cfg.replace(bystanders=0)), make_plan(body, cfg)
    for key in ("poses", "Rh", "Th", "shape"):
        np.testing.assert_array_equal(alone[key], with_others[key])      # the subject's truth is the same
    assert alone["bystanders"] == [] and len(with_others["bystanders"]) == 1
    other = with_others["bystanders"][0]
    assert not np.allclose(other["shape"], with_others["shape"])           # another body shape
    assert not np.allclose(other["poses"], with_others["poses"])           # its own motion
    gap = np.linalg.norm((other["Th"] - with_others["Th"].mean(0))[:, [0, 2]], axis=1)
    np.testing.assert_allclose(gap, 1.1, atol=1e-5)                        # on its circle around the subject
    with np.load(root / "gt" / "bystanders.npz") as saved:
        np.testing.assert_array_equal(saved["poses_0"], other["poses"])


def test_masks_are_the_subjects_visible_pixels_only(crowd):
    import imageio.v3 as iio

    from uvatar.capture import Capture

    root, _ = crowd
    cap = Capture(root)
    seen = 0
    for cam in cap.cameras():
        for frame in cap.frames:
            mask = iio.imread(root / "masks" / cam / f"{frame}.png") > 127
            other = iio.imread(root / "gt" / "bystander_masks" / cam / f"{frame}.png") > 127
            assert mask.any() and not (mask & other).any()
            seen += int(other.sum() > 50)
            image = cap.load_image(cam, frame)
            assert (np.abs(image[other] - SynthConfig().background) > 1e-3).any(axis=-1).mean() > 0.9
    assert seen >= 3  # the bystander is in the pictures


def test_negative_bystanders_is_refused():
    with pytest.raises(ValueError, match="bystanders"):
        SynthConfig(bystanders=-1)
