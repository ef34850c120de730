"""Cross-frame colour consistency for the bake's articulated refinement (:mod:`.refine`).

The surface distance cannot see a limb or the trunk turning about its own axis (a cylinder turned is
the same cylinder), nor the surface sliding along itself; the scan's texture can: a plaid shirt
moves with the body. Each refinement vertex of the posed shadow mesh looks along +/- its normal onto
the scan (the nearer compatible hit, as the texel rays of :mod:`.correspond` do) and takes the
texture colour there. Colours are averaged over a stencil in the vertex's tangent plane: the centre
and 8 points on a ring of ``radius`` metres (a blur *on the surface*: scans' texture atlases are cut
into many small charts, so blurring the texture image would mix unrelated charts). The least-squares
slope of the ring's colours, ``G = 2 / (8 radius^2) sum_j c_j delta_j``, is the derivative of the
blurred colour with respect to the vertex moving in its tangent plane; :func:`.refine.refine_fit`
chains it with the LBS Jacobian.

Each vertex's *reference* is the median over frames of its colour (:func:`reference_colours`), so a
frame whose surface slid or turned against the others pays for it. A bias shared by all frames is
invisible to this term (the fit's own keypoints and the scan distance must get it right).
The image-space twin used by ``uvatar fit`` is :mod:`uvatar.fit.photometric`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.avh.bake.register import ScanSurface, scan_colours
from uvatar.avh.bake.stencil_warp import stencil_caster, stencil_colours_warp
from uvatar.geometry import tangent_basis
from uvatar.geometry.frames import is_torch

__all__ = ["PhotoTarget", "RING_POINTS", "stencil_offsets", "surface_colours", "ray_colours", "reference_colours",
           "chromaticity"]

RING_POINTS = 8


@dataclass
class PhotoTarget:
    """What a frame's colours should be: reference (N, 3) per refinement vertex, known (N,) bool
    where the reference exists, radius the stencil radius (metres) the reference was sampled with."""

    reference: np.ndarray
    known: np.ndarray
    radius: float


_RING_ON_DEVICE: dict = {}   # str(device) -> (cos, sin) of the ring's angles as float64 tensors there


def _ring_angles(device=None):
    """(cos, sin) (RING_POINTS,) of the ring's angles: numpy, or float64 tensors on ``device`` (the
    numpy values, copied there once per device)."""
    angles = np.arange(RING_POINTS) * (2 * np.pi / RING_POINTS)
    if device is None:
        return np.cos(angles), np.sin(angles)
    key = str(device)
    if key not in _RING_ON_DEVICE:
        import torch

        _RING_ON_DEVICE[key] = (torch.as_tensor(np.cos(angles), device=device),
                                torch.as_tensor(np.sin(angles), device=device))
    return _RING_ON_DEVICE[key]


def stencil_offsets(normals, radius: float):
    """(RING_POINTS, N, 3) tangent-plane offsets on a ring of ``radius`` metres around each point:
    numpy, or a tensor on the device of a float64 tensor ``normals``."""
    t, b = tangent_basis(normals)
    cos, sin = _ring_angles(normals.device if is_torch(normals) else None)
    return radius * (cos[:, None, None] * t[None] + sin[:, None, None] * b[None])


def ray_colours(surface: ScanSurface, scan, points, normals, max_distance: float, min_normal_cos: float,
                epsilon: float = 1e-3, device: str | None = None):
    """Scan colour where the +/-normal rays from ``points`` (N, 3) first meet a compatible scan surface
    (scan normal within the angle of ``min_normal_cos``; the nearer of the two) within ``max_distance``
    metres. Returns (colours (N, 3) float64, ok (N,) bool). ``scan``: the TexturedMesh; ``device``: a
    torch device where the rays are cast (:meth:`RayCaster.first_hit_torch`), chosen and the texture
    sampled (:func:`.register.scan_colours`), the same steps; the results come back as numpy, or stay
    on the device for float64 tensor ``points`` and ``normals`` (no read-back)."""
    if is_torch(points):
        return _ray_colours_torch(surface, scan, points, normals, max_distance, min_normal_cos, epsilon)
    if device is not None:
        import torch

        colours, ok = _ray_colours_torch(surface, scan, torch.as_tensor(np.asarray(points, np.float64), device=device),
                                         torch.as_tensor(np.asarray(normals, np.float64), device=device),
                                         max_distance, min_normal_cos, epsilon)
        return colours.cpu().numpy(), ok.cpu().numpy()
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    face, bary = _nearer_compatible_hit(
        surface, p, n, max_distance, min_normal_cos, epsilon, np.where,
        lambda o, d, best: surface.caster.first_hit(o, d, max_distance=np.minimum(max_distance + epsilon, best)),
        np.full(len(p), np.inf), np.full(len(p), -1, np.int64), np.zeros((len(p), 3)))
    ok = face >= 0
    colours = np.zeros((len(p), 3))
    colours[ok] = scan_colours(surface, scan, face[ok], bary[ok])
    return colours, ok


def _nearer_compatible_hit(surface: ScanSurface, p, n, max_distance: float, min_normal_cos: float, epsilon: float,
                           where, cast, best, face, bary, cat=None):
    """(face (N,), -1 where none; bary (N, 3)) of the nearer of the +n and -n rays' first hits whose scan
    normal is within the angle of ``min_normal_cos``: numpy arrays or tensors alike (``where``: np.where
    or torch.where; ``cast(origins, directions, best)``: the caster's first hits no farther than
    ``max_distance + epsilon`` nor than ``best``; ``best``, ``face``, ``bary``: the starting values).

    With ``cat`` (torch.cat) both rays of every point are cast in one call, each as far as
    ``max_distance + epsilon`` (``cast(..., None)``): the same answer, as a -n hit only wins below the +n
    ray's compatible distance, and a first hit beyond it is refused either way. One launch of 2N rays on
    a GPU instead of two of N (latency-bound at a refinement's few thousand rays, issue 39); without it
    the -n rays look no farther than the +n ones' distance (Embree's traversal ends sooner)."""
    if cat is not None:
        both = cast(cat([p - epsilon * n, p + epsilon * n]), cat([n, -n]), None)
        m_both = surface.normals_at_hits(both)
        k = len(p)
        halves = [(both.rows(slice(0, k)), m_both[:k]), (both.rows(slice(k, None)), m_both[k:])]
    for i, sign in enumerate((1.0, -1.0)):
        if cat is not None:
            hits, m = halves[i]
        else:
            d = sign * n
            # the -n ray only wins below the +n ray's compatible distance: it need not look farther
            # (the same hits win; Embree's traversal ends sooner)
            hits = cast(p - epsilon * d, d, best)
            m = surface.normals_at_hits(hits)
        better = hits.hit & ((m * n).sum(1) >= min_normal_cos) & (hits.distance < best)
        best = where(better, hits.distance, best)
        face = where(better, hits.face, face)
        bary = where(better[:, None], hits.bary, bary)
    return face, bary


def _ray_colours_torch(surface: ScanSurface, scan, p, n, max_distance: float, min_normal_cos: float,
                       epsilon: float):
    """:func:`ray_colours` of float64 tensors p, n (N, 3) on their device: (colours (N, 3) float64,
    ok (N,) bool) tensors there. Every choice by ``torch.where`` (no read-back): both rays of every point cast in one
    :meth:`RayCaster.first_hit_torch`, the texture sampled at every ray (face 0 for the misses)
    and kept where one hit."""
    import torch

    far = torch.full((2 * len(p),), max_distance + epsilon, dtype=torch.float64, device=p.device)
    face, bary = _nearer_compatible_hit(
        surface, p, n, max_distance, min_normal_cos, epsilon, torch.where,
        lambda o, d, _: surface.caster.first_hit_torch(o, d, far),
        torch.full((len(p),), float("inf"), dtype=torch.float64, device=p.device),
        torch.full((len(p),), -1, dtype=torch.int64, device=p.device),
        torch.zeros((len(p), 3), dtype=torch.float64, device=p.device), cat=torch.cat)
    ok = face >= 0
    colours = scan_colours(surface, scan, torch.where(ok, face, torch.zeros_like(face)), bary).to(torch.float64)
    return torch.where(ok[:, None], colours, torch.zeros_like(colours)), ok


def surface_colours(surface: ScanSurface, scan, points, normals, radius: float, max_distance: float,
                    min_normal_cos: float, space: str = "rgb", device: str | None = None):
    """Blurred colour and its tangent-plane gradient at each point (module doc).

    space: "rgb", or "chromaticity" (:func:`chromaticity`: the colour divided by the sum of its
    channels, which a white light's shading does not change). Returns (colour (N, 3), gradient
    (N, 3, 3) d colour_c / d point, ok (N,) bool: every stencil ray found the scan). Float64 tensor
    ``points`` and ``normals`` give tensors on their device, computed there without a read-back."""
    if is_torch(points):
        import torch

        p, n, cat, einsum = points, normals, torch.cat, torch.einsum
    else:
        p, n, cat, einsum = np.asarray(points, np.float64), normals, np.concatenate, np.einsum
    offsets = stencil_offsets(n, radius)
    mesh = stencil_caster(surface, scan, p) if is_torch(p) else None
    if mesh is not None:     # the rays, their choice and the texture in one Warp launch (CUDA)
        colours, found = stencil_colours_warp(mesh, surface, scan, p, offsets, n, max_distance, min_normal_cos)
    else:                    # the centres and the ring in one cast: (1 + RING_POINTS, N) points
        tiled = n.repeat(RING_POINTS + 1, 1) if is_torch(n) else np.tile(np.asarray(n, np.float64), (RING_POINTS + 1, 1))
        stencil = cat([p[None], p[None] + offsets]).reshape(-1, 3)
        colours, found = ray_colours(surface, scan, stencil, tiled, max_distance, min_normal_cos, device=device)
    colours = colours.reshape(RING_POINTS + 1, len(p), 3)
    centre, ring = colours[0], colours[1:]
    ok = found.reshape(RING_POINTS + 1, len(p)).all(0)
    colour = (centre + ring.sum(0)) / (RING_POINTS + 1)
    gradient = einsum("jnc,jnd->ncd", ring, offsets) * (2.0 / (RING_POINTS * radius ** 2))
    if space == "chromaticity":
        colour, gradient = chromaticity(colour, gradient)
    elif space != "rgb":
        raise ValueError(f"space must be 'rgb' or 'chromaticity', got {space!r}")
    return colour, gradient, ok


def chromaticity(colour, gradient=None, floor: float = 1e-3):
    """Each colour divided by the sum of its channels (N, 3): a shading factor s (a white light, a
    shadow) leaves s c / sum(s c) unchanged. With ``gradient`` (N, 3, D) d colour / d x, also returns
    the chromaticity's: (d c_k - q_k sum_j d c_j) / S for S = sum_j c_j (at least ``floor``).
    numpy, or float64 tensors (on their device)."""
    if is_torch(colour):
        c, g = colour, gradient
        total = c.sum(-1, keepdim=True).clamp(min=floor)
    else:
        c, g = np.asarray(colour, np.float64), None if gradient is None else np.asarray(gradient, np.float64)
        total = np.maximum(c.sum(-1, keepdims=True), floor)
    q = c / total
    if gradient is None:
        return q
    return q, (g - q[..., None] * g.sum(-2, keepdims=True)) / total[..., None]


def reference_colours(colours, min_frames: int = 3):
    """Median over frames of per-vertex colours. colours: (T, N, 3) with NaN where a frame did not see
    the vertex. Returns (reference (N, 3), known (N,) bool: seen in at least ``min_frames`` frames)."""
    c = np.asarray(colours, np.float64)
    seen = np.isfinite(c).all(-1)
    known = seen.sum(0) >= max(1, int(min_frames))
    reference = np.zeros(c.shape[1:])
    if known.any():
        reference[known] = np.nanmedian(c[:, known], axis=0)
    return reference, known
