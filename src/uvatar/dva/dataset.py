"""In-memory training/driving data for DVA: posed bodies, photos, masks and per-view UV unwraps.

``FrameBank(source, body, model_raster, frames, cameras)`` loads every (frame, camera) once: the posed
LBS vertices, joint rotations, uint8 images and masks, and the image unwrapped into UV at the model's
image-feature resolution (with visibility). Frames whose fit, image or mask cannot be read are skipped
with a warning (``bank.skipped`` says why, ``bank.causes`` counts them by cause); with no frame left
the error counts the causes ("100 frames: 100 missing masks"). Images whose size differs from their
camera's intrinsics are warned about once per camera. Views whose subject mask ``uvatar capture masks``
wrote empty for want of the subject (another person over it, or its identity held:
:func:`uvatar.fit.mask_views.unusable_views`, the source's ``unusable``) are marked in ``bank.usable`` (F, C):
training never takes them as targets and eval does not score them; a frame with none usable is skipped.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from uvatar.dva.corrections import FitParams
from uvatar.dva.features import average_views, unwrap_views
from uvatar.errors import InputError

log = logging.getLogger(__name__)


def fit_params(body, fits, device="cpu") -> FitParams:
    """fits list[BodyFit] -> :class:`~uvatar.dva.corrections.FitParams` (the body model's local
    rotations, Rh, Th, scale and the shape when every fit has one of the same size)."""
    rot = np.stack([np.asarray(body.joint_rotvecs_from_fit(f), np.float32) for f in fits])
    Rh = np.stack([np.asarray(f.Rh, np.float32).reshape(3) for f in fits])
    Th = np.stack([np.asarray(f.Th, np.float32).reshape(3) for f in fits])
    scale = np.array([float(getattr(f, "scale", 1.0)) for f in fits], np.float32)
    shapes = [np.asarray(f.shapes, np.float32).reshape(-1) for f in fits]
    shape = np.stack(shapes) if all(s.size for s in shapes) and len({s.size for s in shapes}) == 1 else None

    def t(a):
        return None if a is None else torch.as_tensor(a, device=device)

    return FitParams(t(rot), t(Rh), t(Th), t(scale), t(shape))


def pose_vertices(body, rotvecs, Rh, Th, scale, shape) -> torch.Tensor:
    """(B, V, 3) float32 posed vertices of the body model (differentiable in every input)."""
    kwargs = {} if shape is None else {"shape": shape}
    return body.pose(rotvecs, Rh=Rh, Th=Th, scale=scale, **kwargs).vertices.float()


def pose_corrected(body, corrections, fits: FitParams, frames: torch.Tensor, shape=None):
    """(posed vertices (B, V, 3) float32, joint rotvecs (B, J, 3) radians) of bank frames ``frames``
    (B,) int64 re-posed with the learned pose offsets of ``corrections``
    (:class:`~uvatar.dva.corrections.TrainingCorrections`), differentiable in the offsets.

    Everything on the body model's device, so nothing is read back: ``fits`` (its ``rotvecs``, ``Rh``,
    ``Th`` (metres), ``scale``; its ``shape`` is not used), ``frames`` and the offsets. ``shape``: (B, S)
    the frames' shape parameters or None, best on the host (a body's bind-state cache looks at it there).
    """
    rot, Rh, Th = corrections.pose_inputs(fits, frames, True)
    return pose_vertices(body, rot, Rh, Th, fits.scale[frames], shape), rot


def body_inputs(body, fits, device="cpu"):
    """fits list[BodyFit] -> joint_rotvecs (B, J, 3), posed vertices (B, V, 3) (torch, no grad)."""
    p = fit_params(body, fits, device)
    with torch.no_grad():
        return p.rotvecs, pose_vertices(body, p.rotvecs, p.Rh, p.Th, p.scale, p.shape)


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) inclusive pixel rows and columns of a (H, W) bool mask's bounding box,
    None where the mask is empty (one pass over its rows and one over its columns)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not rows.size:
        return None
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


def estimate_background(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) median colour of the pixels outside the mask (0 when the mask covers everything)."""
    out = image[mask < 0.5]
    return np.median(out, 0).astype(np.float32) if out.size else np.zeros(3, np.float32)


