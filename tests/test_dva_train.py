"""DVA training, checkpoint/resume, driving, evaluation and the CLI on a tiny toy capture."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.losses import EMPTY_OPACITY
from uvatar.dva.model import preset
from uvatar.dva.train import CHECKPOINT, Trainer, load_run, train_dva
from uvatar.dva.train_step import patch_pixels, target_pixels
from uvatar.errors import InputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dva") / "cap", frames=3, cameras=4, size=24)


def test_patch_pixels_stay_in_the_image():
    import random

    mask = np.zeros((20, 30), bool)
    mask[15:20, 25:30] = True
    pix = patch_pixels(mask, 8, random.Random(0))
    assert pix.shape == (64, 2) and pix[:, 0].max() <= 29 and pix[:, 1].max() <= 19
    assert len({tuple(p) for p in pix}) == 64


def test_a_kept_mask_box_draws_the_crops_the_mask_draws():
    """The bank's :func:`mask_box` is the mask's bounding box (rows, columns of its pixels; None when
    empty), and crops drawn with it are the crops drawn from the mask itself, for the same random state."""
    import random

    from uvatar.dva.dataset import mask_box

    rng = np.random.default_rng(3)
    for mask in (rng.random((40, 50)) > 0.97, np.zeros((40, 50), bool), np.eye(40, 50, 7, bool)):
        ys, xs = np.nonzero(mask)
        box = mask_box(mask)
        assert box == ((int(ys.min()), int(ys.max()), int(xs.min()), int(xs.max())) if ys.size else None)
        a, b = random.Random(5), random.Random(5)
        for _ in range(4):
            assert np.array_equal(patch_pixels(mask, 12, a), patch_pixels(mask, 12, b, box))


def test_target_pixels_put_the_background_colour_outside_the_mask():
    """'mask': a cluttered room outside the person's mask becomes the colour the render is composited
    over; inside the mask (and everywhere with 'photo') the photo's own values, scaled to [0, 1]."""
    from uvatar.dva.model import TrainConfig

    image = np.zeros((4, 5, 3), np.uint8)
    image[..., 0] = 255  # a red room
    image[1:3, 1:3] = (0, 51, 102)  # the person
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:3] = True
    pix = np.array([[1, 1], [2, 2], [0, 0], [4, 3]])  # (x, y): two inside, two outside
    bg = np.array([0.25, 0.5, 0.75], np.float32)
    got = target_pixels(image, mask, pix, bg, "mask")
    np.testing.assert_allclose(got, [[0, 0.2, 0.4], [0, 0.2, 0.4], bg, bg], atol=1e-6)
    np.testing.assert_allclose(target_pixels(image, mask, pix, bg, "photo")[2:], [[1, 0, 0], [1, 0, 0]])
    assert TrainConfig().background == "mask"
    with pytest.raises(ValueError, match="background"):
        TrainConfig(background="room")


def test_an_empty_avatar_is_said(caplog):
    """The run's summary: the mean opacity inside the masks over the last logged steps, and ``empty``
    with a warning naming the flags when it is below EMPTY_OPACITY; nothing logged: None."""
    import logging

    from uvatar.dva.train import _emptiness

    assert _emptiness([], 10) == {"opacity_in_mask": None, "empty": None}
    with caplog.at_level(logging.WARNING):
        assert _emptiness([0.8, 0.9], 1200) == {"opacity_in_mask": 0.85, "empty": False}
        assert not caplog.records
        assert _emptiness([0.0, 0.02, 0.01], 1200) == {"opacity_in_mask": 0.01, "empty": True}
    assert "empty at step 1200" in caplog.text and "--seed" in caplog.text


