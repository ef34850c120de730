"""Bake a whole capture: frames in parallel, atomic per-frame outputs, resume, rejection, replacement.

``bake_capture`` bakes the listed frames (default: all) of a capture into ``BAKED/`` (layout in
:mod:`uvatar.avh.bake.dataset`). A frame already on disk is not baked again; a broken input frame
(unreadable scan, bad fit, any failure) is reported and skipped, never killing the run. A frame whose
mean kappa over the valid texels is below ``config.reject_kappa`` (paper: 130/255) is moved to
``rejected/`` and listed with its reason. ``bake_selection`` bakes a selection made before baking
(``uvatar select CAPTURE --from-capture``) and replaces every rejected frame by the next nearest frame
to its cluster centre.
"""

from __future__ import annotations

import logging
import os
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from uvatar import stage_record
from uvatar.avh.bake.config import BakeConfig
from uvatar.avh.bake.dataset import (
    frame_path,
    read_dataset_info,
    read_frame_scalar,
    rejected_path,
    restore_preview,
    write_baked_frame,
    write_dataset_info,
)
from uvatar.avh.bake.inputs import (
    adopt_body_and_layout,
    clear_scan_cache,
    load_body_and_layout,
    prefetch_task_scans,
    prepared_scan,
    start_fit,
)
from uvatar.avh.bake.refine_together import colour_outliers, load_disagreement, refine_frames_together
from uvatar.capture.layout import frame_name
from uvatar.errors import InputError, one_line
from uvatar.io_utils import sweep_partial_writes
from uvatar.parallel import ExecutorConfig, TaskFailure, keep_pool, run_tasks
from uvatar.resources import check_memory
from uvatar.threads import limit_process_to_one_thread

log = logging.getLogger(__name__)

__all__ = ["FrameResult", "bake_capture", "bake_selection", "heldout_frames", "load_body_and_layout", "start_fit"]


@dataclass
class FrameResult:
    """Outcome of one frame: status "baked" | "rejected" | "broken"; reason for the last two."""

    frame: str
    status: str
    reason: str | None = None
    kappa_mean: float | None = None
    seconds: float = 0.0
    stats: dict = field(default_factory=dict)


# Peak memory of one frame's bake per texel (UV layout, visibility, match and map buffers), bytes:
# measured ~75 B/texel above a 640 MB base at 512² on anny; rounded up for registration and inpainting.
BAKE_BYTES_PER_TEXEL = 256

def heldout_frames(capture_root) -> list[str]:
    """A synthetic capture's held-out frames (:func:`uvatar.avh.poses.heldout_frames`); [] for a
    capture without them (no, unreadable or empty ``gt/info.json``: a real capture)."""
    from uvatar.avh.poses import heldout_frames as listed_heldout_frames

    try:
        return listed_heldout_frames(capture_root)
    except InputError:
        return []


