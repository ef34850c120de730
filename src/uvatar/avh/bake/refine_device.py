"""The device twin of :func:`.refine.refine_fit` (``BakeConfig.torch_device``; issue 39): the whole
Gauss-Newton loop on torch tensors on one device, without a read-back until its end.

The iteration state (joint rotation vectors, Rh, Th, clothing offsets: float64) stays on the device;
the body is posed there (float32, as the numpy path's posing, then cast to float64; on CUDA in three Warp
launches, :mod:`uvatar.body.pose_warp`, instead of ~90 operators); the nearest scan
samples, the stencil colours, the Huber weights, the normal equations (the dense product of
:func:`.refine_model._normal_equations_reference`, one owner of that math), the damped solve and the
step (:func:`.refine_step.apply_step_torch`: the rotation updates through the twins of SciPy's
``Rotation``; on CUDA one Warp launch, :mod:`.refine_step_warp`) run there too. Rows the numpy path
leaves out (no match, no colour) get weight zero instead, and its
data-dependent stop ("fewer than 3 matches per joint") becomes a masked update: the loop always runs
its full count, a stopped fit no longer moves, and the per-iteration stats are read back once at the
end and cut where the numpy path would have stopped appending them. Constants per body (the
refinement vertices, subtree and region weights) go to the device once (:func:`.refine_model._memo`), the
scan's samples once per scan (:meth:`.register.ScanSurface.samples_torch`).

The nearest samples are one Warp launch per iteration (:func:`.register_torch.nearest_samples`, lanes of
threads per query on CUDA). Without
Warp they use a fixed window per chunk of queries, measured once per scan and device; each call then
checks at its end, in the same read, that no slab outgrew it (else it widens the window and runs
again); on the CPU the slab search with its one read per query.

Its solves are ``torch.linalg.solve_ex``: ``torch.linalg.solve`` checks for a singular matrix on the
host, a synchronisation per solve on CUDA (the damped systems are positive definite; a failed solve
makes no step, counted as a stop).
"""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["refine_fit_on_device", "refinement_steps", "run_steps", "step_in_warp", "STEP_IN_WARP_ON_CPU",
           "pose_in_warp_on", "POSE_IN_WARP_ON_CPU", "POSE_FAILURES", "GRAPH_FAILURES", "GRAPHS_ON_CPU"]


#: take the refinement's steps in one Warp launch on the CPU too (tests); on CUDA it does wherever Warp is
STEP_IN_WARP_ON_CPU = False


def step_in_warp(device) -> bool:
    """Is a refinement step applied by :func:`.refine_step_warp.apply_step_warp` on ``device``? On CUDA
    where Warp is installed (one launch instead of ~110), on the CPU with :data:`STEP_IN_WARP_ON_CPU`."""
    import torch

    from uvatar.geometry.raycast_warp import warp_importable

    return (torch.device(device).type == "cuda" or STEP_IN_WARP_ON_CPU) and warp_importable()


#: pose the refinement's body in Warp on the CPU too (tests); on CUDA it does wherever Warp is
POSE_IN_WARP_ON_CPU = False
#: why posing in Warp failed in this process (the twin poses from then on, the same frame to float32
#: rounding); empty: it never did
POSE_FAILURES: list[str] = []


def pose_in_warp_on(posing) -> bool:
    """Is the body ``posing`` posed by :func:`uvatar.body.pose_warp.pose_in_warp` (three launches instead
    of ~90 operators an iteration)? On CUDA where Warp is installed and the body is anny
    (:func:`~uvatar.body.pose_warp.warp_posing_supported`), on the CPU with :data:`POSE_IN_WARP_ON_CPU`;
    not once it has failed in this process (:data:`POSE_FAILURES`)."""
    from uvatar.body.pose_warp import warp_posing_supported
    from uvatar.geometry.raycast_warp import warp_importable

    return ((posing.device.type == "cuda" or POSE_IN_WARP_ON_CPU) and warp_posing_supported(posing)
            and not POSE_FAILURES and warp_importable())


def _huber_weights(residuals, scale: float):
    """:func:`.refine._huber_weights` of a tensor."""
    return (scale / residuals.abs().clamp(min=1e-12)).clamp(max=1.0)


