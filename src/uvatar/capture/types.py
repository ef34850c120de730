"""Plain numpy records of the capture format: textured scans, body fits and cameras.

Conventions (see docs/ARCHITECTURE.md): metres, +Y up; UV (u, v) in [0, 1] with v up, a texture
image's row 0 is v = 1; OpenCV cameras with ``X_cam = R @ X_world + T``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Camera lives below capture and render; re-exported here, where the capture format's records live.
from uvatar.geometry.camera import Camera
from uvatar.geometry.mesh import MeshCounts


@dataclass
class TexturedMesh(MeshCounts):
    """A triangle mesh with its own UV triangles (seams split UVs, not vertices).

    vertices (V, 3) float32 metres; faces (F, 3) int64 into vertices; uvs (U, 2) float32 in [0, 1]
    with v up; uv_faces (F, 3) int64 into uvs; texture (H, W, 3) float32 in [0, 1] (row 0 is v = 1)
    or ``None`` for an untextured mesh; vertex_colors (V, 3) float32 in [0, 1] where the file gave
    colours per vertex (``None`` otherwise; :mod:`uvatar.capture.vertex_colors` turns them into a
    texture).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    texture: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.uvs = np.ascontiguousarray(self.uvs, dtype=np.float32).reshape(-1, 2)
        self.uv_faces = np.ascontiguousarray(self.uv_faces, dtype=np.int64).reshape(-1, 3)
        if self.texture is not None:
            tex = np.asarray(self.texture)
            if tex.dtype == np.uint8:
                tex = tex.astype(np.float32) / 255.0
            if tex.ndim == 2:
                tex = np.repeat(tex[..., None], 3, axis=-1)
            self.texture = np.ascontiguousarray(tex[..., :3], dtype=np.float32)
        if self.vertex_colors is not None:
            self.vertex_colors = np.ascontiguousarray(self.vertex_colors, dtype=np.float32).reshape(-1, 3)

    @property
    def has_uvs(self) -> bool:
        return self.uvs.shape[0] > 0 and self.uv_faces.shape[0] == self.faces.shape[0]


@dataclass
class BodyFit:
    """One person's body-model fit for one frame (EasyMocap convention).

    ``V = R(Rh) @ LBS(poses with zero root, shapes) * scale + Th``. poses (J*3,) local axis-angles
    in the body model's joint order (radians); Rh (3,) axis-angle; Th (3,) metres; shapes (S,).
    """

    poses: np.ndarray
    Rh: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    Th: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    shapes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    scale: float = 1.0
    id: int = 0

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float32).reshape(-1)
        self.Rh = np.asarray(self.Rh, dtype=np.float32).reshape(3)
        self.Th = np.asarray(self.Th, dtype=np.float32).reshape(3)
        self.shapes = np.asarray(self.shapes, dtype=np.float32).reshape(-1)
        self.scale = float(self.scale)
        self.id = int(self.id)

__all__ = ["BodyFit", "Camera", "TexturedMesh"]