def test_scale_correctives_never_shrink_a_primitive_below_touching_its_neighbours():
    """Under a push of constant sign (the volume prior alone; on a real capture the image losses did
    the same) Adam drives every scale corrective to its lower bound within tens of steps, where the
    clamp takes the gradient. The bound is -log(scale_factor): the boxes still touch (their
    half-extents are the rest half-spacing), so the body stays covered; with 0 they keep their rest size
    and overlap. Runs saved before the option keep -2."""
    import torch

    from uvatar.dva.decoders import MotionDecoder
    from uvatar.dva.model import DvaConfig
    from uvatar.dva.primitives import PrimitiveConfig, apply_correctives

    W, B = 4, 2
    features = torch.randn(B, 8, W, W, generator=torch.Generator().manual_seed(0))

    def pushed(cfg):
        rest = torch.full((W * W, 3), 0.01 * cfg.scale_factor)
        torch.manual_seed(0)
        motion = MotionDecoder(8, W, 16)
        opt = torch.optim.Adam(motion.parameters(), lr=2e-3)
        for _ in range(100):
            _, _, scales = apply_correctives(torch.zeros(B, W * W, 3), torch.eye(3).expand(B, W * W, 3, 3), rest,
                                             motion(features), cfg, True)
            opt.zero_grad()
            (0.01 * (scales.prod(-1) / rest.prod(-1)).mean()).backward()
            opt.step()
        return scales

    cfg = PrimitiveConfig()
    assert cfg.scale_corrective_bounds == (pytest.approx(-np.log(cfg.scale_factor)), 1.0)
    scales = pushed(cfg)
    assert torch.allclose(scales, torch.full_like(scales, 0.01), rtol=1e-5)   # exactly touching
    scales = pushed(PrimitiveConfig(min_scale_corrective=0.0))                # 0: never below the rest size,
    assert torch.allclose(scales, torch.full_like(scales, 0.015), rtol=1e-5)  # half a spacing of overlap
    old = preset("tiny").to_dict()
    del old["primitives"]["min_scale_corrective"]
    assert DvaConfig.from_dict(old).primitives.scale_corrective_bounds == (-2.0, 1.0)


def test_motion_prior_pulls_a_runaway_corrective_back():
    """Past its bound a corrective passes no gradient (tanh saturates, the scale clamp cuts it): the
    volume prior alone leaves a runaway motion branch where it is (on the real recording it reached raw
    values in the thousands and the avatar vanished). The motion prior's pull on the raw values brings
    it back into range. Runs saved before the prior keep it off."""
    import torch

    from uvatar.dva.decoders import MotionDecoder
    from uvatar.dva.losses import DvaLoss, LossConfig
    from uvatar.dva.model import DvaConfig
    from uvatar.dva.primitives import PrimitiveConfig, apply_correctives

    W, B = 4, 2
    cfg = PrimitiveConfig()
    features = torch.randn(B, 8, W, W, generator=torch.Generator().manual_seed(0))
    rest = torch.full((W * W, 3), 0.01)
    eye = torch.eye(3).expand(B, W * W, 3, 3)
    img = torch.zeros(1, 3, 8, 8)
    ones = torch.ones(1, 8, 8)

    def run(motion_weight):
        torch.manual_seed(0)
        motion = MotionDecoder(8, W, 16)
        with torch.no_grad():
            motion.tail.bias.fill_(-50.0)  # ran away: every corrective far past its bound
        opt = torch.optim.Adam(motion.parameters(), lr=2e-2)
        loss = DvaLoss(LossConfig(motion=motion_weight))
        for _ in range(300):
            raw = motion(features)
            _, _, scales = apply_correctives(torch.zeros(B, W * W, 3), eye, rest, raw, cfg, True)
            total, terms = loss(img, img, ones, ones, scales, rest, raw)
            opt.zero_grad()
            total.backward()
            opt.step()
        return raw.detach(), terms

    stuck, terms = run(0.0)
    assert "motion" not in terms and stuck.max() < -40    # no gradient reaches it: still far out
    back, terms = run(0.01)
    assert terms["motion"] > 0 and back.abs().max() < 1.0  # pulled back into the corrective's range
    old = DvaConfig().to_dict()
    del old["loss"]["motion"]
    assert DvaConfig.from_dict(old).loss.motion == 0.0
    del old["loss"]["colour_tv"]                            # and before the colour smoothness: off too
    assert DvaConfig.from_dict(old).loss.colour_tv == 0.0 < DvaConfig().loss.colour_tv