def _clothing_offsets(residuals, skin, ok, huber: float, steps: int = 3):
    """:func:`.refine._clothing_offsets` of the rows where ``ok`` (N,) (the others weigh zero): (K,)."""
    import torch

    r = torch.where(ok, residuals, 0.0)
    offsets = torch.zeros(skin.shape[1], dtype=skin.dtype, device=skin.device)
    eye = torch.eye(skin.shape[1], dtype=skin.dtype, device=skin.device)
    for _ in range(steps):
        w = torch.where(ok, _huber_weights(r + skin @ offsets, huber), 0.0)
        a = (skin * w[:, None]).T @ skin
        solved, failed = _solve(a + 1e-9 * eye, (skin * w[:, None]).T @ r)
        offsets = torch.where(failed, torch.zeros_like(solved), -solved)
    return offsets


def _solve(a, b):
    """(x with a x = b, failed 0-d bool) without the read-back of ``torch.linalg.solve``, which on CUDA
    synchronises with the host to check for a singular matrix: the check stays on the device (the
    refinement's damped systems are positive definite; a failure makes no step, where numpy raises)."""
    import torch

    x, info = torch.linalg.solve_ex(a, b)
    return x, info != 0


def _nearest(scan, points, max_distance, device):
    """(distance (N,), index (N,), widest slab (0-d)) tensors of each of ``points``' nearest scan
    sample within ``max_distance``: :func:`.register_torch.nearest_samples` (no read-back: the Warp
    kernel, or without Warp the window search once the scan's window is known; on the CPU the slab search).
    ``device`` is the points' own (the tests wrap this function by that signature)."""
    from uvatar.avh.bake.register_torch import nearest_samples

    return nearest_samples(scan, points, max_distance)


def _body_on_device(body, config, device):
    """(refinement vertices (N,) int64, subtree (N, K), region weights (N, K) float64, conditioning
    joints (K,) int64) as tensors on ``device``: once per body, refinement vertex set and device."""
    import torch

    from uvatar.avh.bake.refine_model import _memo, refine_vertices, refinement_weights

    def make():   # the numpy loop's arrays (one owner: refinement_weights), copied to the device once
        arrays = (refine_vertices(body, config), *refinement_weights(body, config), np.asarray(body.conditioning_joints))
        return tuple(torch.as_tensor(np.asarray(a), device=device) for a in arrays)

    return _memo(body, ("on_device", config.max_untracked_weight, config.max_vertices, str(device)), make)


def _pose(posing, rot, rh, th, scale, shape, rows):
    """(vertices (R, 3), normals (R, 3) of the vertices ``rows`` (R,) int64, joint transforms (J, 4, 4))
    float64 tensors on the posing body's device of one posed frame, in float32 as
    :func:`.refine_model._posed`, no copy to the host: three Warp launches
    (:func:`uvatar.body.pose_warp.pose_in_warp`) where :func:`pose_in_warp_on` says so, else its twin
    :meth:`BodyModel.pose` (~90 operators)."""
    import torch

    if pose_in_warp_on(posing):
        from uvatar.body.pose_warp import pose_in_warp

        try:
            return pose_in_warp(posing, rot, rh, th, scale, shape, rows)
        except Exception as exc:  # noqa: BLE001  a kernel that will not build or launch here: the twin poses
            POSE_FAILURES.append(f"{type(exc).__name__}: {exc}")
            log.warning("posing the body in Warp failed (%s: %s); the refinement poses it through torch from "
                        "now on, the same frame to float32 rounding", type(exc).__name__, exc)
    with torch.no_grad():
        out = posing.pose(rot.to(posing.device, torch.float32)[None],
                          Rh=rh.to(posing.device, torch.float32)[None], Th=th.to(posing.device, torch.float32)[None],
                          scale=scale, shape=shape)
    rows = rows.to(posing.device)
    return (out.vertices[0][rows].to(torch.float64), out.normals[0][rows].to(torch.float64),
            out.joint_transforms[0].to(torch.float64))


def _sample_tensors(sample, device):
    """(colour (N, 3), gradient (N, 3, 3), ok (N,)) of a :class:`.refine.PhotoSample` as tensors on
    ``device`` (no copy when they are there already)."""
    import torch

    return tuple(torch.as_tensor(a, device=device) for a in (sample.colour, sample.gradient, sample.ok))


