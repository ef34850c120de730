"""Everything uvatar reads from the ``anny`` package, in one place.

uvatar's anny backend was written against anny 0.6 (``anny.Anny`` with rig "anny", topology "anny",
pose parameterization "local-ref", bone orientation "cached"). If another anny version lacks what is
used here, :func:`load_anny` / :func:`anny_rest_state` raise a :class:`UvatarError` that names the
missing piece and the supported version, instead of failing deep inside posing.

Axes: anny works in Blender axes (metres, +Z up, the body facing -Y, its left toward +X). uvatar's
world is +Y up facing +Z, so ``x_uvatar = ANNY_TO_WORLD @ x_anny`` (a -90 degree turn about X).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.errors import UvatarError, require

__all__ = ["ANNY_TO_WORLD", "SUPPORTED_ANNY", "AnnyData", "load_anny", "anny_data", "anny_rest_state"]

SUPPORTED_ANNY = "0.6"
# (x, y, z)_anny -> (x, z, -y)_uvatar
ANNY_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _unsupported(what: str) -> UvatarError:
    import anny

    version = getattr(anny, "__version__", "unknown")
    return UvatarError(
        f"anny {version} is not supported by uvatar's anny backend ({what}); it was written for "
        f"anny {SUPPORTED_ANNY}.x: pip install 'anny>={SUPPORTED_ANNY},<0.7'")


def load_anny(device: str | torch.device = "cpu"):
    """The default anny model (float64, on ``device``), or a clear error for an unsupported anny."""
    anny = require("anny", None, "the anny body model")
    try:
        model = anny.Anny(rig="anny", topology="anny", pose_parameterization="local-ref",
                          skinning_method="lbs")
    except TypeError as exc:
        raise _unsupported(f"anny.Anny() does not accept uvatar's arguments: {exc}") from exc
    needed = ["template_vertices", "faces", "texture_coordinates", "face_texture_coordinate_indices",
              "vertex_bone_weights", "vertex_bone_indices", "bone_labels", "bone_parents",
              "reference_bone_orientations", "phenotype_labels", "local_change_labels",
              "facial_action_labels", "get_rest_model", "_get_phenotype_blendshape_coefficients"]
    missing = [n for n in needed if not hasattr(model, n)]
    if missing:
        raise _unsupported(f"anny.Anny lacks {', '.join(missing)}")
    if getattr(model, "pose_parameterization", "local-ref") != "local-ref":
        raise _unsupported("the model does not use the 'local-ref' pose parameterization")
    return model.to(device)


@dataclass(frozen=True)
class AnnyData:
    """Shape-independent anny data in anny axes (numpy, float64 unless said).

    faces (F, 3) int64, uvs (U, 2), uv_faces (F, 3) int64, weights (V, J) dense skinning weights,
    bone_labels J names, parents (J,) int64, reference_rotations (J, 3, 3) (anny's U_c),
    phenotype_labels S names."""

    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    weights: np.ndarray
    bone_labels: tuple[str, ...]
    parents: np.ndarray
    reference_rotations: np.ndarray
    phenotype_labels: tuple[str, ...]


def anny_data(model) -> AnnyData:
    """Read the shape-independent data (UVs, triangles, skinning, rig) from an anny model."""
    faces = model.faces.detach().cpu().numpy().astype(np.int64)
    uv_faces = model.face_texture_coordinate_indices.detach().cpu().numpy().astype(np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or uv_faces.shape != faces.shape:
        raise _unsupported(f"expected triangle faces (F, 3) with matching UV faces, got {faces.shape} "
                           f"and {uv_faces.shape}")
    V = model.template_vertices.shape[0]
    J = len(model.bone_labels)
    idx = model.vertex_bone_indices.detach().cpu().numpy().astype(np.int64)
    w = model.vertex_bone_weights.detach().cpu().numpy().astype(np.float64)
    dense = np.zeros((V, J))
    np.add.at(dense, (np.repeat(np.arange(V), idx.shape[1]), idx.reshape(-1)), w.reshape(-1))
    parents = np.asarray(model.bone_parents, dtype=np.int64)
    if model.reference_bone_orientations is None:
        raise _unsupported("the model has no reference bone orientations")
    return AnnyData(
        faces=faces,
        uvs=model.texture_coordinates.detach().cpu().numpy().astype(np.float64),
        uv_faces=uv_faces,
        weights=dense,
        bone_labels=tuple(model.bone_labels),
        parents=parents,
        reference_rotations=model.reference_bone_orientations.detach().cpu().numpy().astype(np.float64),
        phenotype_labels=tuple(model.phenotype_labels),
    )


def anny_rest_state(model, phenotypes: torch.Tensor) -> dict[str, torch.Tensor]:
    """Shape-dependent bind (rest) state in anny axes, differentiable in ``phenotypes``.

    phenotypes (B, S) in anny's phenotype order -> dict with bind_vertices (B, V, 3),
    bind_heads (B, J, 3) bone heads, bind_rotations (B, J, 3, 3) rest bone orientations R_c
    (all in the model's dtype, float64)."""
    phen = phenotypes.to(device=model.device, dtype=model.dtype)
    B = phen.shape[0]
    zeros = lambda n: torch.zeros(B, n, device=model.device, dtype=model.dtype)  # noqa: E731
    try:
        coeffs = model._get_phenotype_blendshape_coefficients(
            phen, zeros(len(model.local_change_labels)), zeros(len(model.facial_action_labels)))
        rest = model.get_rest_model(coeffs)
        poses = rest["rest_bone_poses"]
        return {"bind_vertices": rest["rest_vertices"], "bind_heads": poses[..., :3, 3],
                "bind_rotations": poses[..., :3, :3]}
    except (AttributeError, KeyError, TypeError) as exc:
        raise _unsupported(f"computing the rest model failed: {exc}") from exc
