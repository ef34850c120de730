"""Forward kinematics and linear blend skinning shared by the backends (torch, batched).

A rig here is: parent indices, per-joint rest offsets (head of a joint relative to its parent's
head in the parent's *unposed* frame), and per-joint local rotations. The chain is

    F_root = L_root,              p_root = offset_root
    F_c    = F_parent @ L_c,      p_c    = p_parent + F_parent @ offset_c

``F`` (B, J, 3, 3) is each joint frame's world rotation and ``p`` (B, J, 3) its world position.
SMPL fits this directly (offset = J_c - J_parent); anny too, with its reference-pose head offsets.

:func:`forward_kinematics` evaluates the chain by pointer doubling (one batched product per doubling
round: log2 of the depth; few operators) or one depth level at a time (least arithmetic: large CPU
batches); :func:`forward_kinematics_reference` is their plain per-joint twin. :func:`skin` is LBS as one
(sparse CSR or dense) matrix product; :func:`skin_reference` loops over joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["rotvec_to_rotmat", "ancestor_matrix", "subtree", "nearest_ancestor", "KinematicLevels", "kinematic_levels", "forward_kinematics", "forward_kinematics_by_level",
           "forward_kinematics_doubling", "forward_kinematics_reference", "DOUBLING_MAX_ON_CPU", "homogeneous",
           "skinning_transforms", "sparse_weights", "skin", "skin_reference"]


def ancestor_matrix(parents) -> np.ndarray:
    """(J, J) bool: ``anc[j, a]`` is True when ``a`` is ``j`` or one of its ancestors (parents (J,),
    -1 for roots; any joint order). One pass per tree level, not per joint."""
    parents = np.asarray(parents, dtype=np.int64).reshape(-1)
    n = len(parents)
    anc = np.eye(n, dtype=bool)
    cur = np.arange(n)
    for _ in range(n):
        cur = np.where(cur >= 0, parents[np.maximum(cur, 0)], -1)
        if (cur < 0).all():
            break
        ok = cur >= 0
        anc[np.flatnonzero(ok), cur[ok]] = True
    return anc


def subtree(parents, roots, include_roots: bool = True) -> np.ndarray:
    """Sorted joint indices of the subtrees hanging from ``roots`` (an int or a list): the roots
    themselves (unless ``include_roots`` is False) and every joint below them."""
    roots = np.atleast_1d(np.asarray(roots, dtype=np.int64))
    inside = ancestor_matrix(parents)[:, roots].any(1)
    if not include_roots:
        inside[roots] = False
    return np.flatnonzero(inside)


def nearest_ancestor(parents, joints) -> np.ndarray:
    """(J,) for every joint, the position in ``joints`` of its nearest ancestor among them (itself
    included), or -1 when none of ``joints`` is above it."""
    joints = np.asarray(joints, dtype=np.int64).reshape(-1)
    full = ancestor_matrix(parents)
    if joints.size == 0:
        return np.full(len(full), -1, dtype=np.int64)
    anc = full[:, joints]                                     # (J, K): joints[k] is j or above j
    scored = np.where(anc, full.sum(1)[joints][None], 0)      # 1 + depth of each candidate above j
    return np.where(anc.any(1), scored.argmax(1), -1)


@dataclass(frozen=True)
class KinematicLevels:
    """A rig's joints for :func:`forward_kinematics`, both ways:

    - by depth: ``levels[k]`` = (joint ids at depth k, index of each one's parent within
      ``levels[k-1]``); depth 0 holds the single root; ``order`` (J,) the joint ids in depth order and
      ``inverse`` (J,) each joint's position in it;
    - by pointer doubling: ``jumps[r]`` (J,) each joint's ancestor ``2**r`` levels up, or ``J`` (an
      identity transform past the root) where the chain is shorter; ceil(log2(depth + 1)) rounds cover
      every chain (``depth``: the deepest joint's)."""

    levels: tuple[tuple[torch.Tensor, torch.Tensor], ...]
    order: torch.Tensor
    inverse: torch.Tensor
    jumps: tuple[torch.Tensor, ...]
    depth: int

    def to(self, device) -> KinematicLevels:
        return KinematicLevels(tuple((a.to(device), b.to(device)) for a, b in self.levels), self.order.to(device),
                               self.inverse.to(device), tuple(j.to(device) for j in self.jumps), self.depth)


def kinematic_levels(parents) -> KinematicLevels:
    """:class:`KinematicLevels` of parents (J,) (-1 for the single root)."""
    parents = np.asarray(parents, dtype=np.int64).reshape(-1)
    J = len(parents)
    roots = np.flatnonzero(parents < 0).tolist()
    if len(roots) != 1:
        raise ValueError(f"expected exactly one root joint, got {roots}")
    up = np.where(parents < 0, J, parents)
    depth = np.zeros(J, np.int64)
    reach = up.copy()
    for _ in range(J):                        # depth = steps to the root (a cycle never gets there)
        depth += reach < J
        if (reach == J).all():
            break
        reach = np.append(up, J)[reach]
    if (reach < J).any():
        raise ValueError("every joint must descend from the root")
    levels, position = [], np.zeros(J, np.int64)
    for k in range(int(depth.max()) + 1):     # the joints at each depth, ids ascending
        ids = np.flatnonzero(depth == k)
        position[ids] = np.arange(len(ids))
        parent_pos = position[parents[ids]] if k else np.zeros(1, np.int64)
        levels.append((torch.from_numpy(ids), torch.from_numpy(parent_pos)))
    order = torch.cat([ids for ids, _ in levels])
    jumps, jump = [], np.append(up, J)
    for _ in range(int(np.ceil(np.log2(int(depth.max()) + 1)))):
        jumps.append(torch.from_numpy(jump[:J].copy()))
        jump = np.append(jump[jump[:J]], J)
    return KinematicLevels(tuple(levels), order, torch.argsort(order), tuple(jumps), int(depth.max()))


#: on the CPU, batches up to this many joints (B x J) go by doubling: below it the operators' overhead
#: rules (anny, B = 1: 0.12 ms by doubling, 0.40 ms by levels), above it the arithmetic (B = 32: 2.0
#: against 0.85 ms; doubling multiplies every joint each round). Elsewhere always by doubling.
DOUBLING_MAX_ON_CPU = 512


def forward_kinematics(levels: KinematicLevels, local_rotations: torch.Tensor, offsets: torch.Tensor):
    """Posed joint frames. local_rotations (B, J, 3, 3), offsets (B or 1, J, 3)
    -> (F (B, J, 3, 3) world rotations, p (B, J, 3) world positions).

    :func:`forward_kinematics_doubling` off the CPU and for small CPU batches (:data:`DOUBLING_MAX_ON_CPU`),
    else :func:`forward_kinematics_by_level`: the same frames within round-off."""
    B, J = local_rotations.shape[:2]
    if local_rotations.device.type == "cpu" and B * J > DOUBLING_MAX_ON_CPU:
        return forward_kinematics_by_level(levels, local_rotations, offsets)
    return forward_kinematics_doubling(levels, local_rotations, offsets)


def forward_kinematics_by_level(levels: KinematicLevels, local_rotations: torch.Tensor, offsets: torch.Tensor):
    """:func:`forward_kinematics` one depth level at a time: one batched product per level (anny: 17),
    each over that level's joints only (the least arithmetic)."""
    B = local_rotations.shape[0]
    offsets = offsets.expand(B, -1, -1)
    ids, _ = levels.levels[0]
    F_prev = local_rotations[:, ids]
    p_prev = offsets[:, ids]
    Fs, ps = [F_prev], [p_prev]
    for ids, parent_pos in levels.levels[1:]:
        F_par = F_prev[:, parent_pos]
        p_prev = p_prev[:, parent_pos] + (F_par @ offsets[:, ids, :, None])[..., 0]
        F_prev = F_par @ local_rotations[:, ids]
        Fs.append(F_prev)
        ps.append(p_prev)
    F = torch.cat(Fs, 1)[:, levels.inverse]
    p = torch.cat(ps, 1)[:, levels.inverse]
    return F, p


def homogeneous(rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) transforms [R | t; 0 0 0 1] of rotations (..., 3, 3) and translations (..., 3), the
    bottom row made on their device (no host data copied there per call)."""
    bottom = rotations.new_zeros(*rotations.shape[:-2], 1, 4)
    bottom[..., 3] = 1
    return torch.cat([torch.cat([rotations, translations[..., None]], -1), bottom], -2)


def forward_kinematics_doubling(levels: KinematicLevels, local_rotations: torch.Tensor, offsets: torch.Tensor):
    """:func:`forward_kinematics` by pointer doubling: each joint's transform [L | offset] is composed
    with its ancestor's 1, 2, 4, ... levels up (``levels.jumps``), so a chain of depth d takes
    ceil(log2(d + 1)) batched 4 x 4 products over all joints (anny's 17 levels: 5): 20 operators
    instead of ~120 (issue 39: the bake's pose refinement poses the body every iteration, and on a GPU
    each operator is a launch), more arithmetic."""
    B = local_rotations.shape[0]
    T = homogeneous(local_rotations, offsets.expand(B, -1, -1))                          # (B, J, 4, 4)
    past_root = torch.eye(4, dtype=T.dtype, device=T.device).expand(B, 1, 4, 4)
    for jump in levels.jumps:
        T = torch.cat([T, past_root], 1)[:, jump] @ T
    return T[..., :3, :3], T[..., :3, 3]


_GENERATORS: dict = {}   # (dtype, device) -> (3, 9) the cross-product generators, made on a device once


def rotvec_to_rotmat(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle (radians) -> (..., 3, 3) rotation matrices, in a dozen operators: Rodrigues
    ``R = I + a K + b K^2`` with K the cross-product matrix of the rotation vector, ``a = sin t / t`` and
    ``b = (1 - cos t) / t^2 = (sin(t/2) / (t/2))^2 / 2`` through ``torch.sinc`` (exact and differentiable
    at t = 0). The posing's conversion (issue 39: every operator is a launch on a GPU, and the bake
    poses the body each refinement step); ``roma.rotvec_to_rotmat`` (about 40 operators, first order
    below 1e-6 rad) is its reference twin."""
    import math

    key = (rotvec.dtype, rotvec.device)
    if key not in _GENERATORS:      # K = sum_k v_k G_k: the constant goes to the device once, not per call
        g = torch.zeros(3, 3, 3, dtype=rotvec.dtype)
        for k, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):
            g[k, i, j], g[k, j, i] = 1.0, -1.0
        _GENERATORS[key] = g.reshape(3, 9).to(rotvec.device)
    K = (rotvec @ _GENERATORS[key]).unflatten(-1, (3, 3))
    angle = torch.linalg.vector_norm(rotvec, dim=-1)[..., None, None]
    a = torch.sinc(angle / math.pi)
    half = torch.sinc(angle / (2 * math.pi))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a * K + (0.5 * half * half) * (K @ K)


def forward_kinematics_numpy(parents, local_rotations, local_translations) -> tuple[np.ndarray, np.ndarray]:
    """:func:`forward_kinematics` for numpy arrays with any leading dims (float64 throughout).

    parents (J,) with a single root; local_rotations (..., J, 3, 3); local_translations (..., J, 3)
    (the offsets, per item or broadcast) -> (world rotations (..., J, 3, 3), world positions (..., J, 3))."""
    R = np.asarray(local_rotations, np.float64)
    t = np.asarray(local_translations, np.float64)
    J = t.shape[-2]
    R = np.broadcast_to(R, (*R.shape[:-2][:-1], J, 3, 3)) if R.ndim >= 3 else np.broadcast_to(R, (J, 3, 3))
    lead = np.broadcast_shapes(R.shape[:-3], t.shape[:-2])
    R = torch.from_numpy(np.array(np.broadcast_to(R, (*lead, J, 3, 3)).reshape(-1, J, 3, 3)))
    t = torch.from_numpy(np.array(np.broadcast_to(t, (*lead, J, 3)).reshape(-1, J, 3)))
    from uvatar.threads import single_threaded

    with single_threaded():  # many small products: one thread beats a contended pool
        F, p = forward_kinematics(kinematic_levels(parents), R, t)
    return F.numpy().reshape(*lead, J, 3, 3), p.numpy().reshape(*lead, J, 3)


def forward_kinematics_reference(parents, local_rotations: torch.Tensor, offsets: torch.Tensor):
    """Plain twin of :func:`forward_kinematics`: one joint at a time in topological order."""
    parents = [int(p) for p in np.asarray(parents).reshape(-1)]
    B, J = local_rotations.shape[:2]
    offsets = offsets.expand(B, -1, -1)
    F: list[torch.Tensor | None] = [None] * J
    p: list[torch.Tensor | None] = [None] * J
    remaining = list(range(J))
    while remaining:
        for j in list(remaining):
            par = parents[j]
            if par < 0:
                F[j], p[j] = local_rotations[:, j], offsets[:, j]
            elif F[par] is not None:
                F[j] = F[par] @ local_rotations[:, j]
                p[j] = p[par] + (F[par] @ offsets[:, j, :, None])[..., 0]
            else:
                continue
            remaining.remove(j)
    return torch.stack(F, 1), torch.stack(p, 1)


def skinning_transforms(F, p, bind_rotations, bind_heads):
    """Rest-to-posed transforms for LBS: T_c = [F_c Bc | p_c - F_c Bc h_c].

    F (B, J, 3, 3), p (B, J, 3); bind_rotations Bc (B or 1, J, 3, 3) (None: identity) map the bind
    (skinning) frame onto the joint frame at rest; bind_heads h (B or 1, J, 3) joint positions of the
    bind mesh -> (B, J, 3, 4)."""
    rot = F if bind_rotations is None else F @ bind_rotations
    trans = p - (rot @ bind_heads[..., None])[..., 0]
    return torch.cat([rot, trans[..., None]], -1)


def sparse_weights(weights: torch.Tensor) -> torch.Tensor:
    """Dense (V, J) skinning weights -> ``torch.sparse_csr`` without the zeros (for :func:`skin`)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        return weights.to_sparse_csr()


def skin(bind_vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """LBS as one (sparse) matrix product. bind_vertices (B or 1, V, 3); weights (V, J) dense or
    ``torch.sparse_csr`` (several times faster on CPU: a vertex has a few influences); transforms (B, J, 3, 4)
    -> (B, V, 3) (a transposed view; call ``.contiguous()`` if needed)."""
    B, J = transforms.shape[:2]
    V = weights.shape[0]
    blended = (weights @ transforms.permute(1, 0, 2, 3).reshape(J, B * 12)).reshape(V, B, 3, 4)
    v = bind_vertices.transpose(0, 1)  # (V, B or 1, 3)
    out = (blended[..., 3] + blended[..., 0] * v[..., 0:1] + blended[..., 1] * v[..., 1:2]
           + blended[..., 2] * v[..., 2:3])
    return out.transpose(0, 1)


def skin_reference(bind_vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Plain twin of :func:`skin`: transform the mesh by each joint and sum with the weights."""
    B, J = transforms.shape[:2]
    v = bind_vertices.expand(B, -1, -1)
    out = torch.zeros_like(v)
    for j in range(J):
        moved = v @ transforms[:, j, :, :3].transpose(-1, -2) + transforms[:, j, None, :, 3]
        out = out + weights[None, :, j, None] * moved
    return out
