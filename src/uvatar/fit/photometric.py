"""Photometric consistency of the body surface across frames: what pins a limb's twist.

Keypoints fix where joints are, the scan distance where the surface is; neither sees a limb or the
trunk turning about its own axis (a cylinder turned is the same cylinder). The texture does: a
plaid shirt or a logo moves with the body. Each frame is seen by C views (renders of its textured
scan, or the capture's calibrated images) with a depth map. A body vertex is *visible* in a view
when it faces the camera and its depth lies within ``clothing`` metres of the view's depth there
(behind the visible cloth, in front of anything occluding it); it then takes the view's colour at
its projection (bilinear, differentiable in the vertex position). :meth:`PhotoTerm.refresh` sets
each vertex's reference colour to the median over frames of its colour (a frame's colour: the mean
over the views that see it); the term is the robust colour distance of every visible sample to its
vertex's reference, so a frame whose surface slid or turned against the others pays for it.
Images are blurred by ``blur_px`` so the basin reaches a few pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.capture.types import Camera
from uvatar.fit.losses import _normalized, gmof
from uvatar.fit.projection import camera_tensors, project_cameras, sample_views

__all__ = ["PhotoViews", "PhotoTerm"]


@dataclass
class PhotoViews:
    """One frame's views: images (C, H, W, 3) float32 in [0, 1], depth (C, H, W) camera-z metres
    (0 where nothing was seen), cameras (C) with those image sizes."""

    images: np.ndarray
    depth: np.ndarray
    cameras: list[Camera]


def _blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B, 3, H, W) -> Gaussian blur of std ``sigma`` pixels (separable, reflect padding)."""
    if sigma <= 0:
        return images
    r = max(1, int(np.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=images.dtype, device=images.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = (k / k.sum()).reshape(1, 1, 1, -1).expand(images.shape[1], 1, 1, -1)
    pad = torch.nn.functional.pad
    out = torch.nn.functional.conv2d(pad(images, (r, r, 0, 0), mode="reflect"), k, groups=images.shape[1])
    return torch.nn.functional.conv2d(pad(out, (0, 0, r, r), mode="reflect"), k.transpose(-1, -2),
                                      groups=images.shape[1])


class PhotoTerm:
    """views: per frame a :class:`PhotoViews` or None (all with the same C, H, W); body_vertices:
    indices (into the posed vertices the term is called with) of the body side. Call
    :meth:`refresh` before the first use and whenever the reference should follow the fit."""

    def __init__(self, views, body_vertices: np.ndarray, device, clothing: float = 0.03, blur_px: float = 1.0,
                 min_frames: int = 2, dtype=torch.float32):
        self.frames = [t for t, v in enumerate(views) if v is not None]
        if not self.frames:
            raise ValueError("PhotoTerm needs at least one frame with views")
        first = views[self.frames[0]]
        C, H, W = first.images.shape[:3]
        for t in self.frames:
            if views[t].images.shape[:3] != (C, H, W) or views[t].depth.shape != (C, H, W):
                raise ValueError(f"frame {t}: views must all be {C} x {H} x {W}")
        self.size = (W, H)
        self.clothing, self.min_frames = clothing, min_frames
        self.device, self.dtype = device, dtype

        self.cams = camera_tensors([views[t].cameras for t in self.frames], device=device, dtype=dtype)  # (F, C)
        imgs = torch.as_tensor(np.stack([views[t].images for t in self.frames]), device=device, dtype=dtype)
        self.images = _blur(imgs.reshape(-1, H, W, 3).permute(0, 3, 1, 2), blur_px)   # (F*C, 3, H, W)
        self.depth = torch.as_tensor(np.stack([views[t].depth for t in self.frames]), device=device,
                                     dtype=dtype).reshape(-1, 1, H, W)
        self.centres = -torch.einsum("fcji,fcj->fci", self.cams.R, self.cams.T)        # camera centres (F, C, 3)
        self.frame_index = torch.as_tensor(self.frames, device=device, dtype=torch.int64)
        self.body_vertices = torch.as_tensor(np.asarray(body_vertices, np.int64), device=device)
        self.reference = self.visible = None

    def refresh(self, vertices: torch.Tensor, normals: torch.Tensor) -> None:
        """Visibility of each (frame, view, vertex) and each vertex's reference colour for the current
        posed body (vertices, normals (T, V', 3)); no gradient."""
        with torch.no_grad():
            v = vertices[self.frame_index][:, self.body_vertices].to(self.dtype)
            n = normals[self.frame_index][:, self.body_vertices].to(self.dtype)
            px, z = project_cameras(v, self.cams)
            W, H = self.size
            inside = (px[..., 0] >= 0) & (px[..., 0] <= W - 1) & (px[..., 1] >= 0) & (px[..., 1] <= H - 1)
            d = sample_views(self.depth, px, self.size, mode="nearest")[..., 0]
            to_cam = self.centres[:, :, None, :] - v[:, None]
            facing = (n[:, None] * to_cam).sum(-1) > 0.3 * to_cam.norm(dim=-1)
            vis = inside & facing & (d > 0) & ((z - d).abs() < self.clothing)
            colour = sample_views(self.images, px, self.size)                      # (F, C, N, 3)
            w = vis.to(self.dtype)[..., None]
            per_frame = (colour * w).sum(1) / w.sum(1).clamp_min(1e-9)              # (F, N, 3)
            seen = vis.any(1)                                                       # (F, N)
            ref = torch.where(seen[..., None], per_frame, torch.nan).nanmedian(0).values
            ok = seen.sum(0) >= self.min_frames
            self.reference = torch.nan_to_num(ref)
            self.visible = (vis & ok[None, None]).to(self.dtype)

    def __call__(self, vertices: torch.Tensor, sigma: float) -> torch.Tensor:
        """(T,) mean robust colour distance of the visible samples to their references (0 for frames
        without views)."""
        if self.reference is None:
            raise RuntimeError("PhotoTerm.refresh must run before the term is evaluated")
        v = vertices[self.frame_index][:, self.body_vertices]
        px, _ = project_cameras(v, self.cams)
        colour = sample_views(self.images, px, self.size)
        r = torch.linalg.norm(colour - self.reference[None, None], dim=-1)
        per = _normalized(gmof(r, sigma), self.visible)
        return vertices.new_zeros(vertices.shape[0]).index_add(0, self.frame_index, per)
