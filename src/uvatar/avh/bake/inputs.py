"""What a bake worker loads: the body model with its UV layout at R texels (memoized once per
process, or adopted from the parent so a worker does not raster it again), and a frame's starting
fit with the shape to pose it by. Shared by the per-frame bake (:mod:`.pipeline`) and the refinement
across frames (:mod:`.refine_together`). :func:`prepared_scan` keeps a frame's scan, read and prepared
for ray queries once, for the colour rounds and the bake that follow in the same process, and takes
the file read that :func:`prefetch_scan` started on a thread while the task before it ran;
:func:`keep_sample` keeps a colour round's closing colour sample beside it for the next round."""

from __future__ import annotations

__all__ = ["load_body_and_layout", "adopt_body_and_layout", "start_fit", "prepared_scan", "prefetch_scan",
           "prefetch_task_scans", "clear_scan_cache", "keep_sample", "kept_sample"]

# -- per-process state ----------------------------------------------------------------------------
_STATE: dict = {}
_SCANS: dict = {}      # (capture root, frame, device, backend, file stamp) -> (TexturedMesh, ScanSurface, bytes)
_SAMPLES: dict = {}    # the same keys -> (fit key, PhotoSample): a colour round's closing sample
_SCAN_RUN: list = [None]   # the run whose scans _SCANS holds
_MEMORY_RESERVE = 1 << 30  # a scan is kept only while this much memory stays available beside it
#: read the next task's scans ahead (:func:`prefetch_scan`) where the bake's device is CUDA; False reads
#: each where it is used (benches compare the two)
READ_AHEAD = True
#: read ahead on the CPU too (tests, scripts/gpu_path_bake.py). Off: a CPU bake's own threads already take
#: the cores (measured on 2 cores: no faster, results/bench_bake_overlap_refine_nocache_cpu_session15.json)
READ_AHEAD_ON_CPU = False
_READING: dict = {}    # the same keys -> Future of the scan file read by prefetch_scan, not yet taken
_READER: list = []     # the one thread that reads them (made on first use)


def load_body_and_layout(body_name: str, texels: int):
    """(BodyModel, BodyLayout) for a body model at a texel resolution; memoized per process."""
    key = (body_name, int(texels))
    if key not in _STATE:
        from uvatar.avh.bake.frame import BodyLayout
        from uvatar.body import load_body_model

        body = load_body_model(body_name)
        _STATE[key] = (body, BodyLayout.from_template(body.template, texels))
    return _STATE[key]


def adopt_body_and_layout(body_name: str, texels: int, pair):
    """Keep ``pair`` (BodyModel, BodyLayout), shipped from the parent process, unless this process
    already holds one for the same body and resolution; returns the one held."""
    return _STATE.setdefault((body_name, int(texels)), pair)


def start_fit(capture, frame: str):
    """(the capture's fit of ``frame``, the shape to pose it with: None when the fit carries its own,
    else the capture's shared shape if it has one)."""
    fit = capture.load_fit(frame)
    if fit.shapes.size:
        return fit, None
    shapes = capture.body_shapes
    return fit, shapes if shapes.size else None


def _scan_bytes(scan, surface) -> int:
    """Rough memory of a prepared scan: its arrays, plus as much again for the k-d tree and the BVH."""
    arrays = [scan.vertices, scan.faces, scan.uvs, scan.uv_faces, scan.texture, surface.vertices, surface.faces,
              surface.vertex_normals, surface.face_normals, surface.sample_points, surface.sample_normals,
              surface.corner_normals]
    return sum(int(a.nbytes) for a in arrays if a is not None) + 2 * int(surface.sample_points.nbytes)


def prepared_scan(capture, frame: str, config, run=None):
    """(TexturedMesh, :class:`~uvatar.avh.bake.register.ScanSurface`) of ``frame``'s scan, its rays on
    ``config.device``. Kept in this process while the kept scans stay under ``config.scan_cache_mb``
    (and 1 GiB of memory stays available), so the colour rounds and the bake read and prepare each
    scan once. Scans are kept first come, first kept (no eviction): every round visits the frames in
    the same order, where a least-recently-used cache smaller than the frames would drop each scan
    just before its next use. ``run``: a token of the bake; a new one drops the scans of the previous
    run (a long-lived Ray worker bakes one capture after another). A scan file changed on disk is read
    again (its size and time are part of the key)."""
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.resources import available_memory

    _enter_run(run)
    key = _scan_key(capture, frame, config)
    stamp = key[-1]
    hit = _SCANS.get(key)
    if hit is not None:
        return hit[0], hit[1]
    reading = _READING.pop(key, None)
    scan = reading.result() if reading is not None else capture.load_scan(frame)   # its error, if any
    surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)
    size = _scan_bytes(scan, surface)
    if (stamp is not None and sum(v[2] for v in _SCANS.values()) + size <= config.scan_cache_mb * 2**20
            and available_memory() > size + _MEMORY_RESERVE):
        _SCANS[key] = (scan, surface, size)
    return scan, surface


