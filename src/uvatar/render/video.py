"""Write frame sequences as MP4 (H.264 through imageio-ffmpeg) or, as a fallback, GIF.

Frames: (H, W, 3) float in [0, 1] or uint8, all the same size. H.264 needs even dimensions, so frames
are padded by one pixel (edge colour) where needed. The file is written atomically.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import atomic_path, check_output_location

__all__ = ["write_video", "to_uint8", "check_video_path", "VIDEO_SUFFIXES"]

VIDEO_SUFFIXES = (".mp4", ".gif")


def check_video_path(path) -> Path:
    """Raise :class:`InputError` unless ``path`` can take a video: a ``.mp4``/``.gif`` name that is
    not an existing folder (call it before rendering, so a bad ``-o`` fails in a second)."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(path, f"a video must end in {' or '.join(VIDEO_SUFFIXES)}, got {path.suffix or 'no suffix'!r}")
    if path.is_dir():
        raise InputError(path, "is a folder; give a video file name")
    return check_output_location(path)


def to_uint8(frame) -> np.ndarray:
    """(H, W[, C]) float in [0, 1] or uint8 -> (H, W, 3) uint8."""
    f = np.asarray(frame)
    if f.dtype != np.uint8:
        f = (np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if f.ndim == 2:
        f = np.repeat(f[..., None], 3, axis=-1)
    if f.shape[-1] == 4:
        f = f[..., :3]
    if f.ndim != 3 or f.shape[-1] != 3:
        raise InputError("frames", f"expected (H, W, 3) frames, got {f.shape}")
    return f


def _even(f: np.ndarray) -> np.ndarray:
    h, w = f.shape[:2]
    return np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(path, frames, fps: float = 25.0, quality: int = 7) -> Path:
    """Write ``frames`` to ``path`` (.mp4; .gif also accepted). Returns the path actually written:
    if MP4 encoding fails (no ffmpeg), a GIF next to it (same stem, .gif) with a warning."""
    path = check_video_path(path)
    frames = [to_uint8(f) for f in frames]
    if not frames:
        raise InputError(path, "no frames to write")
    if any(f.shape != frames[0].shape for f in frames):
        raise InputError(path, "frames differ in size")
    import imageio.v2 as imageio

    if path.suffix.lower() != ".gif":
        try:
            with atomic_path(path) as tmp:
                with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                        quality=quality, pixelformat="yuv420p", macro_block_size=1) as w:
                    for f in frames:
                        w.append_data(_even(f))
            return path
        except OSError as exc:
            if exc.errno is not None:  # the file system said no (full, read-only): a GIF would fail too
                raise
            warnings.warn(f"MP4 encoding failed ({exc}); writing a GIF instead", stacklevel=2)
            path = path.with_suffix(".gif")
        except Exception as exc:  # no ffmpeg binary or codec: fall back to GIF
            warnings.warn(f"MP4 encoding failed ({exc}); writing a GIF instead", stacklevel=2)
            path = path.with_suffix(".gif")
    with atomic_path(path) as tmp:
        imageio.mimsave(tmp, frames, format="GIF", duration=1.0 / fps, loop=0)
    return path