def _bake_one(capture_root: str, out_root: str, frame: str, config: BakeConfig, refined=None,
              run=None, colour_reason: str | None = None, writer=None):
    """Bake one frame in a worker. Every failure becomes a "broken" result with a one-line reason.
    refined: the frame's fit already refined across frames (:mod:`.refine_together`), baked as is;
    run: the bake's token for the scans kept from the colour rounds (:func:`.inputs.prepared_scan`);
    colour_reason: the frame is a colour outlier (:func:`.refine_together.colour_outliers`): baked
    into ``rejected/`` with this reason, so its preview shows what went wrong. writer: a thread pool
    that writes the frame (a Future of its result is returned at once, ``BakeConfig.write_behind``),
    or None: written here, its :class:`FrameResult` returned."""
    from uvatar.avh.bake.frame import bake_fit
    from uvatar.capture import Capture

    t0 = time.perf_counter()
    try:
        capture = Capture(capture_root)
        body, layout = load_body_and_layout(capture.body_model, config.texels)
        fit, shape = start_fit(capture, frame)
        if refined is not None:
            fit, config = refined, replace(config, refine_pose=False)
        scan_path = capture.scan_path(frame)
        scan, surface = prepared_scan(capture, frame, config, run)   # kept from the colour rounds
        baked, fit = bake_fit(body, fit, layout, scan, config, shape, scan_path=str(scan_path), surface=surface)
    except Exception as exc:  # noqa: BLE001 - a broken frame is reported, never fatal
        return FrameResult(frame, "broken", f"broken input: {one_line(exc)}", seconds=time.perf_counter() - t0,
                           stats={"worker_peak_rss_mb": _peak_rss_mb()})
    reason = _reject_reason(baked.kappa_mean, config, colour_reason)
    stats = {**{k: v for k, v in baked.stats.items() if k != "registration"}, "worker_peak_rss_mb": _peak_rss_mb()}
    result = FrameResult(frame, "rejected" if reason else "baked", reason, baked.kappa_mean,
                         time.perf_counter() - t0, stats)

    def write() -> FrameResult:
        write_baked_frame(out_root, frame, baked, fit, rejected=reason is not None, float16=config.texture_float16)
        stale = frame_path(out_root, frame) if reason else rejected_path(out_root, frame)
        stale.unlink(missing_ok=True)
        return result

    return writer.submit(write) if writer is not None else write()


# the thread that writes the frames baked in this process while the next one bakes (``write_behind``),
# set by :func:`_writes_behind` for the bake's in-process tasks; None in pool and Ray workers
_WRITER = None


@contextmanager
def _writes_behind(on: bool):
    """Within: :func:`_bake_task` in this process hands each frame's write to one thread
    (:data:`_WRITER`) when ``on``; every write handed over is on disk when the block ends."""
    global _WRITER
    if not on:
        yield
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="bake-write") as pool:
        _WRITER = pool
        try:
            yield
        finally:
            _WRITER = None


def _bake_task(shared: dict, item):
    """One frame under :func:`uvatar.parallel.run_tasks`, item = (frame, its fit refined across frames
    or None): ``shared`` holds the capture and output folders, the config and the (body, layout) pair,
    shipped once per worker process. Its :class:`FrameResult`, or in this process with
    :data:`_WRITER` set a Future of it (its write still running)."""
    frame, refined = item
    config = shared["config"]
    adopt_body_and_layout(shared["body_name"], config.texels, shared["body_layout"])
    return _bake_one(shared["capture_root"], shared["out_root"], frame, config, refined, shared.get("run"),
                     shared.get("colour_outliers", {}).get(frame), _WRITER)


def _prefetch_bake(shared: dict, item) -> None:
    """The next frame's scan file read on a thread while this frame bakes (:func:`.inputs.prefetch_task_scans`)."""
    prefetch_task_scans(shared, [item[0]])


def _peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux ru_maxrss is in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _reject_reason(kappa_mean: float, config: BakeConfig, colour_reason: str | None = None) -> str | None:
    """Why a baked frame is rejected (κ first, then colour), or None when it is kept."""
    if kappa_mean < config.reject_kappa:
        return (f"mean confidence {kappa_mean:.3f} ({kappa_mean * 255:.0f}/255) below "
                f"{config.reject_kappa:.3f} ({config.reject_kappa * 255:.0f}/255)")
    return colour_reason


def _existing_result(out_root: Path, frame: str, config: BakeConfig,
                     colour_reason: str | None = None) -> FrameResult | None:
    """A frame already baked on disk, re-classified against the current threshold and colour check
    (files moved)."""
    for path in (frame_path(out_root, frame), rejected_path(out_root, frame)):
        if not path.is_file():
            continue
        try:
            kappa_mean = read_frame_scalar(path, "kappa_mean")
        except Exception:  # noqa: BLE001 - unreadable leftovers are baked again
            return None
        reason = _reject_reason(kappa_mean, config, colour_reason)
        want = rejected_path(out_root, frame) if reason else frame_path(out_root, frame)
        if want != path:
            want.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, want)
        return FrameResult(frame, "rejected" if reason else "baked", reason, kappa_mean)
    return None


