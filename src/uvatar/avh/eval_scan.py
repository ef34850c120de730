"""What ``uvatar eval`` measures on a real take, where the only truth is each frame's textured scan
and its own baked maps (no ``gt/``): by body region, geometry against the scan surface both ways,
and the pose-dependent part's R² against the frame's own bake.

- **Regions** (:data:`uvatar.body.masks.REGION_NAMES`: face, head, hands, arms, torso, legs, feet):
  every avatar face takes the region of its UV centroid in :func:`region_label_map`; a pixel seen by
  the avatar takes the region of the face its ray hits, a pixel of the scan's silhouette alone that of
  the nearest avatar pixel (:func:`pixel_regions`). Image metrics per region are those of
  :func:`uvatar.avh.eval_metrics.image_metrics` restricted to the region's pixels.
- **Geometry both ways** (:func:`scan_geometry_mm`): points spread by area over the avatar's mesh →
  distance to the scan surface (accuracy), and over the scan → distance to the avatar (completeness),
  in mm; a scan point takes the region of its nearest avatar point.
- **Own-bake R²** (:class:`OwnBakeR2`): texture and displacement maps of each method against the eval
  frame's own baked maps over texels confident in both that frame (κ > 0.5) and the training frames
  (mean κ > 0.5), fingers and toes left out; ``1 − Σ|pred − own|² / Σ|mean − own|²`` pooled over
  frames, the mean being the training frames' mean map (the same reference as against ``gt/``).
"""

from __future__ import annotations

import numpy as np

from uvatar.avh.pose_metrics import R2Sums
from uvatar.body.masks import REGION_NAMES

SCAN_POINTS = 20000  # points per surface for the two-way distance

SCAN_PROTOCOL = ("; geometry (no gt/ surface): 20,000 points spread by area over each method's mesh -> distance to "
                 "the frame's scan surface (avatar_to_scan_mm) and over the scan -> distance to the mesh "
                 "(scan_to_avatar_mm), mm; geometry_mm = chamfer_mm, their mean")
OWN_BAKE_PROTOCOL = ("; texture_r2_own_bake / displacement_r2_own_bake: each method's maps against the eval frame's "
                     "own baked maps (never trained on) over texels with the frame's kappa > 0.5, training mean kappa "
                     "> 0.5, no fingers/toes, 1 - sum|pred - own|^2 / sum|mean - own|^2 pooled over frames, mean = the "
                     "training frames' mean map; displacement in the avatar's frame, outliers > 5 cm zeroed as in "
                     "training; regions: face, head, hands, arms, torso, legs, feet by skinning weight (body.masks)")


def face_regions(label_map: np.ndarray, uvs: np.ndarray, uv_faces: np.ndarray) -> np.ndarray:
    """(F,) int8 region of each face: the label at its UV centroid (row 0 is v = 1), nearest labelled
    texel for centroids that fall in a gutter."""
    from scipy import ndimage

    R = label_map.shape[0]
    filled = label_map
    if (label_map < 0).any():
        idx = ndimage.distance_transform_edt(label_map < 0, return_distances=False, return_indices=True)
        filled = label_map[idx[0], idx[1]]
    c = np.asarray(uvs, np.float64)[np.asarray(uv_faces)].mean(1)
    cols = np.clip((c[:, 0] * R).astype(int), 0, R - 1)
    rows = np.clip(((1.0 - c[:, 1]) * R).astype(int), 0, R - 1)
    return filled[rows, cols].astype(np.int8)


def pixel_regions(caster, camera, face_labels: np.ndarray, union: np.ndarray) -> np.ndarray:
    """(H, W) int8 region per pixel of ``union`` (-1 elsewhere): the avatar face hit by the pixel's ray,
    or, where the avatar is not seen, the region of the nearest pixel where it is."""
    from scipy import ndimage

    from uvatar.render.cameras import camera_rays

    origins, directions = camera_rays(camera)
    hits = caster.first_hit(origins, directions)
    labels = np.full(camera.height * camera.width, -1, np.int8)
    labels[hits.hit] = face_labels[hits.face[hits.hit]]
    labels = labels.reshape(camera.height, camera.width)
    if (labels >= 0).any():
        idx = ndimage.distance_transform_edt(labels < 0, return_distances=False, return_indices=True)
        labels = labels[idx[0], idx[1]]
    return np.where(union, labels, -1).astype(np.int8)