def sample_colours_on_device(body, fit, surface, scan_mesh, config, radius: float, shape, device):
    """(colour (N, 3), gradient (N, 3, 3), ok (N,)) tensors on ``device``: :func:`.refine.sample_colours`
    with the body posed, the rays cast and the texture sampled there, nothing read back."""
    import torch

    from uvatar.avh.bake.photometric import surface_colours
    from uvatar.avh.bake.refine_model import _posing_body, _shape_tensor

    use = _body_on_device(body, config, device)[0]
    posing = _posing_body(body, device)
    dev = posing.device
    shape_t = _shape_tensor(fit, shape)
    v, n, _ = _pose(posing, torch.as_tensor(body.joint_rotvecs_from_fit(fit), dtype=torch.float64, device=dev),
                    torch.as_tensor(np.asarray(fit.Rh, np.float64), device=dev),
                    torch.as_tensor(np.asarray(fit.Th, np.float64), device=dev),
                    torch.tensor([float(fit.scale)], device=dev), shape_t, use)
    v, n = v.to(device), n.to(device)
    return surface_colours(surface, scan_mesh, v, n, radius, config.photometric_max_distance,
                           float(np.cos(np.radians(config.max_normal_angle_deg))), config.photometric_space, device)


#: why a capture of the refinement's iterations failed in this process (they then run eagerly); empty: none did
GRAPH_FAILURES: list[str] = []
_SIDE_STREAMS: dict = {}   # str(device) -> the torch stream the captures record on


#: tests set it to take the graph path on the CPU (with a stand-in capture, or the real one failing there)
GRAPHS_ON_CPU = False


def _graphs(cuda_graph: bool, device) -> bool:
    """Are the middle iterations replayed from a CUDA graph? ``cuda_graph`` on a CUDA device (or anywhere
    with :data:`GRAPHS_ON_CPU`), no capture failed in this process."""
    import torch

    return cuda_graph and (torch.device(device).type == "cuda" or GRAPHS_ON_CPU) and not GRAPH_FAILURES


def _capture(fn, device):
    """A CUDA graph of ``fn()`` (:func:`uvatar.geometry.warp_torch.capture_graph`, on a side stream
    of ``device``), or None when the capture fails (logged once; the process's refinements run eagerly).
    A bake captures four a frame (the geometric refinement and each colour round), each used up before
    the next: they keep torch's caches (no device synchronise, no cache emptied per capture), each in its
    own memory pool (freed with its graph). Sharing one pool across the captures tripped torch's
    allocator on an H200 (``use_count > 0`` asserted in CUDACachingAllocator.cpp, session 13)."""
    import torch

    from uvatar.geometry.warp_torch import capture_graph

    key = str(torch.device(device))
    try:
        if key not in _SIDE_STREAMS:
            _SIDE_STREAMS[key] = torch.cuda.Stream(device=device)
        return capture_graph(fn, _SIDE_STREAMS[key], keep_caches=True)[0]
    except Exception as exc:  # noqa: BLE001  any failure: the eager iterations are the same steps
        GRAPH_FAILURES.append(f"{type(exc).__name__}: {exc}")
        log.warning("--refine-cuda-graph: the pose refinement's CUDA graph capture failed (%s: %s); its "
                    "iterations run eagerly, the same steps", type(exc).__name__, exc)
        return None


def _iterations(iteration, iterations: int, cuda_graph: bool, device):
    """A generator running ``iteration(first, last)`` for the iterations 0 .. ``iterations``, yielding
    after each (so that :mod:`.refine_in_flight` can interleave several refinements). With ``cuda_graph``
    on CUDA (:func:`_graphs`), the middle ones, alike (the same operators on the same tensors, the state
    updated in place, the stats written at a device-side column), replay one CUDA graph captured after
    the first (eager: also the warm-up of every kernel and library handle they use): one launch each
    instead of hundreds. The rays they cast are counted as the captured one's."""
    from uvatar.geometry.raycast import _RAYS

    graph, rays = None, {}
    for it in range(iterations + 1):
        first, last = it == 0, it == iterations
        if first or last or not _graphs(cuda_graph, device):
            iteration(first, last)
            yield
            continue
        if graph is None:
            before = dict(_RAYS)
            graph = _capture(lambda: iteration(False, False), device)
            if graph is None:                  # nothing was cast while it recorded: the counts as they were
                _RAYS.update(before)
                iteration(first, last)
                yield
                continue
            rays = {q: n - before.get(q, 0) for q, n in _RAYS.items()}   # counted while it recorded: this one
        else:
            for q, n in rays.items():
                _RAYS[q] += n
        graph.replay()
        yield


