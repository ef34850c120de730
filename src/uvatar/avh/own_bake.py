"""Each evaluated frame's own baked maps: the ceiling of the pose-dependent R² and a target without gt.

A held-out frame that the bake also processed (``BAKED/frames/<f>``, never trained on) has maps made
by the same registration and correspondences as the training targets. Two measures use them
(:mod:`uvatar.avh.pose_metrics`'s R², the training frames' mean map as the reference):

- **ceiling** (needs ``gt/``): the own bake scored against the truth like any method. It says how
  much of the true pose-dependent variance survives the bake (resolution, registration jitter,
  correspondence noise): a generator trained on baked maps cannot be expected to explain more.
- **against the own bake** (no ``gt/`` needed, e.g. a real take): each method's maps scored against
  the frame's own baked maps over the bake's confident texels. The generator's R² there measures
  how much of what the bake sees vary with pose it predicts.

Displacements are cleaned as training sees them (zero outside the UV charts and where any axis
exceeds the outlier threshold) and moved to the avatar's frame (rest or body) so that the runtime
re-poses them exactly like the generator's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.data import BakedFrames, load_baked_frames
from uvatar.avh.pose_metrics import R2Sums

__all__ = ["clean_displacements", "OwnBake", "OwnBakes", "r2_against_own_bake"]


def clean_displacements(frames: BakedFrames, outlier_threshold: float, displacement_frame: str = "body",
                        body=None, shape=None) -> tuple[np.ndarray, np.ndarray]:
    """(displacements (N, R, R, 3) metres in ``displacement_frame``, kept (N, R, R) bool): the baked
    body-frame displacements zeroed outside the UV charts and where any axis exceeds
    ``outlier_threshold`` (what training leaves out of its loss), then moved to the rest frame if asked."""
    bad = ~frames.valid | (np.abs(frames.displacement).max(-1) > outlier_threshold)
    if displacement_frame == "rest":
        from uvatar.avh.displacement_frame import displacements_to_frame

        frames = displacements_to_frame(frames, "rest", body, shape)
    return np.where(bad[..., None], 0.0, frames.displacement).astype(np.float32), ~bad


@dataclass
class OwnBake:
    """One frame's baked maps at the avatar's resolution R: texture (R, R, 3), displacement (R, R, 3)
    metres in the avatar's frame (cleaned), kappa (R, R) texture confidence, kept (R, R) bool texels
    whose displacement training would use (valid, inlier, w > 0), valid (R, R) bool texels on the body."""

    texture: np.ndarray
    displacement: np.ndarray
    kappa: np.ndarray
    kept: np.ndarray
    valid: np.ndarray


class OwnBakes:
    """The baked maps of the frames that ``baked_dir`` holds (``BAKED/frames/<f>``), on demand."""

    def __init__(self, baked_dir: str | Path, resolution: int, displacement_frame: str = "body", body=None,
                 shape=None, outlier_threshold: float = 0.05):
        from uvatar.avh.bake.dataset import frame_path

        self.baked_dir, self.resolution = Path(baked_dir), resolution
        self.displacement_frame, self.body, self.shape = displacement_frame, body, shape
        self.outlier_threshold = outlier_threshold
        self._path = frame_path

    def get(self, frame: str) -> OwnBake | None:
        """The frame's own bake, or None when the dataset has no (readable) bake of it."""
        from uvatar.errors import InputError

        if not self._path(self.baked_dir, frame).exists():
            return None
        try:
            frames = load_baked_frames(self.baked_dir, [frame], self.resolution)
        except InputError:
            return None
        disp, kept = clean_displacements(frames, self.outlier_threshold, self.displacement_frame, self.body,
                                         self.shape)
        return OwnBake(texture=frames.texture[0], displacement=disp[0], kappa=frames.kappa[0],
                       kept=kept[0] & (frames.w[0] > 0), valid=frames.valid[0])


def r2_against_own_bake(maps: dict[str, tuple[np.ndarray, np.ndarray | None]], own: OwnBake,
                        mean_texture: np.ndarray, mean_displacement: np.ndarray, confident: np.ndarray,
                        surface: Callable[[np.ndarray | None], np.ndarray], sums: dict[str, R2Sums]) -> dict:
    """Add one frame to the R² sums against its own bake; returns the frame's ``<method>_<kind>_r2_vs_bake``.

    maps: {method: (texture (R, R, 3), displacement (R, R, 3) in the avatar's frame or None)};
    mean_texture / mean_displacement: the training frames' mean maps (the reference);
    confident: (R, R) bool texels scored (the training frames' mean κ > 0.5, no fingers/toes);
    surface: displacement map (or None) -> the clothed surface point per texel (R, R, 3) world metres
    of the frame's posed body (so that rest-frame maps are compared after the same re-posing);
    sums: ``texture`` and ``displacement`` R² sums. Texture over texels where the own bake's κ > 0.5,
    displacement where the own bake's displacement is kept (valid, inlier, w > 0).
    """
    out = {}
    tex_mask = confident & (own.kappa > 0.5)
    frame_r2 = sums["texture"].add({m: t for m, (t, _) in maps.items()}, mean_texture, own.texture, tex_mask)
    out.update({f"{m}_texture_r2_vs_bake": v for m, v in frame_r2.items()})
    disp_mask = confident & own.kept
    preds = {m: surface(d) for m, (_, d) in maps.items()}
    frame_r2 = sums["displacement"].add(preds, surface(mean_displacement), surface(own.displacement), disp_mask)
    out.update({f"{m}_displacement_r2_vs_bake": v for m, v in frame_r2.items()})
    return out