def _write_info(out_root: Path, capture, body_name: str, config: BakeConfig, results: dict[str, FrameResult],
                extra: dict | None = None) -> dict:
    info = read_dataset_info(out_root)
    body, _ = load_body_and_layout(body_name, config.texels)
    baked = sorted(f for f, r in results.items() if r.status == "baked")
    rejected = {f: r.reason for f, r in sorted(results.items()) if r.status in ("rejected", "broken")}
    stats = dict(info.get("frame_stats", {}))
    for f, r in results.items():
        if r.kappa_mean is not None:
            stats[f] = {"kappa_mean": r.kappa_mean,
                        **({k: r.stats[k] for k in ("seconds", "mixed_polarity_texels", "polarity_rule_changed_texels")
                            if k in r.stats} if r.stats else {})}
    shapes = capture.body_shapes
    info.update({
        "texels": config.texels,
        "body_model": {"name": body_name, "shapes": shapes.tolist() if shapes.size else None},
        "capture": str(Path(capture.root).resolve()),
        "frames_baked": baked,
        "rejected": rejected,
        "heldout_frames": heldout_frames(capture.root),
        "conditioning_joints": [int(j) for j in body.conditioning_joints],
        "joint_names": list(body.joint_names),
        "frame_stats": stats,
        "config": config.to_dict(),
    })
    if extra:
        info.update(extra)
    write_dataset_info(out_root, info)
    return info


def bake_capture(capture_root, out_root, config: BakeConfig | None = None, frames=None, workers: int = 1,
                 progress: bool = True, overwrite: bool = False,
                 executor: ExecutorConfig | None = None) -> dict[str, FrameResult]:
    """Bake ``frames`` (default: every frame) of a capture into ``out_root``; returns {frame: result}.

    workers: local processes (1 = in this process), used when ``executor`` is None; executor: where the
    frames run (:class:`uvatar.parallel.ExecutorConfig`, local pool or Ray; same arrays either way).
    overwrite: bake frames again even when on disk.
    ``dataset.json`` is rewritten after every frame, so an interrupted run can be resumed.
    """
    from uvatar.capture import Capture

    config = config or BakeConfig()
    if config.device != "cpu":   # fail early, in one line, without a GPU or without Warp
        from uvatar.geometry.raycast_warp import warp_device

        warp_device(config.device)
    executor = executor or ExecutorConfig(workers=max(1, int(workers)))
    check_memory(BAKE_BYTES_PER_TEXEL * config.texels ** 2 * max(1, workers), "texels",
                 f"baking {config.texels}² texels in {max(1, workers)} process(es)")
    capture = Capture(capture_root)
    if not capture.scans_dir.is_dir():   # a camera-only capture: nothing to bake, and no output made
        raise InputError(capture.scans_dir, "does not exist: AVH bakes one textured scan per frame (a "
                         "volumetric-video capture); a capture of camera images alone drives DVA "
                         "(uvatar train dva)")
    stage_record.require_complete(capture.fitting_dir, "fit", f"uvatar fit {capture.root}", check_inputs=False)
    out = Path(out_root)
    out.mkdir(parents=True, exist_ok=True)
    sweep_partial_writes(out)  # temp files of writes a kill cut short (frames/.000000.*.npz, ...)
    previous = read_dataset_info(out)
    frames = [frame_name(f) for f in (capture.frames if frames is None else frames)]
    unknown = sorted(set(frames) - set(capture.frames))
    if unknown:
        raise InputError(capture.root / "capture.json", f"has no frame(s) {', '.join(unknown[:5])}")
    _begin_record(out, capture, config, frames, overwrite, dry_run=True)   # a changed flag: refused before work
    body_name = capture.body_model
    try:
        load_body_and_layout(body_name, config.texels)  # fail early on a bad body model
    except ValueError as exc:  # an unknown name
        raise InputError(capture.root / "capture.json", str(exc)) from None
    results: dict[str, FrameResult] = previous_results(previous)
    for f in capture.frames:  # everything already on disk (also from earlier calls with other frames)
        done = _existing_result(out, f, config)
        if done is not None:
            results[f] = done
            restore_preview(out, f)
    todo = [f for f in frames if overwrite or f not in results or results[f].status == "broken"]
    _begin_record(out, capture, config, frames, overwrite)

    def finish(result: FrameResult) -> None:
        results[result.frame] = result
        if result.status != "baked":
            log.warning("frame %s %s: %s", result.frame, result.status, result.reason)
        _write_info(out, capture, body_name, config, results)
        stage_record.mark_progress(out, sum(f in results for f in frames))

    shared = {"capture_root": str(capture.root), "out_root": str(out), "config": config, "body_name": body_name,
              "body_layout": load_body_and_layout(body_name, config.texels), "run": uuid.uuid4().hex}
    # one pool for the colour rounds and the bake: its workers keep each scan read and prepared
    # in this process (one worker), each frame is written on a thread while the next one bakes
    in_process = executor.kind == "local" and executor.workers <= 1
    with keep_pool(shared), _writes_behind(config.write_behind and in_process):
        try:
            refined = refine_frames_together(capture.root, out, todo, config, body_name, executor, progress,
                                             rebuild_reference=overwrite, shared=shared)
            # frames whose colours disagree with the others' are rejected (baked into rejected/ for the
            # picture); those already on disk are re-classified, as for a changed --reject-kappa
            outliers = colour_outliers({f: d for f, d in load_disagreement(out).items() if f in capture.frames},
                                       config.reject_colour_ratio, config.pose_refine.photometric_min_frames)
            shared["colour_outliers"] = outliers
            for f, r in list(results.items()):
                if r.status in ("baked", "rejected") and f not in todo:
                    again = _existing_result(out, f, config, outliers.get(f))
                    if again is not None and again.status != r.status:
                        finish(again)
            items = [(f, refined.get(f)) for f in todo]
            for (frame, _), result in run_tasks(_bake_task, items, shared, executor, desc="bake",
                                                progress=progress, initializer=limit_process_to_one_thread,
                                                prefetch=_prefetch_bake):
                finish(FrameResult(frame, "broken", f"worker failed: {result.reason}")
                       if isinstance(result, TaskFailure) else result)
        finally:
            clear_scan_cache()   # the scans a bake in this process kept (pool workers end with the block)
    _write_info(out, capture, body_name, config, results)
    stage_record.finish(out, sum(f in results for f in frames))
    return {f: results[f] for f in frames}


