"""Person masks for every image of a capture: a segmentation model restricted to the fitted person.

The segmenter (MediaPipe, weights inside the ``uvatar[fit]`` wheel) finds *people*; the capture's
body fit says *which* person: each mask is the segmenter's person probability above a threshold,
kept only inside the fitted body's silhouette grown by ``dilate`` of the image height (clothes,
hair and fit error lie within it), and searched only inside that region's box. A bystander next to
the subject can reach into that grown band: with ``exclude_others`` the keypoint detector runs once
more on the image with the subject's region painted over, and the pixels of the band that lie on
the other person found there (:func:`other_person_region`: thick strokes along their skeleton) are
dropped (the subject's own fitted silhouette is kept whole). Written to ``masks/<cam>/<frame>.png`` atomically; existing masks are kept (a
re-run resumes) unless ``overwrite``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.errors import InputError, UvatarError, check_values

log = logging.getLogger(__name__)

__all__ = ["MaskConfig", "body_silhouette", "person_mask", "write_capture_masks", "other_person_region"]

# BlazePose skeleton strokes (index pairs) drawn for another person's region
_BONES = ((11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24), (23, 24), (23, 25), (25, 27),
          (24, 26), (26, 28), (27, 31), (28, 32), (15, 19), (16, 20), (0, 11), (0, 12))


@dataclass(frozen=True)
class MaskConfig:
    """threshold: person probability above which a pixel is the person; dilate: the fitted body's
    silhouette is grown by this fraction of the image height before it bounds the mask;
    render_width: the silhouette is rendered this wide (then resized), for speed;
    use_fit: restrict to the fitted body (off: the segmenter alone, which also takes bystanders);
    exclude_others: drop the pixels of another person found next to the subject (one more detection
    per image; needs use_fit)."""

    segmenter: str = "mediapipe"
    threshold: float = 0.5
    dilate: float = 0.04
    render_width: int = 360
    use_fit: bool = True
    exclude_others: bool = True
    overwrite: bool = False

    def __post_init__(self) -> None:
        check_values([
            (0.0 < self.threshold < 1.0, f"threshold must be in (0, 1), got {self.threshold}"),
            (0.0 <= self.dilate < 0.5, f"dilate must be in [0, 0.5), got {self.dilate}"),
            (self.render_width >= 32, f"render_width must be at least 32, got {self.render_width}"),
        ])


def body_silhouette(vertices: np.ndarray, faces: np.ndarray, camera, render_width: int) -> np.ndarray:
    """(H, W) bool: where the body mesh (V, 3) world metres covers ``camera``'s image (rendered
    ``render_width`` wide by ray casting, then resized to the camera's size)."""
    import cv2

    from uvatar.render.mesh_renderer import render_mesh

    small = camera.scaled_to_width(min(render_width, camera.width))
    mask = render_mesh(vertices, faces, small).mask.astype(np.uint8)
    return cv2.resize(mask, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST) > 0


def other_person_region(image: np.ndarray, subject: np.ndarray, detector, min_conf: float = 0.5) -> np.ndarray | None:
    """(H, W) bool: where another person lies, or None when none is found. ``subject`` (H, W) bool is
    painted over (the image's median colour) before the detector (BlazePose keypoints) runs; the
    region is the person's skeleton drawn with strokes 1/6 of their height wide, and a head disc."""
    import cv2

    img = np.array(image, np.float32, copy=True)
    img[subject] = np.median(img.reshape(-1, 3), axis=0)
    det = detector.detect(img)
    ok = det.conf >= min_conf
    if ok.sum() < 6:
        return None
    xy = det.xy.astype(np.float64)
    height = float(np.ptp(xy[ok][:, 1])) or 1.0
    width = max(2, int(round(height / 6)))
    region = np.zeros(image.shape[:2], np.uint8)
    for a, b in _BONES:
        if ok[a] and ok[b]:
            cv2.line(region, tuple(int(v) for v in xy[a]), tuple(int(v) for v in xy[b]), 1, width)
    head = [k for k in range(11) if ok[k]]
    if head:
        c = xy[head].mean(0)
        cv2.circle(region, (int(c[0]), int(c[1])), int(round(height / 9)), 1, -1)
    region = region > 0
    return region if region.any() else None


