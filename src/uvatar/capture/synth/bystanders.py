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
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["plan_bystanders", "render_with_bystanders", "BYSTANDER_RADIUS"]

BYSTANDER_RADIUS = 1.1  # metres from the subject's mean position

_CLOTHES = (  # (shirt, shirt band, jeans, hair): one outfit per bystander, cycled
    ((0.15, 0.45, 0.20), (0.90, 0.90, 0.85), (0.30, 0.30, 0.32), (0.05, 0.04, 0.03)),
    ((0.85, 0.75, 0.20), (0.20, 0.20, 0.60), (0.55, 0.45, 0.30), (0.60, 0.45, 0.25)),
    ((0.40, 0.20, 0.55), (0.10, 0.10, 0.10), (0.12, 0.12, 0.14), (0.35, 0.33, 0.30)),
)


def plan_bystanders(body, cfg, subject_Th: np.ndarray) -> list[dict]:
    """``cfg.bystanders`` bystanders for the plan (picklable): shape (S,), poses (N, J, 3), Rh (N, 3),
    Th (N, 3) for the N frames of the capture; a function of ``cfg.seed`` only."""
    from uvatar.capture.synth.motion import make_takes

    n = len(subject_Th)
    centre = np.asarray(subject_Th, np.float64).mean(0)
    out = []
    for b in range(int(cfg.bystanders)):
        rng = np.random.default_rng([int(cfg.seed), 404, b])
        shape = rng.uniform(0.25, 0.75, body.default_shape().numel()).astype(np.float32)
        motion = make_takes(body, n, int(cfg.seed) * 1009 + 17 + b, cfg.motion, shape)
        angle = 2 * np.pi * b / cfg.bystanders + rng.uniform(0, 2 * np.pi) + np.pi * np.arange(n) / max(n, 1)
        Th = np.asarray(motion.Th, np.float64).copy()
        Th[:, 0] = centre[0] + BYSTANDER_RADIUS * np.sin(angle)
        Th[:, 2] = centre[2] + BYSTANDER_RADIUS * np.cos(angle)
        out.append({"shape": shape, "poses": np.asarray(motion.poses, np.float32), "Rh": np.asarray(motion.Rh),
                    "Th": Th.astype(np.float32)})
    return out


def _looks(studio) -> list[np.ndarray]:
    """(V, 3) vertex colours per bystander outfit (cached on the studio)."""
    looks = getattr(studio, "_bystander_looks", None)
    if looks is None:
        import scipy.sparse as sp

        from uvatar.capture.synth import appearance as app
        from uvatar.capture.synth import surface as srf

        t = studio.template
        f = srf.features(sp.identity(t.num_vertices, format="csr"), t.vertices, studio.groups)
        looks = []
        for shirt, band, jeans, hair in _CLOTHES:
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
