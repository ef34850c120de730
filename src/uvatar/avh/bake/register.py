"""Pairwise non-rigid registration of the shadow mesh M^S_t to the scan S_t -> M^R_t (AVH §3.2.1).

Progressive (coarse to fine) vertex-to-surface registration with Laplacian regularization, after
Morgenstern et al., "Progressive non-rigid registration of temporal mesh sequences" (CVMP 2019).
Each iteration finds, for every shadow vertex, a match on the scan among three candidates — the
hits of rays along +n and -n (Embree) and the closest scan sample (k-d tree over scan vertices and
face centroids) — keeps the nearest candidate whose scan normal is compatible and that lies within
the stage's distance limit, and solves the sparse linear system

    (W + a I + k L^T L) X = W C + a X_prev + k L^T L X_shadow

(L: uniform graph Laplacian; W: 1 for matched vertices). Stage modes: "closest" (ray hits and
closest-point feet; stiff stages of this kind fix tangential fit error), "rays" (ray hits only) and
"normal" (the flexible finish: each vertex moves only along its normal by a Laplacian-smooth scalar
offset h, ``(W + a I + k L^T L) h = W t``, so the clothing layer is followed without tangential
sliding). The connectivity and UVs never change.
All work is vectorized: one sparse factorization per iteration, no per-vertex Python loops.

Which normal a "normal" stage moves along: a garment is a sheet with a bending length of a few
centimetres, so it stands off the body along the body normal averaged over that length, not along
the raw normal, which fans out over small body features (knuckles, shoulder blades, the chest) and
turns by tens of degrees in creases. Moving along the raw normal lands each vertex on the cloth
``offset x sin(angle)`` away from where its own skin point's cloth lies, and the texel rays then
start there. ``RegistrationConfig.normal_smoothing`` (default 3 cm) averages the normals with a
Gaussian over the rest body (:meth:`BodyLayout.normal_smoothing_matrix`; facing sheets are never
mixed). On a 20-frame `uvatar synth` capture at 512^2 (synthetic fits with flat hands), the median
correspondence error over confident texels is 1.50 mm with raw normals, 1.41 / 1.30 / 1.47 mm with
1.5 / 3 / 5 cm, against 1.46 mm without vertex stages on the ablation frames (the studio's garments
use the same physical model, with a 3 cm bending length). Tried and dropped: vector stages against
a Taubin-low-passed scan and closest-point stages (tangential sliding on folds).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from uvatar.avh.bake.config import STAGE_MODES, RegistrationConfig
from uvatar.avh.bake.register_match import match_vertices
from uvatar.avh.bake.register_torch import _torch_ops, nearest_points_torch, sorted_points_torch
from uvatar.devices import to_numpy
from uvatar.geometry import (
    RayCaster,
    RayCasterConfig,
    gaussian_surface_matrix,
    make_caster,
    mesh_normals,
    sample_mesh_texture,
    smoothed_normals,
    vertex_normals,
)
from uvatar.geometry.frames import is_torch

__all__ = ["STAGE_MODES", "ScanSurface", "register_to_scan", "uniform_laplacian_matrix", "match_vertices"]


def _factor_spd(matrix):
    """SuperLU factorization of a symmetric positive definite matrix: symmetric mode, no pivoting,
    minimum-degree ordering of A^T + A (~2.5x faster and 1.5x less fill than the COLAMD default)."""
    return spla.splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})



@dataclass
class ScanSurface:
    """A scan prepared for queries: Embree scene, normals and a k-d tree of dense surface samples.

    vertices (V, 3) float64 metres; faces (F, 3) int64; vertex_normals (V, 3) unit (area weighted);
    face_normals (F, 3) unit; sample_points (V + F, 3) vertices then face centroids, with
    sample_normals (V + F, 3); caster: :class:`uvatar.geometry.RayCaster`; tree: scipy cKDTree over
    sample_points (None until :meth:`kd_tree` builds it); corner_normals (F, 3, 3) the vertex normals at each face's corners (one gather per
    hit in :meth:`normals_at`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_normals: np.ndarray
    sample_points: np.ndarray
    sample_normals: np.ndarray
    caster: RayCaster
    tree: object
    corner_normals: np.ndarray | None = None
    on_device: dict = field(default_factory=dict, repr=False)   # arrays kept on torch devices, by (what, device)

    @classmethod
    def build(cls, vertices, faces, device: str = "cpu", backend: str = "auto") -> ScanSurface:
        """Prepare a scan; its rays run on ``device`` through ``backend`` (:func:`fast_caster`)."""
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        vn, fn = (np.asarray(n, dtype=np.float64) for n in mesh_normals(v, f))
        centroids = (v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3.0
        points = np.concatenate([v, centroids])
        normals = np.concatenate([vn, fn])
        return cls(v, f, vn, fn, points, normals, fast_caster(v, f, device, backend), None, vn[f])

    def kd_tree(self):
        """The k-d tree over the samples (``tree``), built on first use: a bake whose queries run on
        torch (:meth:`nearest_sample` of tensors) never needs it."""
        if self.tree is None:
            from scipy.spatial import cKDTree

            # sliding-midpoint tree: ~3x faster to build than the balanced one, same (exact) answers
            self.tree = cKDTree(self.sample_points, balanced_tree=False, compact_nodes=False)
        return self.tree

    def nearest_sample(self, points, max_distance: float):
        """(distance (N,), index (N,)) of each point's nearest surface sample within ``max_distance``
        (inf and 0 where there is none). points (N, 3): numpy (the k-d tree) or a float64 torch
        tensor, answered on its device by :func:`nearest_points_torch` (the same samples: exact
        distances, ties aside), as tensors."""
        if not is_torch(points):
            near, idx = self.kd_tree().query(points, distance_upper_bound=max_distance)
            found = np.isfinite(near)
            return near, np.where(found, idx, 0)
        return nearest_points_torch(points, self.sorted_samples_torch(points.device), max_distance)

    def _kept(self, name: str, device, make):
        """``make()``, made once per scan and device and kept in ``on_device`` under (name, device)."""
        key = (name, str(device))
        if key not in self.on_device:
            self.on_device[key] = make()
        return self.on_device[key]

    def sorted_samples_torch(self, device):
        """:func:`sorted_points_torch` of the samples on ``device`` (made once per scan and device)."""
        return self._kept("sorted_samples", device, lambda: sorted_points_torch(self.sample_points, device))

    def grid_samples_torch(self, device):
        """:func:`~uvatar.geometry.nearest_warp.grid_points_torch` of the samples on ``device`` (made once
        per scan and device): the layout the nearest-sample kernel searches."""
        from uvatar.geometry.nearest_warp import grid_points_torch

        return self._kept("grid_samples", device, lambda: grid_points_torch(self.sample_points, device))

    def samples_torch(self, device):
        """(sample_points (S, 3), sample_normals (S, 3)) float64 tensors on ``device``, copied there once
        per scan and device (the refinement's matches are gathered from them every iteration)."""
        import torch

        return self._kept("samples", device, lambda: (torch.as_tensor(self.sample_points, device=device),
                                                      torch.as_tensor(self.sample_normals, device=device)))

    def normals_torch(self, device):
        """(corner normals (F, 9): each face's three vertex normals, face normals (F, 3)) float64 tensors
        on ``device``, copied there once per scan and device (:meth:`normals_at`, the stencil kernel)."""
        import torch

        if self.corner_normals is None:
            self.corner_normals = self.vertex_normals[self.faces]
        return self._kept("normals", device, lambda: (torch.as_tensor(self.corner_normals.reshape(-1, 9), device=device),
                                                      torch.as_tensor(self.face_normals, device=device)))

    def texture_torch(self, scan, device):
        """(uvs (U, 2), uv faces (F, 3), texture (H, W, C)) of ``scan`` (this surface's TexturedMesh) as
        tensors on ``device`` in their own dtypes, copied there once per scan and device
        (:func:`scan_colours`, the stencil kernel)."""
        import torch

        return self._kept("texture", device, lambda: tuple(torch.as_tensor(np.asarray(a), device=device)
                                                           for a in (scan.uvs, scan.uv_faces, scan.texture)))

    def normals_at(self, face, bary):
        """Interpolated unit vertex normals at hits (face (N,), bary (N, 3)); zeros where face < 0.
        numpy, or torch tensors (float64 normals on their device: the corner and face normals kept there)."""
        if self.corner_normals is None:
            self.corner_normals = self.vertex_normals[self.faces]
        ok = face >= 0
        if is_torch(face):
            import torch

            corner_normals, face_normals = self.normals_torch(face.device)
            fo = torch.where(ok, face, torch.zeros_like(face))
            corners = corner_normals[fo].reshape(-1, 3, 3)
            n = torch.einsum("kjc,kj->kc", corners, bary.to(torch.float64))
            length = torch.einsum("kc,kc->k", n, n).sqrt()
            # the numpy path's steps below, chosen by torch.where (no read-back of ``bad``)
            bad = ok & (length < 1e-12)  # opposite normals cancelled: use the (unit) face normal
            n = torch.where(bad[:, None], face_normals[fo], n)
            out = n / torch.where(ok & ~bad, length, torch.ones_like(length))[:, None]
            return torch.where(ok[:, None], out, torch.zeros_like(out))
        fo = np.where(ok, face, 0)
        corners = np.take(self.corner_normals.reshape(-1, 9), fo, axis=0).reshape(-1, 3, 3)   # take: ~5x a fancy index
        n = np.einsum("kjc,kj->kc", corners, np.asarray(bary, np.float64))
        length = np.sqrt(np.einsum("kc,kc->k", n, n))
        bad = ok & (length < 1e-12)  # opposite normals cancelled: use the (unit) face normal
        if bad.any():
            n[bad] = self.face_normals[fo[bad]]
            length[bad] = 1.0
        out = n / np.where(ok, length, 1.0)[:, None]
        out[~ok] = 0.0
        return out

    def normals_at_hits(self, hits) -> np.ndarray:
        """:meth:`normals_at` of a :class:`~uvatar.geometry.RayHits`, computed only for the rays that
        hit (the same values; zeros elsewhere)."""
        if is_torch(hits.hit):                 # a GPU computes every ray's: the misses' are zeros anyway
            return self.normals_at(hits.face, hits.bary)
        idx = np.flatnonzero(hits.hit)
        out = np.zeros((len(hits.hit), 3))
        if len(idx) == len(out):
            return self.normals_at(hits.face, hits.bary)
        out[idx] = self.normals_at(hits.face[idx], hits.bary[idx])
        return out


def scan_colours(surface: ScanSurface, scan, face, bary, device: str | None = None) -> np.ndarray:
    """(K, C) the scan's texture at hits (face (K,), bary (K, 3)) by
    :func:`uvatar.geometry.sample_mesh_texture`; on a torch ``device`` when given (the scan's UVs and
    texture kept there with ``surface``, its scan's), the same values: numpy for numpy face and bary,
    a tensor on their device for tensors."""
    tensors = is_torch(face)
    if device is None and not tensors:
        return sample_mesh_texture(scan.uvs, scan.uv_faces, scan.texture, face, bary)
    import torch

    device = face.device if tensors else device
    uvs, uv_faces, texture = surface.texture_torch(scan, device)
    face_t = torch.as_tensor(face, dtype=torch.int64, device=device)
    out = sample_mesh_texture(uvs, uv_faces, texture, face_t, torch.as_tensor(bary, device=device))
    return out if tensors else to_numpy(out)


def fast_caster(vertices, faces, device: str = "cpu", backend: str = "auto") -> RayCaster:
    """Ray caster on the float32 fast path: no float64 ray preparation or re-intersection of hits
    (float32 hits are ~0.1 um at 1 m); RayHits come back in float32. Embree on the CPU, Warp on CUDA
    (:func:`uvatar.geometry.ray_backends.make_caster`)."""
    return make_caster(vertices, faces, RayCasterConfig(refine=False, precision="float32"), device, backend)


def uniform_laplacian_matrix(faces, num_vertices: int) -> sp.csr_matrix:
    """(V, V) uniform graph Laplacian ``I - D^-1 A`` (rows of a vertex minus its neighbours' mean).

    Isolated vertices get a zero row. ``L @ X`` has the units of X.
    """
    f = np.asarray(faces, dtype=np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(num_vertices, num_vertices)).tocsr()
    adj.data[:] = 1.0  # duplicate edges (two faces per edge) count once
    deg = np.asarray(adj.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    lap = sp.diags((deg > 0).astype(np.float64)) - sp.diags(inv) @ adj
    return lap.tocsr()


class _NumpyOps:
    """The registration's linear algebra on numpy / SciPy (the reference): vertex normals, their
    smoothing and the sparse SPD solves (SuperLU)."""

    def __init__(self, faces, num_vertices: int, smoothing, ltl):
        self.faces, self.smoothing, self.ltl = faces, smoothing, ltl

    def array(self, a):
        return np.asarray(a, dtype=np.float64)

    def numpy(self, a) -> np.ndarray:
        return a

    def weights(self, ok):
        """(V,) float64: 1 where matched."""
        return np.asarray(ok, dtype=np.float64)

    def normals(self, x):
        return np.asarray(vertex_normals(x, self.faces), dtype=np.float64)

    def smooth(self, n):
        return smoothed_normals(self.smoothing, n)

    def ltl_times(self, x):
        return self.ltl @ x

    def solve(self, diagonal, k: float, rhs):
        """``(diag(diagonal) + k L^T L) X = rhs``."""
        return _factor_spd(sp.diags(diagonal) + k * self.ltl).solve(rhs)

    def begin(self, scan, x, closest_distance: float) -> None:
        """Nothing to prepare (the torch twin fits the scan's nearest-sample window here)."""

    def match(self, x, n, scan, max_distance: float, cos_max_angle: float, closest_point: bool, epsilon: float):
        """(targets (V, 3), matched (V,) bool): :func:`match_vertices`."""
        return match_vertices(x, n, scan, max_distance, cos_max_angle, closest_point, epsilon)

    def fraction(self, ok) -> float:
        return float(ok.mean())

    def mean_gap_mm(self, gap, ok, last: float) -> float:
        """The mean length (mm) of the matched rows of ``gap`` (V, 3) metres; ``last`` when none matched."""
        if ok.any():
            return float(np.linalg.norm(gap[ok], axis=1).mean() * 1000)
        return last

    def finish(self, scan, x, fractions, last):
        """(vertices (V, 3), matched fractions, last distance, run again?): here as they are."""
        return x, fractions, last, False


def register_to_scan(shadow_vertices, faces, scan: ScanSurface, config: RegistrationConfig | None = None,
                     bbox_diagonal: float | None = None, epsilon: float = 1e-4, smoothing=None,
                     device: str | None = None):
    """Move the shadow mesh onto the scan. Returns (registered vertices (V, 3) float64, stats dict).

    shadow_vertices (V, 3) metres; faces (F, 3) of the body (the registered mesh keeps them and
    the UVs). ``bbox_diagonal`` scales the per-stage distance limits (default: of the shadow mesh).
    stats: ``matched_fraction`` per iteration and ``mean_match_distance_mm`` of the last one.
    ``smoothing``: the (V, V) normal-averaging matrix of "normal" stages (e.g. over the rest body,
    :meth:`BodyLayout.normal_smoothing_matrix`); None builds it on the shadow mesh when
    ``config.normal_smoothing > 0``. device: a torch device for the normals, their smoothing, the
    matches and the solves (:class:`~uvatar.avh.bake.register_torch._TorchOps`,
    :func:`~uvatar.avh.bake.register_torch.match_vertices_torch`; ``BakeConfig.torch_device``): the
    stats stay there and come back with the vertices in one read at the end; None for numpy, SciPy
    and the k-d tree (the reference).
    """
    config = config or RegistrationConfig()
    x0 = np.asarray(shadow_vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if bbox_diagonal is None:
        bbox_diagonal = float(np.linalg.norm(x0.max(0) - x0.min(0)))
    lap = uniform_laplacian_matrix(f, len(x0))
    ltl = (lap.T @ lap).tocsr()
    cos_max = float(np.cos(np.radians(config.max_normal_angle_deg)))
    if smoothing is None and config.normal_smoothing > 0 and "normal" in config.modes:
        smoothing = gaussian_surface_matrix(x0, vertex_normals(x0, f), config.normal_smoothing)
    ops = _NumpyOps(f, len(x0), smoothing, ltl) if device is None else \
        _torch_ops(faces, len(x0), smoothing, ltl, device)
    x = ops.array(x0)
    ltl_x0 = ops.ltl_times(x)
    ops.begin(scan, x, max((d * bbox_diagonal for d, mode in zip(config.max_distance, config.modes, strict=True)
                            if mode == "closest"), default=0.0))
    matched_fraction = []
    last_distance = float("nan")
    for k, iters, dmax, mode in zip(config.stiffness, config.iterations, config.max_distance,
                                    config.modes, strict=True):
        for _ in range(int(iters)):
            n = ops.normals(x)
            if mode == "normal" and smoothing is not None:
                n = ops.smooth(n)
            target, ok = ops.match(x, n, scan, dmax * bbox_diagonal, cos_max, mode == "closest", epsilon)
            matched_fraction.append(ops.fraction(ok))
            w = ops.weights(ok)
            a = config.anchor_weight
            if mode == "normal":
                # scalar offsets h along the current normals, smooth in the Laplacian sense:
                # (W + a I + k L^T L) h = W t, t = signed distance of the match along n
                t = ((target - x) * n).sum(1)
                h = ops.solve(w + a, k, w * t)
                x = x + h[:, None] * n
            else:
                x = ops.solve(w + a, k, w[:, None] * target + a * x + k * ltl_x0)
            last_distance = ops.mean_gap_mm(target - x, ok, last_distance)
    x, matched_fraction, last_distance, again = ops.finish(scan, x, matched_fraction, last_distance)
    if again:   # a nearest-sample slab outgrew the scan's window, widened now: the same call again (rare)
        return register_to_scan(shadow_vertices, faces, scan, config, bbox_diagonal, epsilon, smoothing, device)
    stats = {"matched_fraction": matched_fraction, "mean_match_distance_mm": last_distance}
    if device is not None:
        stats["solver"] = ops.solver
    return x, stats
