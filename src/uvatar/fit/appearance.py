"""Per-person colour models that decide the pixels several people contest (``MaskConfig.appearance``).

Where other people are fitted (``uvatar fit --person all``), :mod:`uvatar.fit.masks` first orders the
segmented pixels by the depth of the fitted bodies; a poor fit of one person then hands their pixels
to the other, and a person mostly hidden behind another gets nothing. Their clothes usually tell them
apart, so each person gets one colour model over the whole capture (:class:`ColourModel`: an RGB
histogram of :data:`BINS` ** 3 bins, smoothed), learned from the pixels that are surely theirs
(:func:`confident_pixels`: segmented, inside their fitted silhouette eroded, where their body is the
nearest, away from every other body; images where someone is not fitted teach nobody). Each image's
pixels are then labelled once for everyone (:func:`decide`):

- the foreground is the union of everyone's segmented masks and (with two people or more known)
  the pixels unlike the camera's background (:class:`Background`: each pixel's mean colour
  over the images where no person may be there; where people always stand, unknown) whose colour is
  clearly one person's (:data:`ADD_MARGIN` nats over the next, and likelier theirs than the
  background's colours): this brings back a person the segmenter lost behind someone in front,
  and a person's clothes up to :data:`REACH` bands beyond their fitted body (a fit off by more);
- a person's score is their colour log-likelihood plus ``prior`` nats where the depth order gives
  them the pixel (:func:`uvatar.fit.depth_order.nearest_region`) and half that inside their own grown body;
  where the two likeliest people's colours are within :data:`AMBIGUOUS` nats (skin, hair, shadow)
  the colours say nothing and the depth order decides, as without the models (skin is alike, but
  one person shows more of it than the other: that would otherwise tip every hand). A person not
  fitted in this frame has their colours alone: they claim the pixels of their clothes, which then
  are nobody's (an unfitted bystander no longer enters the subject's band);
- the labels are smoothed by a few rounds of neighbourhood voting (:data:`SMOOTH_ROUNDS` of ICM with
  a Potts term of :data:`SMOOTH_NATS`); a person keeps their label's pixels inside their grown body,
  :data:`CLEAR_PX` clear of another person's, in the parts that touch their fitted silhouette.

Measured on ``uvatar synth --bystanders 1`` (60 frames, 4 cameras, 256^2; docs/real.md section 6):
the subject's mean IoU 0.930 -> 0.964, images below 0.9 34 -> 14, bystander pixels in the subject's
masks 3,057 in 42 images -> 618 in 29. What is left: the bystander's hands on the subject and hair
where their fit is off or missing (skin and hair are alike), a pixel or two where the two touch, and
the subject's pixels outside their fitted body grown (fit error) or too dark to tell.
"""

from __future__ import annotations

import numpy as np

from uvatar.fit.depth_order import FAR, nearest_region
from uvatar.fit.depth_order import disc as _disc

__all__ = ["BINS", "ColourModel", "colour_index", "confident_pixels", "Background", "decide"]

BINS = 32                  # histogram bins per RGB channel
MIN_PIXELS = 200           # fewer confident pixels: no colour model for the person
SMOOTH_ROUNDS = 6          # rounds of neighbourhood voting (ICM)
SMOOTH_NATS = 3.0          # nats a label gains when its whole neighbourhood holds it
SMOOTH_WINDOW = 0.01       # the neighbourhood: a box of 2 x this x the image height + 1 pixels
AMBIGUOUS = 2.0            # nats: colours whose two likeliest people are closer than this say nothing
ADD_MARGIN = 4.0           # nats by which a pixel only the background model finds must be one person's colour
REACH = 2                  # beyond the grown body, up to this many bands: pixels clearly of the person's colours
CLEAR_PX = 1               # a person's mask keeps this many pixels clear of another person's label
BACKGROUND_TOL = 0.1       # a pixel this far (max over RGB, [0, 1]) from the background is foreground


