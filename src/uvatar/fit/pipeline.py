"""``uvatar fit``: body fits for a capture that comes without them (AVH §3.1, DVA's LBS tracking).

keypoints per view (detector) -> triangulation -> one batched body fit of the whole sequence (one
shape for all frames) -> ``fits/<frame>.json`` (EasyMocap) + the shape and provenance in
``capture.json`` + ``fitting/`` (per-frame keypoints, overlays, contact sheet, summary.json).

Resumable: each frame's keypoints are written as soon as they are detected and reused by a re-run.
One frame whose detection fails is reported and fitted from its neighbours (temporal smoothness) or
its scan alone; it never stops the run. Existing fits are never replaced without ``force``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from uvatar import stage_record
from uvatar.capture.layout import CAPTURE_JSON, PERSON_JSON, Capture
from uvatar.errors import InputError, UvatarError, check_values
from uvatar.fit.calibration import refine_capture_cameras
from uvatar.fit.identity import SubjectTracker, body_centre
from uvatar.fit.identity_frame import identity_report, images_changed, track_frame
from uvatar.fit.others import OTHERS_NPZ, read_others, write_others
from uvatar.fit.people import build_so_far, choose_people, find_again, frame_views, is_at, lost, subject_hider
from uvatar.fit.records import (
    IDENTITY_JSON,
    check_person_choice,
    fit_inputs,
    fit_record_config,
    keypoint_record_config,
    read_identity_record,
    write_identity_record,
)
from uvatar.fit.sequence import relabel_left_right, scan_inputs, stack_observations
from uvatar.fit.stages import FitStages
from uvatar.io_utils import read_json, write_json

log = logging.getLogger(__name__)

__all__ = ["FitConfig", "FIT_SOURCES", "fit_capture", "resolve_source"]

FIT_SOURCES = ("auto", "scans", "images")
MIN_SCAN_VIEWS_SEEN = 0.75  # share of a scan's virtual views that must show a person


@dataclass(frozen=True)
class FitConfig:
    """What ``uvatar fit`` fits from and what it writes.

    source: "scans" (render each textured scan from virtual cameras and detect there), "images"
        (the capture's calibrated cameras), or "auto" (images when the capture has cameras and
        images, else scans); scans, when present, always add the scan-distance term.
    scan_distance: add the scan-surface distance term where the capture has scans (off: fit to the
        keypoints alone, as for a video capture).
    scan_points: points sampled on each scan for the scan-distance term.
    cut_distance: metres; where the median triangulated keypoint moves farther than this from one
        frame to the next, the capture cuts to another take and no smoothness ties the two frames.
    photo_size: pixels of the unshaded scan renders the photometric term compares across frames
        (where scans exist and the body config's ``w_photo`` > 0; 0: off).
    overlay_frames: frames drawn in ``fitting/contact_sheet.png`` (0: none); overlay_width: pixels.
    refine_cameras: before the body fit, turn each camera by the small rotation that makes the
        subject's detections agree across views (:mod:`uvatar.fit.calibration`), write the refined
        calibration to ``cameras/`` (the original kept in ``cameras/before_refine/``) and fit through
        it. On the real 4-camera recording it takes a 9-12 px disagreement out of two views.
    masks: also fit the body's silhouette to the capture's person masks (``masks/``, made by
        ``uvatar capture masks`` from a first fit): inside each mask and out to its outline
        (:class:`~uvatar.fit.losses.MaskTerm`). Keypoints place a body only to the detector's few
        pixels; on the real 4-camera recording the keypoint fit's silhouette IoU is 0.74-0.83 per
        camera (``docs/real.md``).
    mask_cameras: comma-separated names of the cameras whose masks the silhouette term reads (empty:
        every camera). Leave a camera out to keep it held out: a fit to its masks would be tuned to the
        very outline a score on that camera measures.
    force: replace existing fits.
    person: which person to fit from images when several are in view (:mod:`uvatar.fit.person`):
        most-views, largest, centre, nearest-to:X,Y,Z, box:CAM:FRAME:X0,Y0,X1,Y1 or point:CAM:FRAME:X,Y.
    max_speed: m/s; the subject's torso cannot move faster than this between frames: a person found
        farther from where the subject was is another person (:mod:`uvatar.fit.identity`).
    """

    source: str = "auto"
    model: str = "anny"
    model_dir: str | None = None
    detector: str = "mediapipe"
    scan_distance: bool = True
    scan_points: int = 3000
    cut_distance: float = 0.1
    photo_size: int = 256
    overlay_frames: int = 6
    overlay_width: int = 256
    refine_cameras: bool = False
    masks: bool = False
    mask_cameras: str = ""
    force: bool = False
    device: str = "cpu"
    seed: int = 0
    person: str = "most-views"
    max_speed: float = 3.0

    def __post_init__(self) -> None:
        check_values([
            (self.source in FIT_SOURCES, f"source must be one of {', '.join(FIT_SOURCES)}, got {self.source!r}"),
            (self.scan_points >= 100, f"scan_points must be at least 100, got {self.scan_points}"),
            (self.cut_distance > 0, f"cut_distance must be > 0, got {self.cut_distance}"),
            (self.max_speed > 0, f"max_speed must be > 0, got {self.max_speed}"),
            (self.photo_size == 0 or self.photo_size >= 32, f"photo_size must be 0 or >= 32, got {self.photo_size}"),
            (self.overlay_frames >= 0, f"overlay_frames must be >= 0, got {self.overlay_frames}"),
            (self.overlay_width >= 32, f"overlay_width must be at least 32, got {self.overlay_width}"),
        ])


def resolve_source(capture: Capture, source: str) -> str:
    """The concrete source for ``source`` ("auto" picks images when cameras and images exist)."""
    has_images = capture.has_cameras() and (capture.root / "images").is_dir()
    has_scans = capture.scans_dir.is_dir() and any(capture.scans_dir.iterdir())
    if source == "auto":
        source = "images" if has_images else "scans"
    if source == "images" and not has_images:
        raise InputError(capture.root, "source='images' needs cameras/intri.yml, cameras/extri.yml and images/ "
                                         "(a capture of scans alone: source='scans')")
    if source == "scans" and not has_scans:
        raise InputError(capture.scans_dir, "source='scans' needs textured scans in scans/ (a capture of images "
                                              "alone: source='images')")
    return source


def existing_fits(capture: Capture) -> list[Path]:
    """The capture's fit files (``fits/*.json`` and ``fits.npz``)."""
    fits = sorted(capture.fits_dir.glob("*.json")) if capture.fits_dir.is_dir() else []
    npz = capture.person_root / "fits.npz"
    return fits + ([npz] if npz.is_file() else [])


def _detect_all(capture: Capture, frames: list[str], source: str, detector, stages: FitStages,
                progress: bool, choice=None, cut_distance: float = 0.1, chosen=None,
                avoid: dict | None = None, hide=None, max_speed: float = 3.0,
                avoid_held=()) -> tuple[dict, dict, dict]:
    """Per-frame observations, from ``fitting/keypoints`` (the person's own) where a previous run left
    them; failures; the person report (images: the subject chosen at the seed frame, or ``chosen``
    (seed frame, :class:`~uvatar.fit.person.Person`, report) when given, is tracked forward from it,
    then backward; where the track is lost, at a cut, the person of the same build is found again).
    Views that disagree with the person are rejected (:func:`~uvatar.fit.observe.reject_views`).
    ``avoid`` ({frame: the subject's observation}, when another person is tracked): where the track
    lands on the subject, the person is looked for again away from the subject, and a frame where
    only the subject is found is left to its neighbours (a failure), never fitted to the subject;
    ``hide``: see :func:`frame_views` (the detector never sees the subject there). The subject's
    identity is kept by :class:`~uvatar.fit.identity.SubjectTracker` (``max_speed`` m/s): frames where
    it is lost, ambiguous or crowded are failures (``identity lost``/``ambiguous``/``crowded``), reported in
    ``person["identity"]``, and get no fit; ``avoid_held``: those frames of the subject, where another
    person is left out too (who is who is open there, and the subject, unfitted, is not hidden from
    the detector)."""
    from tqdm import tqdm

    from uvatar.fit.observe import (
        disagreeing_views,
        load_observation,
        observation_path,
        observe_frame,
        reject_views,
        save_observation,
    )

    observations, failures = {}, {}
    person = None
    start, seed_prior = 0, None
    if source == "images" and (chosen is not None or (
            choice is not None and not all(observation_path(capture.person_root, f).is_file() for f in frames))):
        seed, seed_prior, person = chosen or choose_people(capture, frames, choice, detector, stages)[0][1:]
        start = frames.index(seed)
        if person is not None and capture.person is None and seed_prior is not None:
            person["identity"] = {"lost": [], "ambiguous": [], "crowded": [], "reassociated": []}
    order = frames[start:] + frames[:start][::-1]   # forward from the seed, then backward from it
    prior = seed_prior
    tracker = (SubjectTracker(max_speed / capture.fps)
               if person is not None and capture.person is None and seed_prior is not None else None)
    held: dict[str, str] = {}
    keypoints_dir = observation_path(capture.person_root, "-").parent
    before = read_identity_record(keypoints_dir) if tracker is not None else {"statuses": {}}
    statuses = dict(before["statuses"])   # {frame: status other than tracked}, kept for a resumed run
    seen_others = read_others(keypoints_dir.parent) if tracker is not None else {}   # {frame: [(points, conf)]}
    if tracker is not None:
        tracker.start(start, body_centre(seed_prior.points, seed_prior.points_conf))
    bar = tqdm(order, desc=f"keypoints ({source})", unit="frame", disable=not progress, dynamic_ncols=True)
    for n, frame in enumerate(bar):
        if start and n == len(frames) - start:
            prior = observations.get(frames[start], seed_prior)  # the backward pass starts at the seed
            if tracker is not None:
                tracker.start(start, body_centre(prior.points, prior.points_conf))
        path = observation_path(capture.person_root, frame)
        t = frames.index(frame)
        try:
            if frame in avoid_held:
                raise UvatarError("the subject's identity is held at this frame (who is who is open); left out")
            status = before["statuses"].get(frame) if tracker is not None else None
            if status in _HELD_WHY:   # held by the run this one resumes: held again, never re-tracked
                person["identity"][status].append(frame)
                held[frame] = status
                raise UvatarError(f"identity {status}: " + _HELD_WHY[status] + "; left out of the fit")
            if path.is_file():
                obs = load_observation(path)
                if obs.source != source:
                    raise InputError(path, f"keypoints come from {obs.source}, not {source}")
                centre = body_centre(obs.points, obs.points_conf) if tracker is not None else None
                if centre is not None:
                    tracker.subject.update(t, centre)
                if status is not None:
                    person["identity"][status].append(frame)
            else:
                images, cameras = frame_views(capture, frame, source, stages, hide)
                use_prior = prior if source == "images" else None
                obs = observe_frame(images, cameras, detector, stages.triangulate, source, prior=use_prior)
                subject = (avoid or {}).get(frame)
                cut = use_prior is not None and lost(use_prior, obs, cut_distance)
                if tracker is not None:   # with other people seen, only the tracker re-finds the subject
                    cut = cut and images_changed(use_prior, obs) and not tracker.others_seen
                if person is not None and use_prior is not None and (cut or is_at(obs, subject)):
                    again = find_again(capture, frame, detector, stages, build_so_far(observations, seed_prior),
                                      subject, hide)
                    if again is not None:
                        obs = observe_frame(images, cameras, detector, stages.triangulate, source, prior=again)
                        person["chosen_again_after_cuts"].append(frame)
                        if tracker is not None:
                            tracker.start(t, body_centre(obs.points, obs.points_conf))
                if tracker is not None:
                    obs, status = track_frame(tracker, t, obs, images, cameras, detector, stages.triangulate, source)
                    seen_others[frame] = [(o.points, o.points_conf) for o in tracker.others
                                          if o.frame == t and o.points is not None]
                    if status not in ("tracked", "nobody"):
                        person["identity"][status].append(frame)
                        statuses[frame] = status
                        write_identity_record(keypoints_dir, statuses,
                                              max(tracker.others_seen, before.get("other_people_seen", 0)))
                    if obs is None:
                        held[frame] = status
                        raise UvatarError(f"identity {status}: " + _HELD_WHY[status] + "; left out of the fit")
                save_observation(path, obs)
        except UvatarError as exc:
            failures[frame] = str(exc)
            log.warning("frame %s: %s", frame, exc)
            continue
        obs = reject_views(obs, disagreeing_views(obs, stages.triangulate), stages.triangulate)
        if is_at(obs, (avoid or {}).get(frame)):
            failures[frame] = "only the subject found where this person was tracked (fitted from the neighbours)"
            continue
        observations[frame] = obs
        views, seen = len(obs.cameras), obs.num_detected_views
        if (obs.points_conf > 0).sum() < 6:
            failures[frame] = "no person detected (fewer than 6 keypoints triangulated)"
        elif source == "scans" and seen < np.ceil(MIN_SCAN_VIEWS_SEEN * views):
            # every virtual view frames the whole scan: a person missing from several is a broken scan
            failures[frame] = f"only {seen} of {views} views of the scan show a person (a broken scan?)"
        else:
            prior = obs
    if tracker is not None:
        write_others(keypoints_dir.parent, {f: people for f, people in seen_others.items() if people})
    if person is not None and "identity" in person:
        person["identity"] = identity_report(frames, person["identity"], tracker, max_speed)
        person["identity"]["other_people_seen"] = max(person["identity"]["other_people_seen"],
                                                      before.get("other_people_seen", 0))
    return {f: observations[f] for f in frames if f in observations}, failures, person


def mask_camera_names(config: FitConfig) -> list[str]:
    """The cameras named by ``config.mask_cameras`` (empty: every camera)."""
    return [c.strip() for c in config.mask_cameras.split(",") if c.strip()]


_HELD_WHY = {"ambiguous": "two people could be the subject (positions and colours alike)",
             "lost": "the subject is not seen where it can be",
             "crowded": "another person is too close to the subject (their keypoints may be mixed) or over it "
                        "in too many views"}


def _person_masks(capture: Capture, frames, cameras, failures: dict, only: list[str] | None = None) -> list:
    """Per frame, per camera (H, W) bool person masks for the silhouette term (None where a mask is
    missing or unreadable, or the frame failed, or the camera is not in ``only`` when that is given)."""
    if cameras is None:
        raise InputError(capture.root, "masks=True needs a fit from images (calibrated cameras)")
    out = []
    for frame in frames:
        row = []
        for cam in cameras:
            if only and cam.name not in only:
                row.append(None)
                continue
            path = capture.mask_path(cam.name, frame)
            try:
                row.append(capture.load_mask(cam.name, frame) if frame not in failures and path.is_file() else None)
            except InputError as exc:
                log.warning("%s", exc)
                row.append(None)
        out.append(row)
    if not any(m is not None for row in out for m in row):
        raise InputError(capture.masks_dir, "masks=True: no person mask found for the fitted frames")
    return out


def _write_fits(capture: Capture, frames, result, body, config: FitConfig, provenance: dict) -> None:
    """The fits, shape and provenance. Another person than the subject gets no fit where they were
    not detected (``provenance["frames_without_detection"]``): a person walking out of the views is
    not there, and a body filled in from their neighbouring frames would claim pixels in the masks.
    The subject gets none where its identity is held (``provenance["identity_held"]``); a fit left
    there by an earlier run (``force``, or a synthetic capture's own fits) is removed, so that no
    later stage reads a body of another run, or of another person, as this run's."""
    from uvatar.capture.fits import write_fit
    from uvatar.capture.types import BodyFit

    unseen = set(provenance["frames_without_detection"]) if capture.person is not None \
        else set(provenance.get("identity_held", ()))
    for t, frame in enumerate(frames):
        if frame in unseen:
            capture.fit_path(frame).unlink(missing_ok=True)
            continue
        write_fit(capture.fit_path(frame), BodyFit(poses=result.poses[t].reshape(-1), Rh=result.Rh[t],
                                                   Th=result.Th[t], shapes=result.shape,
                                                   scale=float(result.scale[t])))
    shapes = np.asarray(result.shape, np.float64).tolist()
    if capture.person is not None:  # another person: their shape beside their fits, capture.json is the subject's
        write_json(capture.person_root / PERSON_JSON, {"body_model": body.name, "shapes": shapes,
                                                       "provenance": {"fit": provenance}})
        return
    info = read_json(capture.root / CAPTURE_JSON)
    info["body_model"] = {"name": body.name, "shapes": shapes}
    info.setdefault("provenance", {})["fit"] = provenance
    write_json(capture.root / CAPTURE_JSON, info)


def _reprojection_stats(observations: dict, frames, body_points: np.ndarray, min_conf: float) -> dict:
    """Pixel errors: triangulated keypoints reprojected into the views that saw them, and the fitted
    body's keypoints projected against every confident detection."""
    from uvatar.render.cameras import project_points

    tri, body_err = [], []
    for t, frame in enumerate(frames):
        obs = observations.get(frame)
        if obs is None:
            continue
        err = obs.reprojection_px[np.isfinite(obs.reprojection_px)]
        tri.append(err)
        for c, cam in enumerate(obs.cameras):
            seen = obs.conf[c] >= min_conf
            if seen.any():
                xy, _ = project_points(cam, body_points[t][seen])
                body_err.append(np.linalg.norm(xy - obs.xy[c][seen], axis=1))

    def stats(chunks):
        a = np.concatenate(chunks) if chunks else np.zeros(0)
        if a.size == 0:
            return None
        return {"mean": float(a.mean()), "median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
                "count": int(a.size)}

    return {"triangulation_px": stats(tri), "fitted_body_px": stats(body_err)}


def fit_capture(root: str | Path, config: FitConfig | None = None, stages: FitStages | None = None,
                progress: bool = True, frames: list[str] | None = None) -> dict:
    """Fit the body model to every frame of the capture at ``root``; returns the summary written to
    ``fitting/summary.json``. Raises :class:`InputError` when nothing could be fitted.

    With ``config.person`` ``all`` the subject goes to ``fits/`` as usual and every other person seen
    by two views to ``people/<id>/`` (their own summary in ``people/<id>/fitting/summary.json``; the
    returned summary is the subject's, with ``people``: {id: that summary}); with a person id, that
    person alone (the returned summary is theirs)."""
    from uvatar.body.registry import load_body_model
    from uvatar.fit.body_fit import BodyFitConfig
    from uvatar.fit.keypoints import DetectorConfig, load_detector
    from uvatar.fit.person import parse_person
    from uvatar.fit.triangulate import TriangulateConfig
    from uvatar.fit.views import ScanViewsConfig

    config = config or FitConfig()
    stages = stages or FitStages()
    stages.views = stages.views or ScanViewsConfig()
    stages.detector = stages.detector or DetectorConfig()
    stages.triangulate = stages.triangulate or TriangulateConfig()
    stages.body = stages.body or BodyFitConfig()
    capture = Capture(root)
    frames = list(frames or capture.frames)
    if not frames:
        raise InputError(capture.root, "the capture lists no frames")
    choice = parse_person(config.person)
    source = resolve_source(capture, config.source)
    check_person_choice(capture, frames, choice, config.person, source)
    if choice.rule != "id":
        _refuse_existing(capture, config, stages, source)
    if config.refine_cameras and (source != "images" or choice.several or choice.rule == "id"):
        raise InputError(capture.cameras_dir, "refine_cameras=True refines the cameras against one subject seen in "
                                              "the capture's images: fit it alone, from images")
    if config.masks and not capture.masks_dir.is_dir():
        raise InputError(capture.masks_dir, "masks=True needs person masks: run `uvatar capture masks` first")
    if config.masks:
        from uvatar.fit.masks import require_masks

        require_masks(capture.root)
    if config.mask_cameras:
        if not config.masks:
            raise InputError(capture.root, "mask_cameras names the cameras whose masks masks=True reads: "
                                           "set masks=True too")
        unknown = sorted(set(mask_camera_names(config)) - set(capture.cameras()))
        if unknown:
            raise InputError(capture.cameras_dir, f"mask_cameras: no camera {', '.join(unknown)} in the capture "
                                                  f"(it has {', '.join(capture.cameras())})")
    body = load_body_model(config.model, config.model_dir, device=config.device)
    detector = load_detector(config.detector, stages.detector)
    if not choice.several:
        return _fit_person(capture, frames, source, body, detector, stages, config, progress, choice)[0]
    t0 = time.perf_counter()
    chosen = choose_people(capture, frames, choice, detector, stages)
    t_choose = time.perf_counter() - t0
    for pid, *_ in chosen:
        if pid is not None:
            _refuse_existing(capture.for_person(pid), config, stages, source)
    summaries, subject_obs, subject_held = {}, None, ()
    for pid, seed, prior, report in chosen:
        picked = (seed, prior, report) if prior is not None else None
        if choice.rule == "id" and pid is None:
            # the subject's keypoints (saved ones when it was fitted before): where the others are not
            subject_obs = _detect_all(capture, frames, source, detector, stages, progress, choice,
                                      config.cut_distance, picked)[0]
            continue
        log.info("fitting %s", "the subject" if pid is None else f"person {pid}")
        summaries[pid], observations = _fit_person(capture.for_person(pid), frames, source, body, detector, stages,
                                                   config, progress, choice, picked, subject_obs, subject_held)
        if pid is None:
            subject_obs = observations
            subject_held = frozenset(summaries[pid]["provenance"].get("identity_held", ()))
        summaries[pid]["seconds"]["choosing_people"] = t_choose
    if choice.rule == "id":
        return summaries[choice.person_id]
    summary = summaries.pop(None)
    summary["people"] = summaries
    write_json(capture.fitting_dir / "summary.json", summary)
    return summary


def _refuse_existing(capture: Capture, config: FitConfig, stages: FitStages, source: str) -> None:
    """Before any work: refuse fits made with other settings (their stage record names the first
    difference), or fits with no record, unless ``force``; fits made with these settings resume (or,
    complete, are kept: :func:`_fit_person`)."""
    existing = existing_fits(capture)
    if not existing or config.force:
        return
    if stage_record.read_record(capture.fitting_dir) is None:
        raise InputError(capture.fits_dir, f"already holds {len(existing)} fit file(s); force=True replaces them")
    stage_record.begin(capture.fitting_dir, "fit", fit_record_config(config, stages, source),
                       fit_inputs(capture, source), dry_run=True, redo_hint="force=True fits again")


def _fit_person(capture: Capture, frames: list[str], source: str, body, detector, stages: FitStages,
                config: FitConfig, progress: bool, choice, chosen=None, avoid=None,
                avoid_held=()) -> tuple[dict, dict]:
    """Detect, fit and write one person: the subject (``capture.person`` None, chosen by ``choice``
    unless ``chosen`` is given) or another person (``chosen``: their seed frame, Person, report;
    ``avoid``, ``avoid_held``: the subject's observations and held frames, see :func:`_detect_all`); the scans, when present, are the
    subject's alone (their distance and photometric terms are not used for anyone else). Returns
    (summary, the observations {frame: FrameObservation})."""
    from uvatar.fit.body_fit import fit_body_sequence
    from uvatar.fit.body_keypoints import BodyKeypoints

    subject = capture.person is None
    t0 = time.perf_counter()
    hide = None if subject else subject_hider(capture.for_person(None), body)
    fit_state = stage_record.begin(capture.fitting_dir, "fit", fit_record_config(config, stages, source),
                                   fit_inputs(capture, source), on_change="redo" if config.force else "refuse",
                                   skip_complete=not config.force, redo_hint="force=True fits again")
    if fit_state.status == "complete":   # fitted before with these settings and inputs (a --person all rerun)
        log.info("%s: fitted before with these settings; kept", capture.fitting_dir)
        summary = read_json(capture.fitting_dir / "summary.json")
        return summary, _detect_all(capture, frames, source, detector, stages, False, choice, config.cut_distance,
                                    chosen, avoid, hide, config.max_speed, avoid_held)[0]
    keypoints_dir = capture.person_root / "fitting" / "keypoints"
    if stage_record.begin(keypoints_dir, "keypoints", keypoint_record_config(capture, config, stages, source, detector),
                          fit_inputs(capture, source), total=len(frames), on_change="redo").status == "redo":
        # detected for another person, detector, images or rules; with them who else was seen and held
        for stale in [*keypoints_dir.glob("*.npz"), keypoints_dir / IDENTITY_JSON, keypoints_dir.parent / OTHERS_NPZ]:
            stale.unlink(missing_ok=True)
    observations, failures, person = _detect_all(capture, frames, source, detector, stages, progress, choice,
                                                 config.cut_distance, chosen, avoid, hide, config.max_speed,
                                                 avoid_held)
    stage_record.finish(keypoints_dir)
    held = sorted(f for f, why in failures.items() if why.startswith("identity ")) if subject else []
    t_detect = time.perf_counter() - t0
    use_scans = subject and config.scan_distance and capture.scans_dir.is_dir()
    photo = (replace(stages.views, image_size=config.photo_size)
             if use_scans and config.photo_size and stages.body.w_photo > 0 else None)
    scans, photo_views = (scan_inputs(capture, frames, config.scan_points, config.seed, photo, failures, progress)
                          if use_scans else (None, None))
    usable = [f for f in frames if f in observations and f not in failures]
    has_scan = scans is not None and any(s is not None for s in scans)
    if not usable and not has_scan:
        counts: dict[str, int] = {}
        for reason in failures.values():
            counts[reason] = counts.get(reason, 0) + 1
        why = "; ".join(f"{n} {r}" for r, n in counts.items())
        raise InputError(capture.person_root, f"{len(frames)} frames, none usable for fitting: {why}")

    t1 = time.perf_counter()
    observations, relabelled = relabel_left_right(frames, observations, detector.keypoint_names, config.cut_distance)
    cameras_refined = None
    if config.refine_cameras:
        observations, cameras_refined = refine_capture_cameras(capture, observations, usable,
                                                               triangulate_config=stages.triangulate)
    obs = stack_observations(frames, observations, source, scans, len(detector.keypoint_names), config.cut_distance,
                             failures)
    obs.photo = photo_views
    if config.masks:
        obs.masks = _person_masks(capture, frames, obs.cameras, failures, mask_camera_names(config))
    with _fit_progress(progress) as callback:
        result = fit_body_sequence(body, obs, stages.body, progress=callback)
    t_fit = time.perf_counter() - t1

    provenance = {
        "tool": "uvatar fit", "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "source": source, "detector": {"name": detector.name, "version": detector.version},
        "body_model": body.name, "losses": _loss_names(obs, stages.body),
        "config": asdict(config), "frames_without_detection": sorted(failures),
    }
    if held:
        provenance["identity_held"] = held
    seen = ((person or {}).get("identity") or {}).get("other_people_seen")
    if seen:   # other people were near the subject: its masks look for their pixels (uvatar capture masks)
        provenance["other_people_seen"] = int(seen)
    _write_fits(capture, frames, result, body, config, provenance)

    import torch

    with torch.no_grad():
        posed = body.pose(torch.as_tensor(result.poses, dtype=torch.float32, device=body.device),
                          Rh=result.Rh, Th=result.Th, scale=result.scale,
                          shape=torch.as_tensor(result.shape, dtype=torch.float32, device=body.device))
        body_points = BodyKeypoints(body)(posed).cpu().numpy()
    summary = {
        "capture": str(capture.root), "person_id": capture.person, "source": source, "frames": len(frames),
        "frames_fitted": len(frames) - (len(failures) if capture.person is not None else len(held)),
        "frames_without_detection": failures,
        "cuts_after": [frames[t] for t in np.flatnonzero(~obs.continuous)],
        "relabelled_left_right": relabelled,
        "views_disagree": {f: list(o.rejected) for f, o in observations.items() if o.rejected},
        "person": person, "identity": (person or {}).get("identity"), "cameras_refined": cameras_refined,
        "body_model": body.name, "shape": np.asarray(result.shape).tolist(),
        "reprojection": _reprojection_stats(observations, frames, body_points, stages.triangulate.min_conf),
        "frame_loss": {f: float(result.frame_loss[t]) for t, f in enumerate(frames)},
        "seconds": {"detection": t_detect, "fit": t_fit,
                    "detection_per_frame": t_detect / max(len(frames), 1),
                    "fit_per_frame": t_fit / max(len(frames), 1)},
        "provenance": provenance,
    }
    if config.overlay_frames:
        from uvatar.fit.overlay import write_overlays

        summary["contact_sheet"] = str(write_overlays(capture, frames, observations, posed, body, source,
                                                      stages, config))
    write_json(capture.fitting_dir / "summary.json", summary)
    stage_record.finish(capture.fitting_dir)
    return summary, observations


class _fit_progress:
    """A tqdm bar (with ETA) fed by :func:`fit_body_sequence`'s ``progress(done, total, info)``."""

    def __init__(self, enabled: bool):
        self.enabled, self.bar = enabled, None

    def __enter__(self):
        return self if self.enabled else None

    def __call__(self, done: int, total: int, info: dict) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="body fit", unit="step", dynamic_ncols=True)
        self.bar.update(done - self.bar.n)
        self.bar.set_postfix(stage=info.get("stage"), loss=f"{info.get('loss', float('nan')):.4g}", refresh=False)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def _loss_names(obs, body_config) -> list[str]:
    names = ["keypoints3d"]
    if obs.keypoints2d is not None:
        names.append("reprojection2d")
    if obs.scans is not None and any(s is not None for s in obs.scans):
        names.append("scan_distance")
    if obs.masks is not None:
        names.append("silhouette")
    if body_config.w_photo > 0 and obs.photo is not None and any(v is not None for v in obs.photo):
        names.append("photometric")
    return names + ["pose_prior", "joint_limits", "temporal_smoothness", "shape_prior"]
