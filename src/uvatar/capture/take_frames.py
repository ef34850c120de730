"""What every volumetric-take writer (:mod:`~uvatar.capture.uvol_take`, :mod:`~uvatar.capture.vols_take`,
:mod:`~uvatar.capture.abc_take`) asks of a frame before it encodes it: a texture and UVs, the texture as
uint8 RGB, and one texture size for the whole take (their headers and manifests state one); and of the
one-file takes' path and frame rate (:func:`take_path`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["frame_texture", "take_path"]


def frame_texture(mesh: TexturedMesh, where: Path, frame: int, take_size: tuple[int, int] | None,
                  take: str) -> tuple[np.ndarray, tuple[int, int]]:
    """(uint8 (H, W, 3) texture, (W, H)) of frame ``frame`` of a ``take`` (its format's name, for messages)
    written at ``where``; InputError when the frame has no texture or UVs, or a texture of another size
    than ``take_size`` (the first frame's; None for the first frame)."""
    if mesh.texture is None or not mesh.has_uvs:
        raise InputError(where, f"frame {frame} has no texture or no UVs: a {take} take needs both")
    texture = np.asarray(mesh.texture)
    if texture.dtype != np.uint8:
        texture = (np.clip(texture[..., :3], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    size = (texture.shape[1], texture.shape[0])
    if take_size is not None and size != take_size:
        raise InputError(where, f"frame {frame}'s texture is {size[0]} x {size[1]}, the take's "
                                f"{take_size[0]} x {take_size[1]}")
    return np.ascontiguousarray(texture[..., :3]), size


def take_path(path: str | Path, fps: float, suffix: str, take: str) -> Path:
    """The file a one-file ``take`` writer writes: ``path`` itself when it ends in ``suffix``, else
    ``path/avatar<suffix>``; its folder made. InputError when ``fps`` is not > 0."""
    path = Path(path)
    if not fps or fps <= 0:
        raise InputError(path, f"a{'n' if take[0] in 'AEIOU' else ''} {take} take needs a frame rate > 0, not {fps}")
    if path.suffix.lower() != suffix:
        path = path / f"avatar{suffix}"
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