def run_steps(steps):
    """Drive the generator ``steps`` (:func:`refinement_steps`) to its end; its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def refine_fit_on_device(body, fit, scan, config, shape, photo, scan_mesh, start_sample, final_colour_residual,
                         device):
    """:func:`.refine.refine_fit` with ``device`` (its arguments, checked there): the same refined fit
    (BodyFit of numpy arrays) and stats (lists of Python floats, cut where the numpy path stops), from
    one read-back at the end (module doc)."""
    return run_steps(refinement_steps(body, fit, scan, config, shape, photo, scan_mesh, start_sample,
                                      final_colour_residual, device))


def refinement_steps(body, fit, scan, config, shape, photo, scan_mesh, start_sample, final_colour_residual,
                     device, cuda_graph: bool | None = None):
    """:func:`refine_fit_on_device` as a generator: it sets up and runs the first iteration at the first
    ``next()``, one more iteration at each further one (nothing read back in between), and returns the
    (refined fit, stats) from its one read-back. ``cuda_graph``: None = ``config.cuda_graph``."""
    import torch

    from uvatar.avh.bake.photometric import surface_colours
    from uvatar.avh.bake.refine_model import _normal_equations_reference, _posing_body, _shape_tensor
    from uvatar.avh.bake.refine_step import pose_prior_torch
    from uvatar.avh.bake.register_torch import window_outgrown
    from uvatar.capture import BodyFit

    f64 = dict(dtype=torch.float64, device=device)
    use, sub, skin, joints = _body_on_device(body, config, device)
    k = len(joints)
    posing = _posing_body(body, device)
    shape_t = _shape_tensor(fit, shape)   # on the host: the body finds its bind state without a read-back
    scale = torch.tensor([float(fit.scale)], device=posing.device)
    rot = torch.as_tensor(body.joint_rotvecs_from_fit(fit).astype(np.float64), device=device)   # (J, 3)
    rh = torch.as_tensor(np.asarray(fit.Rh, np.float64), device=device)
    th = torch.as_tensor(np.asarray(fit.Th, np.float64), device=device)
    sample_points, sample_normals = scan.samples_torch(device)
    cos_max = float(np.cos(np.radians(config.max_normal_angle_deg)))
    max_angle = float(np.radians(config.max_step_deg))
    iterations = config.iterations
    if photo is not None and config.photometric_iterations is not None:
        iterations = config.photometric_iterations
    if photo is not None:
        reference = torch.as_tensor(np.asarray(photo.reference, np.float64), device=device)
        known = torch.as_tensor(np.asarray(photo.known, bool), device=device)
    n_use = len(use)
    colour_rows = torch.arange(n_use, device=device)[:, None].expand(n_use, 3).reshape(-1)   # (3N,) vertex of each row
    all_rows = torch.arange(n_use, device=device)
    # the iteration state, updated in place (so that a CUDA graph's replays carry it on), and the stats:
    # per iteration (residual mm, matched fraction, reached, colour residual), column ``slot``
    # (own copies: on the CPU torch.as_tensor shares a float64 array's memory, and the state is written to)
    state = SimpleNamespace(rot=rot.clone(), rh=rh.clone(), th=th.clone(), offsets=torch.zeros(skin.shape[1], **f64),
                            running=torch.ones((), dtype=torch.bool, device=device),   # the numpy path goes on
                            widest=torch.zeros((), dtype=torch.int64, device=device), max_distance=None,
                            stats=torch.full((4, iterations + 1), float("nan"), **f64),
                            slot=torch.zeros((), dtype=torch.int64, device=device))

    start_rot = state.rot[joints].clone()   # what the pose prior pulls toward
    if step_in_warp(device):   # chosen once, not per iteration
        from uvatar.avh.bake.refine_step_warp import apply_step_warp as apply_step
    else:
        from uvatar.avh.bake.refine_step import apply_step_torch as apply_step

    def iteration(first: bool, last: bool):
        """One Gauss-Newton iteration from ``state``; the first finds the match distance and the clothing
        offsets (and may start from ``start_sample``), the last only measures."""
        v, n, tr = (a.to(device) for a in _pose(posing, state.rot, state.rh, state.th, scale, shape_t, use))
        if first:
            state.max_distance = config.max_distance * torch.linalg.norm(v.max(0).values - v.min(0).values)
        near, idx, widest = _nearest(scan, v, state.max_distance, device)
        state.widest.copy_(torch.maximum(state.widest, widest))
        m = sample_normals[idx]
        ok = torch.isfinite(near) & ((m * n).sum(1) >= cos_max)
        r = ((v - sample_points[idx]) * m).sum(1)
        count = ok.sum()
        if first:
            state.offsets.copy_(_clothing_offsets(r, skin, ok, config.huber))    # zeros where nothing matched
        r = r + skin @ state.offsets
        row = [torch.where(ok, r.abs(), 0.0).sum() * 1000 / count,   # NaN: none matched
               count.to(torch.float64) / n_use, state.running.to(torch.float64)]
        if photo is not None and not (last and not final_colour_residual):
            if first and start_sample is not None and start_sample.radius == photo.radius:
                colour, grad, seen = _sample_tensors(start_sample, device)
            else:
                colour, grad, seen = surface_colours(scan, scan_mesh, v, n, photo.radius,
                                                     config.photometric_max_distance, cos_max,
                                                     config.photometric_space, device)
            seen = seen & known
            rc = torch.where(seen[:, None], colour - reference, 0.0)     # (N, 3)
            row.append(rc.abs().sum() / (3 * seen.sum()))
        else:
            row.append(torch.full_like(row[0], float("nan")))
        state.stats.index_copy_(1, state.slot[None], torch.stack(row)[:, None])   # column ``slot``: no read-back
        state.slot.add_(1)
        if last:
            return
        running = state.running & (count >= 3 * k)
        centre0 = v.mean(0)
        rows_ok = torch.where(ok, r, 0.0)
        blocks = [(all_rows, torch.where(ok[:, None], m, 0.0),
                   torch.where(ok, _huber_weights(rows_ok, config.huber), 0.0), rows_ok, skin)]
        if photo is not None:
            # one row per (vertex, channel): d colour_c = grad_c . dv; weight zero where unseen
            seen3 = seen[:, None].expand(n_use, 3).reshape(-1)
            rc = rc.reshape(-1)
            wc = torch.where(seen3, config.photometric_weight * _huber_weights(rc, config.photometric_huber), 0.0)
            direction = torch.where(seen[:, None, None], grad, 0.0).reshape(-1, 3)
            blocks.append((colour_rows, direction, wc, rc, None))
        centres = tr[joints, :3, 3]
        a, g = _normal_equations_reference(v, sub, centres, centre0, blocks)
        a = a + torch.diag(config.damping * torch.diagonal(a) + config.prior * count + 1e-12)
        if config.pose_prior > 0:
            a, g = pose_prior_torch(a, g, tr[joints, :3, :3], start_rot, state.rot[joints], config.pose_prior * count)
        step, failed = _solve(a, g)
        step = -step
        running = running & ~failed
        apply_step(state, step, running, tr, joints, centre0, max_angle, k)

    yield from _iterations(iteration, iterations, config.cuda_graph if cuda_graph is None else cuda_graph, device)

    # the one read-back: every stat, the stop flags and the refined state at once
    offset_mean = (skin @ state.offsets).mean() * 1000
    parts = [state.stats.reshape(-1), offset_mean[None], state.widest.to(torch.float64)[None], state.rot.reshape(-1),
             state.rh, state.th]
    host = torch.cat(parts).cpu().numpy()
    cuts = np.cumsum([len(p) for p in parts])[:-1]
    stats_h, off, widest, rot_h, rh_h, th_h = np.split(host, cuts)
    res, mat, kept, col = stats_h.reshape(4, iterations + 1)
    if window_outgrown(scan, device, int(widest[0])):   # a slab was cut short: again, with room for it (rare)
        return (yield from refinement_steps(body, fit, scan, config, shape, photo, scan_mesh, start_sample,
                                            final_colour_residual, device, cuda_graph))
    if photo is not None and not final_colour_residual:
        col = col[:iterations]                           # the last iteration measured no colours
    appended = int(kept.sum())         # the numpy path appends stats at each iteration it reaches
    refined = BodyFit(poses=rot_h.astype(np.float32), Rh=rh_h, Th=th_h, shapes=fit.shapes, scale=fit.scale, id=fit.id)
    stats = {"residual_mm": [float(x) for x in res[:appended]], "matched_fraction": [float(x) for x in mat[:appended]],
             "offset_mm_mean": float(off[0])}
    if photo is not None:
        stats["colour_residual"] = [float(x) for x in col[:appended]]
    return refined, stats