def test_colour_total_variation_counts_seams_between_primitives():
    """One primitive of a 2x2 grid (S = 2) unlike the rest: its seam with its two neighbours is the whole
    variation, 1/6 across each texel axis of the slab and none in depth; a flat payload has none. The
    term joins the loss only with its weight."""
    import torch

    from uvatar.dva.losses import DvaLoss, LossConfig, slab_total_variation

    colour = torch.zeros(1, 4, 3, 2, 2, 2)
    assert float(slab_total_variation(colour)) == 0.0
    colour[:, 2] = 1.0
    assert float(slab_total_variation(colour)) == pytest.approx(1 / 3)
    img, ones = torch.zeros(1, 3, 8, 8), torch.ones(1, 8, 8)
    scales = rest = torch.full((1, 4, 3), 0.01)
    _, off = DvaLoss(LossConfig(colour_tv=0.0))(img, img, ones, ones, scales, rest[0], None, colour)
    total, on = DvaLoss(LossConfig(colour_tv=0.5))(img, img, ones, ones, scales, rest[0], None, colour)
    assert "colour_tv" not in off and on["colour_tv"] == pytest.approx(1 / 3)
    colour.requires_grad_(True)
    DvaLoss(LossConfig(colour_tv=0.5))(img, img, ones, ones, scales, rest[0], None, colour)[0].backward()
    assert colour.grad[0, 2].abs().sum() > 0                 # the odd primitive is pulled toward the rest


def test_column_spread_known_answers_gradcheck_and_weight():
    """The shell prior: an empty column 0; one opaque voxel 1/(3S) wherever it lies; two opaque voxels,
    the outer one hiding the other, the same; opacity spread over the depth more, and the more the
    deeper. float64 gradcheck; the term joins the loss only with its weight and a density."""
    import torch

    from uvatar.dva.losses import DvaLoss, LossConfig, column_spread

    S = 4
    scales = torch.full((1, 1, 3), 0.02, dtype=torch.float64)
    dens = torch.zeros(1, 1, S, S, S, dtype=torch.float64)
    assert float(column_spread(dens, scales)) == 0.0
    one = 1 / (3 * S)
    for z in (0, S - 1):
        d = dens.clone()
        d[:, :, z] = 1e6                                     # opaque: 1 - exp(-1e6 * 0.01) = 1
        assert float(column_spread(d, scales)) == pytest.approx(one)
    d = dens.clone()
    d[:, :, S - 1] = d[:, :, 0] = 1e6                        # the inner voxel is hidden by the outer
    assert float(column_spread(d, scales)) == pytest.approx(one)
    fog = torch.full_like(dens, 40.0)                         # opacity 1 - exp(-0.4) = 0.33 per voxel
    thick = torch.full_like(dens, 40.0)
    thick[:, :, S - 1] = 200.0                               # the same fog with most of it at the top
    assert float(column_spread(thick, scales)) < float(column_spread(fog, scales))
    assert float(column_spread(fog, scales)) > 2 * one
    torch.manual_seed(0)
    d = (torch.rand(1, 2, S, 2, 2, dtype=torch.float64) * 80).requires_grad_(True)
    sc = (torch.rand(1, 2, 3, dtype=torch.float64) * 0.02 + 0.01).requires_grad_(True)
    assert torch.autograd.gradcheck(column_spread, (d, sc))

    img, ones = torch.zeros(1, 3, 8, 8), torch.ones(1, 8, 8)
    rest = torch.full((1, 3), 0.02)
    args = (img, img, ones, ones, scales.float(), rest, None, None)
    assert "shell" not in DvaLoss(LossConfig(shell=0.0))(*args, fog.float())[1]
    assert "shell" not in DvaLoss(LossConfig(shell=0.1))(*args)[1]
    total, terms = DvaLoss(LossConfig(shell=0.1, rgb=0, ssim=0, mask=0, volume=0, beta=0))(*args, fog.float())
    assert terms["shell"] == pytest.approx(float(column_spread(fog, scales)), rel=1e-5)
    assert float(total) == pytest.approx(0.1 * terms["shell"], rel=1e-5)


