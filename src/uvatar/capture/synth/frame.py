"""One worker's studio: the body, its static surface maps, and the making of one frame.

:class:`Studio` holds what every frame reuses (the body model, the ground-truth texel maps, the
subdivided template, the garment-drape averaging matrix, per-segment scan statics, an LRU of two
segments) and :meth:`Studio.make_frame` writes one frame: scan (+ atlas texture), fit, images and
masks, then the ground truth last (its presence marks the frame done for resuming).
:meth:`Studio.posed` poses and drapes the body once per frame; :meth:`Studio.clothed` turns it into
clothed points for any set of body points (scan vertices, gt texels), so both come from one
function and the ground truth is the exact end point of each material point.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from uvatar.capture.synth import appearance as app
from uvatar.capture.synth import clothing as clo
from uvatar.capture.synth import surface as srf
from uvatar.capture.synth.bends import bend_amounts
from uvatar.capture.synth.config import SynthConfig
from uvatar.capture.synth.drape import garment_frame
from uvatar.capture.synth.drift import apply_drift, drift_maps, drift_vectors
from uvatar.capture.synth.gt import scatter_texels, write_gt_frame
from uvatar.capture.synth.scans import (
    ScanTopology,
    atlas_texel_matrix,
    cut_scan,
    fine_mesh,
    pose_scan,
)

__all__ = ["Posed", "Statics", "Studio", "frame_rng"]


def frame_rng(seed: int, frame: int, stream: int) -> np.random.Generator:
    """The random stream ``stream`` of frame ``frame``: a function of (seed, frame) only."""
    return np.random.default_rng([int(seed), int(frame), int(stream), 0x5EED])


@dataclass
class Statics:
    """Pose-independent maps of N surface points ``W`` (N, V): albedo (N, 3), creases (N, K),
    base offset (N,), folds (N, K), cloth weight (N,), drift weights (N, D) (None when not asked for)."""

    W: sp.csr_matrix
    albedo: np.ndarray | None = None
    creases: np.ndarray | None = None
    base: np.ndarray | None = None
    folds: np.ndarray | None = None
    cloth: np.ndarray | None = None
    drift: np.ndarray | None = None


@dataclass
class Posed:
    """One true pose of the body: vertices (V, 3), normals (V, 3), joints (J, 3) float64 world
    metres; garment normals (V, 3) and bridged crease depth (V,) metres (:mod:`.drape`); bends (K,);
    drift (D, 3) world drift per unit static weight (:mod:`.drift`)."""

    vertices: np.ndarray
    normals: np.ndarray
    joints: np.ndarray
    garment_normals: np.ndarray
    bridge: np.ndarray
    bends: np.ndarray
    drift: np.ndarray


class Studio:
    """Per-process state; build with the capture's config and the motion/plan arrays."""

    def __init__(self, cfg: SynthConfig, root: str | Path, plan: dict, device: str = "cpu"):
        from uvatar.body import load_body_model
        from uvatar.geometry.uv_raster import rasterize_uv

        self.cfg, self.root, self.plan = cfg, Path(root), plan
        self.body = load_body_model(cfg.body_model, device=device)
        t = self.body.template
        self.template = t
        self.groups = srf.vertex_groups(self.body)
        self.landmarks = srf.landmarks(self.body)
        self.shape = np.asarray(plan["shape"], dtype=np.float32)
        raster = rasterize_uv(t.uvs, t.uv_faces, cfg.gt_texels)
        W, self.gt_flat = srf.raster_matrix(raster, t.faces, t.num_vertices)
        self.gt_mask = raster.mask
        from uvatar.geometry import gaussian_surface_matrix, vertex_normals

        c = cfg.clothing
        rest_normals = vertex_normals(t.vertices.astype(np.float64), t.faces)
        self.drape = gaussian_surface_matrix(t.vertices, rest_normals, c.bending_length, c.drape_normal_dot)
        self.rest_bends = bend_amounts(t.rest_joints, self.body.semantic_joints, t.rest_joints)
        self.gt = self.statics(W)
        self.light = None  # the studio light (:mod:`.lighting`), built on first use when cfg.light is on
        self._fine = None
        self._segments: OrderedDict[int, tuple] = OrderedDict()

    # -- statics ---------------------------------------------------------------------------------
    def statics(self, W, looks: bool = True, geometry: bool = True) -> Statics:
        f = srf.features(W, self.template.vertices, self.groups)
        reg = app.regions(f, self.landmarks, self.cfg.appearance)
        out = Statics(W=W)
        if looks:
            out.albedo = app.albedo(f, self.landmarks, self.cfg.appearance, reg)
            out.creases = app.crease_maps(f, self.landmarks)
        if geometry:
            out.base = clo.base_offset(f, self.landmarks, reg, self.cfg.clothing)
            out.folds = clo.fold_maps(f, self.landmarks, reg, self.cfg.clothing)
            out.cloth = clo.cloth_weight(reg)
            out.drift = drift_maps(f, self.landmarks, reg, self.cfg.clothing)
        return out

    def fine(self):
        """(FineMesh, rest offsets (Vf,), rest normals (Vf, 3)) for building topologies."""
        if self._fine is None:
            from uvatar.geometry.frames import vertex_normals

            fine = fine_mesh(self.template, self.cfg.subdivision_levels)
            W = srf.bary_matrix(self.template.faces, fine.origin_face, fine.origin_bary, self.template.num_vertices)
            st = self.statics(W, looks=False)
            normals = srf.posed_points(W, self.template.vertices,
                                       vertex_normals(self.template.vertices.astype(np.float64), self.template.faces))[1]
            self._fine = (fine, st.base.astype(np.float64), normals)
        return self._fine

    def segment(self, index: int) -> tuple[ScanTopology, Statics, Statics, np.ndarray, np.ndarray]:
        """(topology, vertex statics, atlas-texel statics, atlas flat indices, fill index) of a segment."""
        if index in self._segments:
            self._segments.move_to_end(index)
            return self._segments[index]
        from uvatar.geometry.uv_raster import fill_atlas_index, rasterize_uv

        with np.load(self.root / "gt" / "topologies" / f"{index:03d}.npz") as data:
            topo = ScanTopology.from_npz(data)
        Wv = topo.vertex_matrix(self.template.faces, self.template.num_vertices)
        vert = self.statics(Wv, looks=False)
        raster = rasterize_uv(topo.uvs, topo.uv_faces, self.cfg.scan_texture)
        Wt, flat = atlas_texel_matrix(topo, raster, self.template.faces, self.template.num_vertices)
        texel = self.statics(Wt, geometry=self.cfg.light != "none")  # lit texels need their clothed points
        entry = (topo, vert, texel, flat, fill_atlas_index(raster.mask))
        self._segments[index] = entry
        while len(self._segments) > 2:
            self._segments.popitem(last=False)
        return entry

    # -- one frame -------------------------------------------------------------------------------
    def pose(self, i: int) -> Posed:
        """The true pose of frame i (see :class:`Posed`)."""
        p = self.plan
        return self.posed(p["poses"][i], p["Rh"][i], p["Th"][i])

    def posed(self, pose, Rh, Th) -> Posed:
        """Pose the body (pose (J, 3) or (J*3,) local axis-angles, Rh (3,), Th (3,)) and drape it."""
        import torch

        with torch.no_grad():
            out = self.body.pose(torch.as_tensor(np.asarray(pose, np.float32).reshape(1, -1, 3)),
                                 Rh=torch.as_tensor(np.asarray(Rh, np.float32)[None]),
                                 Th=torch.as_tensor(np.asarray(Th, np.float32)[None]),
                                 shape=torch.as_tensor(self.shape))
        V = out.vertices[0].double().cpu().numpy()
        N = out.normals[0].double().cpu().numpy()
        J = out.joints[0].double().cpu().numpy()
        c = self.cfg.clothing
        ng, bridge = garment_frame(V, N, self.drape, c.bridge, c.max_bridge)
        bends = bend_amounts(J, self.body.semantic_joints, self.template.rest_joints)
        return Posed(V, N, J, ng, bridge, bends, drift_vectors(J, self.body.semantic_joints, bends, self.rest_bends))

    def clothed(self, st: Statics, posed: Posed) -> tuple[np.ndarray, np.ndarray]:
        """(noise-free clothed points (N, 3), unit offset directions (N, 3)) float64 of the points of
        ``st``: ``W V + offset * normalize(W garment normals) + tangential drift``; offset = base +
        folds + bridging. Scan vertices and gt texels both come from here, so the gt is exact."""
        pts, dirs = srf.posed_points(st.W, posed.vertices, posed.garment_normals)
        bridged = st.cloth.astype(np.float64) * (st.W @ posed.bridge)
        off = clo.offset_amount(st.base, st.folds, posed.bends, self.cfg.clothing, bridged)
        return pts + off[:, None] * dirs + apply_drift(st.drift, posed.drift, dirs), dirs

    def texture(self, st: Statics, posed: Posed, occluder=None, points=None, dirs=None) -> tuple:
        """(texture (N, 3) float32, parts or None) of the points of ``st`` in ``posed``: albedo times
        creases, lit by the studio rig unless ``cfg.light`` is "none" (parts: albedo, crease,
        shading, ao; see :meth:`.lighting.StudioLight.texture`). occluder: the frame's
        :class:`.lighting.Occluder` (built when not given); points, dirs: ``clothed(st, posed)``
        when already at hand."""
        if self.cfg.light == "none":
            return app.shade(st.albedo, st.creases, posed.bends, self.cfg.appearance), None
        occluder = occluder or self.occluder(posed)  # builds self.light on first use
        return self.light.texture(st, posed, occluder, points, dirs)

    def occluder(self, posed: Posed):
        """The frame's light occluder (:class:`.lighting.Occluder`), or None when the light is off."""
        if self.cfg.light == "none":
            return None
        if self.light is None:
            from uvatar.capture.synth.lighting import StudioLight

            self.light = StudioLight(self)
        return self.light.occluder(posed)

    def make_frame(self, i: int) -> dict:
        """Write frame ``i`` (scan, fit, images, masks, gt) and return a small summary."""
        from uvatar.capture.fits import write_fit
        from uvatar.capture.meshio import write_mesh
        from uvatar.capture.synth.fits import noisy_fit
        from uvatar.capture.synth.images import render_views
        from uvatar.capture.types import TexturedMesh
        from uvatar.io_utils import write_image

        cfg, p, name = self.cfg, self.plan, self.plan["frames"][i]
        posed = self.pose(i)
        bends = posed.bends

        topo, vert, texel, flat, fill = self.segment(int(p["segment_of_frame"][i]))
        surface, dirs = self.clothed(vert, posed)
        vertices = pose_scan(surface, dirs, np.zeros(len(surface)), cfg.scan_noise, frame_rng(cfg.seed, i, 1))
        R = cfg.scan_texture
        occluder = self.occluder(posed)
        atlas = scatter_texels(self.texture(texel, posed, occluder)[0], flat, R)
        atlas = atlas.reshape(-1, 3)[fill].reshape(R, R, 3)
        faces, uv_faces = topo.faces, topo.uv_faces
        broken = p["broken"].get(name)
        if broken:
            keep = cut_scan(vertices, faces, np.asarray(broken["direction"]), broken["fraction"])
            faces, uv_faces = faces[keep], uv_faces[keep]
        write_mesh(self.root / "scans" / f"{name}.obj", TexturedMesh(vertices, faces, topo.uvs, uv_faces, atlas))

        tracked = self.body.conditioning_joints if cfg.fit_tracks == "body" else None
        fit = noisy_fit(p["poses"][i], p["Rh"][i], p["Th"][i], self.shape, cfg.fit_noise_deg, frame_rng(cfg.seed, i, 2),
                        tracked=tracked)
        write_fit(self.root / "fits" / f"{name}.json", fit)

        if p["cameras"]:
            if p.get("bystanders"):
                from uvatar.capture.synth.bystanders import render_with_bystanders

                views = render_with_bystanders(self, i, vertices, topo.faces, topo.uvs, topo.uv_faces, atlas,
                                               p["cameras"], cfg.background)
            else:
                views = render_views(vertices, topo.faces, topo.uvs, topo.uv_faces, atlas, p["cameras"], cfg.background)
            for cam, (rgb, mask, *others) in zip(p["cameras"], views, strict=True):
                write_image(self.root / "images" / cam.name / f"{name}.png", rgb)
                write_image(self.root / "masks" / cam.name / f"{name}.png", mask.astype(np.uint8) * 255)
                if others:
                    write_image(self.root / "gt" / "bystander_masks" / cam.name / f"{name}.png",
                                others[0].astype(np.uint8) * 255)

        g = self.gt
        Rg = cfg.gt_texels
        gsurf, gdirs = self.clothed(g, posed)
        gtex, parts = self.texture(g, posed, occluder, gsurf, gdirs)
        lit = {} if parts is None else {  # albedo and shading kept apart (see :mod:`.gt`)
            k: scatter_texels(v.reshape(len(v), -1), self.gt_flat, Rg).squeeze(-1) if v.ndim == 1
            else scatter_texels(v, self.gt_flat, Rg) for k, v in parts.items()}
        gp = srf.posed_points(g.W, posed.vertices, posed.normals)[0]
        write_gt_frame(self.root, name, pose=p["poses"][i].reshape(-1), Rh=p["Rh"][i], Th=p["Th"][i],
                       texture=scatter_texels(gtex, self.gt_flat, Rg), **lit,
                       offset=scatter_texels((gsurf - gp).astype(np.float32), self.gt_flat, Rg),
                       surface=scatter_texels(gsurf.astype(np.float32), self.gt_flat, Rg),
                       mask=self.gt_mask, bends=bends.astype(np.float32), broken=np.bool_(bool(broken)))
        return {"frame": name, "faces": int(len(faces)), "broken": bool(broken)}
