"""Forward kinematics and linear blend skinning shared by the backends (torch, batched).

A rig here is: parent indices, per-joint rest offsets (head of a joint relative to its parent's
head in the parent's *unposed* frame), and per-joint local rotations. The chain is

    F_root = L_root,              p_root = offset_root
    F_c    = F_parent @ L_c,      p_c    = p_parent + F_parent @ offset_c

``F`` (B, J, 3, 3) is each joint frame's world rotation and ``p`` (B, J, 3) its world position.
SMPL fits this directly (offset = J_c - J_parent); anny too, with its reference-pose head offsets.

:func:`forward_kinematics` evaluates the chain one depth level at a time (one batched product per
level); :func:`forward_kinematics_reference` is its plain per-joint twin. :func:`skin` is LBS as one
(sparse CSR or dense) matrix product; :func:`skin_reference` loops over joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["ancestor_matrix", "subtree", "nearest_ancestor", "KinematicLevels", "kinematic_levels", "forward_kinematics", "forward_kinematics_reference",
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
    """Joints grouped by depth. ``levels[k]`` = (joint ids at depth k, index of each one's parent
    within ``levels[k-1]``); depth 0 holds the single root."""

    levels: tuple[tuple[torch.Tensor, torch.Tensor], ...]
    order: torch.Tensor     # (J,) joint ids in depth order
    inverse: torch.Tensor   # (J,) position of each joint in ``order``

    def to(self, device) -> KinematicLevels:
        return KinematicLevels(tuple((a.to(device), b.to(device)) for a, b in self.levels),
                               self.order.to(device), self.inverse.to(device))


def kinematic_levels(parents) -> KinematicLevels:
    """Group joints by depth from parents (J,) (-1 for the single root)."""
    parents = [int(p) for p in np.asarray(parents).reshape(-1)]
    roots = [j for j, p in enumerate(parents) if p < 0]
    if len(roots) != 1:
        raise ValueError(f"expected exactly one root joint, got {roots}")
    children: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    levels, current = [(torch.tensor(roots), torch.zeros(1, dtype=torch.int64))], roots
    while True:
        nxt, parent_pos = [], []
        for pos, j in enumerate(current):
            for c in children[j]:
                nxt.append(c)
                parent_pos.append(pos)
        if not nxt:
            break
        levels.append((torch.tensor(nxt), torch.tensor(parent_pos)))
        current = nxt
    order = torch.cat([ids for ids, _ in levels])
    if len(order) != len(parents):
        raise ValueError("every joint must descend from the root")
    return KinematicLevels(tuple(levels), order, torch.argsort(order))


def forward_kinematics(levels: KinematicLevels, local_rotations: torch.Tensor, offsets: torch.Tensor):
    """Posed joint frames. local_rotations (B, J, 3, 3), offsets (B or 1, J, 3)
    -> (F (B, J, 3, 3) world rotations, p (B, J, 3) world positions)."""
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
