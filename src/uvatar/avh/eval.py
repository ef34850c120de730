"""Evaluate an exported avatar on held-out poses: ``uvatar eval AVATAR CAPTURE --json m.json``.

For each held-out frame (``gt/info.json`` ``heldout_frames``; else every capture frame; or the
frames named in ``EvalConfig.frames``) the avatar and the ground-truth scan are rendered from the
capture's cameras (or those named in ``EvalConfig.cameras``; an orbit of 4 cameras when it has none)
with the same renderer (white background, the synthetic studio's photos are made the same way).
Two image protocols, both reported: ``psnr_db`` / ``ssim`` (= ``*_union_mask``) inside the union of
the two foreground masks, and ``psnr_db_full`` / ``ssim_full`` over the full image. Geometry error: distance in mm between the predicted
clothed surface per texel (posed body texel + displacement) and ``gt/frames/<f>.npz`` ``surface``,
over ``mask``. The same numbers for two baselines:

- ``mean_texture``: the body with the κ-weighted mean training texture and no displacement;
- ``nearest_pose``: the baked maps of the training frame whose encoded pose (sin, cos of the
  conditioning angles) is nearest (displacement outliers > 5 cm zeroed, as in training), its
  displacement in the avatar's frame (rest or body), re-posed exactly like the avatar's;
- ``nearest_time`` (a real take only: scans, no ``gt/``, frames named by take numbers): the baked maps
  of the training frame nearest in the take's time. Not a pose-driven method: a diagnostic of how
  much of the unseen frames' appearance is drift over time (the cloth settling, the light of a
  texture that lags its mesh) rather than a function of the pose, which no pose-driven generator
  can carry.

All three go through the same runtime (subdivision, gutter fill of texels outside the UV charts).
More avatars (``others``, e.g. the other generator conditioning) are evaluated in the same loop.

The pose-dependent part (:mod:`uvatar.avh.pose_metrics`): per method, R² of its texture and
displacement maps against the studio's true maps over confident texels, and every metric binned
by the held-out pose's distance to its nearest training pose. Frames the bake also processed (not
trained on) give two more (:mod:`uvatar.avh.own_bake`): ``bake_ceiling``, the own bake's R² against
the truth (how much of the pose-dependent variance survives the bake), and each method's
``<kind>_r2_vs_bake``, its R² against the frame's own baked maps (no ground truth needed).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.data import load_baked_frames
from uvatar.avh.eval_metrics import (
    METRIC_KEYS,
    bake_ceiling,
    crop_to_masks,
    error_image,
    image_metrics,
    own_bake_r2,
    scaled_camera,
    surface_error_mm,
    uv_r2,
    write_comparison_images,
)
from uvatar.avh.eval_scan import (
    OWN_BAKE_PROTOCOL,
    SCAN_PROTOCOL,
    RegionLabels,
    ScanSurface,
    baked_frame_names,
    geometry_summary,
    pixel_regions,
    pool_regions,
    region_image_metrics,
    scan_geometry_mm,
)
from uvatar.avh.model import with_orientation
from uvatar.avh.own_bake import OwnBakes, clean_displacements
from uvatar.avh.pose_metrics import R2Sums, distance_bins, pose_distance_deg
from uvatar.avh.poses import heldout_frames
from uvatar.avh.runtime import AvatarRuntime
from uvatar.errors import InputError, check_values

log = logging.getLogger(__name__)

METHODS = ("avh", "mean_texture", "nearest_pose")
SHORT_NAMES = {"avh": "AVH", "mean_texture": "mean tex", "nearest_pose": "nearest", "nearest_time": "nearest in time",
               "own_bake": "own bake"}
TIME_PROTOCOL = ("; nearest_time (a real take: no gt/, frames named by the take's frame numbers): the baked maps of "
                 "the training frame nearest in frame number (ties: the earlier), re-posed like nearest_pose; not "
                 "pose-driven, it measures how much of the unseen frames is drift over time rather than pose")
#: the frames each split names, the protocol's first clause
SPLIT_PROTOCOL = {"heldout": "held-out frames (gt/info.json heldout_frames), not trained on",
                  "frames given": "the frames given (--frames; unseen when they lie outside the range the selection "
                                  "chose training frames from: nearest_training_distance_deg says how far they are)"}
PROTOCOL = ("; avatar and ground-truth scan "
            "rendered with the same ray-cast renderer from each capture camera (white background, no shading); "
            "PSNR (dB) and SSIM (Gaussian window sigma 1.5) over the union of the two foreground masks "
            "(psnr_db, ssim = psnr_db_union_mask, ssim_union_mask) and over the full image (psnr_db_full, "
            "ssim_full), averaged over frames x cameras; geometry: mean / median / p90 distance (mm) between predicted "
            "and ground-truth clothed surface point per texel over gt mask (texels at the gt resolution); "
            "pose-dependent part: texture_r2 / displacement_r2 = 1 - sum |pred - gt|^2 / sum |mean - gt|^2 pooled over "
            "the held-out frames' confident texels (gt mask, training frames' mean kappa > 0.5, no fingers/toes), "
            "mean = the training frames' mean map; texture at the avatar's resolution against gt/ texture "
            "area-averaged to it, displacement as the clothed surface point per texel against gt/ surface (gt "
            "resolution); nearest_training_distance_deg: mean over conditioning joints of the geodesic angle to "
            "the nearest training pose; distance_bins: frames split at its median; an avatar with the studio "
            "orientation (model_config.orientation = studio) takes the body's Rh as its last conditioning joint, and "
            "so do the nearest-pose retrieval and the pose distance; bake_ceiling: each held-out frame's own bake "
            "(BAKED/frames/<f>, not trained on) scored against gt like a method, the part of the true pose-dependent "
            "variance that survives the bake, beside every method's R² on the same frames; <kind>_r2_vs_bake: each "
            "method against the frame's own baked maps instead of gt (the measure without gt), same reference, over "
            "the texels where the own bake is confident (kappa > 0.5 for texture; valid, inlier, w > 0 for displacement)")


@dataclass(frozen=True)
class EvalConfig:
    """max_frames / max_cameras: limits (None = all); frames / cameras: evaluate exactly these frame /
    camera names (None = held-out frames / all cameras; applied before the limits); image_size: render
    at this width (cameras' intrinsics scaled; None = capture size); levels / scheme: avatar
    subdivision; sheets_per_camera: one comparison image per frame x camera (``<frame>_<camera>.png``)
    instead of one per frame (first camera, ``<frame>.png``)."""

    max_frames: int | None = None
    max_cameras: int | None = None
    frames: tuple[str, ...] | None = None
    cameras: tuple[str, ...] | None = None
    image_size: int | None = None
    levels: int = 2
    scheme: str = "midpoint"
    progress: bool = True
    sheets_per_camera: bool = False
    pose_source: str = "refined"   # "refined": the fit refined against the frame's scan, as bake does for
                                   # training frames; "fit": the capture's fit as is (pose error included)
    orbit_views: int = 4           # virtual cameras around the person when the capture has none (scans only)
    orbit_size: int = 512          # their image size (pixels, square)
    workers: int = 1               # frames evaluated in this many processes (1: in this one); the same figures

    def __post_init__(self) -> None:
        check_values([
            (self.image_size is None or self.image_size >= 16,
             f"image_size must be at least 16 pixels, got {self.image_size}"),
            (self.pose_source in POSE_PROTOCOL, f"pose_source must be one of {', '.join(POSE_PROTOCOL)}, "
                                                f"got {self.pose_source!r}"),
            (1 <= self.orbit_views <= 64, f"orbit_views must be in 1..64, got {self.orbit_views}"),
            (16 <= self.orbit_size <= 4096, f"orbit_size must be in 16..4096 pixels, got {self.orbit_size}"),
            (self.workers >= 1, f"workers must be at least 1, got {self.workers}")])


ORBIT_DISTANCE_M = 3.0    # virtual cameras' distance to the scan's centre (40° field of view)
ORBIT_ELEVATION_DEG = 10.0


def orbit_protocol(config: EvalConfig) -> str:
    return (f"; cameras: the capture has none, so {config.orbit_views} virtual cameras evenly spaced in azimuth "
            f"around the +Y axis through each frame's scan centre (azimuth 0 on +Z), {ORBIT_DISTANCE_M:g} m away, "
            f"{ORBIT_ELEVATION_DEG:g} deg above, 40 deg field of view, {config.orbit_size}x{config.orbit_size} px, "
            "white background, the real textured scan and each method rendered from the same cameras")


POSE_PROTOCOL = {
    "refined": "; poses: each held-out frame's fit refined against its scan with the bake's skeleton "
               "refinement (the same procedure that produced the training poses), so the metrics measure the "
               "avatar, not the fit noise",
    "fit": "; poses: the capture's fits as they are (fit noise included)",
}


def refined_fit(body, fit, scan):
    """The fit refined against ``scan`` exactly as ``uvatar bake`` refines training frames."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import refine_fit
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.threads import single_threaded

    with single_threaded():
        refined, _ = refine_fit(body, fit, ScanSurface.build(scan.vertices, scan.faces), PoseRefineConfig())
    return refined


def encoded_conditioning(poses: np.ndarray, conditioning) -> np.ndarray:
    """(N, J·3) -> (N, 6·J_c) (sin, cos) of the conditioning angles (numpy twin of the model input)."""
    a = np.asarray(poses, np.float32).reshape(len(poses), -1, 3)[:, list(conditioning)].reshape(len(poses), -1)
    return np.stack([np.sin(a), np.cos(a)], -1).reshape(len(a), -1)


class Baselines:
    """Mean-texture and nearest-training-pose maps from the baked training frames."""

    def __init__(self, baked_dir: str | Path, train_frames: list[str], resolution: int, conditioning,
                 outlier_threshold: float = 0.05, body=None, displacement_frame: str = "body", shape=None,
                 orientation_root: int | None = None):
        self.outlier_threshold = outlier_threshold
        frames = load_baked_frames(baked_dir, train_frames, resolution)
        k = frames.kappa[..., None] * frames.valid[..., None]
        ksum = k.sum(0)
        plain = frames.texture.mean(0)
        self.mean_texture = np.where(ksum > 1e-6, (k * frames.texture).sum(0) / np.maximum(ksum, 1e-6), plain)
        # cleaned as training sees it: zero outside the UV charts and where any axis exceeds the threshold
        self.displacement, kept = clean_displacements(frames, outlier_threshold, displacement_frame, body, shape)
        good = kept.sum(0)[..., None]
        self.mean_displacement = (self.displacement.sum(0) / np.maximum(good, 1)).astype(np.float32)
        self.mean_kappa = (frames.kappa * frames.valid).mean(0).astype(np.float32)
        self.frames = frames
        # the poses the avatar is conditioned on: a studio-orientation avatar's root slot holds Rh, so the
        # nearest training pose is then also the nearest in orientation (the same input as the avatar's)
        self.poses = frames.poses if orientation_root is None else with_orientation(frames.poses, frames.Rh,
                                                                                     orientation_root)
        self.codes = encoded_conditioning(self.poses, conditioning)
        self.conditioning = list(conditioning)

    def nearest(self, pose: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        """(index, texture (R, R, 3), displacement (R, R, 3)) of the nearest training pose.

        The displacement is in the avatar's frame (``displacement_frame``: rest or body), so the
        runtime re-poses it exactly like the generator's; it is cleaned as training sees it.
        """
        code = encoded_conditioning(pose[None], self.conditioning)
        i = int(np.argmin(((self.codes - code) ** 2).sum(1)))
        return i, self.frames.texture[i], self.displacement[i]

    def nearest_in_time(self, frame: str) -> tuple[int, np.ndarray, np.ndarray] | None:
        """(index, texture, displacement) of the training frame nearest to ``frame`` in frame number
        (ties: the earlier); None unless every name is a frame number."""
        names = self.frames.names
        if not (frame.isdigit() and names and all(n.isdigit() for n in names)):
            return None
        i = int(np.argmin([abs(int(n) - int(frame)) + 1e-3 * (int(n) > int(frame)) for n in names]))
        return i, self.frames.texture[i], self.displacement[i]


def _summary(values: list[dict]) -> dict:
    out = {}
    for key in METRIC_KEYS:
        v = np.array([x[key] for x in values if np.isfinite(x.get(key, np.nan))])
        out[key] = float(v.mean()) if len(v) else None
    return out


def _geometry_summary(errors: list[np.ndarray]) -> dict:
    if not errors:
        return {}
    e = np.concatenate(errors)
    return {"geometry_mm": float(e.mean()), "geometry_median_mm": float(np.median(e)),
            "geometry_p90_mm": float(np.percentile(e, 90))}


@dataclass
class _EvalContext:
    """What every evaluated frame shares (built once per process: :func:`_eval_context`)."""

    capture: object
    runtime: AvatarRuntime
    runtimes: dict
    methods: list
    baselines: object
    baked_dir: Path
    frames: list
    split: str
    cams: dict
    camera_names: list | None
    own_bakes: object
    own_frames: set
    regions: object
    config: EvalConfig


def _eval_context(avatar_dir, capture_root, config: EvalConfig, baked_dir=None, body=None, others=None) -> _EvalContext:
    from uvatar.capture import Capture

    capture = Capture(capture_root)
    runtime = AvatarRuntime(avatar_dir, body=body, levels=config.levels, scheme=config.scheme)
    runtimes = {"avh": runtime, **{name: AvatarRuntime(path, body=runtime.body, levels=config.levels,
                                                       scheme=config.scheme) for name, path in (others or {}).items()}}
    methods = [*runtimes, "mean_texture", "nearest_pose"]
    training = runtime.meta.get("training") or {}
    baked_dir = Path(baked_dir or training.get("baked") or "")
    if not (baked_dir / "dataset.json").is_file():
        raise InputError(baked_dir, "baked training data not found (needed for the baselines); pass baked_dir")
    baselines = Baselines(baked_dir, training.get("train_frames") or [], runtime.resolution, runtime.conditioning,
                          body=runtime.body, displacement_frame=runtime.displacement_frame, shape=runtime.shape,
                          orientation_root=runtime.conditioning[-1] if runtime.orientation == "studio" else None)
    try:
        frames = heldout_frames(capture.root)
        split = "heldout"
    except InputError:
        frames, split = list(capture.frames), "all capture frames (no gt/info.json heldout_frames)"
        if not config.frames:
            log.warning("no held-out frames listed; evaluating on every capture frame")
    if config.frames:
        frames, split = select_names(config.frames, capture.frames, capture.root, "frame"), "frames given"
    real_take = not (capture.gt_dir / "frames").is_dir()
    if real_take and frames and baselines.nearest_in_time(frames[0]) is not None:
        methods.append("nearest_time")
    frames = frames[: config.max_frames] if config.max_frames else frames
    cams = capture.cameras()
    if config.cameras:
        if not cams:
            raise InputError(capture.root, "cameras were named but the capture has none")
        cams = {c: cams[c] for c in select_names(config.cameras, list(cams), capture.root, "camera")}
    camera_names = list(cams)[: config.max_cameras or None] if cams else None
    own_bakes = OwnBakes(baked_dir, runtime.resolution, runtime.displacement_frame, runtime.body, runtime.shape,
                         baselines.outlier_threshold)
    own_frames = set(baked_frame_names(baked_dir)) & set(frames)  # eval frames baked on their own too
    if own_frames:  # the frame's own bake re-posed like the avatar: what the maps can reach (an upper bound)
        methods.append("own_bake")
    return _EvalContext(capture, runtime, runtimes, methods, baselines, baked_dir, frames, split, cams, camera_names,
                        own_bakes, own_frames, RegionLabels(runtime), config)


class _Tally:
    """The sums and lists the eval adds each frame to (one per frame in a worker, merged in frame order:
    every sum then adds the same numbers in the same order as one process would)."""

    def __init__(self, ctx: _EvalContext):
        methods = ctx.methods
        self.results = {m: [] for m in methods}
        self.geometry = {m: [] for m in methods}
        self.region_views = {m: [] for m in methods}
        self.scan_geometry = {m: [] for m in methods}
        self.r2 = {"texture": R2Sums(), "displacement": R2Sums()}
        self.r2_ceiling = {"texture": R2Sums(), "displacement": R2Sums()}  # frames with an own bake, own bake included
        self.r2_vs_bake = {"texture": R2Sums(), "displacement": R2Sums()}
        self.own_r2 = ctx.regions.own_bake_r2(ctx.runtime, ctx.baselines) if ctx.own_frames else None
        self.per_frame, self.sheets = [], []
        self.cameras = 0   # views per frame (the last frame's)

    def merge(self, other: _Tally) -> None:
        for mine, theirs in ((self.results, other.results), (self.geometry, other.geometry),
                             (self.region_views, other.region_views), (self.scan_geometry, other.scan_geometry)):
            for m, rows in theirs.items():
                mine[m].extend(rows)
        for mine, theirs in ((self.r2, other.r2), (self.r2_ceiling, other.r2_ceiling),
                             (self.r2_vs_bake, other.r2_vs_bake)):
            for kind, sums in theirs.items():
                mine[kind].merge(sums)
        if self.own_r2 is not None and other.own_r2 is not None:
            self.own_r2.merge(other.own_r2)
        self.per_frame.extend(other.per_frame)
        self.sheets.extend(other.sheets)
        self.cameras = other.cameras or self.cameras


def _frame_task(shared: tuple, frame: str) -> _Tally:
    """One frame in a worker process: its context built once per process (:func:`uvatar.parallel.worker_cache`)."""
    from uvatar.parallel import worker_cache

    key = ("avh-eval", repr(shared[:4]), repr(shared[5]))   # the body (shared[4]) is the same for one eval
    ctx = worker_cache(key, lambda: _eval_context(*shared))
    tally = _Tally(ctx)
    _evaluate_frame(ctx, frame, tally)
    return tally


def _evaluate_frame(ctx: _EvalContext, frame: str, tally: _Tally) -> None:
    """Evaluate one frame into ``tally`` (a frame whose fit or scan cannot be read is skipped, said once)."""
    from uvatar.geometry import RayCaster
    from uvatar.render import orbit_cameras, render_mesh
    from uvatar.render.metrics import error_map, ssim_map

    capture, runtime, runtimes, baselines, config = ctx.capture, ctx.runtime, ctx.runtimes, ctx.baselines, ctx.config
    methods, cams, camera_names, regions = ctx.methods, ctx.cams, ctx.camera_names, ctx.regions
    own_bakes, own_frames = ctx.own_bakes, ctx.own_frames
    results, geometry, region_views, scan_geometry = tally.results, tally.geometry, tally.region_views, tally.scan_geometry
    r2, r2_ceiling, r2_vs_bake, own_r2 = tally.r2, tally.r2_ceiling, tally.r2_vs_bake, tally.own_r2
    per_frame, sheets = tally.per_frame, tally.sheets
    try:
        fit, scan = capture.load_fit(frame), capture.load_scan(frame)
    except InputError as exc:
        log.warning("skipping frame %s: %s", frame, exc)
        return
    if config.pose_source == "refined":
        fit = refined_fit(runtime.body, fit, scan)
    pose = np.asarray(fit.poses, np.float32).reshape(-1)
    Rh = np.asarray(fit.Rh, np.float32).reshape(3)
    shape = np.asarray(fit.shapes, np.float32) if np.size(fit.shapes) else None
    base = runtime.posed_vertices(pose[None], Rh[None], np.asarray(fit.Th, np.float32).reshape(1, 3),
                                  np.array([fit.scale], np.float32), shape)[0]
    conditioned = runtime.conditioning_poses(pose[None], Rh[None])[0]  # what the avatar and retrieval see
    nn_index, nn_tex, nn_disp = baselines.nearest(conditioned)
    maps = {}
    for m, rt in runtimes.items():
        tex, disp = rt.generate(pose[None], Rh=Rh[None])
        maps[m] = (tex[0], disp[0])
    maps.update({"mean_texture": (baselines.mean_texture, None), "nearest_pose": (nn_tex, nn_disp)})
    near_time = baselines.nearest_in_time(frame) if "nearest_time" in methods else None
    if near_time is not None:
        maps["nearest_time"] = near_time[1:]
    own = own_bakes.get(frame) if frame in own_frames else None
    if own is not None:
        entry_r2 = own_r2.add(frame, dict(maps), own.texture, own.displacement, own.kappa, own.valid)
        maps["own_bake"] = (own.texture, own.displacement)
    rotations = runtime.skinning_rotations(pose[None])[0]
    meshes = {m: runtimes.get(m, runtime).mesh(base, t, d, Rh, rotations=rotations) for m, (t, d) in maps.items()}
    cameras = list(cams.values()) if cams else orbit_cameras(
        0.5 * (scan.vertices.min(0) + scan.vertices.max(0)), ORBIT_DISTANCE_M, config.orbit_views,
        ORBIT_ELEVATION_DEG, width=config.orbit_size, height=config.orbit_size)
    cameras = [scaled_camera(c, config.image_size) for c in cameras[: config.max_cameras or None]]
    tally.cameras = len(cameras)
    casters = {m: RayCaster(mesh.vertices, mesh.faces) for m, mesh in meshes.items()}
    gt_caster = RayCaster(scan.vertices, scan.faces)
    distances = pose_distance_deg(conditioned[None], baselines.poses, baselines.conditioning)[0]
    entry = {"frame": frame, "nearest_training_frame": baselines.frames.names[nn_index],
             "nearest_training_distance_deg": float(distances.min()),
             "nearest_pose_baseline_distance_deg": float(distances[nn_index])}
    if near_time is not None:
        entry["nearest_time_training_frame"] = baselines.frames.names[near_time[0]]
    for ci, cam in enumerate(cameras):
        gt = render_mesh(scan.vertices, scan.faces, cam, scan.uvs, scan.uv_faces, scan.texture, raycaster=gt_caster)
        row, masks, labels = [gt.rgb], [gt.mask], ["ground truth"]
        errors, error_labels = [np.ones_like(gt.rgb)], ["|error| x4 (black = 0)"]
        for m, mesh in meshes.items():
            r = render_mesh(mesh.vertices, mesh.faces, cam, mesh.uvs, mesh.uv_faces, mesh.texture,
                            raycaster=casters[m])
            # one SSIM map and one error map for the whole image, its masks and its regions
            smap, err = ssim_map(r.rgb, gt.rgb), error_map(r.rgb, gt.rgb)
            results[m].append(image_metrics(r.rgb, r.mask, gt.rgb, gt.mask, smap, err))
            pix = pixel_regions(casters[m], cam, regions.face_labels(mesh), r.mask | gt.mask)
            region_views[m].append(region_image_metrics(r.rgb, r.mask, gt.rgb, gt.mask, pix, smap, err))
            row.append(r.rgb)
            masks.append(r.mask)
            labels.append(f"{SHORT_NAMES.get(m, m.replace('_', ' '))} {results[m][-1]['psnr_db']:.1f} dB")
            errors.append(error_image(r.rgb, gt.rgb))
            error_labels.append(f"IoU {results[m][-1]['silhouette_iou']:.3f}")
        if (config.sheets_per_camera and camera_names) or ci == 0:
            name = f"{frame}_{camera_names[ci]}" if config.sheets_per_camera and camera_names else frame
            sheets.append((name, crop_to_masks(row + errors, masks), labels + error_labels, len(row)))
    gt_npz = capture.gt_dir / "frames" / f"{frame}.npz"
    if gt_npz.is_file():
        with np.load(gt_npz) as z:
            gt_maps = {k: z[k].astype(np.float32) for k in ("surface", "texture") if k in z.files}
            mask = z["mask"].astype(bool)
        for m, (_, d) in maps.items():
            err = surface_error_mm(runtime, base, d, Rh, gt_maps["surface"], mask, rotations)
            geometry[m].append(err)
            entry[f"{m}_geometry_mm"] = float(err.mean()) if len(err) else None
        entry.update(uv_r2(runtime, baselines, maps, base, Rh, rotations, gt_maps, mask, r2))
    else:  # a real take: the scan is the only truth for the geometry
        surface = ScanSurface(scan.vertices, scan.faces)   # indexed and sampled once for every method
        for m, mesh in meshes.items():
            part = scan_geometry_mm(mesh.vertices, mesh.faces, regions.face_labels(mesh), scan=surface)
            scan_geometry[m].append(part)
            entry[f"{m}_chamfer_mm"] = float(0.5 * (part["avatar_to_scan"].mean() + part["scan_to_avatar"].mean()))
    if own is not None:
        entry.update(entry_r2)
    own_ceiling = (own if own is not None else own_bakes.get(frame)) if gt_npz.is_file() else None
    if own_ceiling is not None:
        entry.update(own_bake_r2(runtime, baselines, {m: v for m, v in maps.items() if m != "own_bake"},
                                  own_ceiling, base, Rh, rotations, (gt_maps, mask), r2_ceiling, r2_vs_bake))
    for m in maps:
        n = len(cameras)
        for key in ("psnr_db", "psnr_db_inside_both"):
            entry[f"{m}_{key}"] = float(np.nanmean([x[key] for x in results[m][-n:]]))
    per_frame.append(entry)


def evaluate_avatar(avatar_dir: str | Path, capture_root: str | Path, config: EvalConfig = EvalConfig(),
                    baked_dir: str | Path | None = None, image_dir: str | Path | None = None, body=None,
                    others: dict[str, str | Path] | None = None) -> dict:
    """Metrics dict (``protocol``, ``frames``, ``cameras``, ``avh``, ``others``, ``baselines``,
    ``distance_bins``, ``per_frame``).

    ``others``: {name: avatar folder} evaluated beside ``avatar_dir`` on the same frames, cameras and
    poses (same body; e.g. another generator conditioning); the baselines come from ``avatar_dir``'s
    training data."""
    from tqdm import tqdm

    ctx = _eval_context(avatar_dir, capture_root, config, baked_dir, body, others)
    capture, runtimes, methods = ctx.capture, ctx.runtimes, ctx.methods
    frames, split, cams, camera_names, own_frames = ctx.frames, ctx.split, ctx.cams, ctx.camera_names, ctx.own_frames
    tally = _Tally(ctx)
    if config.workers <= 1 or len(frames) <= 1:
        for frame in tqdm(frames, desc="eval avh", disable=not config.progress):
            _evaluate_frame(ctx, frame, tally)
    else:   # frames in worker processes, their tallies merged in frame order (the same figures)
        from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks
        from uvatar.threads import limit_process_to_one_thread

        # the body goes to the workers when the caller gave one (else each loads the avatar's by name)
        shared = (str(avatar_dir), str(capture_root), config, str(ctx.baked_dir), body, others)
        done = {}
        for frame, part in run_tasks(_frame_task, frames, shared, ExecutorConfig(workers=config.workers),
                                     desc="eval avh", progress=config.progress,
                                     initializer=limit_process_to_one_thread):
            if isinstance(part, TaskFailure):
                log.warning("skipping frame %s: %s", frame, part.reason)
            else:
                done[frame] = part
        for frame in frames:
            if frame in done:
                tally.merge(done[frame])
    results, geometry, region_views, scan_geometry = tally.results, tally.geometry, tally.region_views, tally.scan_geometry
    r2, r2_ceiling, r2_vs_bake, own_r2 = tally.r2, tally.r2_ceiling, tally.r2_vs_bake, tally.own_r2
    per_frame, sheets = tally.per_frame, tally.sheets
    if not per_frame:
        raise InputError(capture.root, "no frame could be evaluated")
    summary = {m: {**_summary(results[m]), **_geometry_summary(geometry[m])} for m in methods}
    for kind, sums in r2.items():
        for m, value in sums.r2().items():
            summary[m][f"{kind}_r2"] = value
    own = own_r2.summary() if own_r2 is not None and own_r2.frames else {}
    for m in methods:
        if scan_geometry[m]:
            summary[m]["scan_geometry"] = geometry_summary(scan_geometry[m])
            summary[m]["geometry_mm"] = summary[m]["scan_geometry"]["chamfer_mm"]
        if m in own:
            summary[m].update({k: v for k, v in own[m].items() if k != "regions"})
        summary[m]["regions"] = _merge_regions(pool_regions(region_views[m]),
                                               summary[m].get("scan_geometry", {}).get("regions", {}),
                                               own.get(m, {}).get("regions", {}))
    for kind, sums in r2_vs_bake.items():
        for m, value in sums.r2().items():
            summary[m][f"{kind}_r2_vs_bake"] = value
    conditioning = {m: rt.meta.get("model_config", {}).get("conditioning", "global") for m, rt in runtimes.items()}
    protocol = SPLIT_PROTOCOL.get(split, split) + PROTOCOL + POSE_PROTOCOL[config.pose_source] + ("" if cams else orbit_protocol(config))
    if any(scan_geometry.values()):
        protocol += SCAN_PROTOCOL
    if own_r2 is not None and own_r2.frames:
        protocol += OWN_BAKE_PROTOCOL
    if "nearest_time" in methods:
        protocol += TIME_PROTOCOL
    out = {"protocol": protocol, "pose_source": config.pose_source, "own_bake_frames": own_r2.frames if own_r2 else [],
           "split": split, "frames": [e["frame"] for e in per_frame],
           "cameras": tally.cameras, "camera_names": camera_names, "avatar": str(avatar_dir), "capture": str(capture_root),
           "avh": summary["avh"], "others": {m: summary[m] for m in runtimes if m != "avh"},
           "avatars": {m: {"path": str(rt.avatar_dir), "conditioning": conditioning[m]} for m, rt in runtimes.items()},
           "baselines": {m: summary[m] for m in ("mean_texture", "nearest_pose", "nearest_time") if m in summary},
           "upper_bound": {"own_bake": summary["own_bake"]} if own_frames else {},
           "nearest_training_distance_deg": {e["frame"]: e["nearest_training_distance_deg"] for e in per_frame},
           "distance_bins": distance_bins(per_frame, methods),
           "bake_ceiling": bake_ceiling(per_frame, r2_ceiling),
           "per_frame": per_frame, "config": asdict(config)}
    if image_dir is not None:
        out["images"] = write_comparison_images(image_dir, sheets)
    return out


def _merge_regions(*parts: dict) -> dict:
    out: dict = {}
    for part in parts:
        for region, values in part.items():
            out.setdefault(region, {}).update(values)
    return out


def select_names(wanted, available, root, what: str) -> list[str]:
    """``wanted`` names in the given order; InputError naming ``root`` when one is not ``available``."""
    available = set(available)
    missing = [w for w in wanted if w not in available]
    if missing:
        have = sorted(available)
        shown = ", ".join(have) if len(have) <= 8 else f"{', '.join(have[:3])}, ..., {', '.join(have[-2:])}"
        raise InputError(root, f"{what}(s) {', '.join(missing)} not found (have {len(have)}: {shown})")
    return list(wanted)


