"""Per-person colour models deciding the pixels several people contest (uvatar.fit.appearance), on
small scenes drawn here: a red subject and a green other person on a white background, with known
answers."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.fit import appearance
from uvatar.fit.appearance import Background, ColourModel, colour_index, confident_pixels, decide
from uvatar.fit.masks import FAR, MaskConfig, nearest_region

RED, GREEN, WHITE = (0.8, 0.1, 0.1), (0.1, 0.7, 0.2), (1.0, 1.0, 1.0)
RADIUS = 4


def _rect(rows, cols, shape=(80, 80)) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[rows[0]:rows[1], cols[0]:cols[1]] = True
    return m


def _depth(mask: np.ndarray, z: float) -> np.ndarray:
    return np.where(mask, np.float32(z), FAR).astype(np.float32)


def _image(*people) -> np.ndarray:
    """White, then each (mask, colour) painted in order (the last in front), with a little noise."""
    img = np.ones((80, 80, 3), np.float32) * np.float32(WHITE)
    for mask, colour in people:
        img[mask] = colour
    noise = np.random.default_rng(0).normal(0.0, 0.02, img.shape).astype(np.float32)
    return np.clip(img + noise, 0.0, 1.0)


def _tables(image, **pixels) -> dict:
    """{person index: log table} learned from the given pixels of ``image`` (subject=0, other=1)."""
    index = colour_index(image)
    out = {}
    for k, name in enumerate(("subject", "other")):
        if name in pixels:
            model = ColourModel()
            model.add(index, pixels[name])
            out[k] = model.log_table()
    return out


def _pass1(depths: dict, segmented: np.ndarray) -> dict:
    """The depth-ordered masks before the colours: the segmented pixels each person's depth order allows."""
    out = {}
    for k, d in depths.items():
        allowed = nearest_region(d, [o for j, o in depths.items() if j != k], RADIUS)
        out[k] = segmented & allowed
    return out


def test_colour_index_and_the_model_prefer_the_colours_they_learned():
    img = _image((_rect((0, 80), (0, 40)), RED), (_rect((0, 80), (40, 80)), GREEN))
    index = colour_index(img)
    assert index.dtype == np.int32 and index.min() >= 0 and index.max() < appearance.BINS ** 3
    u8 = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(colour_index(u8), index)        # float [0, 1] and uint8 agree
    tables = _tables(img, subject=_rect((0, 80), (0, 40)), other=_rect((0, 80), (40, 80)))
    red, green = index[40, 10], index[40, 60]
    assert tables[0][red] - tables[1][red] > 5 and tables[1][green] - tables[0][green] > 5   # nats
    for t in tables.values():
        np.testing.assert_allclose(np.exp(t.astype(np.float64)).sum(), 1.0, rtol=1e-4)   # a distribution


def test_a_person_without_enough_confident_pixels_has_no_model_and_decide_still_works():
    model = ColourModel()
    model.add(np.zeros((4, 4), np.int32), np.zeros((4, 4), bool))   # no confident pixel at all
    assert model.pixels == 0
    np.testing.assert_allclose(model.log_table(), -np.log(appearance.BINS ** 3), rtol=1e-6)
    model.add(np.zeros((8, 8), np.int32), np.ones((8, 8), bool))
    assert model.pixels == 64 < appearance.MIN_PIXELS and np.ptp(model.log_table()) == 0
    subject, other = _rect((10, 70), (15, 40)), _rect((10, 70), (40, 62))
    img = _image((subject, RED), (other, GREEN))
    out = decide(img, {0: _depth(subject, 5.0)}, {0: subject}, {}, RADIUS, 1.0)   # nobody has a model
    np.testing.assert_array_equal(out[0], subject)
    # a fitted person without a model: the colours cannot speak for them, the masks stay as given
    depths = {0: _depth(subject, 5.0), 1: _depth(other, 4.0)}
    given = {0: subject | other, 1: np.zeros_like(subject)}            # (wrong, on purpose)
    out = decide(img, depths, given, _tables(img, subject=subject), RADIUS, 1.0, _white())
    assert set(out) == {0, 1}
    np.testing.assert_array_equal(out[0], given[0])
    np.testing.assert_array_equal(out[1], given[1])
    assert decide(img, {}, {}, {}, RADIUS, 1.0) == {}                 # nobody fitted: no masks
    assert Background().image() is None                              # no image seen yet
    with pytest.raises(ValueError, match="appearance_prior must be in"):
        MaskConfig(appearance_prior=-1.0)