class FrameBank:
    """All training (or driving) data in memory; see the module docstring."""

    def __init__(self, source, body, image_raster, template, frames, cameras, progress=True):
        from tqdm import tqdm

        self.cameras = list(cameras)
        self.cams = [source.cameras[c] for c in self.cameras]
        self.frames, self.skipped = [], {}
        rot, verts, images, masks, texs, vis, fits, usable = [], [], [], [], [], [], [], []
        unusable = getattr(source, "unusable", frozenset())
        causes: dict[str, int] = {}
        size_warned: set[str] = set()
        for frame in tqdm(list(frames), desc="loading frames", disable=not progress, unit="frame"):
            stage = "fits"
            try:
                row = [(c, frame) not in unusable for c in self.cameras]
                if not any(row):
                    stage = "views without the subject alone"
                    raise InputError(f"masks of frame {frame}", "no view shows the subject alone (another person "
                                                                "over it in every camera: masks/views.json)")
                fit = source.fit(frame)
                stage = "fits for another body model"
                try:
                    r, v = body_inputs(body, [fit])
                except (ValueError, RuntimeError, IndexError) as exc:
                    raise InputError(f"fit {frame}", f"does not fit the body model ({exc})") from None
                stage = "images"
                imgs = [source.image(c, frame) for c in self.cameras]
                stage = "masks"
                msks = [np.asarray(source.mask(c, frame), np.float32) for c in self.cameras]
                stage = "image/mask size mismatch"
                for c, im, m in zip(self.cams, imgs, msks, strict=False):
                    if im.shape[:2] != m.shape[:2]:
                        raise InputError(f"{c.name}/{frame}", f"image {im.shape[:2]} and mask {m.shape[:2]} differ")
                    if c.width and c.height and im.shape[:2] != (c.height, c.width) and c.name not in size_warned:
                        size_warned.add(c.name)
                        log.warning("camera %s: images are %dx%d but its intrinsics say %dx%d (rays and "
                                    "projections will not match the pixels)", c.name, im.shape[1], im.shape[0],
                                    c.width, c.height)
            except InputError as exc:
                cause = f"missing {stage}" if stage in ("fits", "images", "masks") and "missing" in str(exc) \
                    else stage if stage not in ("fits", "images", "masks") else f"unreadable {stage}"
                causes[cause] = causes.get(cause, 0) + 1
                log.warning("skipping frame %s: %s", frame, exc)
                self.skipped[frame] = str(exc)
                continue
            t, s = unwrap_views(image_raster, template, v[0].cpu().numpy(), self.cams, imgs, msks)
            self.frames.append(frame)
            fits.append(fit)
            rot.append(r[0])
            verts.append(v[0])
            images.append([(np.clip(i, 0, 1) * 255 + 0.5).astype(np.uint8) for i in imgs])
            masks.append([(m > 0.5) for m in msks])
            usable.append(row)
            texs.append(torch.as_tensor(t, dtype=torch.float16))
            vis.append(torch.as_tensor(s))
        self.causes = causes
        if not self.frames:
            counted = ", ".join(f"{n} {c}" for c, n in sorted(causes.items(), key=lambda kv: -kv[1]))
            n = len(list(frames))
            raise InputError(getattr(source, "root", "source"),
                             f"no usable frame ({n} frame{'s' if n != 1 else ''}: {counted})")
        self.rotvecs = torch.stack(rot)
        self.fits = fit_params(body, fits)  # what a pose correction starts from
        self.vertices = torch.stack(verts)
        self.images, self.masks = images, masks
        self.mask_boxes = [[mask_box(m) for m in row] for row in masks]  # (F, C) each mask's bounding box
        self.usable = np.array(usable, bool)  # (F, C): False where the subject's mask is empty for want of it
        self.textures = torch.stack(texs)  # (F, C, R, R, 3)
        self.visibility = torch.stack(vis)  # (F, C, R, R)
        self.backgrounds = np.stack([estimate_background(images[0][c].astype(np.float32) / 255.0,
                                                         masks[0][c]) for c in range(len(self.cameras))])

    def __len__(self):
        return len(self.frames)

    def image_texture(self, fi: int, views) -> torch.Tensor:
        """(4, R, R) mean unwrapped colour + coverage from the given camera indices of frame ``fi``."""
        v = list(views)
        return average_views(self.textures[fi, v].float()[None], self.visibility[fi, v][None])[0]
