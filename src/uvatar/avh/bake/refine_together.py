"""Refine the fits of a bake's frames together: geometry per frame, then colour consistency across them.

Round 0 refines every frame against its own scan (:func:`.refine.refine_fit`, surface distance only)
and samples each refinement vertex's blurred scan colour (:func:`.refine.fit_colours`). Each further
round (one per ``PoseRefineConfig.photometric_radii``, coarse to fine) takes the median colour over
frames as the reference (:func:`.photometric.reference_colours`) and refines every frame again with
the colour term. Frames are independent within a round, so each round runs through
:func:`uvatar.parallel.run_tasks` (local processes or Ray), with progress; on a CUDA torch device a
task refines up to ``BakeConfig.frames_in_flight`` frames at once (:mod:`.refine_in_flight`), the
same fits.

The final reference and every refined fit are saved as ``BAKED/photo_reference.npz`` (atomic write)
before any frame is baked. A later call on the same output bakes the saved fits as they are (so a
run killed while baking resumes to identical maps) and refines frames new to it (a frame replaced
by ``bake_selection``) against the saved reference instead of a median over only them. A frame that
fails here is left out; the per-frame bake then refines it alone, or reports it if its input is
broken.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path

import numpy as np

from uvatar.avh.bake.inputs import (
    adopt_body_and_layout,
    keep_sample,
    kept_sample,
    load_body_and_layout,
    prefetch_task_scans,
    prepared_scan,
    start_fit,
)
from uvatar.avh.bake.photometric import PhotoTarget, reference_colours
from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks
from uvatar.threads import limit_process_to_one_thread

log = logging.getLogger(__name__)

__all__ = ["REFERENCE_FILE", "colour_disagreement", "colour_outliers", "load_disagreement", "load_reference",
           "refine_frames_together"]

REFERENCE_FILE = "photo_reference.npz"


def _row(fit) -> tuple:
    """What the reference file keeps of a refined fit: (poses, Rh, Th, scale)."""
    return np.asarray(fit.poses, np.float32), np.asarray(fit.Rh, np.float64), np.asarray(fit.Th, np.float64), \
        float(fit.scale)


def load_reference(out_root, vertices: int):
    """(PhotoTarget, {frame: (poses, Rh, Th, scale)} refined earlier) saved by an earlier call, or
    None (absent, unreadable, or for another vertex set)."""
    path = Path(out_root) / REFERENCE_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            target = PhotoTarget(z["reference"].astype(np.float64), z["known"].astype(bool), float(z["radius"]))
            fits = {str(f): (p, rh, th, float(sc)) for f, p, rh, th, sc in
                    zip(z["frames"], z["poses"], z["Rh"], z["Th"], z["scale"], strict=True)}
    except Exception as exc:  # noqa: BLE001 - a damaged file is rebuilt
        log.warning("%s: unreadable (%s); the reference is rebuilt", path, exc)
        return None
    return (target, fits) if len(target.reference) == vertices else None


def load_disagreement(out_root) -> dict[str, float]:
    """{frame: colour disagreement with the reference} saved with the reference (:func:`colour_disagreement`;
    frames refined without a colour sample are absent); {} when there is no reference file."""
    path = Path(out_root) / REFERENCE_FILE
    try:
        with np.load(path) as z:
            if "disagreement" not in z:
                return {}
            return {str(f): float(d) for f, d in zip(z["frames"], z["disagreement"], strict=True) if np.isfinite(d)}
    except Exception:  # noqa: BLE001 - absent or damaged: no colour check
        return {}


def colour_disagreement(colours: np.ndarray, target: PhotoTarget) -> float:
    """Median over the reference's known points that a frame saw of mean |colour - reference| (RGB in
    [0, 1]); NaN when it saw none. colours (N, 3) with NaN where unseen."""
    c = np.asarray(colours, np.float64)
    seen = target.known & np.isfinite(c).all(-1)
    if not seen.any():
        return float("nan")
    return float(np.median(np.abs(c[seen] - target.reference[seen]).mean(-1)))


def colour_outliers(disagreement: dict[str, float], ratio: float, min_frames: int = 3) -> dict[str, str]:
    """{frame: reason} of the frames whose disagreement exceeds ``ratio`` times the median over all
    frames (``BakeConfig.reject_colour_ratio``; 0 = none; fewer than ``min_frames`` frames: none)."""
    if not ratio or len(disagreement) < min_frames:
        return {}
    typical = float(np.median(list(disagreement.values())))
    limit = ratio * max(typical, 1e-3)
    return {f: (f"colours disagree with the other frames' (median |colour - reference| {d:.3f}, more than "
                f"{ratio:g} x the frames' median {typical:.3f}): its texture does not belong to its mesh, or "
                "the fit sits on the wrong part of the scan")
            for f, d in sorted(disagreement.items()) if d > limit}


def _save_reference(out_root, target: PhotoTarget, rows: dict, disagreement: dict | None = None) -> None:
    """The reference and every refined fit so far, {frame: :func:`_row`} (a resumed bake bakes
    exactly these), with each frame's colour disagreement (NaN where not measured)."""
    from uvatar.io_utils import write_npz

    names = sorted(rows)
    poses, rh, th, scale = zip(*(rows[f] for f in names), strict=True)
    disagreement = disagreement or {}
    write_npz(Path(out_root) / REFERENCE_FILE, reference=target.reference.astype(np.float32), known=target.known,
              radius=np.float64(target.radius), frames=np.array(names), poses=np.stack(poses), Rh=np.stack(rh),
              Th=np.stack(th), scale=np.array(scale),
              disagreement=np.array([disagreement.get(f, np.nan) for f in names], np.float64))


