"""Per-camera frame sources for ``uvatar capture import``: a video file or a folder of images.

A source yields ``(index, image)`` for the selected source-frame indices, decoding one frame at a
time (never a whole video in memory). Videos go through imageio-ffmpeg (the project's video
dependency); image folders are read in file-name order.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.meshio import IMAGE_SUFFIXES
from uvatar.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")


@dataclass
class FrameSource:
    """One camera's frames: ``path`` a video or an image folder; ``width``/``height`` as decoded;
    ``count`` frames (None when the container does not say); ``fps`` (0 when unknown)."""

    name: str
    path: Path
    width: int
    height: int
    count: int | None
    fps: float
    reader: object = None  # the probe's open imageio-ffmpeg reader, still at frame 0 (reused once)

    @property
    def is_video(self) -> bool:
        return self.path.is_file()

    def images(self) -> list[Path]:
        return sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
                      and not p.name.startswith("."))

    def close(self) -> None:
        """Stop the probe's reader if :meth:`frames` never used it."""
        if self.reader is not None:
            self.reader.close()
            self.reader = None

    def frames(self, indices: list[int]) -> Iterator[tuple[int, np.ndarray]]:
        """Yield (index, (H, W, 3) uint8 RGB) for each wanted index (ascending), decoding lazily."""
        wanted = sorted(set(indices))
        if not wanted:
            self.close()
            return
        if not self.is_video:
            files = self.images()
            for i in wanted:
                if i < len(files):
                    yield i, _read_image(files[i])
            return
        import imageio_ffmpeg

        reader, self.reader = self.reader, None
        try:
            if reader is None:
                reader = imageio_ffmpeg.read_frames(str(self.path), pix_fmt="rgb24")
                next(reader)  # the meta data
            w, h = self.width, self.height
            frame_bytes = w * h * 3
            want = iter(wanted)
            target = next(want)
            for i, raw in enumerate(reader):
                if i < target:
                    continue
                if len(raw) != frame_bytes:
                    raise InputError(self.path, f"frame {i} decoded to {len(raw)} bytes, expected {frame_bytes}")
                yield i, np.frombuffer(raw, np.uint8).reshape(h, w, 3)
                target = next(want, None)
                if target is None:
                    return
        except (OSError, RuntimeError) as exc:  # ffmpeg failures
            raise InputError(self.path, f"cannot decode video ({' '.join(str(exc).split())[:200]})") from None
        finally:
            reader.close()


def _read_image(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(path))
    except Exception as exc:  # imageio raises many types for broken files  # noqa: BLE001
        raise InputError(path, f"unreadable image ({type(exc).__name__})") from None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.dtype != np.uint8:
        scale = 255.0 / (65535.0 if img.dtype == np.uint16 else max(1.0, float(img.max())))
        img = np.clip(img.astype(np.float64) * scale + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img[..., :3])


def ffmpeg_problem(text: str, limit: int = 200) -> str:
    """What ffmpeg said was wrong, from an imageio-ffmpeg error ("Could not load meta information
    === stderr === ffmpeg version ... configuration: ... moov atom not found ... Invalid data found
    when processing input"): its version banner, build configuration and library versions dropped,
    ``[in#0 @ 0x...]`` prefixes and repeated lines removed, the last distinct lines kept."""
    import re

    head, _, stderr = text.partition("=== stderr ===")
    banner = re.compile(r"^(ffmpeg version|built with|configuration:|lib[a-z]+\s+\d|Input #|Duration:|Stream #)")
    lines: list[str] = []
    for raw in stderr.splitlines():
        line = re.sub(r"^\[[^\]]*@ 0x[0-9a-f]+\]\s*", "", raw.strip())
        if line and not banner.match(line) and not line.startswith("Error opening input file") \
                and line not in lines:
            lines.append(line)
    kept = [ln for ln in lines if "misdetection possible" not in ln][-2:] or [" ".join(head.split())]
    out = "; ".join(kept)
    return out if len(out) <= limit else out[: limit - 3] + "..."


def probe(name: str, path: Path, count: bool = True) -> FrameSource:
    """Size, frame count and fps of a video or image folder (reads one frame at most; counting a
    video's frames decodes it once, so ``count=False`` skips that when the range is given)."""
    if path.is_file():
        import imageio_ffmpeg

        try:
            reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
            meta = next(reader)  # the reader stays open at frame 0 for FrameSource.frames
        except (OSError, RuntimeError, StopIteration) as exc:
            raise InputError(path, f"cannot open video ({ffmpeg_problem(str(exc))})") from None
        w, h = meta["size"]
        frames = None
        if count:
            try:
                frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
            except (OSError, RuntimeError):
                frames = None
        return FrameSource(name, path, int(w), int(h), frames, float(meta.get("fps") or 0.0), reader)
    src = FrameSource(name, path, 0, 0, None, 0.0)
    files = src.images()
    if not files:
        raise InputError(path, "image folder has no images")
    first = _read_image(files[0])
    src.height, src.width = first.shape[:2]
    src.count = len(files)
    return src


def find_sources(folder: Path, count: bool = True) -> dict[str, FrameSource]:
    """Per-camera sources in a recording folder: videos in ``folder`` or ``folder/videos``, else
    image folders ``folder/images/<cam>`` or ``folder/<cam>``; named by file stem / folder name.
    ``count``: count each video's frames (see :func:`probe`)."""
    for base in (folder / "videos", folder):
        if base.is_dir():
            videos = sorted(p for p in base.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
            if videos:
                return {p.stem: probe(p.stem, p, count) for p in videos}
    for base in (folder / "images", folder):
        if base.is_dir():
            dirs = sorted(p for p in base.iterdir() if p.is_dir() and not p.name.startswith(".")
                          and any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()))
            if dirs:
                return {p.name: probe(p.name, p) for p in dirs}
    raise InputError(folder, "no videos (videos/*.mp4, *.mp4) and no image folders (images/<cam>/) found")
