"""Texel-aligned features (DVA paper §3.4): pose, image and view signals laid out on the W x W UV grid.

* Pose ``F_theta``: each conditioning joint's local axis-angle (3 values) times that joint's skinning
  weight at the texel -> (3 * Jc, W, W), then a 1x1 conv (:class:`PoseEncoder`).
* Image ``F_I``: every driving view is unwrapped into UV at ``R_img = W * image_scale`` texels: a texel
  takes the colour of its posed surface point's pixel when it faces the camera, lies inside the image
  and the foreground mask, and is not occluded (Embree ray from the camera centre, via
  :class:`uvatar.geometry.RayCaster`). Views are averaged where visible; channel 3 is the fraction of
  views that saw the texel. A strided conv encoder takes (4, R_img, R_img) to (C, W, W)
  (:class:`ImageEncoder`). With ``colour_skip`` the same texture is also looked up at every voxel
  column (:func:`texture_at_voxels`) and added to the appearance logits (:class:`uvatar.dva.decoders.DvaDecoder`).
* View ``F_v``: the unit direction from the texel's surface point to the camera dotted with its
  triangle's normal -> (1, W, W) (:func:`view_feature_map`).

UV images follow the package convention: row 0 is v = 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class FeatureConfig:
    """pose_channels: output of the 1x1 pose conv. image_scale: unwrap resolution / W (power of 2).
    image_channels: output of the image encoder. occlusion_eps: slack of the depth test, metres.
    image_centred: the image encoder sees the texture centred on zero (2 x - 1) and its last layer is
    linear. Without it (runs saved before the option) its last layer was a leaky ReLU, and on the real
    recording its output decayed to |f| = 0.008: the avatar rendered the same whatever the driving
    views showed (``docs/real.md``, runs 11-14).
    colour_skip: the driving views' unwrapped colour, looked up at every voxel column of every
    primitive (:func:`voxel_uv_grid`, :func:`texture_at_voxels`), is added to the appearance decoder's
    logits where a driving view saw it, with a learned gain: the encoder's W x W features cannot carry
    detail finer than a primitive, this path carries it at the texture's resolution (runs saved before
    the option have none)."""

    pose_channels: int = 16
    image_scale: int = 4
    image_channels: int = 16
    occlusion_eps: float = 0.01
    image_centred: bool = True
    colour_skip: bool = False


# ----------------------------------------------------------------------------------------------- pose
def texel_skin_weights(raster, template, joints) -> np.ndarray:
    """(Jc, W, W) float32 skinning weights of the conditioning joints at each texel of ``raster``."""
    from uvatar.geometry import sample_vertex_attribute

    w = np.asarray(template.skin_weights, np.float32)[:, list(joints)]
    return np.ascontiguousarray(sample_vertex_attribute(raster, template.faces, w).transpose(2, 0, 1))


def pose_feature_maps(joint_rotvecs: torch.Tensor, texel_weights: torch.Tensor, joints) -> torch.Tensor:
    """joint_rotvecs (B, J, 3) local axis-angles; texel_weights (Jc, W, W); joints: the Jc conditioning
    joints (a sequence, or a long tensor on the device: no host-to-device copy) -> (B, 3*Jc, W, W)."""
    rv = joint_rotvecs[:, joints if isinstance(joints, torch.Tensor) else list(joints)]  # (B, Jc, 3)
    maps = rv[..., None, None] * texel_weights[None, :, None]  # (B, Jc, 3, W, W)
    return maps.flatten(1, 2)


class PoseEncoder(nn.Module):
    """1x1 conv reducing the masked pose maps (3*Jc channels) to ``out`` channels."""

    def __init__(self, num_joints: int, out: int):
        super().__init__()
        self.proj = nn.Conv2d(3 * num_joints, out, 1)

    def forward(self, maps):
        return nn.functional.leaky_relu(self.proj(maps), 0.2)


# ---------------------------------------------------------------------------------------------- image
def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """image (H, W, C) sampled at pixel coordinates xy (M, 2) (pixel centres at integers)."""
    H, W = image.shape[:2]
    x = np.clip(xy[:, 0], 0, W - 1)
    y = np.clip(xy[:, 1], 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2 if H > 1 else 0)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x1])
            + fy * ((1 - fx) * image[y1, x0] + fx * image[y1, x1]))


def unwrap_view(points, normals, camera, image, mask=None, caster=None, eps: float = 0.01):
    """Project one view onto surface points. points/normals (M, 3) world; image (H, W, 3) in [0, 1];
    mask (H, W) optional foreground. Returns colours (M, 3) float32 and visible (M,) bool."""
    points = np.asarray(points, np.float64)
    center = camera.center
    to_cam = center[None] - points
    dist = np.linalg.norm(to_cam, axis=-1)
    facing = (np.asarray(normals) * to_cam).sum(-1) > 0
    z = camera.world_to_camera(points)[:, 2]
    pix = camera.project(points)  # lens distortion included
    H, W = image.shape[:2]
    inside = (z > 0) & (pix[:, 0] >= -0.5) & (pix[:, 0] <= W - 0.5) & (pix[:, 1] >= -0.5) & (pix[:, 1] <= H - 0.5)
    visible = facing & inside
    if mask is not None:
        visible &= _bilinear(np.asarray(mask, np.float32)[..., None], pix)[:, 0] > 0.5
    if caster is not None and visible.any():
        idx = np.flatnonzero(visible)
        dirs = -to_cam[idx] / dist[idx, None]
        occluded = caster.any_hit(np.repeat(center[None], idx.size, 0), dirs,
                                  max_distance=dist[idx] - eps)
        visible[idx[occluded]] = False
    colors = np.zeros((points.shape[0], 3), np.float32)
    if visible.any():
        colors[visible] = _bilinear(np.asarray(image, np.float32), pix[visible])
    return colors, visible


def unwrap_views(raster, template, posed_vertices: np.ndarray, cameras, images, masks=None, eps=0.01):
    """Unwrap each view into UV. posed_vertices (V, 3) numpy; cameras/images/masks: sequences.

    Returns textures (N_views, R, R, 3) float32 and visibility (N_views, R, R) bool at the raster's
    resolution (uncovered texels are never visible)."""
    from uvatar.geometry import RayCaster, texel_normals, texel_positions

    R = raster.resolution
    pts = texel_positions(raster, template.faces, posed_vertices).reshape(-1, 3)
    nrm = texel_normals(raster, template.faces, posed_vertices).reshape(-1, 3)
    covered = raster.mask.reshape(-1)
    caster = RayCaster(np.asarray(posed_vertices, np.float32), template.faces)
    texs = np.zeros((len(images), R * R, 3), np.float32)
    vis = np.zeros((len(images), R * R), bool)
    for i, (cam, img) in enumerate(zip(cameras, images, strict=False)):
        m = None if masks is None else masks[i]
        c, v = unwrap_view(pts[covered], nrm[covered], cam, img, m, caster, eps)
        texs[i, covered] = c
        vis[i, covered] = v
    return texs.reshape(-1, R, R, 3), vis.reshape(-1, R, R)


def average_views(textures: torch.Tensor, visibility: torch.Tensor) -> torch.Tensor:
    """textures (B, N, R, R, 3), visibility (B, N, R, R) -> (B, 4, R, R): mean visible colour and the
    fraction of the N views that saw each texel."""
    vis = visibility.to(textures.dtype)
    count = vis.sum(1)
    mean = (textures * vis[..., None]).sum(1) / count.clamp(min=1)[..., None]
    frac = count / max(1, visibility.shape[1])
    return torch.cat([mean.permute(0, 3, 1, 2), frac[:, None]], 1)


class ImageEncoder(nn.Module):
    """(B, 4, W*scale, W*scale) unwrapped texture -> (B, out, W, W) with log2(scale) stride-2 convs.
    ``centred``: input 2 x - 1 and a linear last layer (:class:`FeatureConfig` ``image_centred``)."""

    def __init__(self, scale: int, out: int, hidden: int = 16, centred: bool = True):
        super().__init__()
        self.centred = bool(centred)
        n = int(round(math.log2(scale)))
        layers, c = [nn.Conv2d(4, hidden, 3, padding=1), nn.LeakyReLU(0.2)], hidden
        for _ in range(n):
            layers += [nn.Conv2d(c, hidden, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        layers += [nn.Conv2d(hidden, out, 3, padding=1), nn.LeakyReLU(0.2)]
        self.net = nn.Sequential(*layers)

    def forward(self, tex):
        if self.centred:
            return self.net[:-1](2.0 * tex - 1.0)
        return self.net(tex)


def voxel_uv_grid(raster, template, voxels: int, scale_factor: float) -> np.ndarray:
    """(W*S, W*S, 2) float32 UV of every voxel column in the payload slab layout of
    :mod:`uvatar.dva.decoders` (row ``wy * S + y``, column ``wx * S + x``: voxel (y, x) of primitive
    ``wy * W + wx``): the primitive's texel UV plus the voxel's offset along its local axes (x along
    +u, y along +v; a box of half-extent ``scale_factor / (2 W)`` in UV, as
    :func:`uvatar.dva.primitives.build_uv_grid` sizes it in metres)."""
    from uvatar.geometry import sample_vertex_attribute

    W, S = raster.resolution, int(voxels)
    centre = sample_vertex_attribute(raster, template.uv_faces, np.asarray(template.uvs, np.float64))  # (W, W, 2)
    local = (2.0 * np.arange(S) + 1.0) / S - 1.0  # voxel centres in [-1, 1]
    half = 0.5 * scale_factor / W
    u = centre[:, None, :, None, 0] + half * local[None, None, None, :]  # (wy, 1, wx, x)
    v = centre[:, None, :, None, 1] + half * local[None, :, None, None]  # (wy, y, 1, 1)
    u, v = np.broadcast_to(u, (W, S, W, S)), np.broadcast_to(v, (W, S, W, S))
    return np.stack([u, v], -1).reshape(W * S, W * S, 2).astype(np.float32)


def uv_sample_grid(uv: torch.Tensor) -> torch.Tensor:
    """UV (..., 2) in [0, 1] -> ``F.grid_sample`` coordinates (..., 2) in [-1, 1] for a texture whose
    row 0 is v = 1."""
    return torch.stack([2.0 * uv[..., 0] - 1.0, 1.0 - 2.0 * uv[..., 1]], -1)


def texture_at_voxels(image_texture: torch.Tensor, uv: torch.Tensor):
    """image_texture (B, 4, R, R) (:func:`average_views`: colour + fraction of views that saw the texel;
    row 0 is v = 1), uv (H, W, 2) -> colour (B, 3, H, W) and weight (B, 1, H, W) in [0, 1]: the
    bilinear colour of the seen texels alone (unseen ones are black in the texture and must not darken
    their neighbours) and how much of the lookup fell on seen texels."""
    seen = (image_texture[:, 3:4] > 0).to(image_texture.dtype)
    both = torch.cat([image_texture[:, :3] * seen, seen], 1)
    grid = uv_sample_grid(uv)
    grid = grid[None].expand(image_texture.shape[0], *grid.shape).to(image_texture.dtype)
    out = F.grid_sample(both, grid, mode="bilinear", padding_mode="border", align_corners=False)
    weight = out[:, 3:4]
    return out[:, :3] / weight.clamp(min=1e-6), weight


# ----------------------------------------------------------------------------------------------- view
def _texel_faces(raster, device) -> torch.Tensor:
    """(R*R,) long: the face of every texel of ``raster`` (0 where uncovered), on ``device``; made once per
    raster (no host-to-device copy per frame)."""
    from uvatar.devices import on_device

    host = raster.__dict__.get("_texel_faces")
    if host is None:
        host = raster.__dict__.setdefault("_texel_faces", np.clip(raster.face_index.reshape(-1), 0, None))
    return on_device(host, device, torch.long)


def view_feature_map(raster, template, posed_vertices: torch.Tensor, camera_centers: torch.Tensor):
    """posed_vertices (B, V, 3), camera_centers (B, 3) -> (B, 1, W, W): texel-to-camera direction
    dotted with the texel's triangle normal (1 faces the camera, -1 faces away)."""
    from uvatar.geometry import face_normals, texel_positions

    R = raster.resolution
    B = posed_vertices.shape[0]
    fn = face_normals(posed_vertices, template.faces)  # (B, F, 3)
    face = _texel_faces(raster, posed_vertices.device)
    n = fn[:, face]  # (B, K, 3)
    p = texel_positions(raster, template.faces, posed_vertices).reshape(B, R * R, 3)
    d = camera_centers[:, None, :] - p
    d = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    return (d * n).sum(-1).reshape(B, 1, R, R)
