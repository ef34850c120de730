"""An exported avatar at run time: generator (onnxruntime) + posed, subdivided, displaced body (§3.5).

For a pose: run the generator -> texture (R, R, 3) and displacement (R, R, 3); pose the body (LBS),
subdivide its triangles ``levels`` times (UVs carried along, one UV per geometric vertex for the
displacement lookup so seams do not crack), rotate the displacement sampled at each vertex into
world axes and add it, except on fingers and toes (mask sampled at the vertex UV). The rotation is
``R(Rh) M_v`` for rest-frame avatars (M_v: the vertex's blended skinning rotation for the pose,
:mod:`uvatar.avh.displacement_frame`) and ``R(Rh)`` for body-frame ones.
Texels outside the UV charts are first filled from the nearest chart texel (:meth:`AvatarRuntime.pad`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from uvatar.avh.avatar_file import avatar_body, read_avatar
from uvatar.avh.data import rotvec_to_rotmat
from uvatar.avh.displacement_frame import SkinningRotations, frame_of_space
from uvatar.avh.export import onnx_session
from uvatar.errors import InputError


def gutter_fill_index(uvs, uv_faces, resolution: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """(valid (R, R) bool, (rows, cols) (R, R) int index of the nearest valid texel for every texel)."""
    from scipy.ndimage import distance_transform_edt

    from uvatar.geometry import rasterize_uv

    valid = rasterize_uv(uvs, uv_faces, resolution).mask
    if not valid.any():
        raise InputError("uvs", f"no texel of the {resolution}x{resolution} UV layout is covered")
    _, idx = distance_transform_edt(~valid, return_indices=True)
    return valid, (idx[0], idx[1])


@dataclass
class AvatarMesh:
    """vertices (V', 3) world metres; faces (F', 3); uvs (U', 2); uv_faces (F', 3); texture (R, R, 3)."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    texture: np.ndarray