def test_confident_pixels_keep_clear_of_the_edge_and_of_the_other_body():
    subject, other = _rect((10, 70), (10, 40)), _rect((10, 70), (42, 75))
    d_s, d_o = _depth(subject, 5.0), _depth(other, 4.0)
    allowed = nearest_region(d_s, [d_o], RADIUS)
    sure = confident_pixels(subject, d_s, [d_o], allowed, RADIUS)
    # eroded by radius // 2 = 2 px (rows 12-67, from column 12), and 4 + 2 px clear of the other body
    # (from column 42: up to column 35)
    expected = _rect((12, 68), (12, 36))
    np.testing.assert_array_equal(sure, expected)
    alone = confident_pixels(subject, d_s, [], nearest_region(d_s, [], RADIUS), RADIUS)
    np.testing.assert_array_equal(alone, _rect((12, 68), (12, 38)))
    assert not confident_pixels(np.zeros_like(subject), d_s, [d_o], allowed, RADIUS).any()


def test_the_colours_give_the_contested_band_to_the_person_whose_clothes_they_are():
    # the other person (green, in front) is fitted 8 px too far right: the depth order alone hands the
    # subject the green pixels in their grown band
    subject, other = _rect((10, 70), (15, 40)), _rect((10, 70), (40, 62))
    img = _image((subject, RED), (other, GREEN))
    depths = {0: _depth(subject, 5.0), 1: _depth(_rect((10, 70), (48, 70)), 4.0)}
    masks = _pass1(depths, subject | other)
    assert (masks[0] & other).sum() >= 60 * 3                          # the depth order's mistake
    tables = _tables(img, subject=subject, other=other)
    out = decide(img, depths, masks, tables, RADIUS, 1.0, _white())
    assert not (out[0] & other).any() and not (out[1] & subject).any() and not (out[0] & out[1]).any()
    inner = subject & ~_rect((0, 80), (39, 80))                       # all but the column touching green
    assert out[0][inner].all() and not (out[0] & ~subject).any()
    # the other person's mask: their pixels inside their own (misplaced) fitted body grown by 4 px,
    # and beyond it (up to two bands) those clearly of their colours: all of them but the column
    # touching red (the corners of the contact are nobody's clear label)
    assert out[1][other & _rect((0, 80), (41, 80))].all() and not (out[1] & ~other).any()
    assert out[1].sum() >= other.sum() - 60


def test_a_subject_mostly_hidden_behind_someone_takes_back_the_pixels_of_their_clothes():
    # the other person stands in front and hides all but an 8 px strip of the subject, and the
    # segmenter lost the subject (their mask is empty)
    subject, other = _rect((10, 70), (15, 45)), _rect((8, 75), (23, 70))
    img = _image((subject, RED), (other, GREEN))
    depths = {0: _depth(subject, 5.0), 1: _depth(other, 4.0)}
    visible = subject & ~other
    masks = {0: np.zeros_like(subject), 1: other.copy()}
    # the depth order gives the subject only the strip's first columns (the other body grown by 4 px)
    assert not (nearest_region(depths[0], [depths[1]], RADIUS) & visible & _rect((0, 80), (19, 80))).any()
    tables = _tables(img, subject=_rect((10, 70), (0, 80)) & visible, other=other)
    out = decide(img, depths, masks, tables, RADIUS, 1.0, _white())
    assert not (out[0] & other).any()
    assert out[0][visible & ~_rect((0, 80), (22, 80))].all()           # the strip, 1 px clear of green
    assert out[0].sum() == (visible & ~_rect((0, 80), (22, 80))).sum()
    # without the background the strip is nobody's foreground: nothing to take back
    assert not decide(img, depths, masks, tables, RADIUS, 1.0)[0].any()
    # a background never seen where the people stand: there the colours alone (the subject's red is
    # likelier theirs than the white studio's) bring the strip back
    unseen = Background()
    for _ in range(3):
        unseen.add(_image(), subject | other)
    assert np.isnan(unseen.image()[subject]).all()
    np.testing.assert_array_equal(decide(img, depths, masks, tables, RADIUS, 1.0, unseen)[0], out[0])


