"""Bake one frame: shadow mesh -> registration -> texel rays -> texture, displacement, confidence.

Functional core: :func:`bake_frame` takes the posed shadow vertices, the body's UV layout and the
scan (arrays) and returns a :class:`BakedFrame` (arrays). :func:`shadow_vertices` poses the body
model by a fit. Conventions: metres, world axes of the posed frame; UV maps (R, R, C) with row 0 at
v = 1.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from uvatar.avh.bake.confidence import confidence, distance_score, normal_match_score, vertex_visibility
from uvatar.avh.bake.config import BakeConfig
from uvatar.avh.bake.correspond import match_texels
from uvatar.avh.bake.inpaint import grow_mask, inpaint_telea
from uvatar.avh.bake.register import ScanSurface, fast_caster, register_to_scan, scan_colours
from uvatar.devices import on_device, to_device_async, to_numpy
from uvatar.errors import InputError
from uvatar.geometry import (
    UVRaster,
    gaussian_surface_matrix,
    rasterize_uv,
    rays_cast,
    vertex_normals,
)
from uvatar.threads import single_threaded

__all__ = ["BodyLayout", "BakedFrame", "bake_frame", "bake_fit", "shadow_vertices", "preview_image", "check_scan"]


@dataclass
class BodyLayout:
    """The body's mesh and UV layout rasterized at R (shared by every frame).

    faces (F, 3) int64; uvs (U, 2); uv_faces (F, 3); raster: UVRaster at R; texel_flat (M,) flat
    indices of the valid texels; texel_face (M,), texel_bary (M, 3) their triangle and barycentrics;
    rest_vertices (V, 3) the rest body (None: unknown), whose neighbourhoods define the
    registration's normal smoothing (:meth:`normal_smoothing_matrix`) and the surface texels the frame
    rejection averages kappa over (:meth:`surface_texels`), both built once and cached.
    """

    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    raster: UVRaster
    texel_flat: np.ndarray
    texel_face: np.ndarray
    texel_bary: np.ndarray
    rest_vertices: np.ndarray | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, faces, uvs, uv_faces, resolution: int, rest_vertices=None) -> BodyLayout:
        raster = rasterize_uv(uvs, uv_faces, int(resolution))
        flat = raster.valid_indices()
        rest = None if rest_vertices is None else np.asarray(rest_vertices, np.float64)
        return cls(np.asarray(faces, np.int64), np.asarray(uvs, np.float32), np.asarray(uv_faces, np.int64),
                   raster, flat, raster.face_index.ravel()[flat], raster.bary.reshape(-1, 3)[flat].astype(np.float64),
                   rest)

    @classmethod
    def from_template(cls, template, resolution: int) -> BodyLayout:
        return cls.build(template.faces, template.uvs, template.uv_faces, resolution, template.vertices)

    def surface_texels(self, min_visibility: float = 0.02, rays: int = 64,
                       stratified: bool = False) -> np.ndarray | None:
        """(M,) bool valid texels on the body's outer surface: rest-pose hemisphere visibility on the
        template itself above ``min_visibility`` (``rays`` per face, ``stratified``: see
        :func:`~uvatar.avh.bake.confidence.face_visibility`; cached; None when the rest body is
        unknown). Interior parts (eyeballs, mouth interior) are False."""
        if self.rest_vertices is None:
            return None
        key = ("surface", float(min_visibility), int(rays), bool(stratified))
        if key not in self._cache:
            caster = fast_caster(self.rest_vertices, self.faces)
            vis = vertex_visibility(self.rest_vertices, self.faces, caster, rays, 1e-4, stratified=stratified)
            self._cache[key] = self.at_texels(vis) > min_visibility
        return self._cache[key]

    def normal_smoothing_matrix(self, sigma: float):
        """(V, V) Gaussian averaging over the rest body at ``sigma`` metres (cached), or None when
        sigma <= 0 or the rest body is unknown."""
        if sigma <= 0 or self.rest_vertices is None:
            return None
        key = ("smoothing", float(sigma))
        if key not in self._cache:
            normals = vertex_normals(self.rest_vertices, self.faces)
            self._cache[key] = gaussian_surface_matrix(self.rest_vertices, normals, sigma)
        return self._cache[key]

    @property
    def resolution(self) -> int:
        return self.raster.resolution

    def at_texels(self, vertex_values) -> np.ndarray:
        """Interpolate per-vertex values (V, C) or (V,) at the valid texels -> (M, C) or (M,) float64:
        one product with the cached sparse (M, V) barycentric matrix (:meth:`interpolation_matrix`;
        :meth:`at_texels_reference` is its plain twin)."""
        vals = np.asarray(vertex_values, dtype=np.float64)
        flat = vals.reshape(len(vals), -1)
        return np.asarray(self.interpolation_matrix(len(vals)) @ flat).reshape(len(self.texel_flat), *vals.shape[1:])

    def at_texels_torch(self, vertex_values, device):
        """:meth:`at_texels` on a torch ``device``: (M[, C]) float64 tensor there, one sparse product
        with the interpolation matrix kept there (per V and device)."""
        import torch

        vals = torch.as_tensor(np.asarray(vertex_values, dtype=np.float64), device=device)
        key = ("interpolation_torch", len(vals), str(device))
        if key not in self._cache:
            m = self.interpolation_matrix(len(vals))
            self._cache[key] = torch.sparse_csr_tensor(
                torch.as_tensor(m.indptr, dtype=torch.int64), torch.as_tensor(m.indices, dtype=torch.int64),
                torch.as_tensor(m.data), m.shape).to(device)
        flat = vals.reshape(len(vals), -1)
        return (self._cache[key] @ flat).reshape(len(self.texel_flat), *vals.shape[1:])

    def at_texels_reference(self, vertex_values) -> np.ndarray:
        """Plain twin of :meth:`at_texels`: gather each texel's three corners and weight them."""
        vals = np.asarray(vertex_values, dtype=np.float64)
        corners = vals[self.texel_vertices]                          # (M, 3[, C])
        if vals.ndim == 1:
            return np.einsum("mk,mk->m", corners, self.texel_bary)
        return np.einsum("mkc,mk->mc", corners.reshape(len(corners), 3, -1),
                         self.texel_bary).reshape(len(corners), *vals.shape[1:])

    def island_gutter(self, texels: int | None):
        """(R, R) bool: the UV islands grown by ``texels`` (cached); None for ``texels`` None (no limit)."""
        if texels is None:
            return None
        key = ("island_gutter", int(texels))
        if key not in self._cache:
            self._cache[key] = grow_mask(self.raster.mask, int(texels))
        return self._cache[key]

    def interpolation_matrix(self, num_vertices: int | None = None):
        """(M, V) scipy CSR matrix: row m holds texel m's barycentrics at its triangle's vertices
        (cached per V; default V: one past the largest vertex index of the faces)."""
        nv = int(self.faces.max()) + 1 if num_vertices is None else int(num_vertices)
        key = ("interpolation", nv)
        if key not in self._cache:
            import scipy.sparse as sp

            m = len(self.texel_flat)
            self._cache[key] = sp.csr_matrix(
                (self.texel_bary.ravel(), self.texel_vertices.ravel(), np.arange(0, 3 * m + 1, 3)), shape=(m, nv))
        return self._cache[key]

    @property
    def texel_vertices(self) -> np.ndarray:
        """(M, 3) int64 body vertices of each valid texel's triangle (cached)."""
        cached = self.__dict__.get("_texel_vertices")
        if cached is None:
            cached = self.faces[self.texel_face]
            self.__dict__["_texel_vertices"] = cached
        return cached

    @property
    def texel_vertex_set(self) -> np.ndarray:
        """(K,) int64 the distinct body vertices of the valid texels' triangles (cached): the vertices
        whose visibility the texels read."""
        cached = self.__dict__.get("_texel_vertex_set")
        if cached is None:
            cached = self.__dict__["_texel_vertex_set"] = np.unique(self.texel_vertices)
        return cached

    def to_map_torch(self, texel_values, fill=0.0, dtype=np.float32) -> np.ndarray:
        """:meth:`to_map` of a tensor (M[, C]) on its device: the map laid out there and read back (numpy)."""
        import torch

        v = texel_values
        r = self.resolution
        out = torch.full((r * r, *v.shape[1:]), fill, dtype=getattr(torch, np.dtype(dtype).name), device=v.device)
        out[on_device(self.texel_flat, v.device)] = v.to(out.dtype)
        return to_numpy(out.reshape(r, r, *v.shape[1:]))

    def to_map(self, texel_values, fill=0.0, dtype=np.float32) -> np.ndarray:
        """(M[, C]) values at the valid texels -> (R, R[, C]) map, ``fill`` elsewhere."""
        v = np.asarray(texel_values)
        r = self.resolution
        out = np.full((r * r, *v.shape[1:]), fill, dtype=dtype)
        out[self.texel_flat] = v
        return out.reshape(r, r, *v.shape[1:])


