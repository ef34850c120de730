"""Driving views unwrapped into UV on the tensors' device: the torch + Warp twin of
:func:`uvatar.dva.features.unwrap_views` / :func:`uvatar.dva.drive.driving_texture`.

The same rule (a texel takes its posed surface point's pixel colour where it faces the camera, lies
in the image and the foreground mask and is not occluded, the occlusion ray stopping ``eps`` short of
the point), in float32 torch: projection through :func:`uvatar.fit.projection.project_cameras` (lens
distortion included), bilinear lookups through :func:`~uvatar.fit.projection.sample_views` (pixel
centres at integers, clamped at the border as the reference's), occlusion through Warp's mesh BVH
(:class:`uvatar.geometry.raycast_warp.MeshOccluder`). On a GPU a frame's driving texture is then made
without the host; the reference (numpy, float64, Embree) stays the CPU default. Texels whose test
sits on a threshold (a grazing normal, a mask edge) may differ from the reference's float64 answer.

:class:`DeviceUnwrap` keeps what does not change from frame to frame on the device (the raster's
coverage, the driving cameras' matrices and centres, the body's faces and its BVH, refitted per frame):
a frame then copies nothing from the host and reads nothing back (what a CUDA graph needs).
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.dva.features import average_views


class DeviceUnwrap:
    """Unwrap driving views of a fixed camera rig onto ``raster`` for a mesh of ``template``'s topology,
    frame after frame, on ``device``: ``__call__(posed_vertices (V, 3), images, masks=None) -> textures
    (N, R, R, 3), visibility (N, R, R)`` as :func:`unwrap_views_device`."""

    def __init__(self, raster, template, cameras, device, eps: float = 0.01):
        from uvatar.devices import on_device
        from uvatar.fit.projection import camera_tensors
        from uvatar.geometry.raycast_warp import MeshOccluder

        dev = torch.device(device)
        self.raster, self.template, self.cameras, self.eps = raster, template, list(cameras), eps
        self.covered = on_device(raster.mask, dev).reshape(-1)
        self.cams = camera_tensors(self.cameras, dev, torch.float32)
        self.centres = torch.as_tensor(np.stack([c.center for c in self.cameras]), dtype=torch.float32, device=dev)
        self.occluder = MeshOccluder(template.faces, dev)

    def __call__(self, posed_vertices: torch.Tensor, images, masks=None):
        from uvatar.fit.projection import project_cameras, sample_views
        from uvatar.geometry import texel_normals, texel_positions

        dev, f32 = posed_vertices.device, torch.float32
        verts = posed_vertices.to(f32)
        raster, faces = self.raster, self.template.faces
        R = raster.resolution
        pts = texel_positions(raster, faces, verts).reshape(-1, 3)
        nrm = texel_normals(raster, faces, verts).reshape(-1, 3)
        pix, depth = project_cameras(pts, self.cams)  # (C, M, 2), (C, M)
        to_cam = self.centres[:, None] - pts[None]
        dist = to_cam.norm(dim=-1)
        texs, vis = [], []
        for k in range(len(self.cameras)):
            img = torch.as_tensor(images[k], dtype=f32, device=dev)
            H, W = img.shape[:2]
            x, y = pix[k, :, 0], pix[k, :, 1]
            seen = self.covered & ((nrm * to_cam[k]).sum(-1) > 0) & (depth[k] > 0)
            seen &= (x >= -0.5) & (x <= W - 0.5) & (y >= -0.5) & (y <= H - 0.5)
            if masks is not None:
                mask = torch.as_tensor(masks[k], device=dev).to(f32)
                seen &= sample_views(mask[None, None], pix[k][None, None], (W, H))[0, 0, :, 0] > 0.5
            direction = -to_cam[k] / dist[k].clamp_min(1e-12)[:, None]
            seen &= ~self.occluder(verts, self.centres[k].expand_as(direction), direction, dist[k] - self.eps)
            colour = sample_views(img.permute(2, 0, 1)[None], pix[k][None, None], (W, H))[0, 0]  # (M, 3)
            texs.append(colour * seen[:, None])
            vis.append(seen)
        return torch.stack(texs).reshape(-1, R, R, 3), torch.stack(vis).reshape(-1, R, R)

    def texture(self, posed_vertices: torch.Tensor, images, masks=None) -> torch.Tensor:
        """(4, R, R): the views averaged (:func:`~uvatar.dva.features.average_views`)."""
        tex, vis = self(posed_vertices, images, masks)
        return average_views(tex[None], vis[None])[0]


def unwrap_views_device(raster, template, posed_vertices: torch.Tensor, cameras, images, masks=None,
                        eps: float = 0.01):
    """posed_vertices (V, 3) torch; cameras: sequence of Camera; images: sequence of (H, W, 3) torch
    float in [0, 1] (or numpy), masks: None or sequence of (H, W) -> textures (N, R, R, 3) float32 and
    visibility (N, R, R) bool, on ``posed_vertices``' device. One call of a new :class:`DeviceUnwrap`
    (which a frame loop keeps instead)."""
    return DeviceUnwrap(raster, template, cameras, posed_vertices.device, eps)(posed_vertices, images, masks)


def driving_texture_device(model, posed_vertices: torch.Tensor, cameras, images, masks=None) -> torch.Tensor:
    """(4, R, R) texel-aligned image input of ``model`` from driving views, on the device
    (:func:`uvatar.dva.drive.driving_texture` is the reference)."""
    tex, vis = unwrap_views_device(model.image_raster, model.template, posed_vertices, cameras, images, masks)
    return average_views(tex[None], vis[None])[0]
