"""What the pose refinement (:mod:`.refine`, and its device twin :mod:`.refine_device`) knows of the
body: the vertices it matches (:func:`refine_vertices`), the skinning weights of each joint's subtree
and region, per-body arrays made once (:func:`_memo`), the body posed for it (:func:`_posed`, on the
device of :func:`_posing_body`), and the Gauss-Newton rows of the LBS Jacobian with their dense normal
equations (:func:`_motion_rows`, :func:`_normal_equations_reference`: numpy arrays or torch tensors,
one owner for both paths)."""

from __future__ import annotations

import weakref

import numpy as np

from uvatar.avh.bake.config import PoseRefineConfig

__all__ = ["subtree_weights", "untracked_skin_weight", "region_weights", "refine_vertices", "refinement_weights"]

_BODY_MEMO: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()   # body -> {key: arrays}, see _memo


def subtree_weights(skin_weights, parents, joints) -> np.ndarray:
    """(V, K) sum of each vertex's skinning weights over the subtree rooted at each of ``joints``."""
    from uvatar.body.kinematics import ancestor_matrix

    anc = ancestor_matrix(parents)
    return np.asarray(skin_weights, dtype=np.float64) @ anc[:, list(joints)].astype(np.float64)


def untracked_skin_weight(skin_weights, joints) -> np.ndarray:
    """(V,) each vertex's skinning weight on joints that are neither the root (moved by Rh/Th) nor
    among ``joints`` (the ones the refinement rotates): the parts a body fit cannot articulate."""
    w = np.asarray(skin_weights, dtype=np.float64)
    moved = np.zeros(w.shape[1], dtype=bool)
    moved[0] = True
    moved[list(joints)] = True
    return w[:, ~moved].sum(1)


def region_weights(skin_weights, parents, joints) -> np.ndarray:
    """(V, K) skinning weights gathered onto ``joints``: every other joint gives its weight to its
    nearest ancestor among ``joints`` (or to the first of ``joints`` if it has none)."""
    from uvatar.body.kinematics import nearest_ancestor

    owner = np.maximum(nearest_ancestor(parents, list(joints)), 0)
    gather = np.zeros((len(owner), len(joints)))
    gather[np.arange(len(owner)), owner] = 1.0
    return np.asarray(skin_weights, dtype=np.float64) @ gather


def _memo(body, key, make):
    """``make()`` once per body model and ``key`` (the refinement's per-body arrays are the same for
    every frame and round of a bake); the entries go with the body."""
    per_body = _BODY_MEMO.setdefault(body, {})
    if key not in per_body:
        per_body[key] = make()
    return per_body[key]


def refine_vertices(body, config: PoseRefineConfig) -> np.ndarray:
    """(N,) int64 the shadow vertices the refinement matches: those the conditioning joints move
    (:func:`untracked_skin_weight` at most ``max_untracked_weight``), evenly thinned to
    ``max_vertices``. The same for every frame, so per-vertex colours compare across frames
    (memoized per body)."""
    key = ("refine_vertices", config.max_untracked_weight, config.max_vertices)
    return _memo(body, key, lambda: _refine_vertices(body, config))


