"""``synthesize(out, config)``: plan the capture, build scan topologies, make frames in parallel.

Everything is a deterministic function of ``config`` (frame randomness is seeded from (seed,
frame), topologies from (seed, segment)), so frames can be made in any order by any number of
processes and a crashed run resumes: topologies and frames already on disk are skipped (a frame is
done when its ``gt/frames/<frame>.npz`` exists; it is written last, atomically). A frame that
fails is reported and skipped.
"""

from __future__ import annotations

import logging
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np

from uvatar.capture.synth.config import SynthConfig
from uvatar.errors import InputError
from uvatar.io_utils import sweep_partial_writes
from uvatar.resources import check_memory

__all__ = ["make_plan", "synthesize"]

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
    from uvatar.capture.synth.motion import concat_takes, make_heldout, make_takes

    n = int(cfg.frames)
    if n < 1:
        raise InputError("--frames", f"must be at least 1, got {n}")
    heldout = cfg.heldout_count()
    shape = body.default_shape().detach().cpu().numpy().astype(np.float32)
    motion = make_takes(body, n - heldout, cfg.seed, cfg.motion, shape)
    if heldout:
        motion = concat_takes(motion, make_heldout(body, heldout, cfg.seed, cfg.motion, shape))
    names = [f"{i:06d}" for i in range(n)]
    segment_of_frame, segments = _segments(n, cfg)
    cams = studio_cameras(cfg.cameras, cfg.image_size, cfg.studio) if cfg.cameras > 0 else []
    return {"frames": names, "poses": motion.poses, "Rh": motion.Rh, "Th": motion.Th, "shape": shape,
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
        "body_model": cfg.body_model,
        "config": {k: v for k, v in cfg.to_dict().items() if k not in ("workers", "preview")}})
    motion_path = root / "gt" / "motion.npz"
    if not motion_path.is_file():
        write_npz(motion_path, poses=plan["poses"], Rh=plan["Rh"], Th=plan["Th"],
                  take_of_frame=plan["take_of_frame"], take_names=np.asarray(plan["take_names"]))


# -- tasks (module level so that worker processes can run them) --------------------------------
_STUDIO = None


def _init_worker(cfg, root, plan):
    import torch

    torch.set_num_threads(1)
    global _STUDIO
    from uvatar.capture.synth.frame import Studio

    _STUDIO = Studio(cfg, root, plan)


def _topology_task(index: int) -> int:
    from uvatar.capture.synth.scans import build_topology
    from uvatar.io_utils import write_npz

    st = _STUDIO
    fine, rest_offset, rest_normals = st.fine()
    seg = st.plan["segments"][index]
    rng = np.random.default_rng([int(st.cfg.seed), 202, index])
    topo = build_topology(fine, rest_offset, rest_normals, seg["target_faces"], rng, st.cfg.scan_texture,
                          st.cfg.chart_area)
    write_npz(st.root / "gt" / "topologies" / f"{index:03d}.npz", **topo.to_npz())
    return index


def _frame_task(i: int) -> dict:
    try:
        return _STUDIO.make_frame(i)
    except Exception as exc:  # a broken frame must not stop the capture; it is reported at the end
        log.exception("frame %d failed", i)
        return {"frame": _STUDIO.plan["frames"][i], "error": f"{type(exc).__name__}: {exc}"}


def _run(tasks, fn, pool, desc, progress):
    """Run ``fn`` over ``tasks`` in ``pool`` (or in process when None) with a tqdm bar."""
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), desc=desc, unit="frame" if fn is _frame_task else "topology",
               disable=not progress, dynamic_ncols=True)
    results = []
    if pool is None:
        for t in tasks:
            results.append(fn(t))
            bar.update(1)
    else:
        from concurrent.futures import as_completed

        futures = [pool.submit(fn, t) for t in tasks]
        for fut in as_completed(futures):
            results.append(fut.result())
            bar.update(1)
    bar.close()
    return results


def _run_pool(cfg, root, plan, topo_todo, frame_todo, workers, progress) -> list[dict]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                             initargs=(cfg, root, plan)) as pool:
        _run(topo_todo, _topology_task, pool, "scan topologies", progress)
        return _run(frame_todo, _frame_task, pool, "frames", progress)


def synthesize(out: str | Path, config: SynthConfig | None = None, progress: bool = True) -> dict:
    """Make (or resume) a synthetic capture in ``out``; returns a summary dict
    (frames, made, skipped, failed, topologies, broken_frames, heldout_frames)."""
    import torch

    from uvatar.body import load_body_model
    from uvatar.capture.synth.gt import gt_frame_path

    cfg = config or SynthConfig()
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    sweep_partial_writes(root)  # temp files of writes a kill cut short (scans/.000001.*.png, ...)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # identical float results in every process (byte-identical outputs)
    try:
        body = load_body_model(cfg.body_model)
        # the plan holds a few (frames, joints, 3) float64 arrays (true motion, fits, takes)
        check_memory(8 * 3 * 8 * body.num_joints * cfg.frames, "frames", f"planning {cfg.frames} frames")
        plan = make_plan(body, cfg)
        _write_meta(root, cfg, plan)
        topo_todo = [s for s in range(len(plan["segments"]))
                     if not (root / "gt" / "topologies" / f"{s:03d}.npz").is_file()]
        frame_todo = [i for i, name in enumerate(plan["frames"]) if not gt_frame_path(root, name).is_file()]
        needed = sorted(set(plan["segment_of_frame"][frame_todo].tolist()))
        topo_todo = [s for s in topo_todo if s in needed]
        workers = max(1, min(int(cfg.workers), len(frame_todo) or 1))
        results = []
        if frame_todo and workers > 1:
            try:
                results = _run_pool(cfg, root, plan, topo_todo, frame_todo, workers, progress)
            except BrokenProcessPool as exc:  # e.g. no importable __main__ for spawn, or a worker died
                log.warning("worker pool failed (%s); making the remaining frames in this process", exc)
                topo_todo = [s for s in topo_todo if not (root / "gt" / "topologies" / f"{s:03d}.npz").is_file()]
                frame_todo = [i for i in frame_todo if not gt_frame_path(root, plan["frames"][i]).is_file()]
                workers = 1
        if frame_todo and workers == 1:
            _init_worker(cfg, root, plan)
            _run(topo_todo, _topology_task, None, "scan topologies", progress)
            results += _run(frame_todo, _frame_task, None, "frames", progress)
        failed = {r["frame"]: r["error"] for r in results if "error" in r}
        if cfg.preview:
            from uvatar.capture.synth.preview import write_preview

            write_preview(root, plan, cfg)
    finally:
        torch.set_num_threads(threads)
        global _STUDIO
        _STUDIO = None
    return {"root": str(root), "frames": len(plan["frames"]), "made": len(frame_todo) - len(failed),
            "skipped": len(plan["frames"]) - len(frame_todo), "failed": failed,
            "topologies": len(plan["segments"]), "broken_frames": sorted(plan["broken"]),
            "heldout_frames": plan["heldout_frames"]}
