"""Ground truth beside a synthetic capture (``OUT/gt/``), see docs/ARCHITECTURE.md.

``gt/info.json`` (read and written by :mod:`uvatar.capture.gt`): broken_frames (frame names), broken ({frame: {"kind", "fraction"}}),
heldout_frames, takes ({name: [first, end) frame indices}), texel_resolution, segments (scan
topologies: first/last frame, face count), seed and the full config.
``gt/frames/<frame>.npz``: pose (J*3,) true local axis-angles, Rh (3,), Th (3,), texture (R, R, 3)
float32 in [0, 1], offset (R, R, 3) world-space clothing offset of the posed frame (m; surface
minus the body texel point, tangential drift included), surface (R, R, 3) true clothed surface
point per body texel (world, m, noise-free), mask (R, R) bool,
bends (K,) (see :mod:`.bends`), broken (bool). With the studio light on (``config.light ==
"studio"``, :mod:`.lighting`), ``texture`` is what the scans and cameras see, the light included,
and the frame also keeps its parts apart: albedo (R, R, 3) float32 (pose independent), crease (R, R)
float32 crease darkening of the pose, shading (R, R) float32 the rig's light (ambient x AO + key +
fill, cast shadows included), ao (R, R) float32 ambient occlusion in [0, 1]; ``texture =
clip(albedo * crease * shading, 0, 1)``. Unlit captures (``light == "none"``) have none of these four
and ``texture = albedo * crease``. All maps in the body UV layout, row 0 = v 1.
``gt/motion.npz``: the whole true motion; ``gt/topologies/<segment>.npz``: scan topologies with each
scan vertex's body origin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.gt import write_gt_info
from uvatar.io_utils import write_npz

__all__ = ["write_gt_frame", "write_gt_info", "gt_frame_path", "scatter_texels"]


def gt_frame_path(root: str | Path, frame: str) -> Path:
    return Path(root) / "gt" / "frames" / f"{frame}.npz"


def scatter_texels(values: np.ndarray, flat: np.ndarray, resolution: int, fill: float = 0.0) -> np.ndarray:
    """(N, C) values at flat texel indices -> (R, R, C) float32 map filled with ``fill`` elsewhere."""
    out = np.full((resolution * resolution, values.shape[1]), fill, dtype=np.float32)
    out[flat] = values
    return out.reshape(resolution, resolution, values.shape[1])


def write_gt_frame(root: str | Path, frame: str, **arrays) -> None:
    write_npz(gt_frame_path(root, frame), **{k: np.asarray(v) for k, v in arrays.items()})