def _restore(capture_root, saved: dict, frames) -> dict:
    """{frame: BodyFit} of the saved refined fits among ``frames`` (shapes as the capture's fit)."""
    from uvatar.capture import BodyFit, Capture

    capture = Capture(capture_root)
    out = {}
    for f in frames:
        if f not in saved:
            continue
        try:
            shapes = start_fit(capture, f)[0].shapes
        except Exception:  # noqa: BLE001 - its fit is gone or broken now: the per-frame bake reports it
            continue
        poses, rh, th, scale = saved[f]
        out[f] = BodyFit(poses=poses, Rh=rh, Th=th, shapes=shapes, scale=scale)
    return out


def _refine_task(shared: dict, group):
    """One round of the frames of ``group``, a tuple of items (frame, fit to start from or None,
    PhotoTarget or None, stencil radius to sample afterwards or None) -> [(refined BodyFit, colours
    (N, 3) at that radius or None) or a TaskFailure] per item. Their refinements run in flight on the
    bake's torch device (:func:`.refine_in_flight.refine_fits`; one at a time elsewhere), each frame's
    failure its own. ``shared`` (capture root, config, body and layout) is the same for every round and
    the bake. The colours a round ends with are sampled where the next round starts (same pose, the next
    round's target radius): a worker keeping the frame's scan keeps that sample with it, and the next
    round takes it instead of casting the same rays again (:func:`.inputs.kept_sample`). The colours
    after a round's last step, which only its stats would read, are not sampled."""
    from uvatar.avh.bake.refine import sample_colours
    from uvatar.avh.bake.refine_in_flight import RefineJob, refine_fits
    from uvatar.capture import Capture
    from uvatar.errors import one_line

    config = shared["config"]
    body, _ = adopt_body_and_layout(shared["body_name"], config.texels, shared["body_layout"])
    capture = Capture(shared["capture_root"])
    out: list = [None] * len(group)
    jobs, prepared = [], []
    prefetch_task_scans(shared, [frame for frame, *_ in group[1:]])   # read while the first is prepared
    for i, (frame, start, target, radius) in enumerate(group):
        try:
            scan, surface = prepared_scan(capture, frame, config, shared.get("run"))   # once for all rounds
            fit, shape = start_fit(capture, frame)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - that frame's failure alone
            out[i] = TaskFailure(one_line(exc))
            continue
        fit = fit if start is None else start
        before = None if target is None else kept_sample(capture, frame, config, fit)
        jobs.append(RefineJob(fit, surface, shape, photo=target, scan_mesh=scan if target is not None else None,
                              start_sample=before, final_colour_residual=False))
        prepared.append((i, frame, scan, surface, shape, radius))
    results = refine_fits(body, jobs, config.pose_refine, config.torch_device)
    for (i, frame, scan, surface, shape, radius), result in zip(prepared, results, strict=True):
        if isinstance(result, Exception):
            out[i] = TaskFailure(one_line(result))
            continue
        fit, _ = result
        if radius is None:
            out[i] = (fit, None)
            continue
        try:
            sample = sample_colours(body, fit, surface, scan, config.pose_refine, radius, shape, config.torch_device)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001
            out[i] = TaskFailure(one_line(exc))
            continue
        keep_sample(capture, frame, config, fit, sample)
        out[i] = (fit, sample.colours)
    return out


def _prefetch_group(shared: dict, group) -> None:
    """The next task's scan files read on a thread while this task's frames refine
    (:func:`.inputs.prefetch_task_scans`; those kept from an earlier round are not read again)."""
    prefetch_task_scans(shared, [frame for frame, *_ in group])


#: deal frames into tasks of ``frames_in_flight`` with CPU tensors too (scripts/gpu_path_bake.py: CUDA's
#: choices on the CPU); on CUDA the bake always does
IN_FLIGHT_ON_CPU = False