def region_image_metrics(pred_rgb, pred_mask, gt_rgb, gt_mask, regions: np.ndarray, smap=None, err=None) -> dict:
    """{region: {psnr_db (union), ssim (union), psnr_db_inside_both, pixels}} for the regions present;
    ``smap``, ``err``: the images' :func:`~uvatar.render.metrics.ssim_map` and
    :func:`~uvatar.render.metrics.error_map` when the caller has them."""
    from uvatar.render.metrics import error_map, psnr_of_error_map, ssim_map, ssim_of_map

    smap = ssim_map(pred_rgb, gt_rgb) if smap is None else smap
    err = error_map(pred_rgb, gt_rgb) if err is None else err
    both = np.asarray(pred_mask, bool) & np.asarray(gt_mask, bool)
    out = {}
    for k, name in enumerate(REGION_NAMES):
        m = regions == k
        if not m.any():
            continue
        inside = m & both
        out[name] = {"psnr_db": psnr_of_error_map(err, m), "ssim": ssim_of_map(smap, m),
                     "psnr_db_inside_both": psnr_of_error_map(err, inside) if inside.any() else float("nan"),
                     "pixels": int(m.sum())}
    return out


class ScanSurface:
    """One frame's scan prepared for :func:`scan_geometry_mm` against several avatars: its closest-point
    index and its ``points`` surface samples (seed + 1), made once instead of once per method."""

    def __init__(self, vertices, faces, points: int = SCAN_POINTS, seed: int = 0):
        from uvatar.geometry.distance import SurfaceIndex
        from uvatar.geometry.sampling import sample_surface

        self.vertices, self.faces, self.points, self.seed = vertices, faces, points, seed
        self.index = SurfaceIndex(vertices, faces)
        self.samples = sample_surface(vertices, faces, points, seed=seed + 1)[0]


def scan_geometry_mm(avatar_vertices, avatar_faces, face_labels, scan_vertices=None, scan_faces=None,
                     points: int = SCAN_POINTS, seed: int = 0, scan: ScanSurface | None = None) -> dict:
    """Two-way surface distance (mm) between an avatar mesh and a scan (``scan_vertices``, ``scan_faces``, or
    a prepared :class:`ScanSurface` with the same ``points`` and ``seed``), overall and by region:
    ``{"avatar_to_scan": (N,), "scan_to_avatar": (N,), "avatar_regions": (N,), "scan_regions": (N,)}``."""
    from scipy.spatial import cKDTree

    from uvatar.geometry.distance import point_surface_distance
    from uvatar.geometry.sampling import sample_surface

    if scan is None:
        scan = ScanSurface(scan_vertices, scan_faces, points, seed)
    elif (scan.points, scan.seed) != (points, seed):
        raise ValueError(f"the prepared scan has {scan.points} points (seed {scan.seed}), asked {points} ({seed})")
    a_pts, _, a_face = sample_surface(avatar_vertices, avatar_faces, points, seed=seed, with_faces=True)
    s_pts = scan.samples
    a_regions = np.asarray(face_labels)[a_face]
    _, nearest = cKDTree(a_pts).query(s_pts)
    return {"avatar_to_scan": 1000.0 * scan.index.closest(a_pts)[2],
            "scan_to_avatar": 1000.0 * point_surface_distance(s_pts, avatar_vertices, avatar_faces),
            "avatar_regions": a_regions, "scan_regions": a_regions[nearest]}


def geometry_summary(parts: list[dict]) -> dict:
    """Pool :func:`scan_geometry_mm` results: mean / median both ways, their mean (``chamfer_mm``),
    and per region the mean both ways."""
    if not parts:
        return {}
    a = np.concatenate([p["avatar_to_scan"] for p in parts])
    s = np.concatenate([p["scan_to_avatar"] for p in parts])
    ar = np.concatenate([p["avatar_regions"] for p in parts])
    sr = np.concatenate([p["scan_regions"] for p in parts])
    out = {"avatar_to_scan_mm": float(a.mean()), "avatar_to_scan_median_mm": float(np.median(a)),
           "scan_to_avatar_mm": float(s.mean()), "scan_to_avatar_median_mm": float(np.median(s)),
           "chamfer_mm": float(0.5 * (a.mean() + s.mean())), "regions": {}}
    for k, name in enumerate(REGION_NAMES):
        if (ar == k).any() and (sr == k).any():
            out["regions"][name] = {"avatar_to_scan_mm": float(a[ar == k].mean()),
                                    "scan_to_avatar_mm": float(s[sr == k].mean()),
                                    "chamfer_mm": float(0.5 * (a[ar == k].mean() + s[sr == k].mean()))}
    return out