def test_curriculum_switches_to_three_views(capture):
    cfg = preset("tiny")
    trainer = Trainer(open_source(capture), capture.parent / "cur", cfg, progress=False)
    assert trainer.bank.textures.shape[1] == 3  # three training cameras
    trainer.step = 0
    _, _, tex, _, _ = trainer.sample()
    full = trainer.bank.image_texture(0, [0, 1, 2])
    assert tex.shape == (1,) + tuple(full.shape)
    lr = cfg.train.lr
    assert trainer.set_lr(0.0) == lr and trainer.set_lr(cfg.train.lr_decay_start) == lr
    assert trainer.set_lr(1.0) == pytest.approx(lr * cfg.train.lr_final)
    assert trainer.opt.param_groups[0]["lr"] == pytest.approx(lr * cfg.train.lr_final)
    trainer.cfg.train.driving_views = 2
    trainer.step = cfg.train.all_views_iters
    for _ in range(5):
        _, _, tex, _, _ = trainer.sample()
        assert float(tex[0, 3].max()) <= 1.0


@pytest.mark.gpu
def test_train_and_resume_on_cuda(capture, tmp_path):
    """A run trained on CUDA resumes there (its checkpoint loads onto the GPU, the RNG state back to
    the CPU where torch keeps it) and goes on step for step."""
    src = open_source(capture)
    s = train_dva(src, tmp_path / "run", preset("tiny"), iters=2, device="cuda", progress=False)
    assert s["steps"] == 2
    s = train_dva(src, tmp_path / "run", preset("tiny"), iters=3, device="cuda", resume=True, progress=False)
    assert s["steps"] == 3 and np.isfinite(s["last"]["total"])


def test_train_resume_and_eval(capture, tmp_path):
    from uvatar.dva.eval import evaluate_dva

    src = open_source(capture)
    run = tmp_path / "run"
    s = train_dva(src, run, preset("tiny"), iters=4, progress=False)
    assert s["steps"] == 4 and (run / CHECKPOINT).is_file() and (run / "run.json").is_file()
    assert s["perceptual"] == "ssim" and np.isfinite(s["last"]["total"])
    # steps 1 and 4 are logged; the toy's crops show the person: its opacity there is said
    assert 0.0 <= s["last"]["opacity_in_mask"] <= 1.0 and s["empty"] in (True, False)
    assert s["opacity_in_mask"] is not None
    s = train_dva(src, run, preset("tiny"), iters=6, resume=True, progress=False)
    assert s["steps"] == 6
    model, body, meta, step = load_run(run)
    assert step == 6 and bool(model.correctives_on) and meta["train_cameras"] == ["cam00", "cam01", "cam02"]
    r = evaluate_dva(run, src, tmp_path / "m.json", progress=False)
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["cameras"] == ["cam03"] and saved["frames"] == ["000002"]
    assert "held-out" in r["protocol"] and r["psnr_db"] == r["psnr_db_full"]  # no box on this capture
    # an avatar that renders no person is said and flagged (NaN: the toy's masks have no interior at this size)
    inside = r["opacity_person_interior"]
    assert r["empty"] == (None if np.isnan(inside) else inside < EMPTY_OPACITY) and saved["empty"] == r["empty"]
    # the scores are those of the comparison image written beside them
    # (gt | prediction | error | mean-colour baseline | projective-texture baseline)
    from uvatar.io_utils import read_image
    from uvatar.render.metrics import psnr, ssim

    sheet = read_image(tmp_path / "m" / "000002_cam03.png")
    w = sheet.shape[1] // 5
    gt, pred, base, proj = (sheet[:, i * w:(i + 1) * w] for i in (0, 1, 3, 4))
    assert r["baseline_mean_colour"]["psnr_db_full"] == pytest.approx(psnr(base, gt), abs=0.05)
    assert r["baseline_projective_texture"]["psnr_db_full"] == pytest.approx(psnr(proj, gt), abs=0.05)
    assert r["psnr_db_full"] == pytest.approx(psnr(pred, gt), abs=0.05)  # 8-bit PNG rounding only
    assert r["ssim_full"] == pytest.approx(ssim(pred, gt), abs=0.005)


