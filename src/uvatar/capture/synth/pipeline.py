"""``synthesize(out, config)``: plan the capture, build scan topologies, make frames in parallel.

Everything is a deterministic function of ``config`` (frame randomness is seeded from (seed,
frame), topologies from (seed, segment)), so frames can be made in any order by any number of
processes and a crashed run resumes: topologies and frames already on disk are skipped (a frame is
done when its ``gt/frames/<frame>.npz`` exists; it is written last, atomically). A frame that
fails is reported and skipped.

``OUT/stage.json`` (:mod:`uvatar.stage_record`) records the settings the frames on disk were made
with: a rerun with other settings (another ``--seed``, ``--frames``, ``--image-size`` ...) is refused
in one line naming the first one that differs (its frames would mix with the old ones); the capture is
marked complete once every frame is made, and a reader downstream (:class:`uvatar.capture.Capture`)
refuses a half-made one.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from uvatar.capture.synth.config import SynthConfig
from uvatar.errors import UvatarError
from uvatar.io_utils import sweep_partial_writes
from uvatar.parallel import ExecutorConfig, clear_worker_cache
from uvatar.resources import check_memory

__all__ = ["make_plan", "synth_record_config", "synthesize"]

log = logging.getLogger(__name__)


def _segments(n: int, cfg: SynthConfig) -> tuple[np.ndarray, list[dict]]:
    rng = np.random.default_rng([int(cfg.seed), 101])
    lo = max(1, int(round(0.8 * cfg.segment_frames)))
    hi = max(lo, int(round(1.2 * cfg.segment_frames)))
    segment_of_frame = np.zeros(n, dtype=np.int64)
    segments, start = [], 0
    while start < n:
        length = int(rng.integers(lo, hi + 1))
        stop = min(n, start + length)
        segment_of_frame[start:stop] = len(segments)
        faces = int(rng.integers(cfg.face_count[0], cfg.face_count[1] + 1))
        segments.append({"first": start, "last": stop - 1, "target_faces": faces})
        start = stop
    return segment_of_frame, segments


def _broken(names: list[str], heldout: int, cfg: SynthConfig) -> dict:
    n = len(names)
    count = n // max(int(cfg.broken_every), 1)
    candidates = n - heldout
    if count == 0 or candidates <= 0:
        return {}
    rng = np.random.default_rng([int(cfg.seed), 303])
    chosen = np.sort(rng.choice(candidates, size=min(count, candidates), replace=False))
    out = {}
    for i in chosen:
        if rng.random() < 0.5:
            kind, direction = "above", [0.0, 1.0, 0.0]
        else:
            a = rng.uniform(0, 2 * np.pi)
            kind, direction = "side", [float(np.cos(a)), 0.0, float(np.sin(a))]
        out[names[int(i)]] = {"kind": kind, "direction": direction,
                              "fraction": float(rng.uniform(*cfg.broken_fraction))}
    return out


def make_plan(body, cfg: SynthConfig) -> dict:
    """The whole capture's plan (picklable): frames, true motion, shape, segments, broken frames,
    cameras, takes and held-out frames."""
    from uvatar.capture.synth.cameras import studio_cameras
    from uvatar.capture.synth.motion import concat_takes, ground_translations, make_heldout, make_takes

    n = int(cfg.frames)  # >= 1 (SynthConfig checks it)
    heldout = cfg.heldout_count()
    shape = body.default_shape().detach().cpu().numpy().astype(np.float32)
    motion = make_takes(body, n - heldout, cfg.seed, cfg.motion, shape)
    if heldout:
        motion = concat_takes(motion, make_heldout(body, heldout, cfg.seed, cfg.motion, shape))
    names = [f"{i:06d}" for i in range(n)]
    segment_of_frame, segments = _segments(n, cfg)
    cams = studio_cameras(cfg.cameras, cfg.image_size, cfg.studio) if cfg.cameras > 0 else []
    from uvatar.capture.synth.bystanders import one_take_floor_path, plan_bystanders

    if cfg.bystanders and cams and cfg.bystander_path == "cross":   # one continuous take (see .bystanders)
        motion.Th = one_take_floor_path(motion.Th, motion.take_of_frame)
        motion.Th[:, 1] = ground_translations(body, motion.poses, motion.Rh, motion.Th, shape)
    others = plan_bystanders(body, cfg, motion.Th, shape) if cfg.bystanders and cams else []
    return {"bystanders": others,"frames": names, "poses": motion.poses, "Rh": motion.Rh, "Th": motion.Th, "shape": shape,
            "take_names": list(motion.names), "take_of_frame": motion.take_of_frame,
            "takes": motion.ranges(), "heldout_frames": names[n - heldout:] if heldout else [],
            "segment_of_frame": segment_of_frame, "segments": segments,
            "broken": _broken(names, heldout, cfg), "cameras": cams}


def _write_meta(root: Path, cfg: SynthConfig, plan: dict) -> None:
    from uvatar.capture.cameras import write_cameras
    from uvatar.capture.layout import write_capture_info
    from uvatar.capture.synth.gt import write_gt_info
    from uvatar.io_utils import write_npz

    write_capture_info(root, plan["frames"], fps=cfg.motion.fps, body_model=cfg.body_model, shapes=plan["shape"],
                       provenance={"generator": "uvatar synth", "seed": cfg.seed, "synthetic": True})
    if plan["cameras"]:
        write_cameras(root / "cameras", plan["cameras"])
    write_gt_info(root, {
        "broken_frames": sorted(plan["broken"]), "broken": plan["broken"],
        "heldout_frames": plan["heldout_frames"], "takes": plan["takes"],
        "texel_resolution": cfg.gt_texels, "scan_texture": cfg.scan_texture,
        "segments": plan["segments"], "seed": cfg.seed, "fit_noise_deg": cfg.fit_noise_deg,
        "body_model": cfg.body_model, "body_shapes": np.asarray(plan["shape"], np.float64).tolist(),
        "config": {k: v for k, v in cfg.to_dict().items() if k not in ("workers", "preview")}})
    if plan.get("bystanders"):
        write_npz(root / "gt" / "bystanders.npz",
                  **{f"{k}_{b}": v for b, person in enumerate(plan["bystanders"]) for k, v in person.items()})
    motion_path = root / "gt" / "motion.npz"
    if not motion_path.is_file():
        write_npz(motion_path, poses=plan["poses"], Rh=plan["Rh"], Th=plan["Th"],
                  take_of_frame=plan["take_of_frame"], take_names=np.asarray(plan["take_names"]))


# -- tasks (module level so that worker processes can run them) --------------------------------
def _one_torch_thread() -> None:
    import torch

    torch.set_num_threads(1)  # identical float results in every process (byte-identical outputs)


def _studio(shared: dict):
    """This process's :class:`~uvatar.capture.synth.frame.Studio` for the run ``shared`` describes
    (built once per worker process, kept for its later tasks)."""
    from uvatar.capture.synth.frame import Studio
    from uvatar.parallel import worker_cache

    return worker_cache(("synth-studio", shared["token"]),
                        lambda: Studio(shared["cfg"], Path(shared["root"]), shared["plan"]))


def _topology_task(st, index: int) -> int:
    from uvatar.capture.synth.scans import build_topology
    from uvatar.io_utils import write_npz

    fine, rest_offset, rest_normals = st.fine()
    seg = st.plan["segments"][index]
    rng = np.random.default_rng([int(st.cfg.seed), 202, index])
    topo = build_topology(fine, rest_offset, rest_normals, seg["target_faces"], rng, st.cfg.scan_texture,
                          st.cfg.chart_area)
    write_npz(st.root / "gt" / "topologies" / f"{index:03d}.npz", **topo.to_npz())
    return index


def _frame_task(st, i: int) -> dict:
    try:
        return st.make_frame(i)
    except Exception as exc:  # a broken frame must not stop the capture; it is reported at the end
        log.exception("frame %d failed", i)
        return {"frame": st.plan["frames"][i], "error": f"{type(exc).__name__}: {exc}"}


def _synth_task(shared: dict, task: tuple[str, int]):
    """One ("topology", segment) or ("frame", index) task under :func:`uvatar.parallel.run_tasks`."""
    kind, index = task
    return (_topology_task if kind == "topology" else _frame_task)(_studio(shared), index)


def _run_phase(shared, kind, indices, executor, progress, made=None) -> list:
    """Run one phase's tasks; those whose worker failed (not the frame itself) run again in this process.
    ``made``: called with each result that is not a failure (progress in the stage record)."""
    from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks

    desc, unit = ("frames", "frame") if kind == "frame" else ("scan topologies", "topology")
    results, lost = [], []
    for (_, index), result in run_tasks(_synth_task, [(kind, i) for i in indices], shared, executor, desc, unit,
                                        progress, initializer=_one_torch_thread):
        if isinstance(result, TaskFailure):
            lost.append(index)
        else:
            results.append(result)
            if made is not None and "error" not in result:
                made(result)
    if lost:
        log.warning("%d %s task(s) lost their worker (%s); running them in this process", len(lost), kind,
                    executor.kind)
        for (_, index), result in run_tasks(_synth_task, [(kind, i) for i in lost], shared, ExecutorConfig(),
                                            desc, unit, progress):
            if isinstance(result, TaskFailure) and kind == "topology":
                raise UvatarError(f"scan topology {index} failed: {result.reason}")
            results.append({"frame": shared["plan"]["frames"][index], "error": result.reason}
                           if isinstance(result, TaskFailure) else result)
    return results


def synth_record_config(cfg: SynthConfig) -> dict:
    """What shapes a synthetic capture (its stage record's settings): every field of ``cfg``, nested ones
    included, but the worker count and the preview (how it runs, an extra picture)."""
    from uvatar.stage_record import config_values

    return config_values(cfg, drop=("workers", "preview"))


def synthesize(out: str | Path, config: SynthConfig | None = None, progress: bool = True,
               executor: ExecutorConfig | None = None) -> dict:
    """Make (or resume) a synthetic capture in ``out``; returns a summary dict
    (frames, made, skipped, failed, topologies, broken_frames, heldout_frames).

    executor: where topologies and frames run (default: a local pool of ``config.workers`` processes).
    Raises InputError, before any work, when ``out`` holds frames made with other settings."""
    import uuid

    import torch

    from uvatar import stage_record
    from uvatar.body import load_body_model
    from uvatar.capture.synth.gt import gt_frame_path

    cfg = config or SynthConfig()
    root = Path(out)
    state = stage_record.begin(root, "synth", synth_record_config(cfg), total=int(cfg.frames), skip_complete=True,
                               redo_hint="another output folder starts over")
    sweep_partial_writes(root)  # temp files of writes a kill cut short (scans/.000001.*.png, ...)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # identical float results in every process (byte-identical outputs)
    try:
        body = load_body_model(cfg.body_model)
        # the plan holds a few (frames, joints, 3) float64 arrays (true motion, fits, takes)
        check_memory(8 * 3 * 8 * body.num_joints * cfg.frames, "frames", f"planning {cfg.frames} frames")
        plan = make_plan(body, cfg)
        if state.status != "complete":  # a complete capture is left as it is (`uvatar fit` adds to capture.json)
            _write_meta(root, cfg, plan)
        topo_todo = [s for s in range(len(plan["segments"]))
                     if not (root / "gt" / "topologies" / f"{s:03d}.npz").is_file()]
        frame_todo = [i for i, name in enumerate(plan["frames"]) if not gt_frame_path(root, name).is_file()]
        needed = sorted(set(plan["segment_of_frame"][frame_todo].tolist()))
        topo_todo = [s for s in topo_todo if s in needed]
        executor = executor or ExecutorConfig(workers=max(1, min(int(cfg.workers), len(frame_todo) or 1)))
        shared = {"cfg": cfg, "root": str(root), "plan": plan, "token": uuid.uuid4().hex}
        results = []
        if frame_todo:
            _run_phase(shared, "topology", topo_todo, executor, progress)
            done = [len(plan["frames"]) - len(frame_todo)]

            def made(_result) -> None:
                done[0] += 1
                stage_record.mark_progress(root, done[0])

            results = _run_phase(shared, "frame", frame_todo, executor, progress, made)
        failed = {r["frame"]: r["error"] for r in results if "error" in r}
        if cfg.preview and (state.status != "complete" or not (root / "preview.png").is_file()):
            from uvatar.capture.synth.preview import write_preview

            write_preview(root, plan, cfg)
    finally:
        torch.set_num_threads(threads)
        clear_worker_cache()
    made = len(plan["frames"]) - len(failed)
    if failed:  # a rerun makes the failed frames again; until then the capture is half made
        stage_record.mark_progress(root, made)
    else:
        stage_record.finish(root, made)
    return {"root": str(root), "frames": len(plan["frames"]), "made": len(frame_todo) - len(failed),
            "skipped": len(plan["frames"]) - len(frame_todo), "failed": failed,
            "topologies": len(plan["segments"]), "broken_frames": sorted(plan["broken"]),
            "heldout_frames": plan["heldout_frames"]}
