"""Bystanders in the synthetic studio (``uvatar synth --bystanders N``): more people in the images.

Each bystander is the body model with its own shape (drawn in [0.25, 0.75] per anny shape
parameter), its own clothes (:class:`~uvatar.capture.synth.appearance.AppearanceConfig` with other
colours, as vertex colours) and its own motion (the synthetic takes drawn with another seed), walking
a circle of ``BYSTANDER_RADIUS`` around the subject's mean position (half a turn over the capture,
bystanders spread evenly on it), so that it passes between the subject and some cameras. It is not
scanned and has no fit: the ground truth, the scans and ``masks/`` stay the subject's alone (the mask
is the subject's *visible* pixels: a bystander in front of it hides it). Each bystander's motion and
shape go to ``gt/bystanders.npz``; the pixels where any bystander is seen go to
``gt/bystander_masks/<cam>/<frame>.png`` (for the tests: no bystander pixel in a subject mask).

The hard case (``bystander_path="cross"``, issue 41: a real take where the fit jumped to the other
person): each bystander has nearly the subject's build (shape within ``CROSS_SHAPE_SPREAD`` of it per
parameter, so the same height), walks in from 1.5 m to the side, crosses in front of the subject
(+Z, camera 00's side) at ``CROSS_GAP`` from it, stays that close while going round its side, passes
behind it and walks off (:data:`CROSS_PATH`, relative to the subject's position; bystanders after
the first mirrored left/right and delayed). The subject's takes are joined into one continuous
walk for this scene (:func:`one_take_floor_path`: no floor jump between takes, as in a real take). With
``bystander_look="subject"`` they wear the subject's clothes colours.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["plan_bystanders", "render_with_bystanders", "BYSTANDER_RADIUS", "CROSS_PATH", "CROSS_GAP", "cross_offsets",
           "one_take_floor_path"]

BYSTANDER_RADIUS = 1.1  # metres from the subject's mean position
CROSS_GAP = 0.42        # metres between the two people's roots while the bystander is close
CROSS_SHAPE_SPREAD = 0.04   # a crossing bystander's shape parameters lie this close to the subject's
# (fraction of the capture, x, z): the crossing bystander's floor offset from the subject (metres);
# in between, points at CROSS_GAP are interpolated along the circle around the subject
CROSS_PATH = ((0.0, -1.5, 0.45), (0.2, -0.40, CROSS_GAP), (0.3, 0.0, CROSS_GAP), (0.55, CROSS_GAP, 0.0),
              (0.8, 0.0, -CROSS_GAP), (1.0, -1.3, -0.5))

_CLOTHES = (  # (shirt, shirt band, jeans, hair): one outfit per bystander, cycled
    ((0.15, 0.45, 0.20), (0.90, 0.90, 0.85), (0.30, 0.30, 0.32), (0.05, 0.04, 0.03)),
    ((0.85, 0.75, 0.20), (0.20, 0.20, 0.60), (0.55, 0.45, 0.30), (0.60, 0.45, 0.25)),
    ((0.40, 0.20, 0.55), (0.10, 0.10, 0.10), (0.12, 0.12, 0.14), (0.35, 0.33, 0.30)),
)


def cross_offsets(n: int, mirror: bool = False, delay: float = 0.0) -> np.ndarray:
    """(n, 2) floor offsets (x, z) metres of a crossing bystander from the subject, frame by frame
    (:data:`CROSS_PATH`; close stretches follow the circle of radius ``CROSS_GAP``); ``mirror``: left
    and right swapped; ``delay``: the path starts this fraction of the capture later."""
    s = np.clip((np.arange(n) / max(n - 1, 1)) - delay, 0.0, 1.0)
    keys = np.array(CROSS_PATH, np.float64)
    xz = np.stack([np.interp(s, keys[:, 0], keys[:, 1]), np.interp(s, keys[:, 0], keys[:, 2])], 1)
    close = (s >= keys[1, 0]) & (s <= keys[-2, 0])   # on the circle around the subject: exactly CROSS_GAP
    xz[close] *= CROSS_GAP / np.maximum(np.linalg.norm(xz[close], axis=1, keepdims=True), 1e-9)
    if mirror:
        xz[:, 0] = -xz[:, 0]
    return xz


def one_take_floor_path(Th: np.ndarray, take_of_frame: np.ndarray) -> np.ndarray:
    """(N, 3) the subject's ``Th`` with its floor jumps between takes taken out (each take continues
    where the previous one ended, the whole path re-centred on the first one's mean): the crossing
    scene is one continuous take, as a real recording is. Th[:, 1] (height above the floor) is kept."""
    Th = np.asarray(Th, np.float64)
    step = np.diff(Th[:, [0, 2]], axis=0)
    step[np.diff(np.asarray(take_of_frame)) != 0] = 0.0
    xz = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    out = Th.copy()
    out[:, [0, 2]] = xz - xz.mean(0) + Th[:, [0, 2]].mean(0)
    return out.astype(np.float32)


def plan_bystanders(body, cfg, subject_Th: np.ndarray, subject_shape=None) -> list[dict]:
    """``cfg.bystanders`` bystanders for the plan (picklable): shape (S,), poses (N, J, 3), Rh (N, 3),
    Th (N, 3) for the N frames of the capture; a function of ``cfg.seed`` (and, for the crossing
    path, the subject's shape (S,) and motion, already :func:`one_take_floor_path`) only."""
    from uvatar.capture.synth.motion import make_takes

    n = len(subject_Th)
    centre = np.asarray(subject_Th, np.float64).mean(0)
    cross = getattr(cfg, "bystander_path", "circle") == "cross"
    near = np.asarray(subject_Th, np.float64)
    out = []
    for b in range(int(cfg.bystanders)):
        rng = np.random.default_rng([int(cfg.seed), 404, b])
        shape = rng.uniform(0.25, 0.75, body.default_shape().numel()).astype(np.float32)
        if cross:
            base = (np.asarray(subject_shape, np.float32) if subject_shape is not None
                    else body.default_shape().detach().cpu().numpy().astype(np.float32))
            shape = np.clip(base + rng.uniform(-CROSS_SHAPE_SPREAD, CROSS_SHAPE_SPREAD, base.shape), 0, 1)
            shape = shape.astype(np.float32)
        motion = make_takes(body, n, int(cfg.seed) * 1009 + 17 + b, cfg.motion, shape)
        Th = np.asarray(motion.Th, np.float64).copy()
        if cross:
            xz = cross_offsets(n, mirror=bool(b % 2), delay=0.1 * (b // 2))
            Th[:, 0], Th[:, 2] = near[:, 0] + xz[:, 0], near[:, 2] + xz[:, 1]
        else:
            angle = 2 * np.pi * b / cfg.bystanders + rng.uniform(0, 2 * np.pi) + np.pi * np.arange(n) / max(n, 1)
            Th[:, 0] = centre[0] + BYSTANDER_RADIUS * np.sin(angle)
            Th[:, 2] = centre[2] + BYSTANDER_RADIUS * np.cos(angle)
        out.append({"shape": shape, "poses": np.asarray(motion.poses, np.float32), "Rh": np.asarray(motion.Rh),
                    "Th": Th.astype(np.float32)})
    return out


def _looks(studio) -> list[np.ndarray]:
    """(V, 3) vertex colours per bystander outfit (cached on the studio): the outfits of
    ``_CLOTHES``, or with ``bystander_look="subject"`` one outfit, the subject's colours."""
    looks = getattr(studio, "_bystander_looks", None)
    if looks is None:
        import scipy.sparse as sp

        from uvatar.capture.synth import appearance as app
        from uvatar.capture.synth import surface as srf

        t = studio.template
        f = srf.features(sp.identity(t.num_vertices, format="csr"), t.vertices, studio.groups)
        looks = []
        outfits = (_CLOTHES if getattr(studio.cfg, "bystander_look", "own") == "own" else
                   ((studio.cfg.appearance.shirt, studio.cfg.appearance.shirt_band, studio.cfg.appearance.jeans,
                     studio.cfg.appearance.hair),))
        for shirt, band, jeans, hair in outfits:
            cfg = replace(studio.cfg.appearance, shirt=shirt, shirt_band=band, jeans=jeans, hair=hair)
            looks.append(np.asarray(app.albedo(f, studio.landmarks, cfg), np.float32))
        studio._bystander_looks = looks
    return looks


def _posed_bystander(studio, b: dict, i: int) -> np.ndarray:
    import torch

    with torch.no_grad():
        out = studio.body.pose(torch.as_tensor(b["poses"][i][None]), Rh=torch.as_tensor(b["Rh"][i][None]),
                               Th=torch.as_tensor(b["Th"][i][None]), shape=torch.as_tensor(b["shape"]))
    return out.vertices[0].double().cpu().numpy()


def render_with_bystanders(studio, i: int, vertices, faces, uvs, uv_faces, atlas, cameras,
                           background: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """[(rgb (H, W, 3) float32, subject mask (H, W) bool, bystander mask (H, W) bool)] per camera:
    the subject's scan (textured) and every bystander (vertex colours, shaded) composited by depth."""
    from uvatar.geometry.raycast import RayCaster
    from uvatar.render.mesh_renderer import render_mesh

    t = studio.template
    looks = _looks(studio)
    people = studio.plan.get("bystanders") or []
    meshes = [_posed_bystander(studio, b, i) for b in people]
    V = np.concatenate(meshes) if meshes else np.zeros((0, 3))
    F = np.concatenate([t.faces + k * t.num_vertices for k in range(len(meshes))]) if meshes else None
    colours = np.concatenate([looks[k % len(looks)] for k in range(len(meshes))]) if meshes else None
    subject = RayCaster(vertices, faces)
    others = RayCaster(V, F) if meshes else None
    out = []
    for cam in cameras:
        s = render_mesh(vertices, faces, cam, uvs=uvs, uv_faces=uv_faces, texture=atlas,
                        background=background, raycaster=subject)
        rgb, mask_s = np.asarray(s.rgb, np.float32), np.asarray(s.mask, bool)
        mask_b = np.zeros_like(mask_s)
        if others is not None:
            o = render_mesh(V, F, cam, vertex_colors=colours, background=background, shading=True, raycaster=others)
            front = o.mask & (~mask_s | (o.depth < s.depth))
            rgb = np.where(front[..., None], o.rgb, rgb).astype(np.float32)
            mask_s, mask_b = mask_s & ~front, front
        out.append((rgb, mask_s, mask_b))
    return out
