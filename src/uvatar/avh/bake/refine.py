"""Articulated fit refinement against the scan: the coarsest stage of the progressive registration.

The paper's fits already include a scan-distance term (AVH §3.1: EasyMocap extended with "the
average 3D distance between the fitted shadow mesh surface and the surface of the scan"). Fits that
lack it, or carry per-joint noise, leave the shadow mesh centimetres off *along* the surface, which
no smooth vertex registration can undo (sliding along a limb is invisible to a surface loss). This
stage therefore first moves the skeleton: the conditioning joints' rotations and the global Rh/Th
minimize a robust point-to-plane distance from the posed shadow vertices to their closest scan
samples (ICP, matches refreshed every iteration), less a clothing thickness per joint region (blended
by the skinning weights and estimated jointly, so the clothing layer does not bias the pose), by
damped Gauss-Newton with the analytic LBS
Jacobian: a world-frame rotation d_k about joint k moves vertex i by ``s_ik d_k x (V_i - c_k)`` with
``s_ik`` the skinning weight of vertex i on k's subtree; it is applied as
``Rot(L_k) <- Rot(L_k) Rot(R_k^T d_k)`` (R_k: joint k's world frame). The clothing thickness starts
from its robust fit at the start pose, so the first pose steps are not spent on it. The refined fit
is what the bake stores, so ``d = x - s`` stays consistent with the stored pose.

Surface sliding *along* itself (a limb turning about its own axis) is invisible to this distance;
with a :class:`~uvatar.avh.bake.photometric.PhotoTarget` the same Gauss-Newton also pulls the scan
colours at the vertices toward their median over frames (one row per vertex and channel, the colour
slope chained with the same LBS Jacobian). :mod:`.refine_together` runs those rounds over a bake.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.avh.bake.config import PoseRefineConfig
from uvatar.avh.bake.refine_model import (
    _memo,
    _posed,
    _shape_tensor,
    refine_vertices,
    refinement_weights,
    region_weights,
    subtree_weights,
    untracked_skin_weight,
)

__all__ = ["PoseRefineConfig", "PhotoSample", "check_refine_inputs", "refine_fit", "refine_vertices", "fit_colours", "sample_colours", "subtree_weights", "region_weights",
           "untracked_skin_weight"]


def _add_pose_prior(a: np.ndarray, g: np.ndarray, frames: np.ndarray, start: np.ndarray, now: np.ndarray,
                    weight: float) -> None:
    """Add ``weight/2 * sum_k |log(L0_k^T L_k)|^2`` (each moved joint's turn away from the start pose, in
    its parent's frame) to the Gauss-Newton system ``(a, g)`` over the world-frame joint steps ``d_k``,
    which turn ``L_k`` into ``L_k exp(R_k^T d_k)``: to first order the deviation becomes
    ``delta_k + R_k^T d_k``, so ``g_k += weight R_k delta_k`` and ``a_kk += weight I``. ``frames`` (K, 3, 3)
    the joints' world frames (scaled; normalised here), ``start``/``now`` (K, 3) local rotation vectors."""
    from scipy.spatial.transform import Rotation

    k = len(start)
    frames = frames / np.linalg.norm(frames, axis=1, keepdims=True)
    delta = (Rotation.from_rotvec(start).inv() * Rotation.from_rotvec(now)).as_rotvec()     # (K, 3)
    g[: 3 * k] += weight * np.einsum("kij,kj->ki", frames, delta).reshape(-1)
    a[np.arange(3 * k), np.arange(3 * k)] += weight


def _rotation_step(step: np.ndarray, max_angle: float) -> np.ndarray:
    angle = np.linalg.norm(step, axis=-1, keepdims=True)
    return step * np.minimum(1.0, max_angle / np.maximum(angle, 1e-12))


@dataclass
class PhotoSample:
    """The blurred scan colours of a frame's refinement vertices at one pose and stencil radius
    (:func:`uvatar.avh.bake.photometric.surface_colours`): colour (N, 3), gradient (N, 3, 3), ok (N,)
    bool where every stencil ray found the scan, radius (metres). A colour round ends with one; the
    next round starts from that pose, so :func:`refine_fit` takes it as its first iteration's colours
    instead of casting the same rays again. With a device (:func:`sample_colours`) the three are
    float64 / bool tensors there, which the next round uses where they are."""

    colour: np.ndarray
    gradient: np.ndarray
    ok: np.ndarray
    radius: float

    @property
    def colours(self) -> np.ndarray:
        """(N, 3) numpy the colours, NaN where the stencil missed the scan (:func:`fit_colours`); read
        back once from the device for a sample of tensors (:func:`sample_colours` with a device)."""
        if not isinstance(self.colour, np.ndarray):
            import torch

            return torch.where(self.ok[:, None], self.colour, float("nan")).cpu().numpy()
        return np.where(self.ok[:, None], self.colour, np.nan)


def sample_colours(body, fit, surface, scan_mesh, config: PoseRefineConfig, radius: float, shape=None,
                   device: str | None = None) -> PhotoSample:
    """:class:`PhotoSample` of the body posed by ``fit`` at stencil ``radius``; with ``device`` posed,
    cast and sampled there and kept there as tensors
    (:func:`.refine_device.sample_colours_on_device`)."""
    from uvatar.avh.bake.photometric import surface_colours

    if device is not None:
        from uvatar.avh.bake.refine_device import sample_colours_on_device

        return PhotoSample(*sample_colours_on_device(body, fit, surface, scan_mesh, config, radius, shape, device),
                           float(radius))
    use = refine_vertices(body, config)
    v, n, _ = _posed(body, body.joint_rotvecs_from_fit(fit), fit.Rh, fit.Th, fit.scale, _shape_tensor(fit, shape))
    colour, grad, ok = surface_colours(surface, scan_mesh, v[use], n[use], radius, config.photometric_max_distance,
                                       float(np.cos(np.radians(config.max_normal_angle_deg))),
                                       config.photometric_space)
    return PhotoSample(colour, grad, ok, float(radius))


def fit_colours(body, fit, surface, scan_mesh, config: PoseRefineConfig, radius: float, shape=None):
    """(N, 3) blurred scan colour at each refinement vertex (:func:`refine_vertices`) of the body posed
    by ``fit``; NaN where the stencil missed the scan. The per-frame input of the cross-frame
    reference (:func:`uvatar.avh.bake.photometric.reference_colours`)."""
    return sample_colours(body, fit, surface, scan_mesh, config, radius, shape).colours


def _huber_weights(residuals, scale: float) -> np.ndarray:
    """IRLS weights of a Huber loss with ``scale``: 1 inside it, ``scale / |r|`` beyond."""
    return np.minimum(1.0, scale / np.maximum(np.abs(residuals), 1e-12))


def _clothing_offsets(residuals, skin, huber: float, steps: int = 3) -> np.ndarray:
    """(K,) clothing thickness per joint region (metres) that best explains point-to-plane
    ``residuals`` (N,) at the start pose, robustly (IRLS Huber): the pose steps then start from a
    consistent layer instead of spending their first updates on it."""
    offsets = np.zeros(skin.shape[1])
    for _ in range(steps):
        rr = residuals + skin @ offsets
        w = _huber_weights(rr, huber)
        a = (skin * w[:, None]).T @ skin
        offsets = -np.linalg.solve(a + 1e-9 * np.eye(len(a)), (skin * w[:, None]).T @ residuals)
    return offsets


def _joint_groups(subtree, min_vertices: int = 128):
    """The refinement vertices grouped by the joints that move them (the nonzero columns of
    ``subtree`` (N, K); a torso vertex has a few, a finger tip a chain): (group of each vertex (N,),
    per group its motion columns in the normal equations (3 per joint, then root rotation and
    translation)). A group of fewer than ``min_vertices`` vertices joins the group whose joints grow
    least by it (a handful of rows is not worth a product of its own)."""
    k = subtree.shape[1]
    patterns, group = np.unique(subtree != 0, axis=0, return_inverse=True)
    group = group.reshape(-1)
    patterns = list(patterns)
    sizes = list(np.bincount(group, minlength=len(patterns)))
    while len(patterns) > 1 and min(sizes) < min_vertices:
        small = int(np.argmin(sizes))
        grow = [np.inf if j == small else (patterns[j] | patterns[small]).sum() * (sizes[j] + sizes[small])
                - patterns[j].sum() * sizes[j] for j in range(len(patterns))]
        into = int(np.argmin(grow))
        patterns[into] = patterns[into] | patterns[small]
        sizes[into] += sizes[small]
        group[group == small] = into
        group[group > small] -= 1
        del patterns[small], sizes[small]
    tail = np.arange(3 * k, 3 * k + 6)
    cols = [np.concatenate([(3 * np.flatnonzero(p)[:, None] + np.arange(3)).ravel(), tail]) for p in patterns]
    return group, cols


def _normal_equations(points, subtree, groups, centres, centre0, blocks):
    """(A, g) of the refinement's Gauss-Newton step, ``A = J^T W J`` and ``g = J^T W r`` over the
    unknowns (3 per joint, root rotation, translation, then one clothing offset per joint region).

    points (N, 3), subtree (N, K) of the refinement vertices; groups: :func:`_joint_groups` of
    ``subtree``; blocks: [(vertex of each row (R,), direction (R, 3), weight (R,), residual (R,),
    clothing-offset columns (R, K) or None)]. Rows are taken a vertex group at a time with only the
    columns that group's joints move (a quarter of them on anny): the products of
    :func:`.refine_model._normal_equations_reference`, without its zeros."""
    group_of, cols = groups
    k = subtree.shape[1]
    motion = 3 * k + 6
    a = np.zeros((motion + k, motion + k))
    g = np.zeros(motion + k)
    cloth = slice(motion, motion + k)
    for vertex, direction, weight, residual, clothing in blocks:
        if not len(vertex):
            continue
        root = np.sqrt(weight)
        wr = weight * residual
        gid = group_of[vertex]
        order = np.argsort(gid, kind="stable")
        bounds = np.searchsorted(gid[order], np.arange(len(cols) + 1))
        for q in np.flatnonzero(np.diff(bounds)):
            rows = order[bounds[q]:bounds[q + 1]]
            joints = cols[q][:-6:3] // 3
            p = points[vertex[rows]]
            d = direction[rows]
            arm = np.cross(p[:, None, :] - centres[joints][None], d[:, None, :])    # (n, J, 3)
            arm *= subtree[vertex[rows]][:, joints, None]
            jac = np.concatenate([arm.reshape(len(rows), -1), np.cross(p - centre0, d), d], axis=1)
            jac_w = jac * root[rows, None]
            c = cols[q]
            a[np.ix_(c, c)] += jac_w.T @ jac_w
            g[c] += jac.T @ wr[rows]
            if clothing is not None:
                coupling = jac_w.T @ (clothing[rows] * root[rows, None])
                a[c, cloth] += coupling
                a[cloth, c] += coupling.T
        if clothing is not None:
            cw = clothing * root[:, None]
            a[cloth, cloth] += cw.T @ cw
            g[cloth] += clothing.T @ wr
    return a, g


def check_refine_inputs(photo, scan_mesh) -> None:
    """:func:`refine_fit`'s check of its arguments: a photometric target needs the textured scan."""
    if photo is not None and scan_mesh is None:
        raise ValueError("refine_fit: a photometric target needs the textured scan (scan_mesh)")


def refine_fit(body, fit, scan, config: PoseRefineConfig | None = None, shape=None, photo=None, scan_mesh=None,
               start_sample: PhotoSample | None = None, final_colour_residual: bool = True,
               device: str | None = None):
    """Refine ``fit`` (BodyFit) toward ``scan`` (:class:`~uvatar.avh.bake.register.ScanSurface`).

    photo: a :class:`~uvatar.avh.bake.photometric.PhotoTarget` (reference colours of the refinement
    vertices) adds the cross-frame colour term, weighted by ``config.photometric_weight`` (squared
    colour error per squared metre of surface distance); it needs ``scan_mesh``, the textured scan.
    Returns (refined BodyFit, stats: mean |point-to-plane residual| in mm per iteration, matched
    fraction, and with ``photo`` the mean |colour - reference| per iteration). Only the body's
    ``conditioning_joints`` and Rh/Th change; shape and scale stay.

    start_sample: the :class:`PhotoSample` of ``fit`` at ``photo.radius`` if the caller has it (the end
    of the previous colour round): the first iteration uses it instead of sampling the scan again
    (the same colours). final_colour_residual: False skips sampling the colours after the last step,
    which only the stats' last ``colour_residual`` would use (the bake's colour rounds).
    device: a torch device (``BakeConfig.torch_device``): the whole loop runs there
    (:func:`.refine_device.refine_fit_on_device`: the posing (:func:`.refine_model._posing_body`), the nearest scan
    samples (:meth:`~uvatar.avh.bake.register.ScanSurface.nearest_sample`), the stencil rays and the
    scan's texture (:func:`.photometric.surface_colours`), the normal equations, the solve and the
    updates) and reads back once at its end, with the same results (within round-off); a start_sample
    may hold tensors there. None: the CPU body, the k-d tree, the grouped numpy products and the numpy
    stencils (the reference).
    """
    from scipy.spatial.transform import Rotation

    from uvatar.avh.bake.photometric import surface_colours
    from uvatar.capture import BodyFit

    config = config or PoseRefineConfig()
    check_refine_inputs(photo, scan_mesh)
    if device is not None:
        from uvatar.avh.bake.refine_device import refine_fit_on_device

        return refine_fit_on_device(body, fit, scan, config, shape, photo, scan_mesh, start_sample,
                                    final_colour_residual, device)
    joints = list(body.conditioning_joints)
    key = (config.max_untracked_weight, config.max_vertices)
    use = refine_vertices(body, config)
    sub, skin = refinement_weights(body, config)    # (N, K) each
    rot = body.joint_rotvecs_from_fit(fit).astype(np.float64)
    rot0 = rot.copy()
    rh = np.asarray(fit.Rh, np.float64).copy()
    th = np.asarray(fit.Th, np.float64).copy()
    shape_t = _shape_tensor(fit, shape)
    cos_max = float(np.cos(np.radians(config.max_normal_angle_deg)))
    max_angle = np.radians(config.max_step_deg)
    k = len(joints)
    groups = _memo(body, ("groups",) + key, lambda: _joint_groups(sub))
    offsets = np.zeros(skin.shape[1])   # clothing thickness per joint region (metres), estimated jointly
    residuals, matched, colour_residuals = [], [], []
    iterations = config.iterations
    if photo is not None and config.photometric_iterations is not None:
        iterations = config.photometric_iterations

    diag = None
    for it in range(iterations + 1):
        v, n, tr = _posed(body, rot, rh, th, fit.scale, shape_t)
        v, n = v[use], n[use]
        if diag is None:
            diag = float(np.linalg.norm(v.max(0) - v.min(0)))
        near, idx = scan.nearest_sample(v, config.max_distance * diag)
        found = np.isfinite(near)
        m = np.take(scan.sample_normals, idx, axis=0)
        ok = found & ((m * n).sum(1) >= cos_max)
        r = ((v - np.take(scan.sample_points, idx, axis=0)) * m).sum(1)
        if it == 0 and ok.any():
            offsets = _clothing_offsets(r[ok], skin[ok], config.huber)
        r = r + skin @ offsets
        residuals.append(float(np.abs(r[ok]).mean() * 1000) if ok.any() else float("nan"))
        matched.append(float(ok.mean()))
        if photo is not None and it == iterations and not final_colour_residual:
            break
        if photo is not None:
            if it == 0 and start_sample is not None and start_sample.radius == photo.radius:
                colour, grad, seen = start_sample.colour, start_sample.gradient, start_sample.ok.copy()
            else:
                colour, grad, seen = surface_colours(scan, scan_mesh, v, n, photo.radius,
                                                     config.photometric_max_distance, cos_max,
                                                     config.photometric_space)
            seen &= photo.known
            rc = (colour - photo.reference)[seen]                                   # (Nc, 3)
            colour_residuals.append(float(np.abs(rc).mean()) if seen.any() else float("nan"))
        if it == iterations or ok.sum() < 3 * k:
            break
        centres = tr[joints, :3, 3]                                                  # (K, 3)
        centre0 = v.mean(0)
        res = r[ok]
        blocks = [(np.flatnonzero(ok), m[ok], _huber_weights(res, config.huber), res, skin[ok])]
        if photo is not None and seen.any():
            # one row per (vertex, channel): d colour_c = grad_c . dv; no clothing-offset column
            rc = rc.reshape(-1)
            wc = config.photometric_weight * _huber_weights(rc, config.photometric_huber)
            blocks.append((np.repeat(np.flatnonzero(seen), 3), grad[seen].reshape(-1, 3), wc, rc, None))
        a, g = _normal_equations(v, sub, groups, centres, centre0, blocks)
        # the prior also holds every other unknown where nothing observes it (a round limb's turn
        # with the colour term off, a tube's slide along its axis): no singular steps
        a += np.diag(config.damping * np.diag(a) + config.prior * int(ok.sum()) + 1e-12)
        if config.pose_prior > 0:
            _add_pose_prior(a, g, tr[joints, :3, :3], rot0[joints], rot[joints], config.pose_prior * int(ok.sum()))
        step = -np.linalg.solve(a, g)
        d_joint = _rotation_step(step[: 3 * k].reshape(k, 3), max_angle)
        d_root = _rotation_step(step[3 * k: 3 * k + 3], max_angle)
        d_trans = step[3 * k + 3: 3 * k + 6]
        offsets += step[3 * k + 6:]
        frames = tr[joints, :3, :3]
        frames = frames / np.linalg.norm(frames, axis=1, keepdims=True)               # drop the scale
        local = np.einsum("kji,kj->ki", frames, d_joint)                             # R_k^T d_k
        rot[joints] = (Rotation.from_rotvec(rot[joints]) * Rotation.from_rotvec(local)).as_rotvec()
        r_delta = Rotation.from_rotvec(d_root)
        rh = (r_delta * Rotation.from_rotvec(rh)).as_rotvec()
        th = r_delta.apply(th - centre0) + centre0 + d_trans
    refined = BodyFit(poses=rot.astype(np.float32).reshape(-1), Rh=rh, Th=th, shapes=fit.shapes,
                      scale=fit.scale, id=fit.id)
    stats = {"residual_mm": residuals, "matched_fraction": matched,
             "offset_mm_mean": float((skin @ offsets).mean() * 1000)}
    if photo is not None:
        stats["colour_residual"] = colour_residuals
    return refined, stats