# settings that do not change a baked frame: where the rays run (same maps within round-off), the scan
# cache, frames refined at once (same fits), writes on a thread (same files), and the rejection threshold (frames on disk are
# re-classified against it on every run)
_BAKE_VOLATILE = ("device", "ray_backend", "scan_cache_mb", "frames_in_flight", "write_behind", "reject_kappa",
                  "reject_colour_ratio")


def _begin_record(out: Path, capture, config: BakeConfig, frames: list[str], overwrite: bool,
                  dry_run: bool = False) -> None:
    """The bake's stage record: its settings and the capture files it reads (a changed one is refused,
    or with ``overwrite`` the bake starts over)."""
    stage_record.begin(out, "bake", bake_record_config(config),
                       stage_record.file_identities(capture.root / "capture.json", capture.fits_dir, capture.scans_dir),
                       total=len(frames), on_change="redo" if overwrite else "refuse", dry_run=dry_run,
                       redo_hint="overwrite=True bakes every frame again")


def bake_record_config(config: BakeConfig) -> dict:
    """The settings of a bake its stage record keeps (named as ``uvatar bake``'s flags' fields)."""
    return stage_record.config_values(config, prefixes={"pose_refine": "refine"}, drop=_BAKE_VOLATILE)


def outcome_line(frames: list[str], baked: list[str], reasons: dict[str, str], reject_kappa: float) -> str:
    """What became of ``frames``, counted by cause: "60 frames: 60 rejected (mean kappa < 130/255)",
    "4 frames: 1 baked, 2 rejected (...), 1 broken input". ``reasons``: dataset.json's "rejected"."""
    from collections import Counter

    causes: Counter = Counter()
    done = set(baked)
    for f in frames:
        if f in done:
            causes["baked"] += 1
        elif f not in reasons:
            causes["not baked"] += 1
        elif reasons[f].startswith("mean confidence"):
            causes[f"rejected (mean kappa < {reject_kappa * 255:.0f}/255)"] += 1
        elif reasons[f].startswith("colours disagree"):
            causes["rejected (colours disagree with the other frames')"] += 1
        else:
            causes[reasons[f].split(":")[0]] += 1  # "broken input", "worker failed"
    order = sorted(causes, key=lambda c: (c != "baked", -causes[c], c))
    return f"{len(frames)} frames: " + ", ".join(f"{causes[c]} {c}" for c in order)


