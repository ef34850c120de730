"""The studio's light: a fixed rig (key, fill, ambient) baked into the texture of every posed frame.

A real studio's captures carry its lighting: an arm lowered against the torso shadows the torso's
side, a bent knee shades its hollow, fabric folds catch the key light on one flank. The synthetic
studio does the same (``SynthConfig.light = "studio"``; ``"none"`` reproduces the unlit captures
made before it exactly). Per frame, the posed clothed body is the occluder: the template
subdivided ``occluder_levels`` times, clothed exactly like the scan vertices (noise free; a broken
scan still lit as the whole person was). For surface points (scan-atlas texels, gt texels) with
their offset directions:

1. each point is snapped onto the occluder along its offset direction (two Embree rays), giving
   the occluder face, barycentrics and the interpolated clothed vertex normal ``n`` (so folds shade);
2. ``ambient * AO``: ambient occlusion at the occluder's vertices, ``ao_rays`` cosine-weighted
   hemisphere rays each (one fixed Fibonacci pattern turned by a fixed per-vertex angle: the same
   pose gives the same shading), occluders within ``ao_distance``, then ``ao_smooth`` passes of
   neighbour averaging over the mesh; interpolated at the snapped barycentrics, so AO is smooth
   (no per-texel noise);
3. ``sum_lights intensity * max(0, n . l) * visibility``: directional key and fill lights; the
   visibility is the fraction of ``shadow_rays`` occlusion rays (a fixed pattern over a cone of
   ``light_radius_deg``: soft shadow edges) from the snapped point that escape, per point.

``shading = ambient * AO + key + fill`` (:func:`shade_points`); the texture is
``clip(albedo * creases * shading, 0, 1)`` (:func:`lit_texture`). All rays go through
:class:`uvatar.geometry.raycast.RayCaster`, batched (no per-ray Python loops).
The world is +Y up and the person faces +Z at Rh = 0; light directions point toward the lights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LightConfig", "Occluder", "StudioLight", "ambient_occlusion", "snap_points", "smoother", "light_visibility", "shade_points", "lit_texture",
           "cosine_directions", "cone_directions"]


@dataclass(frozen=True)
class LightConfig:
    """The rig. key / fill: directions toward each light (world, +Y up; normalized): the key high
    in front on the person's left (+X), the fill lower on the right, a little behind;
    key_intensity, fill_intensity, ambient: weights of the three terms (a surface facing the key,
    unoccluded, gets ambient + key ~ 1); ao_rays: cosine-weighted hemisphere rays per occluder
    vertex; ao_distance (m): occluders further than this do not count; ao_smooth: passes of
    neighbour averaging of the per-vertex AO over the occluder mesh (each: half own value, half the
    mean of the edge neighbours; removes the residual ray-pattern noise); shadow_rays: occlusion rays
    per point and light (1: hard shadows); light_radius_deg: angular radius of each light (soft
    shadow edges); bias (m): ray origins are lifted this far along the normal (no self-shadowing of
    the surface the point lies on); snap (m): how far a point may sit from the occluder surface;
    occluder_levels: template subdivisions of the occluder mesh (1: ~110k triangles)."""

    key: tuple = (0.55, 0.65, 0.75)
    fill: tuple = (-0.75, 0.35, -0.3)
    key_intensity: float = 0.55
    fill_intensity: float = 0.3
    ambient: float = 0.45
    ao_rays: int = 96
    ao_distance: float = 0.35
    ao_smooth: int = 2
    shadow_rays: int = 4
    light_radius_deg: float = 3.0
    bias: float = 0.002
    snap: float = 0.012
    occluder_levels: int = 1

    def __post_init__(self) -> None:
        from uvatar.errors import check_values

        check_values([
            (self.ao_rays >= 1, f"ao_rays must be at least 1, got {self.ao_rays}"),
            (self.shadow_rays >= 1, f"shadow_rays must be at least 1, got {self.shadow_rays}"),
            (self.ao_smooth >= 0, f"ao_smooth must not be negative, got {self.ao_smooth}"),
            (self.ao_distance > 0, f"ao_distance must be positive, got {self.ao_distance}"),
            (min(self.key_intensity, self.fill_intensity, self.ambient) >= 0, "light intensities must not be negative"),
            (self.occluder_levels >= 0, f"occluder_levels must not be negative, got {self.occluder_levels}")])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def cosine_directions(n: int) -> np.ndarray:
    """(n, 3) directions over the +Z hemisphere, cosine-weighted (a Fibonacci lattice on the disc,
    lifted): their plain mean of visibility estimates cosine-weighted ambient occlusion."""
    i = np.arange(n, dtype=np.float64)
    r2 = (i + 0.5) / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(r2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r2)], axis=1)


def cone_directions(direction, n: int, radius_deg: float) -> np.ndarray:
    """(n, 3) unit directions spread evenly over a cone of ``radius_deg`` around ``direction`` (3,)
    (n = 1: the direction itself)."""
    from uvatar.geometry.frames import frames_from_normals

    d = _unit(direction)
    if n == 1 or radius_deg <= 0:
        return np.repeat(d[None], n, axis=0)
    disc = cosine_directions(n)[:, :2] * np.tan(np.radians(radius_deg))
    local = np.concatenate([disc, np.ones((n, 1))], axis=1)
    return _unit(local @ frames_from_normals(d[None])[0].T)


@dataclass
class Occluder:
    """The posed clothed occluder: vertices (V, 3), faces (F, 3), unit vertex normals (V, 3), its
    :class:`RayCaster`, the (V, V) sparse neighbour-averaging matrix of its topology (:func:`smoother`),
    and (lazily) ambient occlusion per vertex (V,)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    caster: object
    smoother: object
    ao: np.ndarray | None = None

    @classmethod
    def build(cls, vertices, faces, smoothing=None) -> Occluder:
        """smoothing: :func:`smoother` of these faces when already at hand (it depends on topology only)."""
        from uvatar.geometry import vertex_normals
        from uvatar.geometry.raycast import RayCaster, RayCasterConfig

        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        n = np.asarray(vertex_normals(v, f), dtype=np.float64)
        return cls(v, f, n, RayCaster(v, f, RayCasterConfig(precision="float32")),
                   smoothing if smoothing is not None else smoother(f, len(v)))