def test_training_reduces_the_loss(capture, tmp_path):
    """A few dozen steps on one frame fit the photo better than the first steps (without the colour
    skip, which starts at the photos' colours: see the next test)."""
    cfg = preset("tiny")
    cfg.train.warmup_iters = 1000
    cfg.features.colour_skip = False
    trainer = Trainer(open_source(capture), tmp_path / "fit", cfg, progress=False)
    trainer.bank.frames = trainer.bank.frames[:1]
    losses = [trainer.train_step()["rgb"] for _ in range(30)]
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5])


def test_colour_skip_starts_near_the_photo(capture, tmp_path):
    """The same first step scores closer to the photo with the colour skip than without: a seen texel
    starts at the driving views' colour."""
    first = {}
    for skip in (False, True):
        cfg = preset("tiny")
        cfg.features.colour_skip = skip
        trainer = Trainer(open_source(capture), tmp_path / f"skip{skip}", cfg, progress=False)
        first[skip] = np.mean([trainer.train_step()["rgb"] for _ in range(3)])
    assert first[True] < 0.85 * first[False]


def test_hide_target_view_leaves_the_scored_camera_out(capture, tmp_path):
    """hide_target_view: every sample's image input comes from the other training cameras; off, the
    target's own view drives it too (3 training cameras, driving_views 3)."""
    for hide in (True, False):
        cfg = preset("tiny")
        cfg.train.hide_target_view, cfg.train.batch, cfg.train.all_views_iters = hide, 6, 0
        trainer = Trainer(open_source(capture), tmp_path / f"hide{hide}", cfg, progress=False)
        seen = []
        trainer.bank.image_texture = lambda fi, views, seen=seen: seen.append(list(views)) or torch.zeros(4, 1, 1)
        _, cams, _, _, _ = trainer.sample()
        assert len(seen) == 6
        for c, views in zip(cams, seen, strict=True):
            assert (c not in views) == hide and len(views) == (2 if hide else 3)


def test_random_background_draws_a_colour_per_sample_and_trains_against_it(capture, tmp_path):
    """background "random": each sample of each step gets its own colour in [0, 1]^3, drawn from the
    run's sampling RNG (the same seed draws the same colours); the target is that colour outside the
    mask, and a step trains. "mask" hands every sample its camera's background."""
    cfg = preset("tiny")
    cfg.train.background, cfg.train.batch = "random", 4
    runs = [Trainer(open_source(capture), tmp_path / f"r{i}", cfg, progress=False) for i in range(2)]
    draws = [[bg for _ in range(3) for bg in t.sample()[4]] for t in runs]
    colours = np.stack(draws[0])
    assert colours.shape == (12, 3) and colours.min() >= 0.0 and colours.max() <= 1.0
    assert len({tuple(c) for c in colours.round(6)}) == 12      # a new colour every sample and step
    np.testing.assert_array_equal(colours, np.stack(draws[1]))   # the seed's colours
    terms = runs[0].train_step()
    assert np.isfinite(terms["total"])
    cfg = preset("tiny")
    trainer = Trainer(open_source(capture), tmp_path / "mask", cfg, progress=False)
    _, cams, _, _, backgrounds = trainer.sample()
    for c, bg in zip(cams, backgrounds, strict=True):
        np.testing.assert_array_equal(bg, trainer.bank.backgrounds[c])
    image = np.zeros((2, 2, 3), np.uint8)
    mask = np.array([[True, False], [False, False]])
    got = target_pixels(image, mask, np.array([[0, 0], [1, 1]]), colours[0], "random")
    np.testing.assert_allclose(got, [[0, 0, 0], colours[0]])