@dataclass
class BakedFrame:
    """One baked frame; all maps (R, R[, C]), row 0 at v = 1.

    texture (R, R, 3) float32 [0, 1]; displacement (R, R, 3) float32 metres d = x - s (world axes
    of the posed frame); kappa (R, R) float32 in [0, 1] (0 where no match); w (R, R) float32
    visibility of M^R_t; valid (R, R) bool texels covered by the UV layout; matched (R, R) bool
    texels with a scan match (the rest is inpainted); points (R, R, 3) float64 match x (zeros where
    unmatched; kept in memory for evaluation, not stored); stats: kappa_mean (over the body's
    surface texels, :meth:`BodyLayout.surface_texels`), kappa_mean_all_texels, matched_fraction,
    registration info, ``seconds`` (wall), ``cpu_seconds`` (this process) and ``rays`` (rays cast) per
    stage.
    """

    texture: np.ndarray
    displacement: np.ndarray
    kappa: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    matched: np.ndarray
    points: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def kappa_mean(self) -> float:
        return float(self.stats["kappa_mean"])


@contextmanager
def _timed(seconds: dict, name: str, rays: dict | None = None, cpu: dict | None = None):
    """Add the block's wall seconds to ``seconds[name]``, the rays it cast to ``rays[name]`` and this
    process's CPU seconds to ``cpu[name]`` (what a frame costs on a machine shared with other jobs).
    The block is a torch profiler range ``bake.<name>`` (``bench/bake.py --profile``: each stage's
    device time)."""
    from torch.profiler import record_function

    t0, r0, c0 = time.perf_counter(), rays_cast(), time.process_time()
    with record_function(f"bake.{name}"):
        yield
    seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
    if rays is not None:
        rays[name] = rays.get(name, 0) + rays_cast() - r0
    if cpu is not None:
        cpu[name] = cpu.get(name, 0.0) + time.process_time() - c0


