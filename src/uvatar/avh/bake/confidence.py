"""Confidence map kappa = v * w * delta * nms (AVH §3.2.4).

- v: visibility of the scan at the match: from each face centroid, ``n_rays`` evenly spread
  hemisphere directions around the face normal (the paper: 64, one lattice for every face; the
  bake: 16, each face its own shifted and turned lattice, ``stratified``, whose errors average out
  over the faces around a vertex: within 0.011 of the 64-ray vertex visibility on average, 0.055
  at the 99th percentile, on a 110k-face scan); v_face = fraction of rays that do NOT hit the scan
  again (self-intersection); averaged to vertices, interpolated at the hit's barycentrics.
- w: the same visibility on the registered mesh M^R_t, interpolated to texels.
- delta: inverse normalized match distance, 1 - min(d, clip) / clip with clip = 1/50 of the fit's
  bounding-box diagonal.
- nms: (n . m + 1) / 2 for the normal n of the query on M^R_t and m of the scan at the match.

``face_visibility`` is batched through Embree (occlusion queries, chunked over faces);
``face_visibility_reference`` is its plain per-face twin.
"""

from __future__ import annotations

import numpy as np

from uvatar.devices import to_numpy
from uvatar.geometry import RayCaster, RayCasterConfig, face_normals
from uvatar.geometry.frames import (
    frames_from_normals,  # re-exported: the bake's callers import it here
    is_torch,
)

__all__ = [
    "hemisphere_directions", "face_lattice_params", "frames_from_normals", "face_visibility", "face_visibility_reference",
    "vertex_visibility", "distance_score", "normal_match_score", "confidence",
]


def hemisphere_directions(n: int = 64, shift=0.5, turn=0.0) -> np.ndarray:
    """Unit directions evenly spread over the +Z hemisphere (Fibonacci lattice, equal area).

    (n, 3) for the default scalar ``shift`` (where each of the n equal-area bands is sampled, in
    [0, 1): 0.5 its middle) and ``turn`` (radians about +Z); arrays shift, turn (B,) give (B, n, 3):
    one lattice per row, shifted within its bands and turned (:func:`face_lattice_params`).
    Torch tensors shift and turn give a float64 tensor on their device.
    """
    if is_torch(shift):
        import torch as xp

        i = xp.arange(n, dtype=xp.float64, device=shift.device)
        shift, turn = shift.to(xp.float64)[..., None], xp.as_tensor(turn, device=shift.device).to(xp.float64)[..., None]
    else:
        xp = np
        i = np.arange(n, dtype=np.float64)
        shift = np.asarray(shift, dtype=np.float64)[..., None]
        turn = np.asarray(turn, dtype=np.float64)[..., None]
    z = 1.0 - (i + shift) / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0)) + turn
    rho = xp.sqrt(xp.clip(1.0 - z * z, 0.0, None))
    return xp.stack([rho * xp.cos(phi), rho * xp.sin(phi), z], axis=-1)


# R2 low-discrepancy sequence (Roberts 2018): consecutive faces get well-spread (shift, turn) pairs
_PLASTIC = 1.32471795724474602596


def face_lattice_params(face_index) -> tuple[np.ndarray, np.ndarray]:
    """(shift (K,), turn (K,)) of the stratified visibility lattice of faces ``face_index`` (K,):
    a deterministic function of the face's index in its mesh (so a face gets the same rays whichever
    subset is cast), spread over [0, 1) x [0, 2 pi) by the R2 sequence."""
    if is_torch(face_index):
        import torch as xp

        f = face_index.to(xp.float64)
    else:
        xp, f = np, np.asarray(face_index, dtype=np.float64)
    shift = xp.remainder(0.5 + f / _PLASTIC, 1.0)
    turn = 2.0 * np.pi * xp.remainder(0.5 + f / _PLASTIC ** 2, 1.0)
    return shift, turn


