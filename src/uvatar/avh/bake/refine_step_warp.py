"""The pose refinement's update, a Gauss-Newton step applied to the refined state, in one Warp launch: the
fast twin of :func:`uvatar.avh.bake.refine_step.apply_step_torch` (CPU and CUDA, float64).

Each joint's rotation step is capped, turned into the joint's frame and composed with its rotation; the
root's step is composed with the fit's ``Rh`` and turns ``Th`` about the body's centre, which then moves by
the translation step; the clothing offsets take theirs; all only while the refinement is ``running``. The
torch twin is ~110 small operators an iteration (quaternions through SciPy's formulas, their Taylor series
below 1e-3 rad); a bake's frame runs ~43 iterations with its colour rounds, and on a GPU each operator is
a launch (issue 39). The same formulas here in float64: the twin's numbers to rounding (tested).
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["apply_step_warp"]


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def rotvec_quat(r: wp.vec3d):
        """(x, y, z, w) of a rotation vector: :func:`.refine_step.rotvec_quaternions`."""
        angle = wp.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        a2 = angle * angle
        scale = wp.sin(angle / wp.float64(2.0)) / wp.max(angle, wp.float64(1.0e-300))
        if angle <= wp.float64(1.0e-3):
            scale = wp.float64(0.5) - a2 / wp.float64(48.0) + a2 * a2 / wp.float64(3840.0)
        return wp.vec4d(scale * r[0], scale * r[1], scale * r[2], wp.cos(angle / wp.float64(2.0)))

    @wp.func
    def quat_rotvec(q: wp.vec4d):
        """The rotation vector of a unit quaternion: :func:`.refine_step.quaternion_rotvecs`."""
        s = wp.float64(1.0)
        if q[3] < wp.float64(0.0):
            s = wp.float64(-1.0)
        x = s * q[0]
        y = s * q[1]
        z = s * q[2]
        w = s * q[3]
        angle = wp.float64(2.0) * wp.atan2(wp.sqrt(x * x + y * y + z * z), w)
        a2 = angle * angle
        scale = angle / wp.max(wp.sin(angle / wp.float64(2.0)), wp.float64(1.0e-300))
        if angle <= wp.float64(1.0e-3):
            scale = wp.float64(2.0) + a2 / wp.float64(12.0) + wp.float64(7.0) * a2 * a2 / wp.float64(2880.0)
        return wp.vec3d(scale * x, scale * y, scale * z)

    @wp.func
    def compose(a: wp.vec3d, b: wp.vec3d):
        """R(a) R(b) as a rotation vector (b first): :func:`.refine_step.compose_rotvecs`."""
        p = rotvec_quat(a)
        q = rotvec_quat(b)
        pv = wp.vec3d(p[0], p[1], p[2])
        qv = wp.vec3d(q[0], q[1], q[2])
        v = p[3] * qv + q[3] * pv + wp.cross(pv, qv)
        return quat_rotvec(wp.vec4d(v[0], v[1], v[2], p[3] * q[3] - wp.dot(pv, qv)))

    @wp.func
    def capped(s: wp.vec3d, max_angle: wp.float64):
        """:func:`.refine_step.rotation_step` of one row."""
        angle = wp.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
        return s * wp.min(max_angle / wp.max(angle, wp.float64(1.0e-12)), wp.float64(1.0))

    @wp.func
    def row(step: wp.array(dtype=wp.float64), i: int):
        return wp.vec3d(step[i], step[i + 1], step[i + 2])

    @wp.kernel
    def apply_step(step: wp.array(dtype=wp.float64), running: wp.array(dtype=wp.bool), joints: wp.array(dtype=wp.int64),
                   tr: wp.array3d(dtype=wp.float64), centre: wp.array(dtype=wp.vec3d), max_angle: wp.float64, k: int,
                   rot: wp.array(dtype=wp.vec3d), rh: wp.array(dtype=wp.vec3d), th: wp.array(dtype=wp.vec3d),
                   offsets: wp.array(dtype=wp.float64)):
        t = wp.tid()
        if not running[0]:
            return
        if t < k:                             # a joint: R_j <- R_j R(F_j^T d_j), F_j its frame's unit columns
            j = int(joints[t])
            d = capped(row(step, 3 * t), max_angle)
            local = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
            for c in range(3):
                norm = wp.sqrt(tr[j, 0, c] * tr[j, 0, c] + tr[j, 1, c] * tr[j, 1, c] + tr[j, 2, c] * tr[j, 2, c])
                local[c] = (tr[j, 0, c] * d[0] + tr[j, 1, c] * d[1] + tr[j, 2, c] * d[2]) / norm
            rot[j] = compose(rot[j], local)
        if t == k:                            # the root: Rh <- R(d) Rh, Th turned about the centre, then moved
            d = capped(row(step, 3 * k), max_angle)
            q = rotvec_quat(d)
            u = wp.vec3d(q[0], q[1], q[2])
            p = th[0] - centre[0]
            uv = wp.cross(u, p)
            th[0] = p + wp.float64(2.0) * q[3] * uv + wp.float64(2.0) * wp.cross(u, uv) + centre[0] + row(step, 3 * k + 3)
            rh[0] = compose(d, rh[0])
        if t < offsets.shape[0]:
            offsets[t] = offsets[t] + step[3 * k + 6 + t]

    return apply_step


def apply_step_warp(state, step, running, tr, joints, centre, max_angle: float, k: int) -> None:
    """:func:`.refine_step.apply_step_torch` in one launch: ``state`` (rot (J, 3), rh (3,), th (3,),
    offsets (K,), running (0-d bool): float64 tensors, updated in place), ``step`` (3k + 6 + K,) float64,
    ``running`` (0-d bool: this step is taken), ``tr`` (J, 4, 4) the posed joints' transforms, ``joints``
    (k,) int64 the refined joints, ``centre`` (3,) the posed body's centre (metres), ``max_angle``
    (radians). On torch's current stream; nothing read back."""
    import torch

    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    dev = step.device
    tr = tr.to(torch.float64).contiguous()
    go = running.reshape(1)
    joints = joints.to(torch.int64).contiguous()
    centre = centre.reshape(1, 3).to(torch.float64).contiguous()
    dim = max(k + 1, state.offsets.shape[0])
    wp.launch(_kernel(), dim=dim,
              inputs=[warp_view(wp, step.contiguous()), warp_view(wp, go), warp_view(wp, joints), warp_view(wp, tr),
                      warp_view(wp, centre, wp.vec3d), float(max_angle), int(k),
                      warp_view(wp, state.rot, wp.vec3d), warp_view(wp, state.rh.reshape(1, 3), wp.vec3d),
                      warp_view(wp, state.th.reshape(1, 3), wp.vec3d), warp_view(wp, state.offsets)],
              device=wp.device_from_torch(dev), stream=launch_stream(dev))
    state.running.copy_(running)