def shadow_vertices(body, fit, shape=None) -> np.ndarray:
    """M^S_t: (V, 3) float64 vertices of ``body`` posed by ``fit`` (EasyMocap Rh/Th/scale).

    shape: (S,) shape parameters (default: the fit's ``shapes`` if any, else the body's default).
    Raises InputError for a pose of the wrong size or with NaN.
    """
    import torch

    rotvecs = body.joint_rotvecs_from_fit(fit)
    if shape is None and np.asarray(fit.shapes).size:
        shape = np.asarray(fit.shapes, dtype=np.float32)
    for name, value in (("Rh", fit.Rh), ("Th", fit.Th), ("scale", fit.scale)):
        if not np.all(np.isfinite(value)):
            raise InputError(f"fit {fit.id}", f"{name} contains NaN or inf")
    with torch.no_grad():
        posed = body.pose(torch.as_tensor(rotvecs)[None], Rh=np.asarray(fit.Rh)[None],
                          Th=np.asarray(fit.Th)[None], scale=np.asarray([fit.scale], np.float32),
                          shape=None if shape is None else torch.as_tensor(shape, dtype=torch.float32))
    verts = posed.vertices[0].detach().cpu().numpy().astype(np.float64)
    if not np.isfinite(verts).all():
        raise InputError(f"fit {fit.id}", "posed body has NaN vertices")
    return verts


def check_scan(scan, path="scan") -> None:
    """Raise InputError unless ``scan`` is a non-empty, finite, textured mesh with UVs."""
    if scan.num_faces == 0 or scan.num_vertices == 0:
        raise InputError(path, "scan has no triangles")
    if not np.isfinite(scan.vertices).all():
        raise InputError(path, "scan vertices contain NaN or inf")
    if not scan.has_uvs:
        raise InputError(path, "scan has no texture coordinates")
    if scan.texture is None or scan.texture.size == 0:
        raise InputError(path, "scan has no texture image")


def bake_fit(body, fit, layout: BodyLayout, scan, config: BakeConfig | None = None, shape=None,
             scan_path: str = "scan", surface: ScanSurface | None = None):
    """Pose the shadow mesh from ``fit`` (refined against the scan first if ``config.refine_pose``)
    and bake. ``surface``: the scan already prepared on ``config.device`` (built here when None).
    Returns (BakedFrame, the fit actually used: store it with the maps)."""
    with single_threaded():
        return _bake_fit(body, fit, layout, scan, config, shape, scan_path, surface)


