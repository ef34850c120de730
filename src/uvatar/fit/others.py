"""The other people near the subject, as ``uvatar fit`` saw them, for the subject's masks.

The subject tracker (:mod:`uvatar.fit.identity`) finds the people in view while someone is near the
subject and keeps their triangulated keypoints. The fit writes the ones it saw, per frame, to
``fitting/others.npz`` (:func:`write_others`; this module owns the format: ``frames`` (M,)
the frame of each row, ``points`` (M, K, 3) metres, ``conf`` (M, K), one row per person seen in a
frame). ``uvatar capture masks`` reads them back (:func:`others_at`: a frame's people, interpolated in
time between the frames they were seen in, since the detector misses a person now and then) and
draws each one's region in a view (:func:`other_regions`): strokes along their projected skeleton and
their torso, split by depth into people **in front of** the subject in that view (their pixels are
theirs even over the subject's fitted silhouette) and **beside or behind** it (theirs outside the
silhouette only). Where only the subject is fitted, this is what keeps a bystander walking in front of
the subject out of the subject's masks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.fit.identity import body_centre
from uvatar.io_utils import read_npz, write_npz

__all__ = ["OTHERS_NPZ", "WINDOW_FRAMES", "FRONT_M", "write_others", "read_others", "others_at", "other_regions",
           "skeleton_region"]

OTHERS_NPZ = "others.npz"   # in fitting/, beside (not among) the per-frame keypoints
WINDOW_FRAMES = 10          # a person is interpolated between sightings at most this many frames apart
STROKE = 1 / 6             # their strokes, as a share of their projected height (1/4 measured: fewer bystander pixels, IoU 0.907 -> 0.881)
FRONT_M = 0.1               # a person's torso this much nearer a camera than the subject's: in front of it

# BlazePose skeleton strokes (index pairs) and torso polygon (shoulders, hips)
BONES = ((11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24), (23, 24), (23, 25), (25, 27),
         (24, 26), (26, 28), (27, 31), (28, 32), (15, 19), (16, 20), (0, 11), (0, 12))
TORSO = (11, 12, 24, 23)


def write_others(fitting_dir: str | Path, seen: dict[str, list]) -> None:
    """Write ``seen`` {frame: [(points (K, 3), conf (K,)), ...]} to ``fitting_dir/others.npz``,
    atomically; frames without anyone are left out, and where nobody was seen there is no file (one
    an earlier run left is removed)."""
    rows = [(frame, np.asarray(p, np.float32), np.asarray(c, np.float32))
            for frame, people in sorted(seen.items()) for p, c in people]
    path = Path(fitting_dir) / OTHERS_NPZ
    if not rows:
        path.unlink(missing_ok=True)
        return
    write_npz(path, frames=np.array([r[0] for r in rows], dtype=str), points=np.stack([r[1] for r in rows]),
              conf=np.stack([r[2] for r in rows]))


def read_others(fitting_dir: str | Path) -> dict[str, list]:
    """{frame: [(points (K, 3), conf (K,)), ...]} from ``fitting_dir/others.npz`` ({} without one)."""
    path = Path(fitting_dir) / OTHERS_NPZ
    if not path.is_file():
        return {}
    data = read_npz(path)
    out: dict[str, list] = {}
    for frame, points, conf in zip(data["frames"].tolist(), data["points"], data["conf"], strict=True):
        out.setdefault(str(frame), []).append((points.astype(np.float64), conf.astype(np.float64)))
    return out


def others_at(seen: dict[str, list], frames: list[str], frame: str, window: int = WINDOW_FRAMES) -> list:
    """[(points (K, 3), conf (K,))] the other people at ``frame`` (of the capture's ordered ``frames``):
    those seen there; else each person seen at the nearest frame before and matched (nearest torso
    centre) with one at the nearest frame after, both within ``window`` frames, interpolated linearly
    (a keypoint kept where both saw it); a person seen on one side only, within ``window // 3`` frames,
    as they were."""
    if frame in seen:
        return list(seen[frame])
    t = frames.index(frame)
    seen_at = sorted(frames.index(f) for f in seen if f in frames)
    before = [s for s in seen_at if t - window <= s < t]
    after = [s for s in seen_at if t < s <= t + window]
    a = seen[frames[before[-1]]] if before else []
    b = seen[frames[after[0]]] if after else []
    out, used = [], set()
    b_centres = [body_centre(pb, cb) for pb, cb in b]
    for pa, ca in a:
        ce = body_centre(pa, ca)
        best = None
        for j, cb_centre in enumerate(b_centres):
            if j in used or ce is None or cb_centre is None:
                continue
            d = float(np.linalg.norm(ce - cb_centre))
            if best is None or d < best[0]:
                best = (d, j)
        if best is not None:
            used.add(best[1])
            pb, cb = b[best[1]]
            w = (t - before[-1]) / (after[0] - before[-1])
            both = (ca > 0) & (cb > 0)
            out.append(((1 - w) * pa + w * pb, np.where(both, np.minimum(ca, cb), 0.0)))
        elif t - before[-1] <= window // 3:
            out.append((pa, ca))
    out += [b[j] for j in range(len(b)) if j not in used and after[0] - t <= window // 3]
    return out


def skeleton_region(xy: np.ndarray, ok: np.ndarray, shape: tuple[int, int], width: float = 1 / 6) -> np.ndarray:
    """(H, W) bool: a person drawn from their keypoints ``xy`` (K, 2) pixels (BlazePose order; ``ok``
    (K,) bool the ones to use): strokes along the bones ``width`` of their height wide, the torso
    filled, and a head disc."""
    import cv2

    height = float(np.ptp(xy[ok][:, 1])) if ok.sum() >= 2 else 0.0
    region = np.zeros(shape, np.uint8)
    if height <= 0:
        return region > 0
    stroke = max(2, int(round(height * width)))
    for a, b in BONES:
        if a < len(ok) and b < len(ok) and ok[a] and ok[b]:
            cv2.line(region, tuple(int(v) for v in xy[a]), tuple(int(v) for v in xy[b]), 1, stroke)
    if all(k < len(ok) and ok[k] for k in TORSO):
        cv2.fillPoly(region, [np.round(xy[list(TORSO)]).astype(np.int32)], 1)
    head = [k for k in range(min(11, len(ok))) if ok[k]]
    if head:
        c = xy[head].mean(0)
        cv2.circle(region, (int(c[0]), int(c[1])), int(round(height / 9)), 1, -1)
    return region > 0


def other_regions(others: list, camera, subject_centre: np.ndarray, shape: tuple[int, int]):
    """(front, beside) (H, W) bool, or None where nobody is in view: the regions (:func:`skeleton_region`)
    of the people ``others`` [(points (K, 3), conf (K,))] in ``camera``'s image of ``shape``, those whose
    torso lies more than ``FRONT_M`` nearer the camera than ``subject_centre`` (3,) in ``front``, the rest
    in ``beside``."""
    from uvatar.fit.projection import project_distorted

    depth = float(camera.world_to_camera(np.asarray(subject_centre, np.float64)[None])[0, 2])
    front, beside = np.zeros(shape, bool), np.zeros(shape, bool)
    for points, conf in others:
        ok = np.asarray(conf) > 0
        centre = body_centre(points, conf)
        if ok.sum() < 4 or centre is None:
            continue
        pix, z = project_distorted(camera, np.asarray(points, np.float64))
        ok &= z > 0
        region = skeleton_region(pix, ok, shape, STROKE)
        if float(camera.world_to_camera(centre[None])[0, 2]) < depth - FRONT_M:
            front |= region
        else:
            beside |= region
    if not (front.any() or beside.any()):
        return None
    return front, beside
