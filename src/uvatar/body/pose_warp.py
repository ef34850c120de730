"""anny posed in three Warp launches: the fast twin of :meth:`uvatar.body.base.BodyModel.pose` for one
frame of an :class:`~uvatar.body.anny_backend.AnnyBody` (CPU and CUDA, float32 as the twin, no autograd).

The bake's pose refinement poses the body at each of its ~43 Gauss-Newton iterations a frame (with its
colour rounds), and the torch twin is ~90 small operators a pose (Rodrigues, kinematics by pointer
doubling, the skinning transforms, the sparse skin, the global transform, the vertex normals), each a
launch on a GPU (issue 39). Here:

1. ``joints`` (a thread a joint): each joint's local rotation (Rodrigues) composed down its chain from the
   root (anny's depth is 17), its skinning transform ``[F B | p - F B h]`` and its posed world transform
   (with ``scale``, ``Rh`` and ``Th``);
2. ``skin`` (a thread a vertex): the vertex's few weights (CSR) blend those transforms, then the global
   transform;
3. ``normals`` (a thread an output row): the area-weighted normal of the row's vertex over its faces
   (vertex-face CSR, a fixed order: no atomics, the same sums every run), and the row's vertex and
   normal in float64.

The rows are any subset of the vertices (the refinement's ~4,000 of 13,718), so the caller needs no
gather. The same frame as the twin to float32 rounding (tested on the CPU: vertices within 1e-6 m).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["warp_posing_supported", "pose_in_warp"]


def warp_posing_supported(body) -> bool:
    """Can :func:`pose_in_warp` pose ``body``? anny (plain linear blend skinning of its bind mesh, no
    pose-dependent shapes); not SMPL/SMPL-X (pose correctives) nor the toy tube."""
    from uvatar.body.anny_backend import AnnyBody

    return isinstance(body, AnnyBody)


@lru_cache(maxsize=1)
def _kernels():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def rodrigues(r: wp.vec3f):
        """:func:`uvatar.body.kinematics.rotvec_to_rotmat`: I + a K + b K^2, a = sin t / t,
        b = (1 - cos t) / t^2 (their series below 1e-4 rad)."""
        t2 = wp.dot(r, r)
        t = wp.sqrt(t2)
        a = wp.float32(1.0) - t2 / wp.float32(6.0)
        b = wp.float32(0.5) - t2 / wp.float32(24.0)
        if t > wp.float32(1.0e-4):
            a = wp.sin(t) / t
            h = wp.sin(t * wp.float32(0.5)) / (t * wp.float32(0.5))
            b = wp.float32(0.5) * h * h
        k = wp.mat33f(wp.float32(0.0), -r[2], r[1], r[2], wp.float32(0.0), -r[0], -r[1], r[0], wp.float32(0.0))
        return wp.identity(n=3, dtype=wp.float32) + a * k + b * (k @ k)

    @wp.kernel
    def joints(rot: wp.array(dtype=wp.vec3d), chain: wp.array2d(dtype=wp.int32), depth: wp.array(dtype=wp.int32),
               offsets: wp.array(dtype=wp.vec3f), bind_rot: wp.array(dtype=wp.mat33f),
               bind_heads: wp.array(dtype=wp.vec3f), to_world: wp.mat33f, rh: wp.array(dtype=wp.vec3d),
               th: wp.array(dtype=wp.vec3d), scale: wp.array(dtype=wp.float32),
               skin_rot: wp.array(dtype=wp.mat33f), skin_t: wp.array(dtype=wp.vec3f),
               world: wp.array3d(dtype=wp.float64)):
        j = wp.tid()
        f = wp.identity(n=3, dtype=wp.float32)
        p = wp.vec3f(wp.float32(0.0), wp.float32(0.0), wp.float32(0.0))
        for d in range(depth[j]):                     # root first: p_c = p + F o_c, F_c = F L_c
            c = chain[j, d]
            p = p + f @ offsets[c]
            f = f @ rodrigues(wp.vec3f(rot[c]))
        fb = f @ bind_rot[j]
        skin_rot[j] = fb
        skin_t[j] = p - fb @ bind_heads[j]
        g = rodrigues(wp.vec3f(rh[0]))
        s = scale[0]
        top = g @ ((to_world @ f) * s)
        t = g @ ((to_world @ p) * s) + wp.vec3f(th[0])
        for a in range(3):
            for b in range(3):
                world[j, a, b] = wp.float64(top[a, b])
            world[j, a, 3] = wp.float64(t[a])
            world[j, 3, a] = wp.float64(0.0)
        world[j, 3, 3] = wp.float64(1.0)

    @wp.kernel
    def skin(bind: wp.array(dtype=wp.vec3f), start: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
             weights: wp.array(dtype=wp.float32), skin_rot: wp.array(dtype=wp.mat33f),
             skin_t: wp.array(dtype=wp.vec3f), to_world: wp.mat33f, rh: wp.array(dtype=wp.vec3d),
             th: wp.array(dtype=wp.vec3d), scale: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec3f)):
        v = wp.tid()
        m = wp.mat33f()
        t = wp.vec3f(wp.float32(0.0), wp.float32(0.0), wp.float32(0.0))
        for e in range(start[v], start[v + 1]):
            w = weights[e]
            m = m + w * skin_rot[cols[e]]
            t = t + w * skin_t[cols[e]]
        x = to_world @ (m @ bind[v] + t)
        out[v] = rodrigues(wp.vec3f(rh[0])) @ (x * scale[0]) + wp.vec3f(th[0])

    @wp.kernel
    def normals(vertices: wp.array(dtype=wp.vec3f), faces: wp.array(dtype=wp.vec3i), start: wp.array(dtype=wp.int32),
                incident: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int64),
                out_v: wp.array(dtype=wp.vec3d), out_n: wp.array(dtype=wp.vec3d)):
        r = wp.tid()
        i = int(rows[r])
        n = wp.vec3f(wp.float32(0.0), wp.float32(0.0), wp.float32(0.0))
        for e in range(start[i], start[i + 1]):
            f = faces[incident[e]]
            a = vertices[f[0]]
            n = n + wp.cross(vertices[f[1]] - a, vertices[f[2]] - a)
        n = n / wp.max(wp.length(n), wp.float32(1.0e-12))
        out_v[r] = wp.vec3d(vertices[i])
        out_n[r] = wp.vec3d(n)

    return joints, skin, normals


def _chains(parents) -> tuple[np.ndarray, np.ndarray]:
    """(chain (J, D) int32: each joint's ancestors from the root down to itself, padded with 0; depth (J,)
    int32: their number), from :func:`uvatar.body.kinematics.ancestor_matrix` (ancestors sorted by their
    own depth)."""
    from uvatar.body.kinematics import ancestor_matrix

    anc = ancestor_matrix(parents)                       # (J, J): a is j or one of its ancestors
    depth = anc.sum(1)
    order = np.argsort(np.where(anc, depth[None, :], len(depth) + 1), axis=1, kind="stable")[:, :depth.max()]
    chain = np.where(np.arange(depth.max())[None, :] < depth[:, None], order, 0)
    return chain.astype(np.int32), depth.astype(np.int32)


class _Rig:
    """One body's constants on its device for the launches: the skinning weights as CSR (the body's own
    ``_weights_csr``), each vertex's faces (:meth:`BodyModel._adjacency`, in face order: the normals' sums
    in a fixed order), the faces, each joint's chain (:func:`_chains`) and anny's axes as a Warp matrix."""

    def __init__(self, body, wp):
        import torch

        dev = body.device
        i32 = lambda x: torch.as_tensor(x).to(device=dev, dtype=torch.int32).contiguous()   # noqa: E731
        weights = body._weights_csr
        adjacency = body._adjacency(weights.shape[0])
        chain, depth = _chains(body._data.parents)
        self.tensors = {"w_start": i32(weights.crow_indices()), "w_cols": i32(weights.col_indices()),
                        "w_values": weights.values().to(torch.float32).contiguous(),
                        "f_start": i32(adjacency.crow_indices()), "f_incident": i32(adjacency.col_indices()),
                        "faces": i32(body._faces_t), "chain": i32(chain), "depth": i32(depth)}
        self.to_world = wp.mat33f(*body._to_world.detach().cpu().reshape(-1).tolist())
        self.num_vertices, self.num_joints = weights.shape


def _rig(body, wp) -> _Rig:
    """The body's :class:`_Rig` on its device, made once per device."""
    cache = body.__dict__.setdefault("_warp_rig_by_device", {})
    key = str(body.device)
    if key not in cache:
        cache[key] = _Rig(body, wp)
    return cache[key]


