"""The pose refinement's update on torch tensors (:func:`apply_step_torch`), the reference twin of
:mod:`.refine_step_warp` (one Warp launch), and the rotation formulas both follow: SciPy's ``Rotation``,
which the numpy refinement (:mod:`.refine`) calls, written out for float64 tensors on any device
(quaternions (x, y, z, w), their Taylor series below 1e-3 rad). :func:`.refine_device.step_in_warp` says
which of the two a device takes.
"""

from __future__ import annotations

__all__ = ["rotvec_quaternions", "quaternion_rotvecs", "compose_rotvecs", "rotate", "rotation_step",
           "apply_step_torch", "pose_prior_torch"]


def rotvec_quaternions(rotvec):
    """(..., 4) unit quaternions (x, y, z, w) of rotation vectors (..., 3) (radians), float64 tensors:
    SciPy's ``Rotation.from_rotvec`` (its Taylor series below 1e-3 rad)."""
    import torch

    angle = torch.linalg.norm(rotvec, dim=-1, keepdim=True)
    small = angle <= 1e-3
    a2 = angle * angle
    safe = torch.where(small, torch.ones_like(angle), angle)
    scale = torch.where(small, 0.5 - a2 / 48 + a2 * a2 / 3840, torch.sin(safe / 2) / safe)
    return torch.cat([scale * rotvec, torch.cos(angle / 2)], -1)


def quaternion_rotvecs(quat):
    """(..., 3) rotation vectors of unit quaternions (x, y, z, w) (..., 4): SciPy's ``as_rotvec``
    (w made non-negative, angle in [0, pi], its Taylor series below 1e-3 rad)."""
    import torch

    quat = torch.where(quat[..., 3:] < 0, -quat, quat)
    xyz, w = quat[..., :3], quat[..., 3:]
    angle = 2 * torch.atan2(torch.linalg.norm(xyz, dim=-1, keepdim=True), w)
    small = angle <= 1e-3
    a2 = angle * angle
    safe = torch.where(small, torch.ones_like(angle), angle)
    scale = torch.where(small, 2 + a2 / 12 + 7 * a2 * a2 / 2880, safe / torch.sin(safe / 2))
    return scale * xyz


def _quaternion_product(p, q):
    """(..., 4) the rotation q then p (SciPy's ``Rotation(p) * Rotation(q)``), quaternions (x, y, z, w)."""
    import torch

    pv, pw, qv, qw = p[..., :3], p[..., 3:], q[..., :3], q[..., 3:]
    vector = pw * qv + qw * pv + torch.linalg.cross(pv, qv, dim=-1)
    return torch.cat([vector, pw * qw - (pv * qv).sum(-1, keepdim=True)], -1)


def compose_rotvecs(a, b):
    """(..., 3) the rotation vector of ``Rotation.from_rotvec(a) * Rotation.from_rotvec(b)`` (b first,
    then a); a, b (..., 3) float64 tensors (broadcast)."""
    import torch

    a, b = torch.broadcast_tensors(a, b)
    return quaternion_rotvecs(_quaternion_product(rotvec_quaternions(a), rotvec_quaternions(b)))


def rotate(rotvec, points):
    """``Rotation.from_rotvec(rotvec).apply(points)``: points (..., 3) turned by rotvec (3,) or (..., 3)."""
    import torch

    q = rotvec_quaternions(rotvec)
    u, w = q[..., :3], q[..., 3:]
    u, points = torch.broadcast_tensors(u, points)
    uv = torch.linalg.cross(u, points, dim=-1)
    return points + 2 * w * uv + 2 * torch.linalg.cross(u, uv, dim=-1)


def apply_step_torch(state, step, running, tr, joints, centre, max_angle: float, k: int) -> None:
    """Take a Gauss-Newton ``step`` (3k + 6 + K,) float64 where ``running`` (0-d bool): each of the ``k``
    refined ``joints`` (k,) turns by its capped step expressed in its posed frame (``tr`` (J, 4, 4), scale
    dropped), the root's capped step composes with ``state.rh`` and turns ``state.th`` about ``centre``
    (3,), which then moves; the clothing offsets move. ``state`` (rot, rh, th, offsets, running) is updated
    in place. The reference twin of :func:`.refine_step_warp.apply_step_warp` (one launch)."""
    import torch

    d_joint = rotation_step(step[: 3 * k].reshape(k, 3), max_angle)
    d_root = rotation_step(step[3 * k: 3 * k + 3], max_angle)
    frames = tr[joints, :3, :3]
    frames = frames / torch.linalg.norm(frames, dim=1, keepdim=True)               # drop the scale
    local = torch.einsum("kji,kj->ki", frames, d_joint)                             # R_k^T d_k
    turned = compose_rotvecs(torch.cat([state.rot[joints], d_root[None]]), torch.cat([local, state.rh[None]]))
    moved = state.rot.clone()
    moved[joints] = turned[:k]
    state.th.copy_(torch.where(running, rotate(d_root, state.th - centre) + centre + step[3 * k + 3: 3 * k + 6],
                               state.th))
    state.rot.copy_(torch.where(running, moved, state.rot))
    state.rh.copy_(torch.where(running, turned[k], state.rh))
    state.offsets.copy_(torch.where(running, state.offsets + step[3 * k + 6:], state.offsets))
    state.running.copy_(running)


def rotation_step(step, max_angle: float):
    """:func:`.refine._rotation_step` of a tensor (rows of rotation vectors capped at ``max_angle``)."""
    angle = step.norm(dim=-1, keepdim=True)
    return step * (max_angle / angle.clamp(min=1e-12)).clamp(max=1.0)


def pose_prior_torch(a, g, frames, start, now, weight):
    """:func:`.refine._add_pose_prior` on tensors (its reference twin is the numpy one there), returning
    the new ``(a, g)``: ``weight`` (float or 0-d tensor) times each of the k joints' turn away from
    ``start`` (k, 3) local rotation vectors, ``now`` (k, 3), in the world frames ``frames`` (k, 3, 3)."""
    import torch

    k = start.shape[0]
    frames = frames / torch.linalg.norm(frames, dim=1, keepdim=True)
    delta = compose_rotvecs(-start, now)                                              # log(L0^T L)
    pull = weight * torch.einsum("kij,kj->ki", frames, delta).reshape(-1)
    g = torch.cat([g[: 3 * k] + pull, g[3 * k:]])
    on = torch.zeros(a.shape[0], dtype=a.dtype, device=a.device)
    on[: 3 * k] = 1.0
    return a + torch.diag(weight * on), g
