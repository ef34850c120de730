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
from uvatar.geometry import tangent_basis

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


def stencil_offsets(normals, radius: float) -> np.ndarray:
    """(RING_POINTS, N, 3) tangent-plane offsets on a ring of ``radius`` metres around each point."""
    t, b = tangent_basis(normals)
    angles = np.arange(RING_POINTS) * (2 * np.pi / RING_POINTS)
    return radius * (np.cos(angles)[:, None, None] * t[None] + np.sin(angles)[:, None, None] * b[None])


def ray_colours(surface: ScanSurface, scan, points, normals, max_distance: float, min_normal_cos: float,
                epsilon: float = 1e-3, device: str | None = None):
    """Scan colour where the +/-normal rays from ``points`` (N, 3) first meet a compatible scan surface
    (scan normal within the angle of ``min_normal_cos``; the nearer of the two) within ``max_distance``
    metres. Returns (colours (N, 3) float64, ok (N,) bool). ``scan``: the TexturedMesh; ``device``: a
    torch device where the rays are cast (:meth:`RayCaster.first_hit_torch`), chosen and the texture
    sampled (:func:`.register.scan_colours`), the same steps; the results come back as numpy."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    if device is None:
        where, limit = np.where, (lambda best: np.minimum(max_distance + epsilon, best))

        def cast(o, d, far):
            return surface.caster.first_hit(o, d, max_distance=far)

        best = np.full(len(p), np.inf)
        face = np.full(len(p), -1, np.int64)
        bary = np.zeros((len(p), 3))
    else:
        import torch

        where, limit = torch.where, (lambda best: best.clamp(max=max_distance + epsilon))

        def cast(o, d, far):
            return surface.caster.first_hit_torch(o, d, far)

        p, n = torch.as_tensor(p, device=device), torch.as_tensor(n, device=device)
        best = torch.full((len(p),), float("inf"), dtype=torch.float64, device=device)
        face = torch.full((len(p),), -1, dtype=torch.int64, device=device)
        bary = torch.zeros((len(p), 3), dtype=torch.float64, device=device)
    for sign in (1.0, -1.0):
        d = sign * n
        # the -n ray only wins below the +n ray's compatible distance: it need not look farther
        # (the same hits win; Embree's traversal ends sooner)
        hits = cast(p - epsilon * d, d, limit(best))
        m = surface.normals_at_hits(hits)
        better = hits.hit & ((m * n).sum(1) >= min_normal_cos) & (hits.distance < best)
        best = where(better, hits.distance, best)
        face = where(better, hits.face, face)
        bary = where(better[:, None], hits.bary, bary)
    ok = face >= 0
    if device is None:
        colours = np.zeros((len(p), 3))
        colours[ok] = scan_colours(surface, scan, face[ok], bary[ok])
        return colours, ok
    colours = torch.zeros((len(p), 3), dtype=torch.float64, device=device)
    colours[ok] = scan_colours(surface, scan, face[ok], bary[ok]).to(torch.float64)
    return colours.cpu().numpy(), ok.cpu().numpy()


def surface_colours(surface: ScanSurface, scan, points, normals, radius: float, max_distance: float,
                    min_normal_cos: float, space: str = "rgb", device: str | None = None):
    """Blurred colour and its tangent-plane gradient at each point (module doc).

    space: "rgb", or "chromaticity" (:func:`chromaticity`: the colour divided by the sum of its
    channels, which a white light's shading does not change). Returns (colour (N, 3), gradient
    (N, 3, 3) d colour_c / d point, ok (N,) bool: every stencil ray found the scan)."""
    p = np.asarray(points, np.float64)
    offsets = stencil_offsets(normals, radius)
    # the centres and the ring in one cast: (1 + RING_POINTS, N) points
    stencil = np.concatenate([p[None], p[None] + offsets]).reshape(-1, 3)
    colours, found = ray_colours(surface, scan, stencil, np.tile(np.asarray(normals, np.float64), (RING_POINTS + 1, 1)),
                                 max_distance, min_normal_cos, device=device)
    colours = colours.reshape(RING_POINTS + 1, len(p), 3)
    centre, ring = colours[0], colours[1:]
    ok = found.reshape(RING_POINTS + 1, len(p)).all(0)
    colour = (centre + ring.sum(0)) / (RING_POINTS + 1)
    gradient = np.einsum("jnc,jnd->ncd", ring, offsets) * (2.0 / (RING_POINTS * radius ** 2))
    if space == "chromaticity":
        colour, gradient = chromaticity(colour, gradient)
    elif space != "rgb":
        raise ValueError(f"space must be 'rgb' or 'chromaticity', got {space!r}")
    return colour, gradient, ok


def chromaticity(colour, gradient=None, floor: float = 1e-3):
    """Each colour divided by the sum of its channels (N, 3): a shading factor s (a white light, a
    shadow) leaves s c / sum(s c) unchanged. With ``gradient`` (N, 3, D) d colour / d x, also returns
    the chromaticity's: (d c_k - q_k sum_j d c_j) / S for S = sum_j c_j (at least ``floor``)."""
    c = np.asarray(colour, np.float64)
    total = np.maximum(c.sum(-1, keepdims=True), floor)
    q = c / total
    if gradient is None:
        return q
    g = np.asarray(gradient, np.float64)
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