def previous_results(info: dict) -> dict[str, FrameResult]:
    """Broken frames recorded by an earlier run (baked/rejected ones are re-read from their files)."""
    return {f: FrameResult(f, "broken", reason) for f, reason in info.get("rejected", {}).items()
            if str(reason).startswith(("broken input", "worker failed"))}


def bake_selection(capture_root, out_root, selection: dict, config: BakeConfig | None = None,
                   workers: int = 1, progress: bool = True, overwrite: bool = False,
                   executor: ExecutorConfig | None = None, source="selection") -> dict:
    """Bake the frames of a pre-bake selection; replace each rejected/broken one by the next candidate.

    selection: {"clusters": [{"split": "train"|"val", "candidates": [frames, nearest first]}], ...}
    as written by :func:`uvatar.avh.bake.select.select_from_capture`. Writes ``dataset.json["selection"]``
    = {"train": [...], "val": [...]} and returns it (with ``replaced`` {old: new} and ``unfilled``).
    A selection whose fits changed since it was made is refused (``source``: its name in the message).
    """
    clusters = selection.get("clusters")
    if not clusters:
        raise InputError(source, "has no 'clusters' (make it with select_from_capture)")
    stage_record.require_inputs_unchanged(selection.get("inputs"), source, f"uvatar select {capture_root} --from-capture",
                                          stage_record.file_identities(Path(capture_root) / "fits"), what="selection")
    config = config or BakeConfig()
    heldout = set(heldout_frames(capture_root))
    cursor = [0] * len(clusters)
    chosen: list[str | None] = [None] * len(clusters)
    used: set[str] = set()
    replaced: dict[str, str] = {}
    status: dict[str, str] = {}
    pending = list(range(len(clusters)))
    while pending:
        wanted = {}
        for c in pending:
            cands = clusters[c]["candidates"]
            while cursor[c] < len(cands) and (cands[cursor[c]] in used or cands[cursor[c]] in heldout):
                cursor[c] += 1
            if cursor[c] < len(cands):
                wanted[c] = cands[cursor[c]]
                used.add(cands[cursor[c]])
        if not wanted:
            break
        results = bake_capture(capture_root, out_root, config, sorted(set(wanted.values())), workers,
                               progress, overwrite, executor)
        pending = []
        for c, f in wanted.items():
            status[f] = results[f].status
            if results[f].status == "baked":
                first = clusters[c]["candidates"][0]
                if f != first:
                    replaced[first] = f
                chosen[c] = f
            else:
                pending.append(c)
    sel = {"train": sorted(f for f, c in zip(chosen, clusters, strict=True) if f and c.get("split") != "val"),
           "val": sorted(f for f, c in zip(chosen, clusters, strict=True) if f and c.get("split") == "val")}
    info = read_dataset_info(out_root)
    info["selection"] = sel
    info["selection_info"] = {"source": "capture", "replaced": replaced,
                              "unfilled": sum(1 for f in chosen if f is None)}
    write_dataset_info(out_root, info)
    return {**sel, "replaced": replaced, "unfilled": sum(1 for f in chosen if f is None)}
