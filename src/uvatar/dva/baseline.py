"""The trivial baseline a DVA avatar must beat: the fitted body in one flat colour.

For a test frame, the posed body mesh is rendered in the held-out camera, filled with the mean
colour of the person's pixels in that frame's driving views (what the driving views tell about the
person, reduced to a single colour, unshaded) over the same background as the avatar's render. It shares the avatar's geometry source (the fit), so the gap between the two is what the
volumetric appearance and shape add.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mean_colour", "mean_colour_render"]


def mean_colour(images: list[np.ndarray], masks: list[np.ndarray]) -> np.ndarray:
    """(3,) float32 mean colour over the masked pixels of the given images ((H, W, 3) uint8 or float
    in [0, 1], masks (H, W) bool); mid grey when no pixel is masked."""
    total, count = np.zeros(3), 0
    for image, mask in zip(images, masks, strict=True):
        img = np.asarray(image)
        img = img.astype(np.float64) / 255.0 if img.dtype == np.uint8 else img.astype(np.float64)
        m = np.asarray(mask, bool)
        total += img[m].sum(0)
        count += int(m.sum())
    return (total / count).astype(np.float32) if count else np.full(3, 0.5, np.float32)


def mean_colour_render(vertices: np.ndarray, faces: np.ndarray, camera, colour: np.ndarray,
                       background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Render the body (V, 3) world metres in ``colour`` (3,) over ``background`` (3,) as seen by
    ``camera`` -> (rgb (H, W, 3) float32, alpha (H, W) float32)."""
    from uvatar.render.mesh_renderer import render_mesh

    colours = np.broadcast_to(np.asarray(colour, np.float32), np.shape(vertices))
    out = render_mesh(vertices, faces, camera, vertex_colors=colours, background=np.asarray(background, np.float32))
    return out.rgb, out.mask.astype(np.float32)