def pool_regions(per_view: list[dict]) -> dict:
    """Mean over views of :func:`region_image_metrics` per region and key."""
    out: dict = {}
    for name in REGION_NAMES:
        rows = [v[name] for v in per_view if name in v]
        if rows:
            out[name] = {k: float(np.nanmean([r[k] for r in rows])) for k in ("psnr_db", "ssim", "psnr_db_inside_both")}
            out[name]["pixels"] = int(sum(r["pixels"] for r in rows))
    return out


class OwnBakeR2:
    """R² of each method's maps against each eval frame's own baked maps, overall and by region
    (texture at the avatar's resolution; displacement in the avatar's frame, rest or body)."""

    def __init__(self, label_map: np.ndarray, keep: np.ndarray, train_confident: np.ndarray,
                 mean_texture: np.ndarray, mean_displacement: np.ndarray):
        self.label_map, self.keep, self.train_confident = label_map, keep, train_confident
        self.mean = {"texture": mean_texture, "displacement": mean_displacement}
        self.sums = {(kind, region): R2Sums() for kind in self.mean for region in ("all",) + REGION_NAMES}
        self.frames: list[str] = []

    def add(self, frame: str, maps: dict[str, tuple], own_texture, own_displacement, own_kappa, own_valid) -> dict:
        """Add one frame: ``maps`` {method: (texture (R, R, 3), displacement (R, R, 3) | None)} and the
        frame's own baked maps at the same resolution, in the same displacement frame."""
        confident = (own_kappa > 0.5) & own_valid & self.train_confident & self.keep
        own = {"texture": own_texture, "displacement": own_displacement}
        out = {}
        self.frames.append(frame)
        for kind in self.mean:
            preds = {m: (np.zeros_like(self.mean[kind]) if mp[kind == "displacement"] is None
                         else mp[kind == "displacement"]) for m, mp in maps.items()}
            for region in ("all",) + REGION_NAMES:
                mask = confident if region == "all" else confident & (self.label_map == REGION_NAMES.index(region))
                if mask.any():
                    r2 = self.sums[(kind, region)].add(preds, self.mean[kind], own[kind], mask)
                    if region == "all":
                        out.update({f"{m}_{kind}_r2_own_bake": v for m, v in r2.items()})
        return out

    def merge(self, other: OwnBakeR2) -> None:
        """Add another tally's frames (the same avatar and training frames; e.g. made in another process)."""
        for key, sums in other.sums.items():
            self.sums[key].merge(sums)
        self.frames.extend(other.frames)

    def summary(self) -> dict:
        """{method: {"texture_r2_own_bake", "displacement_r2_own_bake", "regions": {region: {...}}}}."""
        out: dict = {}
        for (kind, region), sums in self.sums.items():
            for m, value in sums.r2().items():
                entry = out.setdefault(m, {"regions": {}})
                if region == "all":
                    entry[f"{kind}_r2_own_bake"] = value
                else:
                    entry["regions"].setdefault(region, {})[f"{kind}_r2_own_bake"] = value
        return out


class RegionLabels:
    """The avatar's body regions: the UV label map at its resolution and, per mesh topology, each face's."""

    def __init__(self, runtime):
        from uvatar.body.masks import region_label_map

        self.map = region_label_map(runtime.body, runtime.resolution)
        self._faces: dict[tuple, np.ndarray] = {}

    def face_labels(self, mesh) -> np.ndarray:
        key = (len(mesh.faces), len(mesh.uvs))
        if key not in self._faces:
            self._faces[key] = face_regions(self.map, mesh.uvs, mesh.uv_faces)
        return self._faces[key]

    def own_bake_r2(self, runtime, baselines) -> OwnBakeR2:
        from uvatar.avh.data import resample_map

        R = runtime.resolution
        return OwnBakeR2(self.map, ~runtime.fingers_toes_mask(), resample_map(baselines.mean_kappa, R) > 0.5,
                         resample_map(baselines.mean_texture, R), resample_map(baselines.mean_displacement, R))


def baked_frame_names(baked_dir) -> list[str]:
    """Frames a baked dataset holds: ``dataset.json`` ``frames_baked``, else the maps in ``frames/``."""
    from pathlib import Path

    from uvatar.avh.bake.dataset import read_dataset_info

    info = read_dataset_info(Path(baked_dir))
    if "frames_baked" in info:
        return list(info["frames_baked"])
    return sorted(p.stem for p in (Path(baked_dir) / "frames").glob("*.npz"))
