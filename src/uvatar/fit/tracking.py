"""The subject over time: left/right labels kept consistent from frame to frame, and cuts between takes.

Left/right: per frame, :func:`uvatar.fit.observe.resolve_left_right` decides the labels from the
frame alone (the face direction); a person seen from above or turning fast flips that decision now
and then, and the whole triangulated body then jumps to its mirror image (on the shared real
recording: 0.55 m median jump, 6 false cuts in 100 frames). :func:`track_left_right` relabels each
frame to follow the previous one where its mirror image is clearly the closer, then lets the
majority of each continuous stretch decide the labelling of the whole stretch.

Cuts: a change of take or camera set-up moves *every* keypoint at once (fast motion moves the limbs,
not the whole body in one frame) and changes the image content (the background, the framing);
:func:`continuity` asks for both where image thumbnails exist (:func:`image_thumbnail`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["continuity", "image_thumbnail", "image_change", "track_left_right"]

THUMB = 24            # thumbnail side (pixels)
JUMP_FRACTION = 0.9   # share of the shared keypoints that must move farther than the cut distance
PIXEL_CHANGE = 0.1    # a thumbnail pixel changed when its grey level moved more than this
IMAGE_FRACTION = 0.15  # share of changed thumbnail pixels for a view's content to have changed


def image_thumbnail(image: np.ndarray, side: int = THUMB) -> np.ndarray:
    """(side, side) float32 grey thumbnail (box-averaged) of an image (H, W, 3) float32 in [0, 1]."""
    img = np.asarray(image, np.float32)
    grey = img.mean(axis=-1) if img.ndim == 3 else img
    H, W = grey.shape
    ys = np.linspace(0, H, side + 1).astype(int)
    xs = np.linspace(0, W, side + 1).astype(int)
    rows = np.add.reduceat(grey, ys[:-1], axis=0) / np.diff(ys)[:, None]
    return (np.add.reduceat(rows, xs[:-1], axis=1) / np.diff(xs)[None, :]).astype(np.float32)


def image_change(thumbs: np.ndarray | None) -> np.ndarray | None:
    """thumbs (T, C, S, S) grey thumbnails (nan where a frame has none) -> (T-1,) bool: True where the
    content changed in at least half of the views (``IMAGE_FRACTION`` of its thumbnail pixels by more than ``PIXEL_CHANGE``), or where either frame has
    no thumbnails (unknown: the keypoints decide alone). None for None."""
    if thumbs is None:
        return None
    t = np.asarray(thumbs, np.float32)
    changed = (np.abs(t[1:] - t[:-1]) > PIXEL_CHANGE).mean(axis=(-1, -2))   # (T-1, C)
    known = np.isfinite(t).all(axis=(-1, -2))                                          # (T, C)
    both = known[1:] & known[:-1]
    views = (changed > IMAGE_FRACTION) & both
    return np.where(both.any(1), views.sum(1) * 2 >= np.maximum(both.sum(1), 1), True)


def continuity(points: np.ndarray, conf: np.ndarray, cut_distance: float,
               changed: np.ndarray | None = None) -> np.ndarray:
    """(T-1,) bool: False (a cut) where at least ``JUMP_FRACTION`` of the keypoints
    triangulated in both frames t and t+1 (points (T, K, 3) metres, conf (T, K)) move farther than
    ``cut_distance`` and, with ``changed`` ((T-1,) bool from :func:`image_change`), the images changed
    too. True where fewer than 3 keypoints are shared (an undetected frame is bridged by smoothness)."""
    both = (conf[1:] > 0) & (conf[:-1] > 0)
    far = np.linalg.norm(points[1:] - points[:-1], axis=-1) > cut_distance
    shared = both.sum(1)
    jumped = (far & both).sum(1) >= JUMP_FRACTION * np.maximum(shared, 1)
    cut = (shared >= 3) & jumped
    if changed is not None:
        cut &= np.asarray(changed, bool)
    return ~cut


def _median_step(a: np.ndarray, ca: np.ndarray, b: np.ndarray, cb: np.ndarray) -> float:
    both = (ca > 0) & (cb > 0)
    if both.sum() < 3:
        return np.inf
    return float(np.median(np.linalg.norm(a[both] - b[both], axis=-1)))


def track_left_right(points: np.ndarray, conf: np.ndarray, perm: np.ndarray, cut_distance: float) -> np.ndarray:
    """(T,) bool: frames whose left/right labels to swap (points (T, K, 3), conf (T, K), perm (K,) the
    left/right permutation of :func:`uvatar.fit.observe.left_right_swap`).

    A frame is swapped against the previous detected frame (as relabelled) when its mirror image is
    within ``cut_distance`` of it and less than half as far as the frame as labelled; a frame that
    follows neither way starts a new stretch. Each stretch then keeps the labelling most of its frames
    had on their own (the per-frame face-direction rule)."""
    T = len(points)
    swap = np.zeros(T, bool)
    stretch = np.full(T, -1)
    prev, current = None, -1
    for t in range(T):  # T frames, each a vectorised median over its keypoints
        if (conf[t] > 0).sum() < 3:
            continue
        if prev is not None:
            ref = points[prev][perm] if swap[prev] else points[prev]
            cref = conf[prev][perm] if swap[prev] else conf[prev]
            keep = _median_step(points[t], conf[t], ref, cref)
            flip = _median_step(points[t][perm], conf[t][perm], ref, cref)
            if flip <= cut_distance and flip < 0.5 * keep:
                swap[t] = True
            elif keep > cut_distance:
                current += 1  # neither labelling follows: another take (or a lost track)
        if prev is None:
            current += 1
        stretch[t] = current
        prev = t
    for s in range(current + 1):
        members = stretch == s
        if swap[members].sum() * 2 > members.sum():
            swap[members] = ~swap[members]
    return swap
