"""The inputs of a sequence fit, gathered from a capture: per-frame keypoint observations stacked
over frames, cuts between takes, scan samples and the photometric views (``uvatar fit`` calls these)."""

from __future__ import annotations

import logging

import numpy as np

from uvatar.capture.layout import Capture
from uvatar.errors import UvatarError
from uvatar.fit.tracking import continuity, image_change, track_left_right

log = logging.getLogger(__name__)

__all__ = ["scan_inputs", "continuity", "relabel_left_right", "stack_observations"]  # continuity: from tracking


def scan_inputs(capture: Capture, frames: list[str], points: int, seed: int, photo=None, failures=(),
                progress: bool = True) -> tuple[list, list | None]:
    """Each frame's scan, loaded once: ``points`` surface samples (points, normals) for the
    scan-distance term, and, with ``photo`` (a :class:`~uvatar.fit.views.ScanViewsConfig`), its
    unshaded texture seen by the virtual cameras with depth for the photometric term (None for frames
    in ``failures``). Returns (samples, photo views or None); None where a frame has no usable scan."""
    from tqdm import tqdm

    from uvatar.fit.views import scan_photo_views
    from uvatar.geometry.sampling import sample_surface

    samples, views = [], []
    for frame in tqdm(frames, desc="scans", unit="frame", disable=not progress, dynamic_ncols=True):
        mesh = None
        try:
            mesh = capture.load_scan(frame) if capture.has_scan(frame) else None
            samples.append(None if mesh is None else sample_surface(mesh.vertices, mesh.faces, points, seed))
        except UvatarError as exc:
            log.warning("frame %s: scan not used (%s)", frame, exc)
            samples.append(None)
            mesh = None   # a scan that loaded but could not be sampled gives no photo views either
        try:
            use = photo is not None and mesh is not None and frame not in failures
            views.append(scan_photo_views(mesh, photo) if use else None)
        except UvatarError as exc:
            log.warning("frame %s: no photo views (%s)", frame, exc)
            views.append(None)
    return samples, (views if photo is not None else None)


def relabel_left_right(frames, observations: dict, keypoint_names, cut_distance: float) -> tuple[dict, list]:
    """Each frame's left/right labels made to follow the previous frame's
    (:func:`uvatar.fit.tracking.track_left_right`): (observations with the relabelled frames swapped in
    every view and in 3D, the relabelled frame names)."""
    from dataclasses import replace

    from uvatar.fit.observe import left_right_swap

    perm = left_right_swap(keypoint_names)
    present = [f for f in frames if f in observations]
    if not present:
        return observations, []
    points = np.stack([observations[f].points for f in present])
    conf = np.stack([observations[f].points_conf for f in present])
    swap = track_left_right(points, conf, perm, cut_distance)
    out = dict(observations)
    for f in np.asarray(present)[swap]:
        o = observations[f]
        out[f] = replace(o, xy=o.xy[:, perm], conf=o.conf[:, perm], points=o.points[perm],
                         points_conf=o.points_conf[perm], reprojection_px=o.reprojection_px[:, perm])
    return out, [str(f) for f in np.asarray(present)[swap]]


def stack_observations(frames, observations, source, scans, keypoint_count, cut_distance: float = 0.1,
                       failures=()):
    """Stack the per-frame observations into :class:`uvatar.fit.body_fit.FitObservations`; frames in
    ``failures`` contribute nothing (neither keypoints nor scan): their neighbours carry them. Cuts
    come from :func:`uvatar.fit.tracking.continuity` (with the observations' image thumbnails where
    they have them)."""
    from uvatar.fit.body_fit import FitObservations

    observations = {f: o for f, o in observations.items() if f not in failures}
    if scans is not None:
        scans = [None if f in failures else s for f, s in zip(frames, scans, strict=True)]
    T = len(frames)
    k3 = np.zeros((T, keypoint_count, 3), np.float32)
    c3 = np.zeros((T, keypoint_count), np.float32)
    for t, frame in enumerate(frames):
        obs = observations.get(frame)
        if obs is not None:
            k3[t], c3[t] = obs.points, obs.points_conf
    k2 = c2 = cameras = None
    if source == "images" and observations:
        cameras = next(iter(observations.values())).cameras
        C = len(cameras)
        k2 = np.zeros((T, C, keypoint_count, 2), np.float32)
        c2 = np.zeros((T, C, keypoint_count), np.float32)
        for t, frame in enumerate(frames):
            obs = observations.get(frame)
            if obs is not None and len(obs.cameras) == C:
                k2[t], c2[t] = obs.xy, obs.conf
    changed = image_change(_thumbnails(frames, observations)) if source == "images" else None
    out = FitObservations(keypoints3d=k3, keypoints3d_conf=c3, keypoints2d=k2, keypoints2d_conf=c2,
                          cameras=cameras, scans=scans, continuous=continuity(k3, c3, cut_distance, changed))
    return out


def _thumbnails(frames, observations) -> np.ndarray | None:
    """(T, C, S, S) the observations' image thumbnails, nan where a frame has none; None if none has."""
    have = [o.thumbs for o in observations.values() if getattr(o, "thumbs", None) is not None]
    if not have:
        return None
    out = np.full((len(frames), *have[0].shape), np.nan, np.float32)
    for t, frame in enumerate(frames):
        obs = observations.get(frame)
        if obs is not None and obs.thumbs is not None and obs.thumbs.shape == have[0].shape:
            out[t] = obs.thumbs
    return out
