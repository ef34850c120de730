"""Several texture images of one frame made one atlas: photogrammetry and some capture tools texture a
mesh with several images (RealityCapture's and Metashape's texture count, one material a body part),
while uvatar's scans wear one texture. The images become the tiles of a grid, each with a gutter of its
own edge texels (so bilinear lookups near a tile's edge never reach its neighbour), and each corner's
UV is moved into its image's tile.

The grid's cell is the largest image's size (smaller images are resized to it); where the atlas would
pass :data:`MAX_ATLAS_SIDE` texels a side, every tile is scaled down to fit (the bake samples a scan's
texture into a 1024² body atlas, so a 8192² frame atlas keeps what it needs).
"""

from __future__ import annotations

import math

import numpy as np

from uvatar.errors import InputError

__all__ = ["pack_textures", "MAX_ATLAS_SIDE", "GUTTER"]

MAX_ATLAS_SIDE = 8192
GUTTER = 4                  # texels of each tile's edge repeated around it
UV_SLACK = 1e-3             # UVs this far past [0, 1] are clamped onto the tile's edge; farther, refused


def _grid(count: int) -> tuple[int, int]:
    cols = math.ceil(math.sqrt(count))
    return math.ceil(count / cols), cols


def pack_textures(textures: list[np.ndarray], uvs: np.ndarray, uv_faces: np.ndarray, face_texture: np.ndarray,
                  where="the mesh") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One atlas of ``textures`` ((H_i, W_i, 3), float32 in [0, 1] or uint8, v up: row 0 at v = 1), the
    mesh's UVs moved into it: (atlas (H, W, 3) of the textures' dtype, uvs (U', 2) float32, uv_faces
    (F, 3)). ``uvs`` (U, 2), ``uv_faces`` (F, 3), ``face_texture`` (F,) the image of each face (-1: none,
    its corners go to the first tile's centre). InputError naming ``where`` for UVs that wrap (repeat
    their image) far past [0, 1]: a tile cannot repeat."""
    import cv2

    textures = [np.asarray(t) for t in textures]
    if len(textures) == 1:
        return textures[0], np.asarray(uvs, np.float32), np.asarray(uv_faces)
    face_texture = np.asarray(face_texture, np.int64)
    uv_faces = np.asarray(uv_faces, np.int64)
    uvs = np.asarray(uvs, np.float64)
    h = max(t.shape[0] for t in textures)
    w = max(t.shape[1] for t in textures)
    rows, cols = _grid(len(textures))
    scale = min(1.0, (MAX_ATLAS_SIDE // cols - 2 * GUTTER) / w, (MAX_ATLAS_SIDE // rows - 2 * GUTTER) / h)
    th, tw = max(1, int(h * scale)), max(1, int(w * scale))
    ch, cw = th + 2 * GUTTER, tw + 2 * GUTTER
    dtype = textures[0].dtype
    atlas = np.zeros((rows * ch, cols * cw, 3), dtype)
    for k, tex in enumerate(textures):
        tile = tex[..., :3].astype(dtype, copy=False)
        if tile.shape[:2] != (th, tw):
            shrink = tile.shape[0] > th or tile.shape[1] > tw
            tile = cv2.resize(tile, (tw, th), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        r, c = divmod(k, cols)
        atlas[r * ch:(r + 1) * ch, c * cw:(c + 1) * cw] = cv2.copyMakeBorder(
            np.ascontiguousarray(tile), GUTTER, GUTTER, GUTTER, GUTTER, cv2.BORDER_REPLICATE)
    # one new UV for each (UV, image) pair the corners use
    corner_tex = np.repeat(np.maximum(face_texture, 0), 3)
    pairs = np.stack([uv_faces.reshape(-1), corner_tex], axis=1)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    uv = uvs[unique[:, 0]].copy() if len(uvs) else np.full((len(unique), 2), 0.5)
    outside = (uv < -UV_SLACK) | (uv > 1 + UV_SLACK)
    if outside.any():
        raise InputError(where, f"{int(outside.any(axis=1).sum())} UVs lie outside 0-1 (a repeating texture): "
                                f"its {len(textures)} images cannot be made one atlas")
    uv = np.clip(uv, 0.0, 1.0)
    r, c = np.divmod(unique[:, 1], cols)
    atlas_h, atlas_w = rows * ch, cols * cw
    u = (c * cw + GUTTER + uv[:, 0] * tw) / atlas_w
    v = 1.0 - (r * ch + GUTTER + (1.0 - uv[:, 1]) * th) / atlas_h
    return atlas, np.stack([u, v], axis=1).astype(np.float32), inverse.reshape(-1, 3)