def _bake_fit(body, fit, layout, scan, config, shape, scan_path, surface):
    from uvatar.avh.bake.refine import refine_fit

    config = config or BakeConfig()
    check_scan(scan, scan_path)
    sec: dict[str, float] = {}
    rays: dict[str, int] = {}
    cpu: dict[str, float] = {}
    with _timed(sec, "prepare_scan", rays, cpu):
        if surface is None:
            surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)
    refine_stats = None
    with _timed(sec, "refine_pose", rays, cpu):
        if config.refine_pose:
            fit, refine_stats = refine_fit(body, fit, surface, config.pose_refine, shape, device=config.torch_device)
        shadow = shadow_vertices(body, fit, shape)
    baked = bake_frame(shadow, layout, scan, config, scan_path, surface=surface)
    baked.stats["seconds"] = {**sec, **baked.stats["seconds"]}
    baked.stats["rays"] = {**rays, **baked.stats["rays"]}
    baked.stats["cpu_seconds"] = {**cpu, **baked.stats["cpu_seconds"]}
    if refine_stats is not None:
        baked.stats["pose_refine"] = refine_stats
    return baked, fit


def bake_frame(shadow: np.ndarray, layout: BodyLayout, scan, config: BakeConfig | None = None,
               scan_path: str = "scan", surface: ScanSurface | None = None) -> BakedFrame:
    """Bake one frame into the body UV space (AVH §3.2).

    shadow: (V, 3) posed shadow-mesh vertices M^S_t (metres); layout: the body's UV layout at R;
    scan: :class:`uvatar.capture.TexturedMesh` S_t; config: :class:`BakeConfig`; surface: the scan
    prepared for queries (built here when None).
    """
    config = config or BakeConfig()
    check_scan(scan, scan_path)
    if layout.resolution != config.texels:
        raise ValueError(f"layout resolution {layout.resolution} != config.texels {config.texels}")
    sec: dict[str, float] = {}
    rays: dict[str, int] = {}
    cpu: dict[str, float] = {}
    shadow = np.asarray(shadow, dtype=np.float64)
    diag = float(np.linalg.norm(shadow.max(0) - shadow.min(0)))
    eps = config.ray_epsilon

    if surface is None:
        with _timed(sec, "prepare_scan", rays, cpu):
            surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)
    reg_stats: dict = {}
    with _timed(sec, "register", rays, cpu):
        if config.register:
            smoothing = layout.normal_smoothing_matrix(config.registration.normal_smoothing)
            registered, reg_stats = register_to_scan(shadow, layout.faces, surface, config.registration,
                                                     bbox_diagonal=diag, epsilon=eps, smoothing=smoothing,
                                                     device=config.torch_device)
        else:
            registered = shadow
    with _timed(sec, "correspond", rays, cpu):
        device = config.torch_device
        if device is None:
            r = layout.at_texels(registered)
            n = layout.at_texels(vertex_normals(registered, layout.faces))
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        else:   # the texels' points and normals made, and their rays cast, on the device
            r = layout.at_texels_torch(registered, device)
            n = layout.at_texels_torch(vertex_normals(registered, layout.faces), device)
            n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)
        matches = match_texels(r, n, surface, config.polarity_rule, config.polarity_ratio,
                               config.max_match_distance, eps)
        hit = matches.hit
    with _timed(sec, "texture", rays, cpu):
        if device is None:
            colors = np.zeros((len(r), 3), np.float32)
            colors[hit] = scan_colours(surface, scan, matches.face[hit], matches.bary[hit])
            s = layout.at_texels(shadow)
            disp = np.where(hit[:, None], matches.points - s, 0.0)
        else:   # from the matches still on the device; colours and displacements stay there for the inpainting
            colors, disp = _texel_colours_and_displacements(layout, shadow, surface, scan, matches, device)
    with _timed(sec, "visibility_registered", rays, cpu):
        w_caster = fast_caster(registered, layout.faces, config.device, config.ray_backend)
        w_vertex = vertex_visibility(registered, layout.faces, w_caster, config.visibility_rays, eps,
                                     needed=layout.texel_vertex_set, stratified=config.visibility_stratified,
                                     device=config.torch_device)
        w = np.clip(layout.at_texels(w_vertex), 0.0, 1.0) if device is None else \
            layout.at_texels_torch(w_vertex, device).clamp(0.0, 1.0)
    # on a device: the matches' tensors kept there (hit, distance, face, bary, scan normals), n there too
    m = matches if device is None else SimpleNamespace(**matches.on_device)
    with _timed(sec, "confidence", rays, cpu):
        delta = distance_score(_where(m.hit, m.distance, np.inf), config.distance_clip * diag)
        nms = normal_match_score(n, m.scan_normal)
        use = m.hit & (w * delta * nms > 0)
    with _timed(sec, "visibility_scan", rays, cpu):
        # the scan's visibility v only matters where the other factors of kappa are not zero: only the
        # scan faces around those texels' matches are ray cast (the same values there)
        if device is None:
            hit_vertices = surface.faces[matches.face[use]]                       # (K, 3)
            needed = hit_vertices.ravel()
        else:
            hit_vertices, needed = _needed_scan_vertices(surface, m.face[use])
        v_vertex = vertex_visibility(surface.vertices, surface.faces, surface.caster, config.visibility_rays, eps,
                                     needed=needed, stratified=config.visibility_stratified,
                                     device=config.torch_device)
        if device is None:
            v = np.zeros(len(r))
            v[use] = np.einsum("kj,kj->k", v_vertex[hit_vertices], matches.bary[use])
        else:
            import torch

            v = torch.zeros(len(r), dtype=torch.float64, device=device)
            v[use] = torch.einsum("kj,kj->k", torch.as_tensor(v_vertex, device=device)[hit_vertices],
                                  m.bary[use].to(torch.float64))
        kappa = _where(m.hit, confidence(v, w, delta, nms), 0.0)   # v = 0 only where another factor is
    with _timed(sec, "inpaint", rays, cpu):
        matched_map = layout.to_map(hit, fill=False, dtype=bool)
        texture, displacement = _inpaint_maps(layout, colors, disp, matched_map, config)
    if device is not None:   # the maps laid out on the device, the per-texel values read back for the stats
        kappa_map, w_map, points_map = (layout.to_map_torch(a, dtype=dt)
                                        for a, dt in ((kappa, np.float32), (w, np.float32), (m.points, np.float64)))
        kappa, w = to_numpy(kappa), to_numpy(w)
    else:
        kappa_map, w_map = layout.to_map(kappa), layout.to_map(w)
        points_map = layout.to_map(matches.points, dtype=np.float64)
    valid = layout.raster.mask.copy()
    surface_texels = layout.surface_texels(config.interior_visibility, config.visibility_rays,
                                           config.visibility_stratified)
    on_surface = kappa if surface_texels is None else kappa[surface_texels]
    stats = {
        "kappa_mean": float(on_surface.mean()) if len(on_surface) else 0.0,
        "kappa_mean_all_texels": float(kappa.mean()) if len(kappa) else 0.0,
        "matched_fraction": float(hit.mean()) if len(hit) else 0.0,
        "positive_fraction": float(matches.positive[hit].mean()) if hit.any() else 0.0,
        "mixed_polarity_texels": int(matches.mixed.sum()) if matches.mixed is not None else 0,
        "polarity_rule_changed_texels": int(matches.rule_changed.sum()) if matches.rule_changed is not None else 0,
        "median_match_distance_mm": float(np.median(matches.distance[hit]) * 1000) if hit.any() else None,
        "bbox_diagonal": diag,
        "registration": reg_stats,
        "seconds": sec,
        "rays": rays,
        "cpu_seconds": cpu,
    }
    return BakedFrame(
        texture=np.clip(texture, 0.0, 1.0).astype(np.float32),
        displacement=displacement.astype(np.float32),
        kappa=kappa_map,
        w=w_map,
        valid=valid,
        matched=matched_map,
        points=points_map,
        stats=stats,
    )