def colour_index(image: np.ndarray, bins: int = BINS) -> np.ndarray:
    """(H, W) int32 histogram bin (of ``bins`` ** 3, ``bins`` a power of two <= 256) of every pixel of
    ``image`` (H, W, 3), float in [0, 1] or uint8."""
    img = np.asarray(image)
    q = img if img.dtype == np.uint8 else np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    q = (q[..., :3] // (256 // bins)).astype(np.int32)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


class ColourModel:
    """One person's colours: counts of :func:`colour_index` bins, added image by image
    (:meth:`add`), and the smoothed log-probability per bin (:meth:`log_table`)."""

    def __init__(self) -> None:
        self.counts = np.zeros(BINS ** 3, np.float64)

    def add(self, index: np.ndarray, mask: np.ndarray) -> None:
        """Count the bins ``index`` (H, W) of the pixels of ``mask`` (H, W) bool."""
        self.counts += np.bincount(index[mask], minlength=BINS ** 3)

    @property
    def pixels(self) -> int:
        return int(self.counts.sum())

    def log_table(self, smooth: float = 0.5, floor: float = 0.05) -> np.ndarray:
        """(BINS^3,) float32 log-probability of each bin: the counts blurred by ``smooth`` bins, mixed
        with ``floor`` of a flat distribution (an unseen colour is unlikely, not impossible); flat when
        the model has fewer than :data:`MIN_PIXELS` pixels."""
        from scipy.ndimage import gaussian_filter

        flat = np.full(BINS ** 3, 1.0 / BINS ** 3)
        if self.pixels < MIN_PIXELS:
            return np.log(flat).astype(np.float32)
        p = gaussian_filter(self.counts.reshape(BINS, BINS, BINS), smooth, mode="constant").ravel()
        p = (1.0 - floor) * p / p.sum() + floor * flat
        return np.log(p).astype(np.float32)


def confident_pixels(mask: np.ndarray, depth: np.ndarray, others: list[np.ndarray], allowed: np.ndarray,
                     radius: int) -> np.ndarray:
    """(H, W) bool: the pixels surely the person's, to learn their colours from: in their mask (H, W)
    bool, inside their fitted silhouette (``depth`` < FAR) eroded by ``radius`` // 2 pixels, where the
    depth order gives them the pixel (``allowed``) and ``radius`` + ``radius`` // 2 pixels away from
    every other fitted body (``others``: their depths)."""
    import cv2

    margin = max(1, radius // 2)
    core = cv2.erode((depth < FAR).astype(np.uint8), _disc(margin)) > 0
    sure = mask & core & allowed
    if others:
        near = np.logical_or.reduce([d < FAR for d in others]).astype(np.uint8)
        sure &= cv2.dilate(near, _disc(radius + margin)) == 0
    return sure


class Background:
    """One static camera's background, from the images' pixels where no person may be (:meth:`add`):
    :meth:`image` (H, W, 3) float32 in [0, 1], every pixel's mean colour, NaN where fewer than
    ``min_count`` images saw it free (where people always stand: there the colours alone decide);
    :meth:`log_table` the colours of all those pixels (a :class:`ColourModel`)."""

    def __init__(self, min_count: int = 3) -> None:
        self.min_count = min_count
        self.total: np.ndarray | None = None
        self.count: np.ndarray | None = None
        self.colours = ColourModel()
        self._image: np.ndarray | None = None
        self._table: np.ndarray | None = None

    def add(self, image: np.ndarray, covered: np.ndarray) -> None:
        """``image`` (H, W, 3) float [0, 1] or uint8; ``covered`` (H, W) bool: where people may be."""
        img = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else np.asarray(image, np.float32)
        free = ~np.asarray(covered, bool)
        if self.total is None:
            self.total = np.zeros(img.shape[:2] + (3,), np.float32)
            self.count = np.zeros(img.shape[:2], np.int32)
        self.total[free] += img[free][:, :3]
        self.count += free
        self.colours.add(colour_index(image), free)
        self._image = self._table = None

    def image(self) -> np.ndarray | None:
        if self.total is None:
            return None
        if self._image is None:
            known = self.count >= self.min_count
            self._image = np.full(self.total.shape, np.nan, np.float32)
            self._image[known] = self.total[known] / self.count[known][:, None]
        return self._image

    def log_table(self) -> np.ndarray:
        if self._table is None:
            self._table = self.colours.log_table()
        return self._table


def decide(image: np.ndarray, depths: dict, masks: dict, tables: dict, radius: int, prior: float,
           background: Background | None = None) -> dict:
    """{person: (H, W) bool mask} for the people fitted in this image, disjoint. ``image`` (H, W, 3)
    float [0, 1] or uint8; ``depths`` {person: (H, W) body depth} of the people fitted here; ``masks``
    {person: (H, W) bool} their segmented masks so far (the foreground); ``tables`` {person:
    :meth:`ColourModel.log_table`} of every person of the capture with a colour model (a person with a
    table and no depth is not fitted here and only claims their colours; where a fitted person has
    none, the colours cannot speak for them: the masks are returned as they are);
    ``radius``: the grown band in pixels; ``prior``: nats the depth order adds (see the module doc);
    ``background``: the camera's :class:`Background` (its image, NaN where unknown, and its colours)
    or None."""
    import cv2

    h, w = image.shape[:2]
    fitted = list(depths)
    out = {k: np.zeros((h, w), bool) for k in fitted}
    if not fitted:
        return out
    if any(k not in tables for k in fitted):
        return {k: np.array(masks[k], bool) if k in masks else out[k] for k in fitted}
    kernel = _disc(max(1, radius))
    cores = {k: depths[k] < FAR for k in fitted}
    grown = {k: cv2.dilate(cores[k].astype(np.uint8), kernel) > 0 for k in fitted}
    segmented = np.logical_or.reduce([np.asarray(m, bool) for m in masks.values()]) if masks \
        else np.zeros((h, w), bool)
    fg = segmented.copy()
    reach = {k: cv2.dilate(cores[k].astype(np.uint8), _disc(max(1, REACH * radius))) > 0 for k in fitted} \
        if REACH > 1 else grown
    region = np.logical_or.reduce([reach[k] for k in fitted])
    known = len(set(tables) | set(fitted))
    bg = background.image() if background is not None and known > 1 else None
    if bg is not None:   # someone the segmenter lost behind another
        img = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else np.asarray(image, np.float32)
        with np.errstate(invalid="ignore"):
            fg |= np.abs(img[..., :3] - bg).max(axis=-1) > BACKGROUND_TOL   # NaN: False
        fg |= np.isnan(bg[..., 0])   # never seen free of people: the colours decide (below)
    region &= fg
    if not region.any():
        return out
    ys, xs = np.nonzero(region)
    pad = max(1, REACH) * radius + 2
    crop = (slice(max(ys.min() - pad, 0), min(ys.max() + pad + 1, h)),
            slice(max(xs.min() - pad, 0), min(xs.max() + pad + 1, w)))
    index = colour_index(image[crop])
    people = fitted + [k for k in tables if k not in depths]
    colours = np.stack([tables[k][index] for k in people])
    scores = colours.copy()
    if len(people) > 1:   # colours alike (skin, hair) say nothing: the depth order decides there
        top2 = np.sort(colours, axis=0)[-2:]
        scores = np.where(top2[1] - top2[0] < AMBIGUOUS, 0.0, colours - top2[1]).astype(np.float32)
    for i, k in enumerate(fitted):
        allowed = nearest_region(depths[k][crop], [depths[j][crop] for j in fitted if j != k], radius)
        bonus = prior * allowed + 0.5 * prior * grown[k][crop]
        scores[i] += bonus
    # a pixel only the background model calls foreground must be one person's colour, clearly
    if len(people) > 1:
        sure = top2[1] - top2[0] > ADD_MARGIN
        if bg is not None:
            sure &= top2[1] > background.log_table()[index]   # likelier a person's than the background's
        region[crop] &= segmented[crop] | sure
    else:
        region[crop] &= segmented[crop]
    inside = region[crop]
    size = 2 * max(1, int(round(SMOOTH_WINDOW * h))) + 1
    label = np.argmax(scores, axis=0)
    for _ in range(SMOOTH_ROUNDS):   # each pixel leans to the label its neighbours hold (ICM, Potts)
        share = np.stack([cv2.blur(((label == i) & inside).astype(np.float32), (size, size))
                          for i in range(len(people))])
        label = np.argmax(scores + SMOOTH_NATS * share, axis=0)
    for i, k in enumerate(fitted):
        mine = np.zeros((h, w), bool)
        mine[crop] = (label == i) & inside & grown[k][crop]
        if REACH > 1 and len(people) > 1:   # beyond the grown body: their clothes' colour, clearly
            clear = (colours[i] == top2[1]) & (top2[1] - top2[0] > ADD_MARGIN)
            mine[crop] |= (label == i) & inside & reach[k][crop] & clear
        # 1 px clear of what the others' colours claim (their specks opened away): where two
        # people touch, the pixel between them is mixed
        theirs = cv2.morphologyEx(((label != i) & inside).astype(np.uint8), cv2.MORPH_OPEN, _disc(1))
        mine[crop] &= cv2.dilate(theirs, _disc(CLEAR_PX)) == 0
        # keep the parts that touch the person's fitted body (drop specks and stray islands)
        n, comp = cv2.connectedComponents(mine.astype(np.uint8), connectivity=8)
        keep = np.unique(comp[mine & cores[k]])
        out[k] = np.isin(comp, keep[keep != 0]) if n > 1 else mine
    return out