def smoother(faces, num_vertices: int):
    """(V, V) sparse ``(I + D^-1 A) / 2``: each vertex's value halfway to the mean of its edge neighbours."""
    import scipy.sparse as sp

    from uvatar.geometry.laplacian import uniform_laplacian

    return (sp.identity(num_vertices, format="csr") - 0.5 * uniform_laplacian(num_vertices, faces, normalized=True)
            ).tocsr()


def ambient_occlusion(occ: Occluder, points, normals, cfg: LightConfig, chunk: int = 8192) -> np.ndarray:
    """(N,) cosine-weighted ambient occlusion in [0, 1] (1: open sky) at points (N, 3) with unit
    normals (N, 3): the fraction of ``cfg.ao_rays`` hemisphere rays that meet no surface of ``occ``
    within ``cfg.ao_distance``. The ray pattern is turned about each normal by a fixed angle drawn
    from the point's index (deterministic)."""
    from uvatar.geometry.frames import frames_from_normals

    p = np.asarray(points, dtype=np.float64)
    nrm = _unit(normals)
    base = cosine_directions(cfg.ao_rays)
    k = cfg.ao_rays
    angle = np.random.default_rng(0x40).uniform(0, 2 * np.pi, len(p))
    out = np.empty(len(p))
    for s in range(0, len(p), chunk):
        e = slice(s, s + chunk)
        frames = frames_from_normals(nrm[e])                                   # (B, 3, 3) columns t, b, n
        c, si = np.cos(angle[e])[:, None], np.sin(angle[e])[:, None]
        t = c * frames[:, :, 0] + si * frames[:, :, 1]
        b = -si * frames[:, :, 0] + c * frames[:, :, 1]
        d = (base[None, :, 0:1] * t[:, None] + base[None, :, 1:2] * b[:, None]
             + base[None, :, 2:3] * frames[:, None, :, 2])                      # (B, k, 3)
        o = np.repeat(p[e] + cfg.bias * nrm[e], k, axis=0)
        blocked = occ.caster.any_hit(o, d.reshape(-1, 3), max_distance=cfg.ao_distance)
        out[e] = 1.0 - blocked.reshape(-1, k).mean(axis=1)
    return out


def light_visibility(occ: Occluder, points, normals, direction, cfg: LightConfig) -> np.ndarray:
    """(N,) fraction of ``cfg.shadow_rays`` rays toward a directional light (a cone of
    ``cfg.light_radius_deg`` around ``direction``) from points (N, 3) lifted along their normals
    (N, 3) that escape ``occ``: 1 lit, 0 in full shadow."""
    dirs = cone_directions(direction, cfg.shadow_rays, cfg.light_radius_deg)
    p = np.asarray(points, dtype=np.float64) + cfg.bias * _unit(normals)
    k = len(dirs)
    o = np.repeat(p, k, axis=0)
    d = np.tile(dirs, (len(p), 1))
    return 1.0 - occ.caster.any_hit(o, d).reshape(-1, k).mean(axis=1)