def prefetch_scan(capture, frame: str, config, run=None) -> None:
    """Start reading ``frame``'s scan file (``capture.load_scan``: the mesh and its texture decoded) on
    this process's reader thread, for :func:`prepared_scan` to take when the frame's task comes: the
    read then overlaps the task before it, whose kernels keep a GPU busy while the host waits
    (:data:`READ_AHEAD`, where ``config.device`` is CUDA or :data:`READ_AHEAD_ON_CPU`). Nothing is
    started for a scan kept or already being read, a file that cannot be stat'ed (its task reports it)
    or with less than twice the memory reserve available. A read that fails raises in
    :func:`prepared_scan`, as reading it there would."""
    from uvatar.resources import available_memory

    if not (READ_AHEAD and (str(config.device).startswith("cuda") or READ_AHEAD_ON_CPU)):
        return
    _enter_run(run)
    key = _scan_key(capture, frame, config)
    if key in _SCANS or key in _READING or key[-1] is None or available_memory() < 2 * _MEMORY_RESERVE:
        return
    if not _READER:
        from concurrent.futures import ThreadPoolExecutor

        _READER.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="scan-read"))
    _READING[key] = _READER[0].submit(capture.load_scan, frame)


def prefetch_task_scans(shared: dict, frames) -> None:
    """:func:`prefetch_scan` of each of ``frames`` for a bake's task (``shared``: the bake's task inputs,
    capture_root, config and run): the prefetch of :func:`uvatar.parallel.run_tasks`, and a task's own for
    its later frames. Never raises: a read ahead that cannot start is the frame's task's to meet."""
    import logging

    from uvatar.capture import Capture
    from uvatar.errors import one_line

    try:
        capture = Capture(shared["capture_root"])
        for frame in frames:
            prefetch_scan(capture, frame, shared["config"], shared.get("run"))
    except Exception as exc:  # noqa: BLE001 - the task reads the scan itself and reports what fails
        logging.getLogger(__name__).debug("no read ahead of %s: %s", list(frames), one_line(exc))


def _enter_run(run) -> None:
    """A new bake's token (:func:`prepared_scan`'s ``run``) drops the previous run's scans."""
    if run != _SCAN_RUN[0]:
        clear_scan_cache()
        _SCAN_RUN[0] = run


def _scan_key(capture, frame: str, config) -> tuple:
    """The key of a frame's prepared scan: capture, frame, where its rays run, the file's size and time."""
    try:
        st = capture.scan_path(frame).stat()
        stamp = (st.st_size, st.st_mtime_ns)
    except OSError:
        stamp = None     # read_mesh reports the missing file
    return (str(capture.root), frame, config.device, config.ray_backend, stamp)


def _fit_key(fit) -> bytes:
    """The pose a sample was taken at, exactly (poses, Rh, Th, scale)."""
    import numpy as np

    return b"".join(np.ascontiguousarray(x, dtype=np.float64).tobytes()
                    for x in (fit.poses, fit.Rh, fit.Th, [fit.scale]))


def keep_sample(capture, frame: str, config, fit, sample) -> None:
    """Keep a colour round's closing :class:`~uvatar.avh.bake.refine.PhotoSample` of ``frame`` at
    ``fit`` beside the frame's kept scan (nothing when the scan is not kept: the cache stays bounded
    by ``scan_cache_mb``); one per frame, the latest."""
    key = _scan_key(capture, frame, config)
    if key in _SCANS:
        _SAMPLES[key] = (_fit_key(fit), sample)


def kept_sample(capture, frame: str, config, fit):
    """The sample :func:`keep_sample` kept for ``frame`` if it was taken at exactly ``fit``, else None."""
    kept = _SAMPLES.get(_scan_key(capture, frame, config))
    return kept[1] if kept is not None and kept[0] == _fit_key(fit) else None


def clear_scan_cache() -> None:
    """Drop the scans :func:`prepared_scan` keeps in this process, and the colour samples kept with
    them, and the reads :func:`prefetch_scan` started (a bake run in process calls it at its end)."""
    _SCANS.clear()
    _SAMPLES.clear()
    for reading in _READING.values():
        reading.cancel()         # one already running finishes on its thread and is dropped
    _READING.clear()