def test_load_run_errors(tmp_path):
    with pytest.raises(InputError, match="checkpoint"):
        load_run(tmp_path)
    (tmp_path / CHECKPOINT).write_text("junk")
    with pytest.raises(InputError, match="unreadable"):
        load_run(tmp_path)


def test_cli_train_render_eval(capture, tmp_path):
    from uvatar.cli.main import main

    run = tmp_path / "run"
    assert main(["train", "dva", str(capture), str(run), "--preset", "tiny", "--iters", "2"]) == 0
    out = tmp_path / "drive.gif"
    assert main(["render", "dva", str(run), "--motion", str(capture), "--views", "cam00,cam02",
                 "--camera", "cam03", "--frames", "0:2", "-o", str(out)]) == 0
    assert out.is_file()
    refined = tmp_path / "drive_refined.gif"
    assert main(["render", "dva", str(run), "--motion", str(capture), "--views", "cam00,cam02",
                 "--camera", "cam03", "--frames", "0:2", "--refine-pose", "3", "--refine-residual", "2",
                 "-o", str(refined)]) == 0
    assert refined.is_file()
    assert main(["eval", "dva", str(run), str(capture), "--json", str(tmp_path / "m.json")]) == 0
    assert "psnr_db" in json.loads((tmp_path / "m.json").read_text())
    assert main(["render", "dva", str(run), "--motion", str(capture), "--views", "nope",
                 "-o", str(out)]) == 1


def test_cli_train_bad_values_are_one_line_errors(capture, tmp_path, capsys):
    from uvatar.cli.main import main

    run = tmp_path / "run"
    for flag, value, words in (("--iters", "0", "--iters: must be at least 1"), ("--grid", "0", "--grid: must be"),
                               ("--voxels", "-3", "--voxels: must be"), ("--minutes", "0", "--minutes: must be > 0"),
                               ("--loss-ssim", "-1", "ssim loss weight must be >= 0")):
        assert main(["train", "dva", str(capture), str(run), "--preset", "tiny", flag, value]) == 1
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err
    assert not run.exists()


def test_broken_frames_are_skipped(tmp_path):
    root = write_toy_capture(tmp_path / "cap", frames=4, cameras=4, size=8)  # frame 3 is held out
    (root / "images" / "cam01" / "000001.png").unlink()
    (root / "fits" / "000000.json").write_text("{not json")
    s = train_dva(open_source(root), tmp_path / "run", preset("tiny"), iters=1, progress=False)
    assert set(s["skipped_frames"]) == {"000000", "000001"} and s["frames"] == 1 and s["steps"] == 1
    assert "cam01" in s["skipped_frames"]["000001"] and "invalid JSON" in s["skipped_frames"]["000000"]
    (root / "fits" / "000002.json").unlink()
    # 000002's fit is gone too: the capture source drops fitless frames, the rest are counted by cause
    with pytest.raises(InputError, match=r"no usable frame \(2 frames: 1 unreadable fits, 1 missing images\)"):
        train_dva(open_source(root), tmp_path / "run2", preset("tiny"), iters=1, progress=False)


def test_no_usable_frame_counts_missing_masks(tmp_path, capsys):
    """A capture without masks: `train dva` exits 1 and says so by cause, not 'all broken'."""
    import shutil

    from uvatar.cli.main import main

    root = write_toy_capture(tmp_path / "cap", frames=4, cameras=4, size=8)
    shutil.rmtree(root / "masks")
    assert main(["train", "dva", str(root), str(tmp_path / "run"), "--preset", "tiny", "--iters", "1"]) == 1
    err = capsys.readouterr().err
    assert "no usable frame (3 frames: 3 missing masks)" in err and "Traceback" not in err