def snap_points(occ: Occluder, points, dirs, cfg: LightConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Snap points (N, 3) onto the occluder along their offset directions dirs (N, 3): of the first
    hits of two rays through the point, one from ``cfg.snap`` outside it inward and one from
    ``cfg.snap`` inside it outward (rays never start on the surface, where a hit is ambiguous), the
    one nearer the point. Returns (hit (N,) bool, surface points (N, 3), unit normals (N, 3)
    interpolated from the occluder's vertex normals, ambient occlusion (N,) interpolated likewise);
    points that meet nothing keep themselves, dirs and AO 1."""
    p = np.asarray(points, dtype=np.float64)
    d = _unit(dirs)
    down = occ.caster.first_hit(p + cfg.snap * d, -d, max_distance=2 * cfg.snap)
    up = occ.caster.first_hit(p - cfg.snap * d, d, max_distance=2 * cfg.snap)
    use_up = np.abs(up.distance - cfg.snap) < np.abs(down.distance - cfg.snap)
    face = np.where(use_up, up.face, down.face)
    bary = np.where(use_up[:, None], up.bary, down.bary).astype(np.float64)
    hit = face >= 0
    tri = occ.faces[np.maximum(face, 0)]
    normal = _unit(np.einsum("nk,nkc->nc", bary, occ.normals[tri]) + 1e-12)
    surface = np.einsum("nk,nkc->nc", bary, occ.vertices[tri])
    normal = np.where(hit[:, None], normal, d)
    surface = np.where(hit[:, None], surface, p)
    ao = np.ones(len(p))
    if occ.ao is not None:
        ao = np.where(hit, np.einsum("nk,nk->n", bary, occ.ao[tri]), 1.0)
    return hit, surface, normal, ao


def shade_points(occ: Occluder, points, dirs, cfg: LightConfig) -> dict:
    """The rig's light at points (N, 3) of the posed clothed surface with offset directions (N, 3).

    Returns a dict of (N,) float64 arrays: shading (ambient * ao + key + fill), ao, key and fill
    (each ``intensity * max(0, n . l) * visibility``), and snapped (bool: the point met the
    occluder). Computes the occluder's per-vertex AO on first use."""
    if occ.ao is None:
        ao = ambient_occlusion(occ, occ.vertices, occ.normals, cfg)
        for _ in range(cfg.ao_smooth):
            ao = occ.smoother @ ao
        occ.ao = ao
    hit, surface, normal, ao = snap_points(occ, points, dirs, cfg)
    out = {"ao": ao, "snapped": hit}
    total = cfg.ambient * ao
    for name, direction, intensity in (("key", cfg.key, cfg.key_intensity), ("fill", cfg.fill, cfg.fill_intensity)):
        lam = np.clip(normal @ _unit(direction), 0.0, None)
        term = np.zeros(len(lam))
        facing = lam > 0
        if facing.any() and intensity > 0:
            term[facing] = intensity * lam[facing] * light_visibility(occ, surface[facing], normal[facing],
                                                                      direction, cfg)
        out[name] = term
        total = total + term
    out["shading"] = total
    return out


def lit_texture(albedo_rgb: np.ndarray, crease_factor: np.ndarray, shading: np.ndarray) -> np.ndarray:
    """(N, 3) float32 texture: clip(albedo (N, 3) * crease factor (N,) * shading (N,), 0, 1)."""
    out = np.asarray(albedo_rgb, np.float64) * (np.asarray(crease_factor, np.float64)
                                                * np.asarray(shading, np.float64))[:, None]
    return np.clip(out, 0.0, 1.0).astype(np.float32)


class StudioLight:
    """The rig bound to a :class:`~uvatar.capture.synth.frame.Studio`: the occluder's topology and
    statics (built once per process) and the lit texture of any surface points of a frame."""

    def __init__(self, studio):
        from uvatar.capture.synth.scans import fine_mesh
        from uvatar.capture.synth.surface import bary_matrix

        self.studio, self.cfg = studio, studio.cfg.lighting
        t = studio.template
        fine = fine_mesh(t, self.cfg.occluder_levels)
        W = bary_matrix(t.faces, fine.origin_face, fine.origin_bary, t.num_vertices)
        self.statics = studio.statics(W, looks=False)
        self.faces = fine.faces
        self.smoother = smoother(fine.faces, len(fine.vertices))

    def occluder(self, posed) -> Occluder:
        """The frame's posed clothed occluder (noise free)."""
        points, _ = self.studio.clothed(self.statics, posed)
        return Occluder.build(points, self.faces, self.smoother)

    def texture(self, st, posed, occ: Occluder, points=None, dirs=None) -> tuple[np.ndarray, dict]:
        """(texture (N, 3) float32, parts) of the points of statics ``st`` (looks and geometry) in
        ``posed``; parts: albedo (N, 3) float32 and (N,) float32 crease factor, shading, ao."""
        from uvatar.capture.synth.appearance import crease_factor

        if points is None:
            points, dirs = self.studio.clothed(st, posed)
        light = shade_points(occ, points, dirs, self.cfg)
        crease = crease_factor(st.creases, posed.bends, self.studio.cfg.appearance)
        parts = {"albedo": st.albedo.astype(np.float32), "crease": crease.astype(np.float32),
                 "shading": light["shading"].astype(np.float32), "ao": light["ao"].astype(np.float32)}
        return lit_texture(st.albedo, crease, light["shading"]), parts
