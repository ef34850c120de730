"""Person masks for every image of a capture: a segmentation model restricted to the fitted person.

The segmenter (MediaPipe, weights inside the ``uvatar[fit]`` wheel) finds *people*; the capture's
body fit says *which* person: each mask is the segmenter's person probability above a threshold,
kept only inside the fitted body's silhouette grown by ``dilate`` of the image height (clothes,
hair and fit error lie within it), and searched only inside that region's box. A bystander next to
the subject can reach into that grown band: with ``exclude_others`` the keypoint detector runs once
more on the image with the subject's region painted over, and the pixels of the band that lie on
the other person found there (:func:`other_person_region`: thick strokes along their skeleton) are
dropped (the subject's own fitted silhouette is kept whole). Written to ``masks/<cam>/<frame>.png``
atomically; existing masks are kept (a re-run resumes) unless ``overwrite``.

Where other people are fitted too (``uvatar fit --person all``: ``people/<id>/fits``), every fitted
body is rendered with its depth in each view and the masks are ordered by depth
(:func:`nearest_region`): a person keeps a segmented pixel only where their own body is the nearest
fitted body there (each other body grown by the same ``dilate``, at its nearest depth, so a hand or
sleeve of the person in front just beside their fitted outline still counts as theirs), and in
their own grown band only where no other body (grown) lies. Each person gets their own masks
(``masks/`` for the subject, ``people/<id>/masks/``); the detector of ``exclude_others`` is then not
needed (it still runs where the frame has no other fitted body). Before the segmenter runs, the
other people's pixels (their grown bodies, where this person may not take them) are painted over:
a person detector that sees the one in front would otherwise segment them instead. With
``appearance`` (the default), these depth-ordered masks are held back until every image is segmented:
each person's colour model is learned from them over the whole capture, and every image's contested
pixels are decided again by colour and depth together (:mod:`uvatar.fit.appearance`), then written.
A capture with the subject alone is masked as before (no colour pass).

Where only the subject is fitted but ``uvatar fit`` saw other people near it (their keypoints in
``fitting/others.npz``, :mod:`uvatar.fit.others`), each one's region (their projected
skeleton) is dropped from the subject's mask: over the subject's fitted silhouette too where they are in
front of it in that view. A subject mask that still holds more pixels outside the fitted silhouette
than ``max_outside`` of it has someone else's in it (:func:`~uvatar.fit.mask_views.crowded_mask`): it
is written empty, reported as crowded, and so is one covering under a tenth of the silhouette (the
subject hidden behind someone: :func:`~uvatar.fit.mask_views.hidden_mask`); both are recorded in
``masks/views.json`` with the identity-held and partial ones
(:func:`~uvatar.fit.mask_views.unusable_views`, which DVA reads to leave those views out).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar import stage_record
from uvatar.errors import InputError, UvatarError, check_values
from uvatar.fit.depth_order import FAR, body_depth, body_silhouette, nearest_region
from uvatar.fit.depth_order import disc as _disc
from uvatar.fit.mask_views import crowded_mask, hidden_mask, record_views

log = logging.getLogger(__name__)

PARTIAL_FRACTION = 0.5   # a subject mask covering less of its fitted silhouette is reported as partial

__all__ = ["MaskConfig", "body_silhouette", "body_depth", "nearest_region", "person_mask", "write_capture_masks",
           "other_person_region", "hide_body", "posed_vertices", "FAR"]

@dataclass(frozen=True)
class MaskConfig:
    """threshold: person probability above which a pixel is the person; dilate: the fitted body's
    silhouette is grown by this fraction of the image height before it bounds the mask;
    render_width: the silhouette is rendered this wide (then resized), for speed;
    use_fit: restrict to the fitted body (off: the segmenter alone, which also takes bystanders);
    exclude_others: drop the pixels of another person found next to the subject (one more detection
    per image; needs use_fit); appearance: where other people are fitted, per-person colour models
    decide the pixels they contest (:mod:`uvatar.fit.appearance`); appearance_prior: the weight (nats)
    of the depth order against the colours there; max_outside: where ``uvatar fit`` saw other people
    near the subject and only the subject is fitted, a subject mask with more pixels outside its fitted
    silhouette than this share of the silhouette holds someone else's
    (:func:`~uvatar.fit.mask_views.crowded_mask`): written
    empty, reported as crowded."""

    segmenter: str = "mediapipe"
    threshold: float = 0.5
    dilate: float = 0.04
    render_width: int = 360
    use_fit: bool = True
    exclude_others: bool = True
    appearance: bool = True
    appearance_prior: float = 1.0
    max_outside: float = 0.3
    overwrite: bool = False

    def __post_init__(self) -> None:
        check_values([
            (0.0 < self.threshold < 1.0, f"threshold must be in (0, 1), got {self.threshold}"),
            (0.0 <= self.dilate < 0.5, f"dilate must be in [0, 0.5), got {self.dilate}"),
            (self.render_width >= 32, f"render_width must be at least 32, got {self.render_width}"),
            (0.0 <= self.appearance_prior < 100.0,
             f"appearance_prior must be in [0, 100) nats, got {self.appearance_prior}"),
            (self.max_outside > 0.0, f"max_outside must be above 0, got {self.max_outside}"),
        ])


def hide_body(images: list, cameras: list, vertices: np.ndarray, faces: np.ndarray, grow: float,
              render_width: int = 360) -> list[np.ndarray]:
    """The images (H, W, 3) float32 with the body mesh's silhouette, grown by ``grow`` of the image
    height, painted in each image's median colour (one per camera)."""
    import cv2

    out = []
    for image, cam in zip(images, cameras, strict=True):
        sil = body_silhouette(vertices, faces, cam, render_width)
        sil = cv2.dilate(sil.astype(np.uint8), _disc(max(1, int(round(grow * cam.height))))) > 0
        out.append(painted_over(image, sil))
    return out