def _where(condition, a, b):
    """``np.where``, or ``torch.where`` for a tensor condition."""
    if type(condition).__module__.startswith("torch"):
        import torch

        return torch.where(condition, a, b)
    return np.where(condition, a, b)


def _needed_scan_vertices(surface: ScanSurface, faces_of_hits):
    """(the scan vertices of those faces (K, 3) tensor, the distinct ones (numpy indices)): the
    visibility_scan stage's vertex set from hit faces (K,) on a torch device (the scan's faces kept
    there with ``surface``)."""
    import torch

    key = ("faces", str(faces_of_hits.device))
    if key not in surface.on_device:
        surface.on_device[key] = torch.as_tensor(surface.faces, device=faces_of_hits.device)
    hit_vertices = surface.on_device[key][faces_of_hits]
    mask = torch.zeros(len(surface.vertices), dtype=torch.bool, device=faces_of_hits.device)
    mask[hit_vertices.reshape(-1)] = True
    return hit_vertices, np.flatnonzero(mask.cpu().numpy())


def _texel_colours_and_displacements(layout: BodyLayout, shadow, surface, scan, matches, device):
    """The texture stage on a torch ``device``: (colours (M, 3) float32, displacements d = x - s (M, 3)
    float64) tensors there, zeros where unmatched, from the matches' tensors kept there
    (``TexelMatches.on_device``); the numpy path's steps."""
    import torch

    kept = matches.on_device
    hit = kept["hit"]
    colors = torch.zeros((len(hit), 3), dtype=torch.float32, device=device)
    colors[hit] = scan_colours(surface, scan, kept["face"][hit], kept["bary"][hit]).to(torch.float32)
    s = layout.at_texels_torch(shadow, device)
    disp = torch.where(hit[:, None], kept["points"] - s, torch.zeros_like(s))
    return colors, disp


