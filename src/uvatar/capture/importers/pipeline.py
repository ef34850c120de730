"""``uvatar capture import``: per-camera videos or image folders + a calibration → a capture folder.

Writes ``cameras/intri.yml`` + ``extri.yml`` (uvatar's world: +Y up, metres; lens distortion kept,
images are not undistorted), ``images/<cam>/<frame>.jpg`` (or .png) and, last, ``capture.json``
(body model anny by default, no shapes yet: ``uvatar fit`` adds them). Frame names are the source
frame indices (``000010`` is the video's 11th frame) so masks and fits line up with the source.
Resumable: images already written are kept; every write is atomic; ``capture.json`` is written
last. ``images/stage.json`` (:mod:`uvatar.stage_record`) records the source and the image options
the images were written with (a resume with others is refused naming the flag) and marks the import
complete; :class:`uvatar.capture.Capture` refuses a half-made one.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.importers.calibration import (
    UNITS_SPELLED,
    UP_AXES,
    find_calibration,
    match_names,
    read_calibration,
    to_uvatar_world,
    unit_scale,
)
from uvatar.capture.importers.sources import FrameSource, find_sources
from uvatar.capture.layout import frame_name
from uvatar.capture.types import Camera
from uvatar.errors import InputError, check_values

log = logging.getLogger(__name__)

# Decoded frames this many pixels narrower/shorter than the calibration are taken as cropped at the
# right/bottom (codec padding to a multiple of 16: 1088 → 1080): K stays, the size is the decoded one.
MAX_CROP_PX = 16


@dataclass
class ImportConfig:
    """Options of ``uvatar capture import``.

    start, end: source frame range [start, end) (end 0: to the last frame); stride: every n-th
    frame; resize: image scale factor (0, 1] (K is scaled with it); up: the source world's up axis
    ("" = the calibration's own: +z for Qualisys and Pose2Sim, +y otherwise); units: of the
    calibration's translations ("" = its own); image_format: "jpg" (default: the source is
    already lossy H.264, q95 JPEG is ~8x smaller than PNG and adds less error than the video
    codec did) or "png" (lossless, for image-folder sources); jpeg_quality 1..100; fps: 0 = from
    the video; body_model: written to capture.json for ``uvatar fit``; cameras: names to keep
    (empty: all that have both a source and a calibration); point_voxel: a point-cloud take's
    surface grid step in point spacings (:class:`uvatar.capture.point_cloud.PointCloudConfig`);
    workers: processes a volumetric video's frames are read and written in (1: this process).
    """

    start: int = 0
    end: int = 0
    stride: int = 1
    resize: float = 1.0
    up: str = ""
    units: str = ""
    image_format: str = "jpg"
    jpeg_quality: int = 95
    fps: float = 0.0
    body_model: str = "anny"
    cameras: tuple[str, ...] = ()
    point_voxel: float = 1.5
    workers: int = 1

    def __post_init__(self) -> None:
        self.cameras = tuple(self.cameras)
        check_values([
            (self.start >= 0, f"start must be >= 0, got {self.start}"),
            (self.end >= 0, f"end must be >= 0 (0: to the last frame), got {self.end}"),
            (self.end == 0 or self.end > self.start, f"end ({self.end}) must be after start ({self.start})"),
            (self.stride >= 1, f"stride must be >= 1, got {self.stride}"),
            (0 < self.resize <= 1, f"resize must be in (0, 1], got {self.resize}"),
            (self.up in ("",) + UP_AXES, f"up must be one of {', '.join(UP_AXES)}, got {self.up!r}"),
            (self.units == "" or unit_scale(self.units) is not None,
             f"units must be {UNITS_SPELLED}, got {self.units!r}"),
            (self.image_format in ("jpg", "png"), f"image_format must be jpg or png, got {self.image_format!r}"),
            (1 <= self.jpeg_quality <= 100, f"jpeg_quality must be in 1..100, got {self.jpeg_quality}"),
            (self.fps >= 0, f"fps must be >= 0, got {self.fps}"),
            (self.point_voxel > 0, f"point_voxel must be > 0 point spacings, got {self.point_voxel}"),
            (self.workers >= 1, f"workers must be >= 1, got {self.workers}"),
        ])


def fit_camera_to_image(cam: Camera, width: int, height: int, source: str) -> tuple[Camera, str]:
    """The calibrated camera for images decoded at ``width`` x ``height`` and a note on what changed.

    Same size: unchanged. A few pixels smaller (≤ MAX_CROP_PX, e.g. 1080 decoded vs 1088
    calibrated): the codec's padding was cropped at the right/bottom, so K stays and the size
    becomes the decoded one. The same aspect ratio at another size: K is scaled. Otherwise
    InputError (the calibration does not belong to these images).
    """
    if not cam.width or not cam.height or (cam.width, cam.height) == (width, height):
        return Camera(cam.name, cam.K, cam.R, cam.T, width, height, cam.dist), ""
    dw, dh = cam.width - width, cam.height - height
    if 0 <= dw <= MAX_CROP_PX and 0 <= dh <= MAX_CROP_PX:
        note = (f"{cam.name}: decoded {width}x{height}, calibrated {cam.width}x{cam.height}: "
                f"taken as {dw} px cropped at the right / {dh} at the bottom (K kept)")
        return Camera(cam.name, cam.K, cam.R, cam.T, width, height, cam.dist), note
    if abs(width / cam.width - height / cam.height) < 2e-3:
        scaled = cam.scaled(width, height)
        return scaled, f"{cam.name}: calibrated {cam.width}x{cam.height}, decoded {width}x{height}: K scaled"
    raise InputError(source, f"camera {cam.name}: images are {width}x{height} but the calibration says "
                             f"{cam.width}x{cam.height} (neither a crop of <= {MAX_CROP_PX} px nor a scale)")


def _resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if image.shape[1] == width and image.shape[0] == height:
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def _write(path: Path, image: np.ndarray, cfg: ImportConfig) -> None:
    import imageio.v3 as iio

    from uvatar.io_utils import atomic_path

    kwargs = {"quality": cfg.jpeg_quality} if cfg.image_format == "jpg" else {}
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, image, **kwargs)


def _sweep_temp(folder: Path) -> None:
    """Remove temp files of killed atomic writes (``.<stem>.*``) so they are never read back."""
    if folder.is_dir():
        for p in folder.glob(".*"):
            if p.is_file():
                p.unlink(missing_ok=True)


def _begin_images(out: Path, src: Path, sources: dict[str, FrameSource], cfg: ImportConfig, total: int) -> None:
    """The stage record of ``out/images`` (:mod:`uvatar.stage_record`), before the first image is
    written: a resume into images written from another source or with another resize / format /
    quality is refused in one line naming the setting (they would be kept and mix with the new ones),
    as is one whose source videos changed since. The frame range, cameras, up axis, units and frame
    rate may change: an image is its source frame's whatever the range, and the cameras and
    capture.json are written again by every run."""
    from uvatar import stage_record

    images = out / "images"
    (out / ".import-images.json").unlink(missing_ok=True)  # the resume guard this record replaced
    config = {"source": str(src.resolve()), "resize": cfg.resize, "image_format": cfg.image_format,
              "jpeg_quality": cfg.jpeg_quality}
    stage_record.begin(images, "capture import", config,
                       stage_record.file_identities(*(s.path for s in sources.values())), total=total,
                       redo_hint="another output folder starts over")


def _frame_indices(sources: dict[str, FrameSource], cfg: ImportConfig) -> list[int]:
    counts = [s.count for s in sources.values() if s.count is not None]
    total = min(counts) if counts else None
    end = cfg.end or total
    if end is None:
        raise InputError("end", "the videos do not report their frame count; give end")
    if total is not None and end > total:
        log.warning("end %d is past the shortest source (%d frames): stopping at %d", end, total, total)
        end = total
    frames = list(range(cfg.start, end, cfg.stride))
    if not frames:
        raise InputError("start", f"no frame in [{cfg.start}, {end}) with stride {cfg.stride}")
    return frames


def import_capture(src: str | Path, out: str | Path, cfg: ImportConfig | None = None,
                   calibration: str | Path | None = None, progress: bool = True) -> dict:
    """Import a recording folder ``src`` (videos or image folders + a calibration) into the capture
    folder ``out``; returns the summary written to the log (frames, cameras, notes, seconds)."""
    cfg = cfg or ImportConfig()
    src, out = Path(src), Path(out)
    t0 = time.perf_counter()
    if not src.is_dir():
        raise InputError(src, "recording folder does not exist")
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    calib_path = Path(calibration) if calibration else find_calibration(src)
    if calib_path is None:
        raise InputError(src, "no calibration found (intri.yml/extri.yml, .qca, .toml, .json); give calibration")
    calib = read_calibration(calib_path)
    sources = find_sources(src, count=cfg.end == 0)
    try:
        return _import(src, out, cfg, calib, calib_path, sources, progress, t0)
    finally:
        for source in sources.values():
            source.close()


def _import(src: Path, out: Path, cfg: ImportConfig, calib, calib_path: Path, sources: dict[str, FrameSource],
            progress: bool, t0: float) -> dict:
    from tqdm import tqdm

    from uvatar import stage_record
    from uvatar.capture.cameras import write_cameras
    from uvatar.capture.layout import write_capture_info

    names = match_names(list(calib.cameras), list(sources))
    if cfg.cameras:
        unknown = [c for c in cfg.cameras if c not in sources]
        if unknown:
            raise InputError("cameras", f"no source for {', '.join(unknown)} (have {', '.join(sources)})")
        names = {s: c for s, c in names.items() if s in cfg.cameras}
    missing = [s for s in (cfg.cameras or sources) if s not in names]
    if missing:
        raise InputError(calib_path, f"no calibration for camera(s) {', '.join(missing)} "
                                     f"(calibrated: {', '.join(calib.cameras)})")
    notes = list(calib.notes)
    unused = sorted(set(calib.cameras) - set(names.values()))
    if unused:
        notes.append(f"calibrated cameras without images, skipped: {', '.join(unused)}")
    world, S = to_uvatar_world(calib, cfg.up or None, cfg.units or None)
    cameras: dict[str, Camera] = {}
    for sname, cname in names.items():
        source = sources[sname]
        cam, note = fit_camera_to_image(world[cname], source.width, source.height, str(source.path))
        if note:
            notes.append(note)
        if cfg.resize != 1.0:
            cam = cam.scaled(max(1, round(cam.width * cfg.resize)), max(1, round(cam.height * cfg.resize)))
        cam.name = sname
        cameras[sname] = cam
    for note in notes:
        log.warning(note)
    frames = _frame_indices({s: sources[s] for s in cameras}, cfg)
    out.mkdir(parents=True, exist_ok=True)
    _begin_images(out, src, {s: sources[s] for s in cameras}, cfg, len(frames) * len(cameras))
    write_cameras(out / "cameras", cameras)
    ext = "." + cfg.image_format
    todo = {}
    for name in cameras:
        folder = out / "images" / name
        _sweep_temp(folder)
        todo[name] = [i for i in frames if not (folder / f"{frame_name(i)}{ext}").is_file()]
    bar = tqdm(total=sum(map(len, todo.values())), desc="import", unit="image", disable=not progress or None)
    written = 0
    for name, cam in cameras.items():
        folder = out / "images" / name
        got = set()
        for i, image in sources[name].frames(todo[name]):
            _write(folder / f"{frame_name(i)}{ext}", _resize(image, cam.width, cam.height), cfg)
            got.add(i)
            written += 1
            bar.update(1)
        short = [i for i in todo[name] if i not in got]
        if short:
            raise InputError(sources[name].path, f"ended before frame {short[0]} ({len(short)} frames missing)")
        stage_record.mark_progress(out / "images", sum(len(frames) - len(todo[c]) for c in cameras) + written)
    bar.close()
    fps = cfg.fps or next((s.fps for s in sources.values() if s.fps), 0.0) or 25.0
    provenance = {"tool": "uvatar capture import", "source": str(src.resolve()), "calibration": str(calib_path),
                  "calibration_format": calib.format, "source_up": cfg.up or calib.up,
                  "source_units": cfg.units or calib.units, "world_from_source": S.tolist(),
                  "source_frames": [frames[0], frames[-1] + 1, cfg.stride], "notes": notes,
                  "config": asdict(cfg)}
    write_capture_info(out, [frame_name(i) for i in frames], fps=fps / cfg.stride, body_model=cfg.body_model,
                       provenance=provenance)
    stage_record.finish(out / "images")
    return {"capture": str(out), "frames": len(frames), "cameras": list(cameras), "images_written": written,
            "images_kept": len(frames) * len(cameras) - written, "notes": notes,
            "seconds": round(time.perf_counter() - t0, 1)}
