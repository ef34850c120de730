"""Depth order of fitted bodies in a camera's image: which body is nearest at each pixel.

The one owner of the rendering of a body's depth (:func:`body_depth`), its silhouette, and the rule
that decides which pixels a person may take when other bodies are fitted too (:func:`nearest_region`);
:mod:`uvatar.fit.masks` (the depth-ordered masks) and :mod:`uvatar.fit.appearance` (the colour models
that decide the contested pixels) both build on it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FAR", "body_depth", "body_silhouette", "disc", "nearest_region"]

FAR = np.float32(1e9)  # depth (metres) of a pixel no body covers


def body_depth(vertices: np.ndarray, faces: np.ndarray, camera, render_width: int) -> np.ndarray:
    """(H, W) float32: the camera depth (metres) of the body mesh (V, 3) world metres in ``camera``'s
    image, :data:`FAR` where it does not cover the pixel (rendered ``render_width`` wide by ray
    casting, the nearest hit per pixel, then resized to the camera's size)."""
    import cv2

    from uvatar.render.mesh_renderer import render_mesh

    small = camera.scaled_to_width(min(render_width, camera.width))
    r = render_mesh(vertices, faces, small)
    depth = np.where(r.mask, r.depth, FAR).astype(np.float32)
    return cv2.resize(depth, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)


def body_silhouette(vertices: np.ndarray, faces: np.ndarray, camera, render_width: int) -> np.ndarray:
    """(H, W) bool: where the body mesh covers ``camera``'s image (:func:`body_depth` < :data:`FAR`)."""
    return body_depth(vertices, faces, camera, render_width) < FAR


def disc(radius: int) -> np.ndarray:
    """(2r+1, 2r+1) uint8 elliptic structuring element of ``radius`` pixels (for cv2 dilate / erode)."""
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def nearest_region(depth: np.ndarray, others: list[np.ndarray], radius: int) -> np.ndarray:
    """(H, W) bool: the pixels a person may take when other bodies are fitted too. ``depth`` (H, W)
    the person's body depth (:func:`body_depth`), ``others`` the other bodies' depths; each body is
    grown by ``radius`` pixels (an other body at the nearest depth within that radius). The person
    keeps their own body's pixels where no grown other body lies in front, and the pixels of their
    grown band that no grown other body covers."""
    import cv2

    core = depth < FAR
    kernel = disc(max(1, int(radius)))
    grown = cv2.dilate(core.astype(np.uint8), kernel) > 0
    if not others:
        return grown
    near = np.minimum.reduce([cv2.erode(np.asarray(d, np.float32), kernel) for d in others])
    return (core & (depth <= near)) | (grown & ~core & (near >= FAR))