def person_mask(image: np.ndarray, segmenter, prior: np.ndarray | None, config: MaskConfig,
                detector=None) -> np.ndarray:
    """(H, W) bool person mask of ``image`` (H, W, 3) float32 [0,1]; ``prior`` (H, W) bool is the
    fitted body's silhouette (None: the segmenter alone); with ``detector`` (and a prior), another
    person's pixels in the grown band are dropped (:func:`other_person_region`)."""
    import cv2

    h = image.shape[0]
    roi = None
    region = None
    if prior is not None:
        if not prior.any():
            return np.zeros(image.shape[:2], bool)
        r = max(1, int(round(config.dilate * h)))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        region = cv2.dilate(prior.astype(np.uint8), kernel) > 0
        ys, xs = np.nonzero(region)
        roi = (float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max()))
    prob = segmenter.segment(image, roi=roi)
    mask = prob > config.threshold
    if region is not None:
        mask &= region
        if detector is not None:
            other = other_person_region(image, region, detector)
            if other is not None:
                mask &= ~other | prior
    # keep the connected component(s) that overlap the body, drop specks
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if count > 2:
        if prior is not None:
            keep = np.unique(labels[prior & mask])
        else:
            sizes = np.bincount(labels.ravel())
            sizes[0] = 0
            keep = [int(sizes.argmax())]
        mask = np.isin(labels, [k for k in keep if k != 0])
    return mask


def write_capture_masks(root: str | Path, config: MaskConfig | None = None, progress: bool = True,
                        model_dir: str | None = None) -> dict:
    """Masks for every (camera, frame) image of the capture at ``root``; returns a summary
    ({"written", "kept", "failed": {image: reason}}). Needs fits unless ``config.use_fit`` is off."""
    import torch
    from tqdm import tqdm

    from uvatar.body.registry import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.segment import load_segmenter
    from uvatar.io_utils import write_image

    config = config or MaskConfig()
    capture = Capture(root)
    cameras = capture.cameras()
    if not cameras:
        raise InputError(capture.cameras_dir, "the capture has no cameras (cameras/intri.yml, extri.yml)")
    frames = capture.frames
    if config.use_fit:
        missing = [f for f in frames if not capture.has_fit(f)]
        if len(missing) == len(frames):
            raise InputError(capture.fits_dir, "no fits: run `uvatar fit` first (or use_fit=False to use the "
                                               "segmenter alone, which also masks bystanders)")
    body = load_body_model(capture.body_model, model_dir) if config.use_fit else None
    segmenter = load_segmenter(config.segmenter)
    detector = None
    if body is not None and config.exclude_others:
        from uvatar.fit.keypoints import load_detector

        detector = load_detector("mediapipe")
    summary = {"written": 0, "kept": 0, "failed": {}}
    jobs = [(f, c) for f in frames for c in cameras]
    for frame, cam_name in tqdm(jobs, desc="masks", unit="image", disable=not progress, dynamic_ncols=True):
        out = capture.root / "masks" / cam_name / f"{frame}.png"
        if out.is_file() and not config.overwrite:
            summary["kept"] += 1
            continue
        try:
            image_path = capture.image_path(cam_name, frame)
            if not image_path.is_file():
                raise InputError(image_path, "image is missing")
            image = capture.load_image(cam_name, frame)
            prior = None
            if body is not None:
                if not capture.has_fit(frame):
                    raise InputError(capture.fit_path(frame), "no fit for this frame")
                fit = capture.load_fit(frame)
                shapes = fit.shapes if fit.shapes.size else capture.body_shapes
                with torch.no_grad():
                    posed = body.pose(body.joint_rotvecs_from_fit(fit), Rh=fit.Rh, Th=fit.Th, scale=[fit.scale],
                                      shape=torch.as_tensor(shapes) if shapes.size else None)
                prior = body_silhouette(posed.vertices[0].cpu().numpy(), body.template.faces, cameras[cam_name],
                                        config.render_width)
            write_image(out, person_mask(image, segmenter, prior, config, detector).astype(np.uint8) * 255)
            summary["written"] += 1
        except UvatarError as exc:
            summary["failed"][f"{cam_name}/{frame}"] = str(exc)
            log.warning("%s/%s: %s", cam_name, frame, exc)
    if summary["written"] + summary["kept"] == 0:
        raise InputError(capture.root, f"{len(jobs)} images, no mask written: "
                                       f"{len(summary['failed'])} failed (first: "
                                       f"{next(iter(summary['failed'].values()), '-')})")
    return summary
