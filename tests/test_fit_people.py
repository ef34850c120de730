"""Several people fitted (``uvatar fit --person all``): depth-ordered masks per person, the people
layout, and bad input. Known answers on boxes standing in for bodies; a fake segmenter."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from uvatar.errors import InputError
from uvatar.fit.masks import FAR, MaskConfig, body_depth, nearest_region, person_mask
from uvatar.render.cameras import look_at_camera

CAM = look_at_camera((0.0, 1.0, 5.0), (0.0, 1.0, 0.0), fov_deg=40.0, width=120, height=120)


def _body(x: float, z: float):
    """A 0.5 x 1.6 x 0.3 m box standing at (x, 0.2 .. 1.8, z): a person for the renderer."""
    m = trimesh.creation.box(extents=(0.5, 1.6, 0.3))
    return np.asarray(m.vertices) + [x, 1.0, z], np.asarray(m.faces)


class UnionSegmenter:
    """Every person's pixels (both bodies' silhouettes grown by 2 px: the clothes), as a real
    segmenter that cannot tell touching people apart."""

    def __init__(self, people: np.ndarray):
        import cv2

        self.prob = (cv2.dilate(people.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0).astype(np.float32)

    def segment(self, image, roi=None):
        out = np.zeros_like(self.prob)
        x0, y0, x1, y1 = (int(v) for v in roi)
        out[y0:y1 + 1, x0:x1 + 1] = self.prob[y0:y1 + 1, x0:x1 + 1]
        return out


def test_the_subject_mask_excludes_the_person_in_front_and_keeps_its_own_visible_pixels():
    import cv2

    subject = body_depth(*_body(0.0, 0.0), CAM, 120)      # 5 m away
    front = body_depth(*_body(0.35, 1.0), CAM, 120)       # 4 m away, covering the subject's right side
    s, f = subject < FAR, front < FAR
    assert (s & f).sum() > 200 and (s & ~f).sum() > 300      # overlapping in the view, part of it visible
    assert np.all(front[s & f] < subject[s & f])              # the depth buffer: the nearest hit
    image = np.zeros((120, 120, 3), np.float32)
    seg = UnionSegmenter(s | f)
    config = MaskConfig(dilate=0.04)                          # 5 px at 120 px
    r = 5
    naive = person_mask(image, seg, s, config)
    assert (naive & f).sum() > 200                            # without the other fit: the front person leaks in
    mask = person_mask(image, seg, s, config, allowed=nearest_region(subject, [front], r))
    grown_front = cv2.dilate(f.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (11, 11))) > 0
    assert not (mask & f).any()                               # not one pixel of the person in front
    visible = s & ~grown_front
    assert mask[visible].all()                                # every visible subject pixel away from their edge
    band = (seg.prob > 0) & ~s & ~f                           # the subject's clothes beyond the fitted body
    away = band & ~grown_front
    assert away.any() and mask[away].all()
    # the person in front keeps every pixel of their own body, where they hide the subject too
    theirs = person_mask(image, seg, f, config, allowed=nearest_region(front, [subject], r))
    assert theirs[f].all() and not (theirs & s & ~f & ~grown_front).any()


def test_nearest_region_without_others_is_the_grown_body_and_a_body_behind_takes_nothing_in_front():
    depth = np.full((40, 40), FAR, np.float32)
    depth[10:30, 10:20] = 3.0
    alone = nearest_region(depth, [], 2)
    assert alone[10:30, 8:22].all() and alone[8:32, 10:20].all() and not alone[:, 25:].any()
    behind = np.full_like(depth, FAR)
    behind[5:35, 15:35] = 4.0                                 # overlapping, farther: the first keeps its body
    region = nearest_region(depth, [behind], 2)
    assert region[10:30, 10:20].all()
    assert not region[10:30, 20:23].any()                     # the band over the other body is theirs
    assert region[10:30, 8:10].all()                          # the band where no one else is stays


def test_person_ids_and_the_people_layout(tmp_path):
    from uvatar.capture.layout import Capture, write_capture_info
    from uvatar.fit.person import parse_person

    assert parse_person("all").rule == "all" and parse_person("all").several
    choice = parse_person("2")
    assert choice.rule == "id" and choice.person_id == "2" and choice.several
    assert not parse_person("most-views").several
    write_capture_info(tmp_path, ["000000"])
    (tmp_path / "people" / "2" / "fits").mkdir(parents=True)
    (tmp_path / "people" / "10" / "fits").mkdir(parents=True)
    (tmp_path / "people" / "x").mkdir()
    (tmp_path / "people" / "2" / "person.json").write_text(json.dumps({"body_model": "anny", "shapes": [0.5, 0.25]}))
    cap = Capture(tmp_path)
    assert cap.people() == ["2", "10"] and cap.person is None and cap.fits_dir == tmp_path / "fits"
    other = cap.for_person(2)
    assert other.fits_dir == tmp_path / "people" / "2" / "fits"
    assert other.mask_path("c0", "000000") == tmp_path / "people" / "2" / "masks" / "c0" / "000000.png"
    assert other.fitting_dir == tmp_path / "people" / "2" / "fitting"
    assert other.body_shapes.tolist() == [0.5, 0.25] and other.frames == ["000000"]


@pytest.mark.parametrize("spec, match", [("0", "person id is >= 1"), ("all:3", "expected one of"),
                                         ("-1", "expected one of"), ("two", "expected one of")])
def test_bad_person_specs_are_one_line_errors(spec, match):
    from uvatar.fit.person import parse_person

    with pytest.raises(InputError, match=match) as err:
        parse_person(spec)
    assert "\n" not in str(err.value)


def test_bad_people_inputs_are_one_line_errors(tmp_path):
    from uvatar.capture.layout import Capture, write_capture_info
    from uvatar.capture.types import BodyFit
    from uvatar.fit.evaluate import bystander_truth
    from uvatar.fit.pipeline import FitConfig, fit_capture

    write_capture_info(tmp_path, ["000000"])
    with pytest.raises(InputError, match="person id is a whole number"):
        Capture(tmp_path, person="abc")
    with pytest.raises(InputError, match="bystanders.npz.*no bystanders' ground truth"):
        bystander_truth(Capture(tmp_path, person=1), {"000000": BodyFit(poses=np.zeros(6))})
    (tmp_path / "scans").mkdir()
    trimesh.creation.box().export(tmp_path / "scans" / "000000.obj")
    with pytest.raises(InputError, match=r"needs source='images' \(this run: source='scans'\)"):
        fit_capture(tmp_path, FitConfig(person="all"), progress=False)


@pytest.fixture(scope="module")
def crowd_fitted(tmp_path_factory):
    """A small studio capture with one bystander (3 frames, 4 cameras, 256^2; ~30 s), fitted with
    ``person="all"`` and masked; and a copy with the subject's fits alone, masked as before
    (``single``): (root, fit summary, mask summary, single). Beside them, ``ordered`` (the people's
    masks without the colour models) and ``lone`` (``single`` masked without them)."""
    import shutil

    import torch

    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize
    from uvatar.fit.masks import write_capture_masks
    from uvatar.fit.pipeline import FitConfig, fit_capture

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        root = tmp_path_factory.mktemp("crowd") / "cap"
        synthesize(root, preset("quick", frames=3, cameras=4, image_size=256, seed=0, preview=False, bystanders=1),
                   progress=False)
        shutil.move(root / "masks", root / "masks_true")
        shutil.rmtree(root / "fits")
        summary = fit_capture(root, FitConfig(source="images", person="all", overlay_frames=0, photo_size=0),
                              progress=False)
        single = root.parent / "single"
        shutil.copytree(root, single, ignore=shutil.ignore_patterns("people"))
        masks = write_capture_masks(root, MaskConfig(), progress=False)
        write_capture_masks(single, MaskConfig(), progress=False)
        ordered = root.parent / "ordered"          # the people's masks by the depth order alone
        shutil.copytree(root, ordered)
        write_capture_masks(ordered, MaskConfig(appearance=False, overwrite=True), progress=False)
        lone = root.parent / "lone"                # the subject alone, no colour pass either way
        shutil.copytree(single, lone)
        write_capture_masks(lone, MaskConfig(appearance=False, overwrite=True), progress=False)
    finally:
        torch.set_num_threads(threads)
    return root, summary, masks, single


def test_person_all_fits_the_subject_and_the_bystander_each_near_their_truth(crowd_fitted):
    from uvatar.body import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.evaluate import evaluate_fits

    root, summary, _, _ = crowd_fitted
    assert list(summary["people"]) == ["1"] and summary["person_id"] is None
    assert [o["id"] for o in summary["person"]["others"]] == ["1"]
    body = load_body_model("anny")
    errors = {}
    for pid in (None, "1"):
        cap = Capture(root, pid)
        fitted = [f for f in cap.frames if cap.has_fit(f)]
        unseen = (summary if pid is None else summary["people"][pid])["frames_without_detection"]
        held = summary["provenance"].get("identity_held", [])   # the subject's identity held: no fit, reported
        assert pid is not None or all(unseen[f].startswith("identity ") for f in held)
        assert fitted == [f for f in cap.frames if (f not in held if pid is None else f not in unseen)]
        assert len(fitted) >= 2
        ev = evaluate_fits(body, cap, {f: cap.load_fit(f) for f in fitted}, cap.body_shapes)
        errors[pid] = ev["mpjpe_mm"]
        if pid is not None:
            assert ev["bystander"] == 0 and len(cap.body_shapes) == len(body.shape_names)
    assert errors[None] < 60 and errors["1"] < 80, errors           # mm, each on their own truth
    np.testing.assert_allclose(Capture(root).body_shapes, summary["shape"], atol=1e-6)  # capture.json: the subject's
    assert not np.allclose(Capture(root, 1).body_shapes, summary["shape"], atol=1e-3)   # person.json: theirs
    assert (root / "people" / "1" / "fitting" / "summary.json").is_file()


def test_person_all_masks_per_person_and_the_subject_mask_leaves_the_bystander_out(crowd_fitted):
    import imageio.v3 as iio

    from uvatar.capture.layout import Capture
    from uvatar.fit.segment import mask_iou

    root, _, masks, single = crowd_fitted
    assert masks["people"] == ["1"] and not masks["failed"]
    assert masks["written"] + masks["not_seen"] == 2 * 3 * 4 and masks["written"] >= 4 * 4
    cap, alone, other = Capture(root), Capture(single), Capture(root, 1)
    leaked, leaked_alone, ious, theirs_iou = 0, 0, [], []
    for cam in cap.cameras():
        for frame in cap.frames:
            mine = cap.load_mask(cam, frame)
            theirs = other.load_mask(cam, frame) if other.has_fit(frame) else np.zeros_like(mine)
            bystander = iio.imread(root / "gt" / "bystander_masks" / cam / f"{frame}.png") > 127
            truth = iio.imread(root / "masks_true" / cam / f"{frame}.png") > 127
            assert not (mine & theirs).any()                  # a pixel is one person's at most
            ious.append(mask_iou(mine, truth))
            if other.has_fit(frame):                          # where the bystander's body is known
                leaked += int((mine & bystander).sum())
                leaked_alone += int((alone.load_mask(cam, frame) & bystander).sum())
                if bystander.sum() > 500:
                    theirs_iou.append(mask_iou(theirs, bystander))
    # the subject's masks without the bystander's fit take in hundreds of their pixels; ordered by
    # depth, at most a few dozen (the bystander's hands beyond their fitted body, grown)
    assert leaked_alone > 300 and leaked <= 0.1 * leaked_alone, (leaked, leaked_alone)
    assert np.mean(ious) > 0.85, ious
    assert len(theirs_iou) >= 4 and np.median(theirs_iou) > 0.85, theirs_iou   # the bystander's own masks


class FrontPersonSegmenter:
    """A person segmenter that finds the most prominent person only: the green one when any green
    pixel is in the search box (grown by 6 px, as a detector sees beyond its box), else the red one
    (and nobody when ``blind``)."""

    def __init__(self, blind=False):
        self.blind, self.rois = blind, []

    def segment(self, image, roi=None):
        self.rois.append(roi)
        green = (image[..., 1] > 0.5) & (image[..., 0] < 0.5)
        red = (image[..., 0] > 0.5) & (image[..., 1] < 0.5)
        x0, y0, x1, y1 = (int(v) for v in roi)
        box = np.zeros(green.shape, bool)
        box[max(y0 - 6, 0):y1 + 7, max(x0 - 6, 0):x1 + 7] = True
        if self.blind and not (green & box).any():
            return np.zeros(green.shape, np.float32)
        return ((green if (green & box).any() else red) & box).astype(np.float32)


def test_the_others_are_painted_over_before_the_segmenter_looks_for_the_person():
    subject = np.full((60, 60), FAR, np.float32)
    subject[10:50, 10:30] = 5.0
    front = np.full_like(subject, FAR)
    front[5:55, 25:45] = 4.0                                   # in front, covering the subject's right side
    image = np.zeros((60, 60, 3), np.float32)
    image[subject < FAR] = (1.0, 0.0, 0.0)
    image[front < FAR] = (0.0, 1.0, 0.0)
    allowed = nearest_region(subject, [front], 2)
    hide = (front < FAR) & ~allowed
    config = MaskConfig(dilate=2 / 60)
    prior = subject < FAR
    # the segmenter sees the person in front first: without painting, nothing of the subject is left
    assert not person_mask(image, FrontPersonSegmenter(), prior, config, allowed=allowed).any()
    mask = person_mask(image, FrontPersonSegmenter(), prior, config, allowed=allowed, hide=hide)
    visible = np.zeros_like(prior)
    visible[10:50, 10:23] = True                                # the subject's pixels 2 px clear of the front one
    assert mask[visible].all() and not (mask & (front < FAR)).any()
    # a segmenter that finds nobody once the others are painted over: the image as it is, then the
    # depth order (here it finds only the one in front, so the subject's mask stays empty, never theirs)
    seg = FrontPersonSegmenter(blind=True)
    blind = person_mask(image, seg, prior, config, allowed=allowed, hide=hide)
    assert not (blind & (front < FAR)).any()
    assert len(seg.rois) == 2 and seg.rois[1][2] > seg.rois[0][2]    # again, around the whole body


def test_the_colour_models_leave_out_more_of_the_bystander_and_a_lone_subject_is_masked_as_before(crowd_fitted):
    import imageio.v3 as iio

    from uvatar.capture.layout import Capture
    from uvatar.fit.segment import mask_iou

    root, _, masks, single = crowd_fitted
    assert set(masks["colour_pixels"]) == {"subject", "1"} and min(masks["colour_pixels"].values()) > 1000
    scores = {}
    for name in ("cap", "ordered"):
        cap = Capture(root.parent / name)
        leaked, ious = 0, []
        for cam in cap.cameras():
            for frame in cap.frames:
                mine = cap.load_mask(cam, frame)
                bystander = iio.imread(root / "gt" / "bystander_masks" / cam / f"{frame}.png") > 127
                truth = iio.imread(root / "masks_true" / cam / f"{frame}.png") > 127
                leaked += int((mine & bystander).sum())
                ious.append(mask_iou(mine, truth))
        scores[name] = (leaked, float(np.mean(ious)))
    # measured: 428 -> 41 bystander pixels, mean IoU 0.896 -> 0.942
    assert scores["cap"][0] <= 0.25 * scores["ordered"][0] and scores["cap"][1] > scores["ordered"][1] + 0.01, scores
    alone, lone = Capture(single), Capture(root.parent / "lone")
    for cam in alone.cameras():
        for frame in alone.frames:
            np.testing.assert_array_equal(alone.load_mask(cam, frame), lone.load_mask(cam, frame))