class AvatarRuntime:
    """Loads ``AVATAR/`` (see :mod:`uvatar.avh.export`) and turns poses into textured meshes.

    body: the BodyModel (default: ``load_body_model`` of avatar.json's body model);
    levels / scheme: subdivision of the body ("midpoint" keeps the surface, "loop" smooths it).
    """

    def __init__(self, avatar_dir: str | Path, body=None, device: str = "cpu", levels: int = 2,
                 scheme: str = "midpoint"):
        from uvatar.geometry import subdivide

        self.avatar_dir = Path(avatar_dir)
        self.meta = read_avatar(self.avatar_dir)
        self.session = onnx_session(self.avatar_dir / self.meta["model"], device)
        name, self.shape = avatar_body(self.meta, self.avatar_dir / "avatar.json")
        if body is None:
            if name == "none":
                raise InputError(self.avatar_dir / "avatar.json", "avatar has no body model")
            from uvatar.body import load_body_model

            body = load_body_model(name)
        self.body = body
        self.conditioning = [int(j) for j in self.meta["conditioning_joints"]]
        # "studio": the last conditioning joint is the root and its slot carries the body's Rh
        self.orientation = (self.meta.get("model_config") or {}).get("orientation", "body")
        self.resolution = int(self.meta["resolution"])
        t = body.template
        v, f, uv, uvf, origin = subdivide(t.vertices, t.faces, t.uvs, t.uv_faces, levels, scheme)
        self.faces, self.uvs, self.uv_faces = f, uv.astype(np.float32), uvf
        self.vertex_matrix = origin.vertex_matrix.astype(np.float32)
        self.vertex_uv = origin.vertex_uv.astype(np.float32)
        self.displacement_weight = 1.0 - self._sample(self.fingers_toes_mask()[..., None].astype(np.float32))[:, 0]
        self.valid_mask, self._fill_index = gutter_fill_index(t.uvs, t.uv_faces, self.resolution)
        self.displacement_frame = self.meta.get("displacement_frame") or frame_of_space(
            self.meta.get("displacement_space"))
        self._skinning: SkinningRotations | None = None

    def pad(self, image: np.ndarray) -> np.ndarray:
        """(R, R, C) map with texels outside the UV charts replaced by the nearest chart texel.

        Bilinear lookups at chart borders then never mix in values the generator was not trained on.
        """
        image = np.asarray(image)
        if image.shape[:2] != self.valid_mask.shape:
            return image
        return image[self._fill_index[0], self._fill_index[1]]

    def fingers_toes_mask(self) -> np.ndarray:
        """(R, R) bool texels where displacement is not applied (body.npz, else part_masks)."""
        from uvatar.avh.avatar_file import read_fingers_toes_mask

        mask = read_fingers_toes_mask(self.avatar_dir)  # a truncated file is an InputError naming it
        if mask is not None and mask.shape == (self.resolution,) * 2:
            return mask
        from uvatar.body import part_masks

        return np.asarray(part_masks(self.body, self.resolution)["fingers_toes"], bool)

    def _sample(self, image: np.ndarray) -> np.ndarray:
        from uvatar.geometry import sample_texture

        return np.asarray(sample_texture(image, self.vertex_uv), np.float32)

    def conditioning_poses(self, poses, Rh=None) -> np.ndarray:
        """(T, J·3) root-zero local poses (+ (T, 3) Rh) -> the poses whose conditioning joints the
        generator reads: for a studio-orientation avatar the root slot holds Rh (zero, the body facing
        the studio's +Z, where no Rh is given)."""
        poses = np.asarray(poses, np.float32).reshape(len(poses), -1)
        if self.orientation != "studio":
            return poses
        from uvatar.avh.model import with_orientation

        Rh = np.zeros((len(poses), 3), np.float32) if Rh is None else np.asarray(Rh, np.float32).reshape(-1, 3)
        return with_orientation(poses, Rh, self.conditioning[-1])

    def generate(self, poses: np.ndarray, batch_size: int = 8, Rh=None) -> tuple[np.ndarray, np.ndarray]:
        """(T, J·3) local axis-angles (+ (T, 3) Rh, read by studio-orientation avatars) -> texture
        (T, R, R, 3) in [0, 1], displacement (T, R, R, 3) body frame."""
        poses = self.conditioning_poses(poses, Rh).reshape(len(poses), -1, 3)
        angles = poses[:, self.conditioning].reshape(len(poses), -1)
        tex, disp = [], []
        for s in range(0, len(angles), batch_size):
            t, d = self.session.run(["texture", "displacement"], {"pose_angles": angles[s:s + batch_size]})
            tex.append(t.transpose(0, 2, 3, 1))
            disp.append(d.transpose(0, 2, 3, 1))
        return np.concatenate(tex), np.concatenate(disp)

    def posed_vertices(self, poses, Rh=None, Th=None, scale=None, shape=None) -> np.ndarray:
        """(T, J·3) poses (+ global Rh, Th (T, 3), scale (T,)) -> base-mesh vertices (T, V, 3)."""
        T = len(poses)
        shape = self.shape if shape is None else shape
        with torch.no_grad():
            posed = self.body.pose(torch.as_tensor(np.asarray(poses, np.float32)).reshape(T, -1, 3),
                                   Rh=None if Rh is None else torch.as_tensor(np.asarray(Rh, np.float32)),
                                   Th=None if Th is None else torch.as_tensor(np.asarray(Th, np.float32)),
                                   scale=None if scale is None else torch.as_tensor(np.asarray(scale, np.float32)),
                                   shape=None if shape is None else torch.as_tensor(shape))
        return posed.vertices.cpu().numpy()

    def skinning_rotations(self, poses) -> np.ndarray:
        """(T, J·3) local axis-angles -> (T, V, 3, 3) blended LBS rotation per base vertex (no Rh)."""
        if self._skinning is None:
            self._skinning = SkinningRotations(self.body, self.shape)
        return self._skinning.vertices(np.asarray(poses, np.float32).reshape(len(poses), -1))

    def displaced_vertices(self, base_vertices: np.ndarray, displacement: np.ndarray | None,
                           Rh: np.ndarray | None = None, rotations: np.ndarray | None = None) -> np.ndarray:
        """Subdivide posed base vertices (V, 3) and add the displacement map (R, R, 3) (or None).

        rotations: (V, 3, 3) blended skinning rotations of the pose (:meth:`skinning_rotations`),
        required for rest-frame avatars, ignored for body-frame ones.
        """
        v = np.asarray(self.vertex_matrix @ np.asarray(base_vertices, np.float32), np.float32)
        if displacement is None:
            return v
        d = self._sample(self.pad(np.asarray(displacement, np.float32))) * self.displacement_weight[:, None]
        if self.displacement_frame == "rest":
            if rotations is None:
                raise ValueError("a rest-frame displacement needs the pose's skinning rotations")
            V = len(base_vertices)
            m = np.asarray(self.vertex_matrix @ np.asarray(rotations, np.float32).reshape(V, 9), np.float32)
            d = np.einsum("vab,vb->va", m.reshape(-1, 3, 3), d)
        if Rh is not None:
            d = d @ rotvec_to_rotmat(np.asarray(Rh, np.float64)).T.astype(np.float32)
        return v + d

    def mesh(self, base_vertices, texture, displacement, Rh=None, pose=None, rotations=None) -> AvatarMesh:
        """One textured, displaced mesh from posed base vertices (V, 3) and the maps; rest-frame
        avatars also need the local pose (J·3,) or its skinning ``rotations`` (V, 3, 3)."""
        if self.displacement_frame == "rest" and displacement is not None and rotations is None:
            if pose is None:
                raise ValueError("a rest-frame avatar needs the pose (or its skinning rotations) to displace")
            rotations = self.skinning_rotations(np.asarray(pose)[None])[0]
        return AvatarMesh(self.displaced_vertices(base_vertices, displacement, Rh, rotations), self.faces,
                          self.uvs, self.uv_faces, self.pad(np.asarray(texture, np.float32)))

    def sole_offset(self) -> float:
        """Metres from the body's lowest point to the avatar's surface's (its displacements included) at
        the rest pose: the shoes' learned thickness under the body's soles (negative: below them)."""
        zero = np.zeros((1, 3 * self.body.num_joints), np.float32)
        texture, displacement = self.generate(zero)
        base = self.posed_vertices(zero)[0]
        surface = self.mesh(base, texture[0], displacement[0], pose=zero[0]).vertices
        return float(surface[:, 1].min() - self.displaced_vertices(base, None)[:, 1].min())

    def meshes(self, poses, Rh=None, Th=None, scale=None, shape=None):
        """Yield an :class:`AvatarMesh` per pose (generator and body posed in batches)."""
        T = len(poses)
        Rh = np.zeros((T, 3), np.float32) if Rh is None else np.asarray(Rh, np.float32)
        for s in range(0, T, 8):
            sl = slice(s, min(s + 8, T))
            tex, disp = self.generate(np.asarray(poses)[sl], Rh=Rh[sl])
            base = self.posed_vertices(np.asarray(poses)[sl], Rh[sl], None if Th is None else np.asarray(Th)[sl],
                                       None if scale is None else np.asarray(scale)[sl], shape)
            rot = self.skinning_rotations(np.asarray(poses)[sl]) if self.displacement_frame == "rest" else None
            for k in range(len(base)):
                yield self.mesh(base[k], tex[k], disp[k], Rh[sl][k], rotations=None if rot is None else rot[k])