def face_visibility(vertices, faces, caster: RayCaster | None = None, n_rays: int = 64,
                    offset: float = 1e-4, faces_per_batch: int = 16384, which=None,
                    stratified: bool = False, device: str | None = None) -> np.ndarray:
    """Fraction of ``n_rays`` hemisphere rays from each face centroid that escape the mesh.

    vertices (V, 3) metres; faces (F, 3). Rays start ``offset`` metres above the centroid along the
    face normal. 1 = fully visible, 0 = every ray hits the mesh again (inside a fold).
    which: (K,) face indices to compute (default: all). Returns (F,), or (K,) for ``which``.
    stratified: False, every face casts the same Fibonacci lattice (in its own tangent frame); True,
    each face's lattice is shifted within its equal-area bands and turned about the normal by
    :func:`face_lattice_params` (a stratified estimate per face whose errors average out over the
    faces around a vertex: fewer rays per face give the vertex visibility of many more).
    Rays are built in float32 (Embree's precision) and launched as one occlusion batch per
    ``faces_per_batch`` faces. device: a torch device where the rays are built, in one batch, and
    cast (:meth:`RayCaster.any_hit_torch`: on the caster's GPU without a copy), the same formulas
    (:func:`_face_visibility_torch`); None: numpy.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    caster = caster or RayCaster(v, f, RayCasterConfig(precision="float32"))
    index = np.arange(len(f)) if which is None else np.asarray(which, dtype=np.int64)
    if device is not None:
        return _face_visibility_torch(v, f, caster, n_rays, offset, index, stratified, device)
    sel = f[index]
    normals = np.asarray(face_normals(v, sel), dtype=np.float64) if len(sel) else np.zeros((0, 3))
    centroids = (v[sel].mean(axis=1) + offset * normals).astype(np.float32)
    dirs = hemisphere_directions(n_rays).astype(np.float32)
    out = np.empty(len(sel))
    for s in range(0, len(sel), faces_per_batch):
        frames = frames_from_normals(normals[s:s + faces_per_batch]).astype(np.float32)   # (B, 3, 3)
        b = len(frames)
        if stratified:
            local = hemisphere_directions(n_rays, *face_lattice_params(index[s:s + faces_per_batch]))
            d = np.matmul(local.astype(np.float32), frames.transpose(0, 2, 1)).reshape(b * n_rays, 3)
        else:
            d = np.matmul(dirs, frames.transpose(0, 2, 1)).reshape(b * n_rays, 3)        # (B*n, 3)
        o = np.repeat(centroids[s:s + faces_per_batch], n_rays, axis=0)
        blocked = caster.any_hit(o, d).reshape(b, n_rays)
        out[s:s + faces_per_batch] = 1.0 - blocked.mean(axis=1)
    return out


def _face_visibility_torch(v, f, caster, n_rays, offset, index, stratified, device) -> np.ndarray:
    """:func:`face_visibility` of faces ``index`` with its rays built and cast on a torch ``device``."""
    import torch

    sel = f[index]
    if not len(sel):
        return np.zeros(0)
    # the normals and centroids as the numpy path has them (bit for bit: a normal's sign decides its
    # tangent frame, and faces with n_z ~ 0 flip on a last-bit difference); the rays from them on the device
    normals = np.asarray(face_normals(v, sel), dtype=np.float64)
    centroids = torch.as_tensor((v[sel].mean(axis=1) + offset * normals).astype(np.float32), device=device)
    frames = frames_from_normals(torch.as_tensor(normals, device=device)).to(torch.float32)   # (B, 3, 3)
    if stratified:
        local = hemisphere_directions(n_rays, *face_lattice_params(torch.as_tensor(index, device=device)))
    else:
        local = torch.as_tensor(hemisphere_directions(n_rays), device=device)[None]
    d = torch.matmul(local.to(torch.float32), frames.transpose(1, 2)).reshape(-1, 3)  # (B*n, 3)
    o = centroids.repeat_interleave(n_rays, dim=0)
    blocked = caster.any_hit_torch(o, d).reshape(len(sel), n_rays)
    return to_numpy(1.0 - blocked.to(torch.float64).mean(dim=1))


def face_visibility_reference(vertices, faces, caster: RayCaster | None = None, n_rays: int = 64,
                              offset: float = 1e-4, stratified: bool = False) -> np.ndarray:
    """Plain per-face twin of :func:`face_visibility` (one Embree call per face; tests only)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    caster = caster or RayCaster(v, f)
    out = np.empty(len(f))
    for i, tri in enumerate(f):
        e = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
        n = e / np.linalg.norm(e)
        frame = frames_from_normals(n[None])[0]
        if stratified:
            shift, turn = face_lattice_params([i])
            dirs = hemisphere_directions(n_rays, shift[0], turn[0])
        else:
            dirs = hemisphere_directions(n_rays)
        d = dirs @ frame.T
        o = np.repeat((v[tri].mean(0) + offset * n)[None], n_rays, axis=0)
        out[i] = 1.0 - caster.any_hit(o, d).mean()
    return out


def vertex_visibility(vertices, faces, caster: RayCaster | None = None, n_rays: int = 64,
                      offset: float = 1e-4, needed=None, stratified: bool = False,
                      device: str | None = None) -> np.ndarray:
    """(V,) face visibility averaged onto the vertices (plain mean over incident faces; 1 if none).

    needed: optional (V,) bool or vertex indices; only faces touching a needed vertex are ray cast
    (exactly the same values there) and the other vertices get NaN. stratified: see
    :func:`face_visibility`, as is ``device``.
    """
    f = np.asarray(faces, dtype=np.int64)
    nv = len(vertices)
    if needed is None:
        which = None
        fv = face_visibility(vertices, f, caster, n_rays, offset, stratified=stratified, device=device)
        fw = f
    else:
        mask = np.zeros(nv, bool)
        mask[needed] = True
        which = np.flatnonzero(mask[f].any(axis=1))
        fv = face_visibility(vertices, f, caster, n_rays, offset, which=which, stratified=stratified,
                             device=device)
        fw = f[which]
    total = np.bincount(fw.ravel(), weights=np.repeat(fv, 3), minlength=nv)
    count = np.bincount(fw.ravel(), minlength=nv)
    out = np.divide(total, count, out=np.ones(nv), where=count > 0)
    if needed is not None:
        out[~mask] = np.nan
    return out


def distance_score(distance, clip: float) -> np.ndarray:
    """delta = 1 - min(d, clip) / clip in [0, 1]; d (..., ) metres (inf -> 0). numpy, or a torch
    tensor (float64 out)."""
    if is_torch(distance):
        import torch

        d = distance.to(torch.float64).clamp(max=clip)
    else:
        d = np.minimum(np.asarray(distance, dtype=np.float64), clip)
    return 1.0 - d / clip


def normal_match_score(n, m) -> np.ndarray:
    """nms = (n . m + 1) / 2 for unit normals n, m (..., 3): 1 aligned, 0 opposite (numpy or torch)."""
    if is_torch(n):
        return (((n * m).sum(-1) + 1.0) / 2.0).clamp(0.0, 1.0)
    return np.clip(((np.asarray(n) * np.asarray(m)).sum(-1) + 1.0) / 2.0, 0.0, 1.0)


def confidence(v, w, delta, nms) -> np.ndarray:
    """kappa = v * w * delta * nms (all in [0, 1], same shape; numpy or torch)."""
    if is_torch(v):
        return v * w * delta * nms
    return np.asarray(v) * np.asarray(w) * np.asarray(delta) * np.asarray(nms)