def _groups(items: list, config, executor: ExecutorConfig | None) -> list[tuple]:
    """``items`` dealt into tasks: on a CUDA torch device (or any with :data:`IN_FLIGHT_ON_CPU`) up to
    ``config.frames_in_flight`` frames a task (fewer where that would leave one of the executor's workers
    without one), else one frame a task (frames in flight gain nothing on a CPU, and a task per frame
    keeps every worker busy)."""
    device = config.torch_device
    in_flight = device is not None and (device.startswith("cuda") or IN_FLIGHT_ON_CPU)
    size = config.frames_in_flight if in_flight else 1
    workers = max(1, (executor or ExecutorConfig()).workers)
    size = max(1, min(size, -(-len(items) // workers)))
    return [tuple(items[k:k + size]) for k in range(0, len(items), size)]


def refine_frames_together(capture_root, out_root, frames, config, body_name: str,
                           executor: ExecutorConfig | None = None, progress: bool = True,
                           rebuild_reference: bool = False, shared: dict | None = None) -> dict:
    """{frame: refined BodyFit} for ``frames`` (module doc); {} when the term is off
    (``refine_pose`` false or no ``photometric_radii``) or fewer than ``photometric_min_frames``
    frames can build a reference and none is saved. ``shared``: the bake's task inputs (capture_root,
    config, body_name, body_layout), passed on so that one kept pool (:func:`uvatar.parallel.keep_pool`)
    runs every round and the bake."""
    from uvatar.avh.bake.refine import refine_vertices

    pr = config.pose_refine
    frames = list(frames)
    if not (config.refines_across_frames and frames):
        return {}
    body_layout = load_body_and_layout(body_name, config.texels)
    vertices = len(refine_vertices(body_layout[0], pr))
    saved = None if rebuild_reference else load_reference(out_root, vertices)
    if saved is None and len(frames) < pr.photometric_min_frames:
        return {}
    radii = list(pr.photometric_radii)
    done: dict = {}
    if shared is None:
        shared = {"capture_root": str(capture_root), "config": config, "body_name": body_name,
                  "body_layout": body_layout, "run": uuid.uuid4().hex}
    fits: dict = {}
    if saved is not None:
        target, stored = saved
        done = _restore(capture_root, stored, frames)
        frames = [f for f in frames if f not in done]
        if not frames:
            return done
        # the new frames: refined alone, then against the saved reference, once per radius; the last
        # round samples their colours at the reference's radius for the colour check
        rounds = [(None, None)] + [(target, None)] * (len(radii) - 1) + [(target, target.radius)]
    else:
        # (target to refine against, stencil radius to sample afterwards) per round
        rounds = [(None, radii[0])] + [("median", r) for r in radii[1:]] + [("median", None)]
    colours: dict = {}
    disagreement: dict = {}
    last_radius = radii[0]
    for i, (target, radius) in enumerate(rounds):
        if target == "median":
            stacked = np.stack([colours[f] for f in frames if f in colours])
            reference, known = reference_colours(stacked, pr.photometric_min_frames)
            target = PhotoTarget(reference, known, last_radius)
            disagreement = {f: colour_disagreement(c, target) for f, c in colours.items()}
        colours = {}
        desc = "refine poses" if i == 0 else f"colour round {i}/{len(rounds) - 1}"
        groups = _groups([(f, fits.get(f), target, radius) for f in frames], config, executor)
        for group, results in run_tasks(_refine_task, groups, shared, executor, desc=desc, progress=progress,
                                        unit="frame" if len(groups) == len(frames) else "group of frames",
                                        initializer=limit_process_to_one_thread, prefetch=_prefetch_group):
            if isinstance(results, TaskFailure):      # the whole task (a lost worker)
                results = [results] * len(group)
            for (frame, *_), result in zip(group, results, strict=True):
                if isinstance(result, TaskFailure):
                    log.warning("frame %s: pose refinement across frames skipped it (%s)", frame, result.reason)
                    continue
                fits[frame], c = result
                if c is not None:
                    colours[frame] = c
        frames = [f for f in frames if f in fits]
        if radius is not None:
            last_radius = radius
        if not frames:
            return done
        if saved is None and radius is not None and len(colours) < pr.photometric_min_frames:
            return dict(fits)   # too few frames left for a median: geometry only
    refined = dict(fits)
    rows = {f: _row(fit) for f, fit in refined.items()}
    if saved is None:
        _save_reference(out_root, target, rows, disagreement)
    else:
        disagreement = {**load_disagreement(out_root),
                        **{f: colour_disagreement(c, saved[0]) for f, c in colours.items()}}
        _save_reference(out_root, saved[0], {**saved[1], **rows}, disagreement)
        refined.update(done)
    return refined