def painted_over(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A float32 copy of ``image`` (H, W, C) with the pixels of ``mask`` (H, W) bool in the image's
    median colour (what a person detector or segmenter should not see)."""
    img = np.array(image, np.float32, copy=True)
    img[mask] = np.median(img.reshape(-1, img.shape[-1]), axis=0)
    return img


def other_person_region(image: np.ndarray, subject: np.ndarray, detector, min_conf: float = 0.5) -> np.ndarray | None:
    """(H, W) bool: where another person lies, or None when none is found. ``subject`` (H, W) bool is
    painted over (the image's median colour) before the detector (BlazePose keypoints) runs; the
    region is the person's skeleton (:func:`uvatar.fit.others.skeleton_region`)."""
    from uvatar.fit.others import skeleton_region

    img = painted_over(image, subject)
    det = detector.detect(img)
    ok = det.conf >= min_conf
    if ok.sum() < 6:
        return None
    region = skeleton_region(det.xy.astype(np.float64), ok, image.shape[:2])
    return region if region.any() else None


def _box(mask: np.ndarray) -> tuple[float, float, float, float]:
    ys, xs = np.nonzero(mask)
    return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())


def dilate_px(config: MaskConfig, height: int) -> int:
    """The silhouette's growth in pixels for an image ``height`` pixels high."""
    return max(1, int(round(config.dilate * height)))


def person_mask(image: np.ndarray, segmenter, prior: np.ndarray | None, config: MaskConfig,
                detector=None, allowed: np.ndarray | None = None, hide: np.ndarray | None = None,
                others: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(H, W) bool person mask of ``image`` (H, W, 3) float32 [0,1]; ``prior`` (H, W) bool is the
    fitted body's silhouette (None: the segmenter alone); with ``detector`` (and a prior), another
    person's pixels in the grown band are dropped (:func:`other_person_region`); ``allowed`` (H, W)
    bool: the only pixels the person may take (:func:`nearest_region`, where others are fitted);
    ``hide`` (H, W) bool: pixels painted over (the image's median colour) before the segmenter runs,
    e.g. the other people in front, so that it finds this person and not them (where it then finds
    nobody, e.g. a person mostly hidden, it runs once more on the image as it is, around the whole
    fitted body); ``others``: (front, beside) (H, W) bool, the regions of people the fit saw near the
    subject but did not fit (:func:`uvatar.fit.others.other_regions`): dropped from the mask, those in
    front of the subject even over its fitted silhouette, the others outside it."""

    import cv2

    shown = image
    if hide is not None and hide.any():
        shown = painted_over(image, hide)

    roi = whole_roi = None
    region = None
    if prior is not None:
        grow = dilate_px(config, image.shape[0])
        if allowed is not None and prior.any():
            x0, y0, x1, y1 = _box(prior)   # the whole body's grown box
            h, w = prior.shape
            whole_roi = (max(x0 - grow, 0.0), max(y0 - grow, 0.0), min(x1 + grow, w - 1.0), min(y1 + grow, h - 1.0))
            prior = prior & allowed
        if not prior.any():
            return np.zeros(image.shape[:2], bool)
        kernel = _disc(grow)
        region = cv2.dilate(prior.astype(np.uint8), kernel) > 0
        if allowed is not None:
            region &= allowed
        roi = _box(region)
    prob = segmenter.segment(shown, roi=roi)
    if shown is not image and not (prob[region] > config.threshold).any():
        # nobody found with the others painted over (a person mostly hidden): the image as it is,
        # around the whole body (the segmenter may find them only together with the one in front)
        prob = segmenter.segment(image, roi=whole_roi)
    mask = prob > config.threshold
    if region is not None:
        mask &= region
        if detector is not None:
            other = other_person_region(image, region, detector)
            if other is not None:
                mask &= ~other | prior
        if others is not None:
            front, beside = others
            mask &= ~front & (~beside | prior)
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


def posed_vertices(body, capture, frame: str) -> np.ndarray:
    """(V, 3) the body of ``capture``'s person posed by their fit of ``frame``."""
    import torch

    fit = capture.load_fit(frame)
    shapes = fit.shapes if fit.shapes.size else capture.body_shapes
    with torch.no_grad():
        posed = body.pose(body.joint_rotvecs_from_fit(fit), Rh=fit.Rh, Th=fit.Th, scale=[fit.scale],
                          shape=torch.as_tensor(shapes) if shapes.size else None)
    return posed.vertices[0].cpu().numpy()


def write_capture_masks(root: str | Path, config: MaskConfig | None = None, progress: bool = True,
                        model_dir: str | None = None) -> dict:
    """Masks for every (camera, frame) image of the capture at ``root``, for the subject and every
    other fitted person (``people/<id>/``, depth-ordered; see the module doc); returns a summary
    ({"written", "kept", "failed": {image: reason}, "not_seen": images of another person's frames
    without a fit, "people": ids, "colour_pixels": {person: confident pixels of their colour model}
    with ``appearance``, "identity_held": "cam/frame" of the frames where ``uvatar fit`` held the
    subject's identity (lost or ambiguous: no fit; an empty mask is written), "partial": {frame:
    cameras} where the subject's mask covers less than ``PARTIAL_FRACTION`` of its fitted silhouette
    (hidden behind someone, or cut off), "crowded": {frame: cameras} where another person overlaps the
    subject and their pixels cannot be told apart (``MaskConfig.max_outside``) or hides it
    (:func:`~uvatar.fit.mask_views.hidden_mask`); an empty mask is written}; the three are also written to ``masks/views.json``,
    :func:`~uvatar.fit.mask_views.record_views`). Needs fits unless ``config.use_fit`` is off (then the subject's masks
    alone, from the segmenter). With ``appearance`` and other people, the masks are written after
    every image is segmented (the colour models need them all; held in memory, packed)."""
    from tqdm import tqdm

    from uvatar.body.registry import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.others import other_regions, others_at, read_others
    from uvatar.fit.segment import load_segmenter

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
    people = [capture] + ([capture.for_person(p) for p in capture.people()] if config.use_fit else [])
    body = load_body_model(capture.body_model, model_dir) if config.use_fit else None
    segmenter = load_segmenter(config.segmenter)
    detector = None
    if body is not None and config.exclude_others:
        from uvatar.fit.keypoints import load_detector

        detector = load_detector("mediapipe")
    jobs = [(f, c) for f in frames for c in cameras]
    _begin_record(capture, people, config, len(jobs) * len(people))
    summary = {"written": 0, "kept": 0, "failed": {}, "not_seen": 0, "people": [p.person for p in people[1:]],
               "identity_held": [], "partial": {}, "crowded": {}}
    fit_record = (capture.info.get("provenance") or {}).get("fit") or {}
    held = set(fit_record.get("identity_held") or ()) if config.use_fit else set()
    others_near = bool(fit_record.get("other_people_seen") or held)   # the fit saw someone beside the subject
    seen_others = read_others(capture.person_root / "fitting") if config.use_fit else {}
    colour = _ColourPass(config, people, cameras) if config.appearance and body is not None \
        and len(people) > 1 else None
    poser = _Poser(body, people)
    for n, (frame, cam_name) in enumerate(tqdm(jobs, desc="masks", unit="image", disable=not progress,
                                               dynamic_ncols=True)):
        if n and colour is None:  # the masks of the images before this one are on disk ("5 of 12 masks")
            stage_record.mark_progress(capture.masks_dir, n * len(people))
        todo = [k for k, p in enumerate(people)
                if config.overwrite or not (p.masks_dir / cam_name / f"{frame}.png").is_file()]
        summary["kept"] += len(people) - len(todo)
        if not todo:
            continue
        if frame in held and 0 in todo:   # the fit left the subject's identity open: no pixel is surely theirs
            image_shape = (cameras[cam_name].height, cameras[cam_name].width)
            _write_mask(capture, cam_name, frame, np.zeros(image_shape, bool), summary)
            summary["identity_held"].append(f"{cam_name}/{frame}")
            todo = [k for k in todo if k != 0]
            if not todo:
                continue
        posed = poser.frame(frame)
        try:
            image = _load_image(capture, cam_name, frame)
        except UvatarError as exc:
            for k in todo:
                _failed(summary, people[k], cam_name, frame, exc)
            continue
        cam = cameras[cam_name]
        depths = {k: body_depth(v, body.template.faces, cam, config.render_width) for k, v in posed.items()}
        masks = {}
        for k in todo:
            person = people[k]
            if k and k not in depths:
                summary["not_seen"] += 1   # another person not detected in this frame: no fit, no mask
                continue
            try:
                prior = allowed = hide = None
                others = [d for j, d in depths.items() if j != k]
                if body is not None:
                    if k not in depths:
                        raise InputError(person.fit_path(frame), "no fit for this frame")
                    prior = depths[k] < FAR
                    if others:
                        allowed, hide = _depth_order(depths, k, dilate_px(config, cam.height))
                near = None
                if k == 0 and not others and seen_others:   # people the fit saw but did not fit
                    near = other_regions(others_at(seen_others, frames, frame), cam,
                                         posed[0].mean(0), prior.shape)
                masks[k] = person_mask(image, segmenter, prior, config, None if others else detector, allowed,
                                       hide, near)
                if k == 0 and not others and others_near and (crowded_mask(masks[k], prior, config.max_outside)
                                                              or hidden_mask(masks[k], prior)):
                    summary["crowded"].setdefault(frame, []).append(cam_name)   # someone else's pixels too
                    masks[k] = np.zeros_like(masks[k])
                    continue
                if k == 0 and prior is not None and prior.any() and \
                        (masks[k] & prior).sum() < PARTIAL_FRACTION * prior.sum():
                    summary["partial"].setdefault(frame, []).append(cam_name)   # hidden or cut off in this view
            except UvatarError as exc:
                _failed(summary, person, cam_name, frame, exc)
        if colour is not None:
            colour.learn(frame, cam_name, image, depths, masks)
        else:
            for k, mask in masks.items():
                _write_mask(people[k], cam_name, frame, mask, summary)
    if colour is not None:
        colour.finish(poser, body, capture, summary)
    if summary["written"] + summary["kept"] == 0:
        raise InputError(capture.root, f"{len(jobs)} images, no mask written: "
                                       f"{len(summary['failed'])} failed (first: "
                                       f"{next(iter(summary['failed'].values()), '-')})")
    record_views(capture, summary, rewritten=config.overwrite)
    # every image was looked at: those that failed are reported (a property of the image, not a half-made run)
    stage_record.finish(capture.masks_dir)
    return summary


def _begin_record(capture, people: list, config: MaskConfig, total: int) -> None:
    """The stage record of ``masks/`` (:mod:`uvatar.stage_record`), before any mask is written: the
    settings (every MaskConfig field but ``overwrite``) and the fits the masks are cut from (the
    subject's and every other person's). A rerun with other settings, or after a fit was redone, is
    refused in one line (the masks on disk would be kept) unless ``overwrite``, which writes every mask
    again; until the last image the record says the masks are half made, and ``uvatar fit --masks`` and
    ``uvatar train dva`` refuse them (:func:`require_masks`). The temp files of writes a kill cut short
    are removed."""
    from uvatar.io_utils import sweep_partial_writes

    fits = [p.fits_dir for p in people] if config.use_fit else []
    stage_record.begin(capture.masks_dir, "capture masks", stage_record.config_values(config, drop=("overwrite",)),
                       stage_record.file_identities(*fits), total=total,
                       on_change="redo" if config.overwrite else "refuse",
                       redo_hint="overwrite=True writes every mask again")
    for person in people:  # temp files of mask writes a kill cut short (masks/00/.000003.*.png)
        sweep_partial_writes(person.masks_dir)


def require_masks(root) -> None:
    """Refuse, in one line, masks that ``uvatar capture masks`` left half made (killed before its last
    image); masks without a record (a synthetic capture's, or made before records) are taken as they are."""
    stage_record.require_complete(Path(root) / "masks", "capture masks", f"uvatar capture masks {root}",
                                  unit="masks", check_inputs=False)


def _load_image(capture, cam_name: str, frame: str) -> np.ndarray:
    image_path = capture.image_path(cam_name, frame)
    if not image_path.is_file():
        raise InputError(image_path, "image is missing")
    return capture.load_image(cam_name, frame)


def _write_mask(person, cam_name: str, frame: str, mask: np.ndarray, summary: dict) -> None:
    from uvatar.io_utils import write_image

    write_image(person.masks_dir / cam_name / f"{frame}.png", mask.astype(np.uint8) * 255)
    summary["written"] += 1
    if person.person is None:
        summary.setdefault("_subject_written", set()).add(f"{cam_name}/{frame}")


def _depth_order(depths: dict, k: int, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(allowed, hide) of person ``k`` among the fitted bodies ``depths``: :func:`nearest_region`, and
    the others' grown bodies where ``k`` may not take them (painted over before the segmenter runs)."""
    import cv2

    others = [d for j, d in depths.items() if j != k]
    allowed = nearest_region(depths[k], others, radius)
    near = cv2.dilate(np.logical_or.reduce([d < FAR for d in others]).astype(np.uint8), _disc(radius)) > 0
    return allowed, near & ~allowed


class _Poser:
    """The posed vertices {person index: (V, 3)} of one frame at a time (the people fitted there)."""

    def __init__(self, body, people: list) -> None:
        self.body, self.people, self.name, self.posed = body, people, None, {}

    def frame(self, frame: str) -> dict:
        if self.name != frame:
            self.name = frame
            self.posed = {k: posed_vertices(self.body, p, frame) for k, p in enumerate(self.people)
                          if self.body is not None and p.has_fit(frame)}
        return self.posed


class _ColourPass:
    """The masks of a capture with other people, held back (packed) while every person's colour model
    learns from the images (:meth:`learn`), then decided again with the colours and written
    (:meth:`finish`; :mod:`uvatar.fit.appearance`)."""

    DEPTH_CACHE = 512 * 2 ** 20   # bytes of rendered depths kept for the second pass (the rest re-rendered)

    def __init__(self, config: MaskConfig, people: list, cameras: dict) -> None:
        from uvatar.fit.appearance import Background, ColourModel

        self.config, self.people, self.cameras = config, people, cameras
        self.models = [ColourModel() for _ in people]
        self.pending: dict[tuple[str, str], dict[int, np.ndarray]] = {}
        self.backgrounds = {c: Background() for c in cameras}
        self.depths: dict[tuple[str, str], dict[int, np.ndarray]] = {}
        self.cached = 0

    def learn(self, frame: str, cam_name: str, image: np.ndarray, depths: dict, masks: dict) -> None:
        import cv2

        from uvatar.fit.appearance import colour_index, confident_pixels

        u8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if masks:
            self.pending[(frame, cam_name)] = {k: np.packbits(m) for k, m in masks.items()}
            size = sum(d.nbytes for d in depths.values())
            if self.cached + size <= self.DEPTH_CACHE:
                self.depths[(frame, cam_name)], self.cached = depths, self.cached + size
        if len(depths) < len(self.people):
            return   # someone is not fitted in this frame: their pixels may lie in anyone's
        index = colour_index(u8)
        radius = dilate_px(self.config, image.shape[0])
        covered = np.logical_or.reduce([d < FAR for d in depths.values()] + list(masks.values()))
        self.backgrounds[cam_name].add(u8, cv2.dilate(covered.astype(np.uint8), _disc(2 * radius)) > 0)
        for k, mask in masks.items():
            others = [d for j, d in depths.items() if j != k]
            allowed = nearest_region(depths[k], others, radius)
            self.models[k].add(index, confident_pixels(mask, depths[k], others, allowed, radius))

    def finish(self, poser: _Poser, body, capture, summary: dict) -> None:
        from uvatar.fit.appearance import MIN_PIXELS, decide

        tables = {k: m.log_table() for k, m in enumerate(self.models) if m.pixels >= MIN_PIXELS}
        summary["colour_pixels"] = {("subject" if p.person is None else p.person): m.pixels
                                    for p, m in zip(self.people, self.models, strict=True)}
        for (frame, cam_name), packed in self.pending.items():
            cam = self.cameras[cam_name]
            shape = (cam.height, cam.width)
            masks = {k: np.unpackbits(p, count=shape[0] * shape[1]).reshape(shape).astype(bool)
                     for k, p in packed.items()}
            depths = self.depths.pop((frame, cam_name), None)
            if depths is None:
                depths = {k: body_depth(v, body.template.faces, cam, self.config.render_width)
                          for k, v in poser.frame(frame).items()}
            for k in depths:   # kept masks (a resumed run) are foreground too
                path = self.people[k].masks_dir / cam_name / f"{frame}.png"
                if k not in masks and path.is_file():
                    masks[k] = self.people[k].load_mask(cam_name, frame)
            image = capture.load_image(cam_name, frame)
            decided = decide(image, depths, masks, tables, dilate_px(self.config, cam.height),
                             self.config.appearance_prior, self.backgrounds[cam_name])
            for k in packed:
                _write_mask(self.people[k], cam_name, frame, decided[k], summary)


def _failed(summary: dict, person, cam_name: str, frame: str, exc: Exception) -> None:
    who = "" if person.person is None else f"people/{person.person}/"
    summary["failed"][f"{who}{cam_name}/{frame}"] = str(exc)
    log.warning("%s%s/%s: %s", who, cam_name, frame, exc)