def test_an_unfitted_bystander_inside_the_subjects_band_is_left_out():
    # only the subject is fitted in this frame; the segmenter took the bystander's arm (green) that
    # reaches into the subject's grown band; the bystander's colours are known from other frames
    subject, arm = _rect((10, 70), (15, 40)), _rect((20, 30), (40, 44))
    img = _image((subject, RED), (arm, GREEN))
    depths = {0: _depth(subject, 5.0)}
    masks = {0: subject | arm}
    learned = _image((_rect((0, 80), (0, 40)), GREEN))                # the bystander in another frame
    tables = {0: _tables(img, subject=subject)[0], 1: _tables(learned, other=_rect((0, 80), (0, 40)))[1]}
    out = decide(img, depths, masks, tables, RADIUS, 1.0, _white())
    assert set(out) == {0} and not (out[0] & arm).any()
    assert out[0][subject & ~_rect((19, 31), (39, 80))].all()          # all of the subject, 1 px clear of the arm
    # without the bystander's model the arm stays in (the mask as the depth order gave it)
    alone = decide(img, depths, masks, {0: tables[0]}, RADIUS, 1.0)
    np.testing.assert_array_equal(alone[0], subject | arm)


def test_the_background_is_each_pixels_mean_where_nobody_covers_it():
    person = _rect((10, 70), (15, 40))
    bg = Background()
    for k in range(4):
        img = _image((person, RED)) if k == 1 else _image()           # someone there in one frame
        img[:, :5] = 0.5                                               # a grey wall
        bg.add(img, person if k == 1 else np.zeros_like(person))
    image = bg.image()
    assert image.shape == (80, 80, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image[:, :5], 0.5, atol=0.03)
    white_floor = ~person & ~_rect((0, 80), (0, 5))
    assert image[white_floor].min() > 0.9 and image[person].min() > 0.9   # white, where the person stood too
    assert np.isnan(_seen_once()).all()                               # free in 2 images of 3: unknown
    table = bg.log_table()
    white, grey, red = (colour_index(np.array([[c]], np.float32))[0, 0] for c in (WHITE, (0.5,) * 3, RED))
    assert table[white] > table[grey] > table[red]                    # the background's colours


def _seen_once() -> np.ndarray:
    """The pixels of a background seen free in fewer than min_count images: unknown (NaN)."""
    bg = Background(min_count=3)
    covered = _rect((0, 80), (0, 40))
    for _ in range(2):
        bg.add(_image(), np.zeros_like(covered))
    bg.add(_image(), covered)
    return bg.image()[covered]


def _white() -> Background:
    """A white studio's background, seen free of people in 3 images."""
    bg = Background()
    for _ in range(3):
        bg.add(_image(), np.zeros((80, 80), bool))
    return bg


def test_a_person_takes_their_clear_colours_up_to_two_bands_beyond_their_fitted_body():
    # the subject's fit ends at column 39, their red reaches column 51; the band is 4 px: the
    # segmented mask stops at column 43, the colours take the red up to two bands (column 47)
    red = _rect((10, 70), (15, 52))
    img = _image((red, RED))
    core = _rect((10, 70), (15, 40))
    depths = {0: _depth(core, 5.0)}
    masks = {0: red & _rect((0, 80), (0, 44))}
    learned = _image((_rect((0, 80), (0, 40)), GREEN))                # someone else, known from elsewhere
    tables = {0: _tables(img, subject=core)[0], 1: _tables(learned, other=_rect((0, 80), (0, 40)))[1]}
    out = decide(img, depths, masks, tables, RADIUS, 1.0, _white())
    assert out[0][_rect((12, 68), (15, 47))].all() and not (out[0] & ~red).any()
    assert not out[0][:, 48:].any()
    # with nobody else's colours there is nothing to tell clothes from: the mask stays as segmented
    np.testing.assert_array_equal(decide(img, depths, masks, {0: tables[0]}, RADIUS, 1.0, _white())[0], masks[0])
