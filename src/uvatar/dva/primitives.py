"""Articulated volumetric primitives on the W x W UV grid of the body model (DVA paper §3.3).

Primitive ``k = row * W + col`` belongs to UV texel (row, col) (row 0 is v = 1). It sits at the posed
surface point of its texel, oriented by the texel's tangent frame (columns: tangent dP/du, bitangent,
normal; frames are left-handed on mirrored UV islands, which the marcher handles because it only needs
orthonormal axes), with half-extents from the spacing of rest-pose neighbours (``|dP/du| / W`` and
``|dP/dv| / W`` in metres, times ``PrimitiveConfig.scale_factor``; the normal axis gets their mean).
Texels outside UV islands are snapped to the nearest covered texel, so every primitive lives on the body.

Correctives from the motion branch, 9 values per primitive (switched on after a warm-up):
``t = t_hat + R_hat @ (dt * max_translation)`` (a local-frame offset, metres),
``R = R_hat @ exp(drot * max_rotation)`` (axis-angle in the local frame),
``s = s_hat * exp(clamp(ds, lo, 1))`` (multiplicative; keeps scales positive), with
``lo = -log(scale_factor)`` by default: at its smallest a primitive still touches its neighbours, so
the body's surface stays covered (with the earlier ``lo = -2`` every scale corrective of a real
capture ran to its bound within tens of steps of the warm-up's end, since every loss asks for
smaller boxes there and Adam steps do not shrink with the gradient; the clamp then took the gradient
and the avatar vanished: ``docs/real.md`` §4). At that bound the volume prior holds the boxes just
touching, and the marcher's border fade leaves a strip of thin density between neighbours: seams a new
view sees through. ``min_scale_corrective = 0`` (the ``cpu`` preset) keeps every box at least its rest
size, overlapping its neighbours by ``scale_factor`` (``docs/real.md`` runs 46-51).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.errors import InputError


@dataclass
class PrimitiveConfig:
    """grid: W (K = W*W primitives). scale_factor: multiplies the rest half-spacing (1 = boxes touch,
    > 1 overlap). min_scale / max_scale: clamp on the initial half-extent, metres.
    max_translation (m) / max_rotation (rad): size of a unit corrective. min_scale_corrective: lower
    bound of the log scale corrective (None: ``-log(scale_factor)``, the size at which neighbouring
    primitives touch; 0: never below the rest size, so neighbours keep their overlap; runs saved before
    the option used -2)."""

    grid: int = 16
    scale_factor: float = 1.5
    min_scale: float = 0.004
    max_scale: float = 0.2
    max_translation: float = 0.05
    max_rotation: float = 0.5
    min_scale_corrective: float | None = None

    @property
    def scale_corrective_bounds(self) -> tuple[float, float]:
        """(lo, hi) of the log scale corrective."""
        lo = (-float(np.log(self.scale_factor)) if self.min_scale_corrective is None
              else float(self.min_scale_corrective))
        return min(lo, 0.0), 1.0


@dataclass
class UVGrid:
    """Static texel data of the primitive grid (numpy, K = W*W).

    raster: a :class:`uvatar.geometry.UVRaster` at resolution W with every texel covered (snapped).
    covered: (W, W) bool, True where the texel centre itself lies in a UV island.
    rest_scales: (K, 3) float32 initial half-extents, metres.
    """

    raster: object
    covered: np.ndarray
    rest_scales: np.ndarray

    @property
    def size(self) -> int:
        return self.raster.resolution

    @property
    def num(self) -> int:
        return self.size ** 2


def snap_raster(raster):
    """Fill uncovered texels of a UVRaster with the face/barycentrics of the nearest covered texel."""
    from scipy.ndimage import distance_transform_edt

    from uvatar.geometry import UVRaster

    if not raster.mask.any():
        raise InputError("uv layout", "no texel of the UV grid is covered by a triangle")
    _, (rows, cols) = distance_transform_edt(~raster.mask, return_indices=True)
    face = raster.face_index[rows, cols]
    bary = raster.bary[rows, cols]
    return UVRaster(raster.resolution, face, bary, np.ones_like(raster.mask))


def build_uv_grid(template, cfg: PrimitiveConfig | None = None) -> UVGrid:
    """Rasterize the template's UV layout at W and compute the rest-pose primitive scales.

    template: any object with vertices (V,3), faces (F,3), uvs (U,2), uv_faces (F,3) (a BodyTemplate).
    """
    from uvatar.geometry import face_tangents, rasterize_uv

    cfg = cfg or PrimitiveConfig()
    W = int(cfg.grid)
    raster = rasterize_uv(template.uvs, template.uv_faces, W)
    snapped = snap_raster(raster)
    du, dv = face_tangents(np.asarray(template.vertices, np.float64), template.faces, template.uvs,
                           template.uv_faces)
    face = snapped.face_index.reshape(-1)
    su = np.linalg.norm(du[face], axis=-1) / W * 0.5 * cfg.scale_factor
    sv = np.linalg.norm(dv[face], axis=-1) / W * 0.5 * cfg.scale_factor
    su = np.where(su > 0, su, sv)
    sv = np.where(sv > 0, sv, su)
    sn = 0.5 * (su + sv)
    scales = np.clip(np.stack([su, sv, sn], -1), cfg.min_scale, cfg.max_scale).astype(np.float32)
    return UVGrid(snapped, raster.mask.copy(), scales)


def articulated_frames(grid: UVGrid, template, posed_vertices: torch.Tensor):
    """Posed primitive placement from LBS: posed_vertices (B, V, 3) ->
    positions (B, K, 3) metres, rotations (B, K, 3, 3) (columns tangent, bitangent, normal)."""
    from uvatar.geometry import texel_positions, texel_tangent_frames

    B, K = posed_vertices.shape[0], grid.num
    pos = texel_positions(grid.raster, template.faces, posed_vertices).reshape(B, K, 3)
    rot = texel_tangent_frames(grid.raster, template.faces, template.uv_faces, template.uvs,
                               posed_vertices).reshape(B, K, 3, 3)
    return pos, rot


def apply_correctives(positions, rotations, rest_scales, motion, cfg: PrimitiveConfig, enabled: bool):
    """positions (B,K,3), rotations (B,K,3,3), rest_scales (K,3), motion (B,9,W,W) ->
    final positions, rotations, scales (B,K,3). With ``enabled`` False the correctives are ignored."""
    from uvatar.body.kinematics import rotvec_to_rotmat

    B, K = positions.shape[:2]
    scales = rest_scales[None].expand(B, K, 3)
    if not enabled:
        return positions, rotations, scales
    m = motion.reshape(B, 9, K).transpose(1, 2)  # (B, K, 9)
    dt = torch.tanh(m[..., 0:3]) * cfg.max_translation
    drot = rotvec_to_rotmat(torch.tanh(m[..., 3:6]) * cfg.max_rotation)
    ds = m[..., 6:9].clamp(*cfg.scale_corrective_bounds)
    positions = positions + torch.einsum("bkij,bkj->bki", rotations, dt)
    rotations = rotations @ drot
    scales = scales * torch.exp(ds)
    return positions, rotations, scales