def test_image_size_differing_from_intrinsics_is_warned(tmp_path, caplog):
    from uvatar.io_utils import write_image

    root = write_toy_capture(tmp_path / "cap", frames=2, cameras=4, size=8)
    for f in ("000000", "000001"):
        write_image(root / "images" / "cam01" / f"{f}.png", np.zeros((16, 16, 3)))
        write_image(root / "masks" / "cam01" / f"{f}.png", np.ones((16, 16)))
    with caplog.at_level("WARNING"):
        train_dva(open_source(root), tmp_path / "run", preset("tiny"), iters=1, progress=False)
    warned = [r.getMessage() for r in caplog.records if "intrinsics say" in r.getMessage()]
    assert warned == ["camera cam01: images are 16x16 but its intrinsics say 8x8 (rays and projections will "
                      "not match the pixels)"]


def test_any_body_model_on_the_easymocap_layout(tmp_path, capsys):
    """EasyMocap folders are not tied to SMPL: --model anny reads anny-sized fits (here the masks are
    missing, so training stops there, after the fits were posed with anny); the default (SMPL, no
    model files) fails with one line; a run refuses another --model at render/eval time."""
    from tests.fixtures.dva_capture import toy_cameras
    from uvatar.capture import BodyFit, write_cameras, write_fit
    from uvatar.cli.main import main
    from uvatar.io_utils import write_image

    cams = toy_cameras(4, 8)
    write_cameras(tmp_path / "em", cams)
    for f in ("000000", "000001"):
        write_fit(tmp_path / "em" / "fits" / f"{f}.json", BodyFit(poses=np.zeros(312, np.float32)))
        for c in cams:
            write_image(tmp_path / "em" / "images" / c / f"{f}.jpg", np.full((8, 8, 3), 0.3, np.float32))
    args = ["train", "dva", str(tmp_path / "em"), str(tmp_path / "run"), "--preset", "tiny", "--iters", "1"]
    assert main([*args, "--model", "anny"]) == 1
    assert "no usable frame (1 frame: 1 missing masks)" in capsys.readouterr().err
    assert main([*args, "--model", "smpl", "--model-dir", str(tmp_path / "no_smpl")]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len([line for line in err.splitlines() if line.strip()]) == 1


def test_run_refuses_another_body_model(capture, tmp_path):
    train_dva(open_source(capture), tmp_path / "run", preset("tiny"), iters=1, progress=False)
    with pytest.raises(InputError, match="was trained with body model 'toy', not 'anny'"):
        load_run(tmp_path / "run", body_model="anny")
    model, body, meta, _ = load_run(tmp_path / "run", body_model="toy")
    assert meta["body_model"] == "toy" and meta["model_dir"] is None


def test_cli_train_flags_reach_the_saved_config(capture, tmp_path):
    """--grid, --voxels, --batch, --patch, --min-scale-corrective, --loss-ssim and --loss-colour-tv land
    in the run's saved config (run.json), and --seed in its summary."""
    from uvatar.cli.main import main

    run = tmp_path / "run"
    assert main(["train", "dva", str(capture), str(run), "--preset", "tiny", "--iters", "1", "--grid", "6",
                 "--voxels", "2", "--loss-ssim", "0.4", "--loss-colour-tv", "0.3", "--batch", "2", "--patch", "12",
                 "--seed", "7", "--min-scale-corrective", "0"]) == 0
    saved = json.loads((run / "run.json").read_text())
    cfg = saved["config"]
    assert cfg["train"]["batch"] == 2 and cfg["train"]["patch"] == 12 and saved["summary"]["seed"] == 7
    assert cfg["primitives"]["min_scale_corrective"] == 0.0
    assert cfg["primitives"]["grid"] == 6 and cfg["decoder"]["voxels"] == 2 and cfg["loss"]["ssim"] == 0.4
    assert cfg["loss"]["colour_tv"] == 0.3