def refinement_weights(body, config: PoseRefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """(subtree (N, K), region (N, K)) float64 skinning weights of the refinement vertices
    (:func:`refine_vertices`) on each conditioning joint's subtree and region (memoized per body): what
    the numpy loop and its device twin both use."""
    key = (config.max_untracked_weight, config.max_vertices)
    tpl, joints = body.template, list(body.conditioning_joints)
    use = refine_vertices(body, config)
    sub = _memo(body, ("subtree",) + key, lambda: subtree_weights(tpl.skin_weights, tpl.joint_parents, joints)[use])
    skin = _memo(body, ("region",) + key, lambda: region_weights(tpl.skin_weights, tpl.joint_parents, joints)[use])
    return sub, skin


def _refine_vertices(body, config: PoseRefineConfig) -> np.ndarray:
    tracked = untracked_skin_weight(body.template.skin_weights, list(body.conditioning_joints))
    candidates = np.flatnonzero(tracked <= config.max_untracked_weight)
    if config.max_vertices is None or config.max_vertices >= len(candidates):
        return candidates
    return candidates[np.linspace(0, len(candidates) - 1, config.max_vertices).round().astype(np.int64)]


def _posed(body, rot, rh, th, scale, shape_t):
    """(vertices (V, 3), normals (V, 3), joint transforms (J, 4, 4)) float64 numpy of one posed frame
    (posed on the body model's device)."""
    import torch

    dev = body.device
    with torch.no_grad():
        out = body.pose(torch.as_tensor(rot, dtype=torch.float32, device=dev)[None],
                        Rh=torch.as_tensor(rh, dtype=torch.float32, device=dev)[None],
                        Th=torch.as_tensor(th, dtype=torch.float32, device=dev)[None],
                        scale=torch.tensor([float(scale)], device=dev),
                        shape=None if shape_t is None else shape_t.to(dev))
    return (out.vertices[0].cpu().numpy().astype(np.float64), out.normals[0].cpu().numpy().astype(np.float64),
            out.joint_transforms[0].cpu().numpy().astype(np.float64))


def _posing_body(body, device: str | None):
    """The body model the refinement poses on ``device``: for a CUDA device, anny's own instance there
    (built once per body; float32 posing on the GPU, within round-off of the CPU's); else ``body``
    (the CPU, and models without a device twin here)."""
    import torch

    if device is None or torch.device(device).type == "cpu" or getattr(body, "name", None) != "anny":
        return body
    return _memo(body, ("posing", str(device)), lambda: _anny_on(body, device))


def _anny_on(body, device):
    """A twin of the AnnyBody ``body`` (its config) on ``device``."""
    from dataclasses import replace

    from uvatar.body.anny_backend import AnnyBody

    return AnnyBody(replace(body.config, device=str(device)))


def _shape_tensor(fit, shape):
    import torch

    if shape is None and np.asarray(fit.shapes).size:
        shape = fit.shapes
    return None if shape is None else torch.as_tensor(np.asarray(shape, np.float32))


def _cross_cat(x):
    """(cross product over the last axis, concatenate along an axis) for numpy arrays or torch tensors."""
    if type(x).__module__.startswith("torch"):
        import torch

        return (lambda a, b: torch.linalg.cross(*torch.broadcast_tensors(a, b), dim=-1)), \
            (lambda xs, axis: torch.cat(xs, dim=axis))
    return np.cross, (lambda xs, axis: np.concatenate(xs, axis=axis))


def _motion_rows(points, directions, subtree, centres, centre0):
    """Jacobian rows of ``directions . dv`` (N rows) for the refinement's unknowns: per joint a
    world rotation d_k (vertex moves ``s_ik d_k x (v - c_k)``), the root rotation about ``centre0``
    and the translation. -> (N, 3K + 6). numpy arrays or torch tensors (all of one kind)."""
    cross, cat = _cross_cat(points)
    arm = cross(points[:, None, :] - centres[None], directions[:, None, :])          # (N, K, 3)
    return cat([(subtree[..., None] * arm).reshape(len(points), -1),
                cross(points - centre0, directions), directions], 1)


def _normal_equations_reference(points, subtree, centres, centre0, blocks):
    """Plain twin of :func:`_normal_equations`: every row over every unknown, one dense product.
    numpy arrays, or torch tensors on one device (:mod:`.refine_device`: one product of every row
    over every unknown suits a GPU better than the CPU path's vertex groups)."""
    k = subtree.shape[1]
    _, cat = _cross_cat(points)
    jacs, weights, residuals = [], [], []
    for vertex, direction, weight, residual, clothing in blocks:
        rows = _motion_rows(points[vertex], direction, subtree[vertex], centres, centre0)
        extra = 0 * rows[:, :k] if clothing is None else clothing
        jacs.append(cat([rows, extra], 1))
        weights.append(weight)
        residuals.append(residual)
    jac, w, r = cat(jacs, 0), cat(weights, 0), cat(residuals, 0)
    jac_w = jac * (w ** 0.5)[:, None]
    return jac_w.T @ jac_w, jac.T @ (w * r)
