"""Face and vertex normals (numpy or torch, batched, differentiable in torch).

Normals follow the right-hand rule of the triangle's vertex order (counter-clockwise seen from
the side the normal points to). Vertex normals are area weighted: the sum of the (unnormalized)
cross products of the incident faces, then normalized. This module is the one home of that math
(body posing, the bake, the renderer and the engine export call it).
"""

from __future__ import annotations

import numpy as np

__all__ = ["face_normals", "vertex_normals", "mesh_normals", "vertex_face_adjacency", "normalize", "is_torch", "frames_from_normals",
           "face_index_tensor"]

_EPS = 1e-12


def is_torch(x) -> bool:
    """True when ``x`` is a torch tensor (without importing torch when it is not loaded)."""
    return type(x).__module__.startswith("torch")


def face_index_tensor(faces, device):
    """``faces`` (F, 3) (numpy, a list or a tensor) as a long tensor on ``device``; a host array is copied
    once and kept (:func:`uvatar.devices.on_device`): no host-to-device copy, hence no stream sync, per
    call."""
    import torch

    if is_torch(faces):
        return faces.to(device=device, dtype=torch.long)
    from uvatar.devices import on_device

    return on_device(faces, device, torch.long)


def normalize(x, eps: float = _EPS):
    """Unit vectors along the last axis (numpy or torch); zero vectors stay zero."""
    if is_torch(x):
        import torch

        return x / torch.linalg.norm(x, dim=-1, keepdim=True).clamp_min(eps)
    x = np.asarray(x)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), eps)


def _face_corners(vertices, faces):
    """(..., F, 3, 3) corner positions; faces (F, 3) int (numpy or torch)."""
    if is_torch(vertices):

        return vertices[..., face_index_tensor(faces, vertices.device), :]
    return np.asarray(vertices)[..., np.asarray(faces, dtype=np.int64), :]


def _face_cross(vertices, faces):
    """(..., F, 3) cross(v1 - v0, v2 - v0): direction = normal, length = 2 x area."""
    tri = _face_corners(vertices, faces)
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    if is_torch(tri):
        import torch

        return torch.linalg.cross(e1, e2, dim=-1)
    return _cross_numpy(e1, e2)


def _cross_numpy(a, b):
    """``np.cross(a, b)`` of (..., 3) arrays, written out: the same products and differences, a few
    times faster (np.cross moves its axes around for the general case)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def face_normals(vertices, faces):
    """Unit face normals. vertices (..., V, 3), faces (F, 3) -> (..., F, 3); same backend as input."""
    return normalize(_face_cross(vertices, faces))


def vertex_face_adjacency(faces, num_vertices: int):
    """(V, F) torch sparse CSR with a 1 where vertex v is a corner of face f (the fast path of
    :func:`vertex_normals` on CPU tensors). faces (F, 3) int64 torch tensor."""
    import warnings

    import torch

    F = faces.shape[0]
    cols = torch.arange(F, device=faces.device).repeat_interleave(3)
    values = torch.ones(3 * F, device=faces.device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # sparse CSR is "beta"; invariant checks off
        return torch.sparse_coo_tensor(torch.stack([faces.reshape(-1), cols]), values,
                                       (num_vertices, F)).coalesce().to_sparse_csr()


def _vertex_normals_sparse(vertices, faces, adjacency, eps: float = _EPS):
    """Torch fast path: one sparse (V, F) product for the whole batch (twin: the index_add path)."""
    import torch

    lead, V = vertices.shape[:-2], vertices.shape[-2]
    rows = vertices.reshape(-1, V, 3).transpose(0, 1).reshape(V, -1)  # (V, N*3): gathers whole rows
    tri = rows[faces].reshape(faces.shape[0], 3, -1, 3)
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)  # |n| = 2 area
    normals = adjacency.to(cross.dtype) @ cross.reshape(faces.shape[0], -1)
    normals = torch.nn.functional.normalize(normals.reshape(V, -1, 3), dim=-1, eps=eps)
    return normals.transpose(0, 1).reshape(*lead, V, 3)


def mesh_normals(vertices, faces):
    """(area-weighted unit vertex normals (..., V, 3), unit face normals (..., F, 3)) of one mesh:
    :func:`vertex_normals` and :func:`face_normals` from one computation of the faces' cross products."""
    cross = _face_cross(vertices, faces)
    return _vertex_normals_from_cross(vertices, faces, cross), normalize(cross)


def vertex_normals(vertices, faces, adjacency=None):
    """Area-weighted unit vertex normals. vertices (..., V, 3), faces (F, 3) -> (..., V, 3).

    Vertices that belong to no face get a zero normal. ``adjacency`` (torch only):
    :func:`vertex_face_adjacency` of these faces, for one sparse product instead of three scatters.
    """
    if adjacency is not None and is_torch(vertices):
        return _vertex_normals_sparse(vertices, faces, adjacency)
    return _vertex_normals_from_cross(vertices, faces, _face_cross(vertices, faces))


def _vertex_normals_from_cross(vertices, faces, cross):
    """:func:`vertex_normals` from the faces' cross products ``cross`` (..., F, 3)."""
    if is_torch(vertices):
        import torch

        f = face_index_tensor(faces, vertices.device)
        out = torch.zeros_like(vertices)
        for k in range(3):  # three corners, not a per-vertex loop
            out = out.index_add(-2, f[:, k], cross)
        return normalize(out)
    faces = np.asarray(faces, dtype=np.int64)
    vertices = np.asarray(vertices)
    lead = vertices.shape[:-2]
    nv = vertices.shape[-2]
    cross2 = cross.reshape(-1, cross.shape[-2], 3)
    out = np.zeros((cross2.shape[0], nv, 3), dtype=np.float64)
    for b in range(cross2.shape[0]):  # batch loop (small); accumulation itself is bincount
        for c in range(3):
            out[b, :, c] = sum(np.bincount(faces[:, k], weights=cross2[b, :, c], minlength=nv)
                               for k in range(3))
    return normalize(out.reshape(*lead, nv, 3)).astype(np.result_type(vertices.dtype, np.float32))


def frames_from_normals(normals) -> np.ndarray:
    """(N, 3, 3) orthonormal frames with columns (t, b, n) for unit normals n (N, 3).

    Branchless construction of Duff et al. 2017 ("Building an orthonormal basis, revisited").
    numpy (float64), or a torch tensor (float64, on its device).
    """
    if is_torch(normals):
        import torch as xp

        n = normals.to(xp.float64)
    else:
        xp, n = np, np.asarray(normals, dtype=np.float64)
    sign = xp.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = xp.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = xp.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return xp.stack([t, bt, n], axis=2)