def _inpaint_maps(layout: BodyLayout, colors, disp, matched_map, config: BakeConfig):
    """(texture (R, R, 3), displacement (R, R, 3)) float32 numpy: the texels' colours (M, 3) and
    displacements (M, 3) (numpy, or tensors on the device) as maps, the unmatched texels inpainted; on
    ``config.torch_device`` through
    :func:`.inpaint_torch.inpaint_telea_torch` (the maps are laid out there too), else OpenCV's Telea.
    One call for both maps: the nearest-texel fill is computed once."""
    device = config.torch_device
    if device is None:
        both = inpaint_telea(np.concatenate([layout.to_map(colors), layout.to_map(disp)], axis=-1),
                             ~matched_map, config.inpaint_radius, config.inpaint_band,
                             layout.island_gutter(config.inpaint_gutter))
        return both[..., :3], both[..., 3:]
    import torch

    from uvatar.avh.bake.inpaint_torch import inpaint_telea_torch

    r = layout.resolution
    values = torch.cat([torch.as_tensor(a, device=device).to(torch.float32) for a in (colors, disp)], dim=1)
    maps = torch.zeros((r * r, 6), dtype=torch.float32, device=device)
    maps[on_device(layout.texel_flat, device)] = values          # the layout's constants go over once
    gutter = layout.island_gutter(config.inpaint_gutter)
    both = inpaint_telea_torch(maps.reshape(r, r, 6), to_device_async(~matched_map, device),
                               config.inpaint_radius, config.inpaint_band,
                               None if gutter is None else on_device(gutter, device))
    both = to_numpy(both)
    return both[..., :3], both[..., 3:]


def _colormap(x: np.ndarray) -> np.ndarray:
    """(H, W) in [0, 1] -> (H, W, 3) a simple blue-green-yellow-red ramp."""
    x = np.clip(x, 0.0, 1.0)[..., None]
    stops = np.array([[0.1, 0.1, 0.5], [0.0, 0.6, 0.6], [0.9, 0.9, 0.1], [0.8, 0.1, 0.1]])
    pos = x * (len(stops) - 1)
    i = np.clip(np.floor(pos).astype(int), 0, len(stops) - 2)
    f = pos - i
    return (stops[i[..., 0]] * (1 - f) + stops[i[..., 0] + 1] * f).astype(np.float32)


def preview_image(texture, displacement, kappa, valid, max_size: int = 512,
                  displacement_scale: float = 0.05) -> np.ndarray:
    """(h, 3h, 3) float32 preview: texture | |d| (0 .. ``displacement_scale`` metres) | kappa.

    Texels outside the UV islands are shown dark grey; maps larger than ``max_size`` are subsampled.
    """
    step = max(1, int(np.ceil(texture.shape[0] / max_size)))
    tex = np.asarray(texture, np.float32)[::step, ::step]
    mag = np.linalg.norm(np.asarray(displacement, np.float32)[::step, ::step], axis=-1)
    kap = np.asarray(kappa, np.float32)[::step, ::step]
    ok = np.asarray(valid, bool)[::step, ::step, None]
    grey = np.float32(0.15)
    panels = [np.where(ok, tex, grey), np.where(ok, _colormap(mag / displacement_scale), grey),
              np.where(ok, np.repeat(kap[..., None], 3, axis=-1), grey)]
    return np.concatenate(panels, axis=1)
