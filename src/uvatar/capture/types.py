"""Plain numpy records of the capture format: textured scans, body fits and cameras.

Conventions (see docs/ARCHITECTURE.md): metres, +Y up; UV (u, v) in [0, 1] with v up, a texture
image's row 0 is v = 1; OpenCV cameras with ``X_cam = R @ X_world + T``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class TexturedMesh:
    """A triangle mesh with its own UV triangles (seams split UVs, not vertices).

    vertices (V, 3) float32 metres; faces (F, 3) int64 into vertices; uvs (U, 2) float32 in [0, 1]
    with v up; uv_faces (F, 3) int64 into uvs; texture (H, W, 3) float32 in [0, 1] (row 0 is v = 1)
    or ``None`` for an untextured mesh.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    texture: np.ndarray | None = None

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

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

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


@dataclass
class Camera:
    """A pinhole camera in the OpenCV convention (x right, y down, z forward).

    K (3, 3) intrinsics in pixels; R (3, 3) world→camera rotation; T (3,) metres, so that
    ``X_cam = R @ X_world + T``; width, height in pixels (0 when unknown); dist (5,) OpenCV
    distortion (k1, k2, p1, p2, k3).
    """

    name: str
    K: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    width: int = 0
    height: int = 0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        self.name = str(self.name)
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.T = np.asarray(self.T, dtype=np.float64).reshape(3)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        self.dist = np.pad(dist, (0, max(0, 5 - dist.size)))[: max(5, dist.size)]
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,), metres: ``-R.T @ T``."""
        return -self.R.T @ self.T

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points → (..., 3) camera-frame points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.T

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project (..., 3) world points to (..., 2) pixel coordinates (x right, y down).

        Distortion is ignored (ideal pinhole); points behind the camera give meaningless pixels;
        check ``world_to_camera(points)[..., 2] > 0`` for that.
        """
        cam = self.world_to_camera(points)
        z = cam[..., 2:3]
        z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        pix = (cam / z) @ self.K.T
        return pix[..., :2]
