"""Per-frame loss terms of the body fit (torch, batched over frames T; each returns (T,)).

Robust terms use Geman-McClure, ``gmof(r, s) = s^2 r^2 / (s^2 + r^2)`` (metres^2; tends to ``s^2`` for
outliers). Every data term is normalized by its total confidence, so a frame without observations
contributes 0 (the temporal term then carries it).

Scan distance (both directions) is signed along a normal, ``d = (v - p) . n``: d > 0 means the body
lies OUTSIDE the scan surface, which clothing never explains, so it costs fully; the body lying
inside (d < 0) is what clothing looks like (a garment stands off the skin by up to a few cm), so that
side costs only beyond ``inside_tolerance`` and with ``inside_weight``: pulling the body onto the
cloth would inflate the shape by the clothing thickness.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["gmof", "keypoint3d_term", "keypoint2d_term", "signed_scan_cost", "ScanTerm", "MaskTerm",
           "pose_prior_term", "smoothness_term"]


def gmof(r: torch.Tensor, sigma: float) -> torch.Tensor:
    """Geman-McClure of residual magnitudes r (any shape, metres or pixels)."""
    r2 = r * r
    s2 = sigma * sigma
    return s2 * r2 / (s2 + r2)


def _normalized(cost: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """cost, weight (T, ...) -> (T,) weighted mean per frame (0 where the weight sums to 0)."""
    w = weight.reshape(weight.shape[0], -1)
    return (cost.reshape(cost.shape[0], -1) * w).sum(1) / w.sum(1).clamp_min(1e-9)


def keypoint3d_term(pred, obs, conf, weights, sigma: float) -> torch.Tensor:
    """pred, obs (T, K, 3) metres; conf (T, K); weights (K,) -> (T,) robust mean squared error."""
    r = torch.linalg.norm(pred - obs, dim=-1)
    return _normalized(gmof(r, sigma), conf * weights)


def keypoint2d_term(pred, cams, obs, conf, weights, sigma_px: float) -> torch.Tensor:
    """pred (T, K, 3) world; obs (T, C, K, 2) distorted pixels, conf (T, C, K) -> (T,).

    The pixel error is turned into metres at the keypoint's depth (``px * z / f``, z and f not
    differentiated), so its scale matches the 3D terms."""
    from uvatar.fit.projection import project_cameras

    px, z = project_cameras(pred, cams)                       # (T, C, K, 2), (T, C, K)
    f = cams.K[:, 0, 0].reshape(1, -1, 1)
    to_m = (z.detach().clamp_min(0.1) / f)
    r = torch.linalg.norm(px - obs, dim=-1) * to_m
    w = conf * weights * (z.detach() > 0.05)
    return _normalized(gmof(r, sigma_px * float(to_m.mean())), w)


def signed_scan_cost(d, sigma: float, inside_tolerance: float, inside_weight: float):
    """d (...) signed body-minus-scan distance along the normal (metres) -> robust cost (...)."""
    outside = gmof(torch.relu(d), sigma)
    inside = gmof(torch.relu(-d - inside_tolerance), sigma)
    return outside + inside_weight * inside


class ScanTerm:
    """Scan-surface distance both ways with nearest neighbours refreshed on demand (ICP style).

    scans: per frame (points (P, 3), normals (P, 3)) or None; body_vertices: indices (into the posed
    vertices the term is called with) of the body side; scan_samples: scan points per frame (evenly
    strided); max_distance: matches farther than this (m) or with normals more than 60 degrees apart
    are dropped (missing scan parts, fingers the body fit does not track). :meth:`refresh` stores
    the matches as constant tensors, so the loss itself is one batched expression over frames."""

    def __init__(self, scans, body_vertices: np.ndarray, scan_samples: int, max_distance: float,
                 device, dtype=torch.float32):
        from scipy.spatial import cKDTree

        self.frames = [t for t, s in enumerate(scans) if s is not None and len(s[0])]
        self.body_vertices = torch.as_tensor(np.asarray(body_vertices, np.int64), device=device)
        self.max_distance = max_distance
        self.device, self.dtype = device, dtype
        self.trees, self.points, self.normals = [], [], []
        S = scan_samples
        self.sub = np.zeros((len(self.frames), S, 3))
        self.sub_n = np.zeros((len(self.frames), S, 3))
        self.sub_ok = np.zeros((len(self.frames), S), bool)
        for i, t in enumerate(self.frames):
            p, n = (np.asarray(a, np.float64) for a in scans[t])
            self.trees.append(cKDTree(p))
            self.points.append(p)
            self.normals.append(n)
            take = np.linspace(0, len(p) - 1, min(S, len(p))).round().astype(np.int64)
            self.sub[i, : len(take)], self.sub_n[i, : len(take)], self.sub_ok[i, : len(take)] = p[take], n[take], True
        self.frame_index = torch.as_tensor(self.frames, device=device, dtype=torch.int64)
        self.matches = None

    def refresh(self, vertices: torch.Tensor, normals: torch.Tensor) -> None:
        """Nearest neighbours for the current posed body (T, V, 3) (no gradient)."""
        from scipy.spatial import cKDTree

        v = vertices.detach()[:, self.body_vertices].cpu().double().numpy()
        n = normals.detach()[:, self.body_vertices].cpu().double().numpy()
        F, N, S = len(self.frames), v.shape[1], self.sub.shape[1]
        tp, tn, ok_b = np.zeros((F, N, 3)), np.zeros((F, N, 3)), np.zeros((F, N), bool)
        idx_s, ok_s = np.zeros((F, S), np.int64), np.zeros((F, S), bool)
        for i, t in enumerate(self.frames):   # one k-d tree query per frame
            dist, idx = self.trees[i].query(v[t], distance_upper_bound=self.max_distance)
            found = np.isfinite(dist)
            idx = np.where(found, idx, 0)
            tp[i], tn[i] = self.points[i][idx], self.normals[i][idx]
            ok_b[i] = found & ((tn[i] * n[t]).sum(1) > 0.5)
            dist_s, j = cKDTree(v[t]).query(self.sub[i], distance_upper_bound=self.max_distance)
            found = np.isfinite(dist_s) & self.sub_ok[i]
            idx_s[i] = np.where(found, j, 0)
            ok_s[i] = found & ((self.sub_n[i] * n[t][idx_s[i]]).sum(1) > 0.5)

        def t_(a, dtype=None):
            return torch.as_tensor(a, device=self.device, dtype=dtype or self.dtype)
        self.matches = (t_(tp), t_(tn), t_(ok_b), t_(idx_s, torch.int64), t_(ok_s))

    def __call__(self, vertices, normals, sigma: float, inside_tolerance: float, inside_weight: float):
        """(T,) mean robust signed distance, body->scan and scan->body averaged (0 without scan)."""
        tp, tn, ok_b, idx_s, ok_s = self.matches
        vb = vertices[self.frame_index][:, self.body_vertices]                     # (F, N, 3)
        nb = normals[self.frame_index][:, self.body_vertices].detach()
        d_b = ((vb - tp) * tn).sum(-1)
        gather = idx_s[..., None].expand(-1, -1, 3)
        sub = torch.as_tensor(self.sub, device=vb.device, dtype=vb.dtype)
        d_s = ((vb.gather(1, gather) - sub) * nb.gather(1, gather)).sum(-1)
        cost_b = signed_scan_cost(d_b, sigma, inside_tolerance, inside_weight)
        cost_s = signed_scan_cost(d_s, sigma, inside_tolerance, inside_weight)
        per = 0.5 * ((cost_b * ok_b).sum(1) / ok_b.sum(1).clamp_min(1) + (cost_s * ok_s).sum(1) / ok_s.sum(1).clamp_min(1))
        return vertices.new_zeros(vertices.shape[0]).index_add(0, self.frame_index, per)


class MaskTerm:
    """Silhouette, both ways: the projected body must fall inside each camera's person mask, and
    reach the mask's outline.

    masks: per frame, per camera (H, W) bool or None (cameras of different sizes are padded to the
    largest, top-left aligned, so pixel coordinates stay each camera's own). *Inside*: the Euclidean distance transform of
    the mask's outside (pixels; 0 inside), sampled with ``grid_sample`` at the projected vertices.
    *Outline*: ``outline_points`` pixels spread along each mask's outline, each to its nearest
    projected vertex (found without gradient, then measured with it); a body that sits inside the
    mask but short of one side of it is pulled out to that side, which the inside half alone never
    asks. Both in pixels, turned into metres at the vertex depth, Geman-McClure with ``sigma``.
    ``outline_weight`` scales the outline half (0: inside only)."""

    def __init__(self, masks, cams, body_vertices: np.ndarray, device, dtype=torch.float32,
                 outline_points: int = 200, seed: int = 0):
        from scipy.ndimage import binary_erosion, distance_transform_edt

        T, C = len(masks), cams.K.shape[0]
        shapes = np.array([m.shape for frame in masks for m in frame if m is not None])
        H, W = shapes.max(0)
        dt = np.zeros((T, C, H, W), np.float32)
        valid = np.zeros((T, C), np.float32)
        outline = np.zeros((T, C, outline_points, 2), np.float32)
        rng = np.random.default_rng(seed)
        for t, frame in enumerate(masks):
            for c, m in enumerate(frame):
                if m is not None and m.any():
                    m = np.pad(m.astype(bool), ((0, H - m.shape[0]), (0, W - m.shape[1])))
                    dt[t, c] = distance_transform_edt(~m)
                    valid[t, c] = 1.0
                    ys, xs = np.nonzero(m & ~binary_erosion(m))
                    pick = rng.choice(len(xs), outline_points, replace=len(xs) < outline_points)
                    outline[t, c] = np.stack([xs[pick], ys[pick]], 1)
        self.dt = torch.as_tensor(dt, device=device, dtype=dtype).reshape(T * C, 1, H, W)
        self.valid = torch.as_tensor(valid, device=device, dtype=dtype)
        self.outline = torch.as_tensor(outline, device=device, dtype=dtype)
        self.size = (W, H)
        self.cams = cams
        self.body_vertices = torch.as_tensor(body_vertices, device=device)

    def __call__(self, vertices, sigma: float, outline_weight: float = 1.0):
        from uvatar.fit.projection import project_cameras, sample_views

        px, z = project_cameras(vertices[:, self.body_vertices], self.cams)   # (T, C, N, 2)
        d = sample_views(self.dt, px, self.size)[..., 0]                      # (T, C, N) pixels
        f = self.cams.K[:, 0, 0].reshape(1, -1, 1)
        metres = z.detach().clamp_min(0.1) / f                                # (T, C, N) metres per pixel
        inside = _normalized(gmof(d * metres, sigma), self.valid[..., None].expand_as(d))
        if outline_weight <= 0:
            return inside
        return inside + outline_weight * self._outline(px, metres, sigma)

    def _outline(self, px, metres, sigma: float):
        """(T,) Geman-McClure of each outline point's distance to its nearest projected vertex."""
        T, C, B = self.outline.shape[:3]
        with torch.no_grad():
            nearest = torch.cat([torch.cdist(self.outline[t:t + 8], px[t:t + 8]).argmin(-1)
                                 for t in range(0, T, 8)])                    # (T, C, B)
        hit = torch.gather(px, 2, nearest[..., None].expand(T, C, B, 2))
        scale = torch.gather(metres, 2, nearest)
        cost = gmof((hit - self.outline).norm(dim=-1) * scale, sigma)
        return _normalized(cost, self.valid[..., None].expand_as(cost))


def pose_prior_term(rotvecs: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """rotvecs (T, Jc, 3) local axis-angles, weights (Jc,) -> (T,) weighted mean squared angle (rad^2)."""
    return ((rotvecs ** 2).sum(-1) * weights).sum(-1) / weights.sum().clamp_min(1e-9)


def smoothness_term(x: torch.Tensor, continuous: torch.Tensor | None = None,
                    sigma: float | None = None, robust: torch.Tensor | None = None) -> torch.Tensor:
    """x (T, N, 3) per-frame points (or (T, N*3) values) -> (T,) mean squared first difference per
    point, split between the two frames each difference touches (0 for a single frame).
    continuous: (T-1,) 1 where frame t+1 follows frame t in time, 0 at a cut (another take).
    sigma: robust (Geman-McClure) scale of a point's step, metres: a step much larger than it (a fast
    move the keypoints see) costs a bounded amount instead of pulling the frames together; robust:
    (T-1,) bool, the steps it applies to (default all; a frame nothing observes is pulled to its
    neighbours quadratically, whatever the distance)."""
    T = x.shape[0]
    out = x.new_zeros(T)
    if T < 2:
        return out
    step = x[1:] - x[:-1]
    d = step.reshape(T - 1, -1).pow(2).sum(1) / max(1, x[0].numel() // 3)
    if sigma is not None and x.dim() == 3:
        d_robust = gmof(step.norm(dim=-1), sigma).sum(1) / x.shape[1]
        d = d_robust if robust is None else torch.where(robust.to(torch.bool), d_robust, d)
    if continuous is not None:
        d = d * continuous.to(d)
    out = out.index_add(0, torch.arange(T - 1, device=x.device), 0.5 * d)
    return out.index_add(0, torch.arange(1, T, device=x.device), 0.5 * d)
