"""Texture videos: a volumetric take's textures as the frames of one video (UVOL 1's ``.mp4``), read
frame by frame through imageio-ffmpeg.

:class:`TextureVideo` decodes forward from where it last stopped (an import asks for its frames in
order) and seeks (ffmpeg's accurate input seek) when asked for an earlier frame or one far ahead. The
frames come out as uvatar textures: (H, W, 3) uint8, row 0 at v = 1 (a video's top row, the v = 1 of
three.js's default ``flipY``, as the UVOL 1 player maps it).

UVOL 1's texture encoder also writes a **frame counter** into each frame: 16 blocks of 8 x 8 pixels
along the bottom-left edge, block ``i`` (from the left) white for bit ``i`` of the frame's number, black
otherwise; the player reads it (the mean of each block's bottom 4 rows) where the browser cannot say
which video frame it shows. :meth:`TextureVideo.open` reads it from every frame of the video in the
pass that counts them (ffmpeg crops the strip before it is decoded to RGB), so the import can check that
the video's frames are the meshes' frames, one for one. The counter overwrites whatever texels lie there (the
encoder warns that it may "bleed into your textures"); where a video carries one, :meth:`TextureVideo.frame`
fills that corner from the texels around it (:func:`fill_counter`, OpenCV's Telea inpainting) so that a
chart lying under it keeps its own colours rather than black and white blocks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError

__all__ = ["TextureVideo", "read_counter", "fill_counter", "open_video", "close_videos", "COUNTER_BITS",
           "COUNTER_BLOCK"]

COUNTER_BITS, COUNTER_BLOCK = 16, 8      # the UVOL 1 encoder's encoderByteLength and encoderWindowSize
#: the texels the counter changes: its 9 rows and 129 columns (the encoder's rectangles are inclusive),
#: with the video codec's ringing around them (a 3-texel margin)
COUNTER_ROWS, COUNTER_COLUMNS = 12, COUNTER_BITS * COUNTER_BLOCK + 4
_SEEK_AHEAD = 64                         # frames beyond which a seek is cheaper than decoding forward


def read_counter(strip: np.ndarray) -> int | None:
    """The UVOL 1 frame counter in a frame's bottom strip ((rows, >= 128, 3) uint8, the frame's last
    rows): each block's bottom 4 rows, its middle 4 columns, must be clearly black or white (a video
    codec blurs the edges); None when any block is neither (no counter in this frame)."""
    rows = strip[-4:, :COUNTER_BITS * COUNTER_BLOCK].astype(np.float32).mean(-1)
    blocks = rows.reshape(rows.shape[0], COUNTER_BITS, COUNTER_BLOCK)[:, :, 2:6].mean((0, 2))
    if ((blocks > 64) & (blocks < 192)).any():
        return None
    return int(((blocks >= 192).astype(np.int64) << np.arange(COUNTER_BITS)).sum())


def fill_counter(image: np.ndarray) -> np.ndarray:
    """``image`` ((H, W, 3) uint8) with the counter's corner (the bottom ``COUNTER_ROWS`` rows, the first
    ``COUNTER_COLUMNS`` columns) filled from the texels around it (OpenCV's Telea inpainting, radius 5)."""
    import cv2

    mask = np.zeros(image.shape[:2], np.uint8)
    mask[-COUNTER_ROWS:, :COUNTER_COLUMNS] = 255
    return cv2.inpaint(np.ascontiguousarray(image), mask, 5, cv2.INPAINT_TELEA)


@dataclass
class TextureVideo:
    """One texture video: its ``size`` (width, height), ``fps`` (the container's), frame ``count``
    (decoded, not the container's guess) and each frame's counter (:meth:`counters`); ``has_counter``:
    its frames carry UVOL 1's counter, filled in by :meth:`frame` (set by whoever decided so from
    :meth:`counters`)."""

    path: Path
    size: tuple[int, int] = (0, 0)
    fps: float = 0.0
    count: int = 0
    has_counter: bool = False
    _counters: list = field(default_factory=list, repr=False)
    _reader: object = field(default=None, repr=False)
    _next: int = 0

    @classmethod
    def open(cls, path: Path) -> TextureVideo:
        """Probe a texture video: its size and rate, then one pass over its frames (only their bottom
        strip decoded to RGB) for the frame count and each frame's counter; InputError naming it when
        ffmpeg cannot read it or it holds no frame."""
        import imageio_ffmpeg

        from uvatar.capture.importers.sources import ffmpeg_problem

        path = Path(path)
        if not path.is_file():
            raise InputError(path, "texture video is missing")
        try:
            reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
            meta = next(reader)
            reader.close()
        except (OSError, RuntimeError, StopIteration) as exc:
            raise InputError(path, f"cannot open the texture video ({ffmpeg_problem(str(exc))})") from None
        video = cls(path, tuple(int(v) for v in meta["size"]), float(meta.get("fps") or 0.0))
        video._counters = video._read_counters()
        video.count = len(video._counters)
        if not video.count:
            raise InputError(path, "texture video holds no frame")
        return video

    def counters(self) -> list[int | None]:
        """Every frame's UVOL 1 counter (None where a frame has none), read when the video was opened."""
        return list(self._counters)

    def _read_counters(self) -> list[int | None]:
        """One decoding pass, each frame cropped to the counter's strip (the whole frame when it is
        smaller): a counter (or None) a frame."""
        import imageio_ffmpeg

        width, height = self.size
        strip_rows, strip_columns = COUNTER_BLOCK, COUNTER_BITS * COUNTER_BLOCK
        fits = width >= strip_columns and height >= strip_rows
        crop = f"crop={strip_columns}:{strip_rows}:0:{height - strip_rows}" if fits else f"crop={width}:{height}:0:0"
        out: list[int | None] = []
        quiet = logging.getLogger("imageio_ffmpeg")      # it warns that the crop is not the source size
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            reader = imageio_ffmpeg.read_frames(str(self.path), pix_fmt="rgb24", output_params=["-vf", crop])
            next(reader)
            for raw in reader:
                if not fits:
                    out.append(None)
                    continue
                strip = np.frombuffer(raw, np.uint8).reshape(strip_rows, strip_columns, 3)
                out.append(read_counter(strip))
        except (OSError, RuntimeError) as exc:
            raise InputError(self.path, f"cannot decode the texture video ({' '.join(str(exc).split())[:160]})") from None
        finally:
            quiet.setLevel(level)
        return out

    def _start(self, frame: int) -> None:
        import imageio_ffmpeg

        self.close()
        params = ["-ss", f"{(frame - 0.5) / self.fps:.6f}"] if frame > 0 and self.fps > 0 else []
        self._reader = imageio_ffmpeg.read_frames(str(self.path), pix_fmt="rgb24", input_params=params)
        next(self._reader)
        self._next = frame if params else 0

    def frame(self, index: int) -> np.ndarray:
        """Video frame ``index`` (0-based, in decoding order) as (H, W, 3) uint8, its counter filled in
        where the video has one; InputError naming the video when it ends before it or ffmpeg fails."""
        if not 0 <= index < self.count:
            raise InputError(self.path, f"texture video has {self.count} frames: no frame {index}")
        if self._reader is None or index < self._next or index >= self._next + _SEEK_AHEAD:
            self._start(index)
        width, height = self.size
        try:
            while True:
                raw = next(self._reader, None)
                if raw is None:
                    self.close()
                    raise InputError(self.path, f"texture video ends before frame {index}")
                self._next += 1
                if self._next - 1 == index:
                    if len(raw) != width * height * 3:
                        raise InputError(self.path, f"frame {index} decoded to {len(raw)} bytes, expected "
                                                    f"{width * height * 3}")
                    image = np.frombuffer(raw, np.uint8).reshape(height, width, 3).copy()
                    return fill_counter(image) if self.has_counter else image
        except (OSError, RuntimeError) as exc:
            self.close()
            raise InputError(self.path, f"cannot decode the texture video ({' '.join(str(exc).split())[:160]})") from None

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None


_OPEN: dict[Path, TextureVideo] = {}     # the videos an import has open (closed at its end)


def open_video(path: Path) -> TextureVideo:
    """The open :class:`TextureVideo` of ``path`` (opened and probed once, then kept for the frames
    after), until :func:`close_videos`."""
    path = Path(path)
    if path not in _OPEN:
        _OPEN[path] = TextureVideo.open(path)
    return _OPEN[path]


def close_videos() -> None:
    for video in _OPEN.values():
        video.close()
    _OPEN.clear()
