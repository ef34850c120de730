"""What every volumetric-take writer (:mod:`~uvatar.capture.uvol_take`, :mod:`~uvatar.capture.vols_take`)
asks of a frame before it encodes it: a texture and UVs, the texture as uint8 RGB, and one texture size
for the whole take (their headers and manifests state one)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["frame_texture"]


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
