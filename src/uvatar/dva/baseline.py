"""The baselines a DVA avatar is scored against in ``uvatar eval dva``; both share the avatar's
geometry source (the fit) and its inputs at test time (the driving views of the test frame).

* **mean colour** (trivial): the posed body mesh rendered in the held-out camera, filled with the mean
  colour of the person's pixels in the frame's driving views, unshaded.
* **projective texture** (strong, no learning): the driving views' pixels of the frame unwrapped onto
  the posed body (each texel from the views that see it, face on, unoccluded and inside the person's
  mask, averaged; texels no view sees take the nearest seen texel's colour) and the textured body
  rendered in the held-out camera. It is as sharp as the photos and as well placed as the fit: what a
  learned avatar adds over it is geometry and appearance beyond the fitted surface.

Both are rendered over the same background as the avatar's render.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mean_colour", "mean_colour_render", "projective_texture", "textured_body_render"]


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


def projective_texture(template, vertices: np.ndarray, cameras, images, masks, resolution: int = 256) -> np.ndarray:
    """(R, R, 3) float32 texture in the template's UV layout (rows as :func:`uvatar.geometry.rasterize_uv`
    lays them out, what :func:`uvatar.render.mesh_renderer.render_mesh` reads): the views ``images``
    ((H, W, 3) uint8 or float in [0, 1]) of ``cameras`` unwrapped onto the body posed at ``vertices``
    (V, 3) world metres, inside ``masks`` (H, W) bool, averaged over the views that see each texel;
    texels no view sees take the nearest seen texel's colour (mid grey when no view sees any)."""
    import torch
    from scipy.ndimage import distance_transform_edt

    from uvatar.dva.features import average_views, unwrap_views
    from uvatar.geometry import rasterize_uv

    raster = rasterize_uv(template.uvs, template.uv_faces, int(resolution))
    floats = [np.asarray(i, np.float32) / 255.0 if np.asarray(i).dtype == np.uint8 else np.asarray(i, np.float32)
              for i in images]
    tex, vis = unwrap_views(raster, template, np.asarray(vertices, np.float32), cameras, floats,
                            [np.asarray(m, np.float32) for m in masks])
    avg = average_views(torch.as_tensor(tex)[None], torch.as_tensor(vis)[None])[0].numpy()
    colour, seen = np.ascontiguousarray(avg[:3].transpose(1, 2, 0)), avg[3] > 0
    if not seen.any():
        return np.full_like(colour, 0.5)
    _, (rows, cols) = distance_transform_edt(~seen, return_indices=True)
    return colour[rows, cols]


def textured_body_render(vertices: np.ndarray, template, camera, texture: np.ndarray,
                         background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Render the body (V, 3) world metres with ``texture`` (R, R, 3) (from :func:`projective_texture`)
    over ``background`` (3,) as seen by ``camera`` -> (rgb (H, W, 3) float32, alpha (H, W) float32)."""
    from uvatar.render.mesh_renderer import render_mesh

    out = render_mesh(vertices, template.faces, camera, template.uvs, template.uv_faces, texture,
                      background=np.asarray(background, np.float32))
    return out.rgb, out.mask.astype(np.float32)