def pose_in_warp(body, rot, rh, th, scale, shape=None, rows=None):
    """One frame of ``body`` (:func:`warp_posing_supported`) posed on its device: ``rot`` (J, 3) local
    rotation vectors (radians), ``rh`` (3,) and ``th`` (3,) (metres) float64 tensors, ``scale`` (1,) a
    float32 tensor there (other dtypes are converted), ``shape`` as :meth:`BodyModel.pose` takes it (None:
    the default), ``rows`` (R,) int64 vertex indices (None: all) -> (vertices (R, 3), normals (R, 3), joint
    transforms (J, 4, 4)) float64 tensors, posed in float32 as :meth:`BodyModel.pose` (its twin) and
    given in float64; the inputs go to the body's device (no copies where they are already there). On
    torch's current stream; nothing read back (the bind state of a shape given on the host is found in the
    body's cache). No autograd: the inputs are read detached (the refinement's posing needs no gradient)."""
    import torch

    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    joints_k, skin_k, normals_k = _kernels()
    dev = body.device
    rig = _rig(body, wp)
    t = rig.tensors
    state = body._bind_state(shape)
    if rows is None:
        rows = torch.arange(rig.num_vertices, device=dev)
    n_rows, n_joints = rows.shape[0], rig.num_joints
    f32 = dict(dtype=torch.float32, device=dev)
    skin_rot = torch.empty(n_joints, 3, 3, **f32)
    skin_t = torch.empty(n_joints, 3, **f32)
    world = torch.empty(n_joints, 4, 4, dtype=torch.float64, device=dev)
    posed = torch.empty(rig.num_vertices, 3, **f32)
    out_v = torch.empty(n_rows, 3, dtype=torch.float64, device=dev)
    out_n = torch.empty(n_rows, 3, dtype=torch.float64, device=dev)
    to_world = rig.to_world
    view = lambda x, dtype=None: warp_view(wp, x, dtype)   # noqa: E731
    f64 = dict(dtype=torch.float64, device=dev)
    rot_v = view(rot.to(**f64).reshape(n_joints, 3).contiguous(), wp.vec3d)
    rh_v, th_v = view(rh.to(**f64).reshape(1, 3), wp.vec3d), view(th.to(**f64).reshape(1, 3), wp.vec3d)
    scale_v = view(scale.to(**f32).reshape(1))
    launch = dict(device=wp.device_from_torch(dev), stream=launch_stream(dev))
    skin_rot_v, skin_t_v = view(skin_rot, wp.mat33f), view(skin_t, wp.vec3f)
    wp.launch(joints_k, dim=n_joints,
              inputs=[rot_v, view(t["chain"]), view(t["depth"]), view(state["offsets"][0], wp.vec3f),
                      view(state["bind_rotations"][0], wp.mat33f), view(state["bind_heads"][0], wp.vec3f),
                      to_world, rh_v, th_v, scale_v, skin_rot_v, skin_t_v, view(world)], **launch)
    posed_v = view(posed, wp.vec3f)
    wp.launch(skin_k, dim=rig.num_vertices,
              inputs=[view(state["bind_vertices"][0], wp.vec3f), view(t["w_start"]), view(t["w_cols"]),
                      view(t["w_values"]), skin_rot_v, skin_t_v, to_world, rh_v, th_v, scale_v, posed_v], **launch)
    wp.launch(normals_k, dim=n_rows,
              inputs=[posed_v, view(t["faces"], wp.vec3i), view(t["f_start"]), view(t["f_incident"]),
                      view(rows.to(device=dev, dtype=torch.int64)), view(out_v, wp.vec3d), view(out_n, wp.vec3d)], **launch)
    return out_v, out_n, world
