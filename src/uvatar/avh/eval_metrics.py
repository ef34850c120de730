"""What ``uvatar eval`` measures on one rendered view or one frame's maps: image metrics (PSNR / SSIM over
the mask union, inside both masks and the full image; silhouette IoU), error images and contact sheets,
the predicted clothed surface per texel and its distance to the truth, and the pose-dependent R² of a
frame's maps against the truth (:func:`uv_r2`) and against the frame's own bake (:func:`own_bake_r2`).
``baselines``: a :class:`uvatar.avh.eval.Baselines` (the training frames' mean maps and κ).
:mod:`uvatar.avh.eval` runs them over the frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.avh.data import resample_map, rotvec_to_rotmat
from uvatar.avh.own_bake import r2_against_own_bake
from uvatar.avh.pose_metrics import R2Sums
from uvatar.avh.runtime import AvatarRuntime

__all__ = ["METRIC_KEYS", "bake_ceiling", "crop_to_masks", "error_image", "image_metrics", "own_bake_r2",
           "predicted_surface", "scaled_camera", "surface_error_mm", "uv_r2", "write_comparison_images"]


def scaled_camera(camera, width: int | None):
    """Camera for its image resized to ``width`` pixels wide, aspect kept (None: unchanged)."""
    if not width or width == camera.width:
        return camera
    return camera.scaled_to_width(width)


METRIC_KEYS = ("psnr_db", "ssim", "psnr_db_union_mask", "ssim_union_mask", "psnr_db_full", "ssim_full",
               "psnr_db_inside_both", "silhouette_iou")


def image_metrics(pred_rgb, pred_mask, gt_rgb, gt_mask, smap=None, err=None) -> dict:
    """PSNR (dB) / SSIM inside the union of the masks (``psnr_db``, ``ssim`` and the same values as
    ``*_union_mask``; NaN when the union is empty) and over the full image (``*_full``). ``smap``, ``err``:
    the images' :func:`~uvatar.render.metrics.ssim_map` and :func:`~uvatar.render.metrics.error_map` when
    the caller has them (made here otherwise).

    Two diagnostics split the union error into its causes: ``psnr_db_inside_both`` (appearance: PSNR
    where both masks cover the pixel) and ``silhouette_iou`` (shape: |A ∩ B| / |A ∪ B| of the masks).
    """
    from uvatar.render.metrics import error_map, psnr_of_error_map, ssim_map, ssim_of_map

    smap = ssim_map(pred_rgb, gt_rgb) if smap is None else smap  # one map for both masks
    err = error_map(pred_rgb, gt_rgb) if err is None else err     # one error map for every mask
    full = {"psnr_db_full": psnr_of_error_map(err), "ssim_full": ssim_of_map(smap)}
    pm, gm = np.asarray(pred_mask, bool), np.asarray(gt_mask, bool)
    union, both = pm | gm, pm & gm
    if not union.any():
        p = s = float("nan")
    else:
        p, s = psnr_of_error_map(err, union), ssim_of_map(smap, union)
    inside = psnr_of_error_map(err, both) if both.any() else float("nan")
    iou = float(both.sum() / union.sum()) if union.any() else float("nan")
    return {"psnr_db": p, "ssim": s, "psnr_db_union_mask": p, "ssim_union_mask": s, **full,
            "psnr_db_inside_both": inside, "silhouette_iou": iou}


def error_image(pred_rgb, gt_rgb, gain: float = 4.0) -> np.ndarray:
    """(H, W, 3) float heat map of the per-pixel error ``gain · mean |pred − gt|`` (inferno; black = 0)."""
    import cv2

    err = np.clip(gain * np.abs(np.asarray(pred_rgb, np.float32) - np.asarray(gt_rgb, np.float32)).mean(-1), 0, 1)
    heat = cv2.applyColorMap((err * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return heat[..., ::-1].astype(np.float32) / 255.0


def surface_error_mm(runtime: AvatarRuntime, base_vertices, displacement, Rh, gt_surface, gt_mask,
                     rotations=None) -> np.ndarray:
    """Per-texel distances (mm) between predicted clothed surface and gt ``surface`` (G, G, 3) over ``gt_mask``.

    rotations: (V, 3, 3) blended skinning rotations of the pose (rest-frame avatars)."""
    pos, covered = predicted_surface(runtime, base_vertices, displacement, Rh, gt_surface.shape[0], rotations)
    m = np.asarray(gt_mask, bool) & covered
    return np.linalg.norm(pos[m] - gt_surface[m], axis=-1) * 1000.0


def predicted_surface(runtime: AvatarRuntime, base_vertices, displacement, Rh, G: int,
                      rotations=None) -> tuple[np.ndarray, np.ndarray]:
    """(predicted clothed surface point per texel (G, G, 3) world metres, texels covered (G, G) bool):
    the posed body's texel point plus the displacement map (None: none) in world axes."""
    from uvatar.geometry import rasterize_uv, texel_positions

    t = runtime.body.template
    raster = rasterize_uv(t.uvs, t.uv_faces, G)
    pos = np.asarray(texel_positions(raster, t.faces, np.asarray(base_vertices, np.float32)), np.float32)
    if displacement is not None:
        keep = resample_map(runtime.fingers_toes_mask().astype(np.float32), G) < 0.5
        d = resample_map(np.asarray(displacement, np.float32), G) * keep[..., None]
        if runtime.displacement_frame == "rest":
            from uvatar.avh.displacement_frame import rest_to_body, texel_skinning_rotations

            d = rest_to_body(d, texel_skinning_rotations(raster, t.faces, np.asarray(rotations, np.float32)))
        pos = pos + d @ rotvec_to_rotmat(np.asarray(Rh, np.float64)).T.astype(np.float32)
    return pos, raster.mask


def uv_r2(runtime: AvatarRuntime, baselines, maps: dict, base, Rh, rotations, gt_maps: dict,
           gt_mask: np.ndarray, sums: dict[str, R2Sums]) -> dict:
    """Add one frame to the texture / displacement R² sums (:mod:`uvatar.avh.pose_metrics`) over its
    confident texels; returns the frame's ``<method>_texture_r2`` / ``<method>_displacement_r2``."""
    out = {}
    R = runtime.resolution
    keep = ~runtime.fingers_toes_mask()
    if "texture" in gt_maps:
        confident = (resample_map(baselines.mean_kappa, R) > 0.5) & keep & (
            resample_map(gt_mask.astype(np.float32), R) > 0.999)
        preds = {m: resample_map(np.asarray(t, np.float32), R) for m, (t, _) in maps.items()}
        frame_r2 = sums["texture"].add(preds, baselines.mean_texture, resample_map(gt_maps["texture"], R), confident)
        out.update({f"{m}_texture_r2": v for m, v in frame_r2.items()})
    G = gt_maps["surface"].shape[0]
    mean_pos, covered = predicted_surface(runtime, base, baselines.mean_displacement, Rh, G, rotations)
    confident = (resample_map(baselines.mean_kappa, G) > 0.5) & covered & gt_mask & (
        resample_map(keep.astype(np.float32), G) > 0.5)
    preds = {m: predicted_surface(runtime, base, d, Rh, G, rotations)[0] for m, (_, d) in maps.items()}
    frame_r2 = sums["displacement"].add(preds, mean_pos, gt_maps["surface"], confident)
    out.update({f"{m}_displacement_r2": v for m, v in frame_r2.items()})
    return out


def own_bake_r2(runtime: AvatarRuntime, baselines, maps: dict, own, base, Rh, rotations,
                 gt: tuple[dict, np.ndarray] | None, ceiling: dict[str, R2Sums], vs_bake: dict[str, R2Sums]) -> dict:
    """Add a frame that has its own bake to the ceiling sums (its own bake scored against ``gt`` (maps,
    mask) like a method, beside the methods on the same frames; skipped without gt) and to the sums
    against the own bake (:mod:`uvatar.avh.own_bake`); returns the frame's ``own_bake_<kind>_r2`` and
    ``<method>_<kind>_r2_vs_bake``."""
    out = {}
    if gt is not None:
        frame = uv_r2(runtime, baselines, {**maps, "own_bake": (own.texture, own.displacement)}, base, Rh,
                       rotations, gt[0], gt[1], ceiling)
        out.update({k: v for k, v in frame.items() if k.startswith("own_bake_")})
    R = runtime.resolution

    def surface(d):
        return predicted_surface(runtime, base, d, Rh, R, rotations)[0]

    covered = predicted_surface(runtime, base, None, Rh, R)[1]
    confident = (baselines.mean_kappa > 0.5) & ~runtime.fingers_toes_mask() & covered
    out.update(r2_against_own_bake(maps, own, baselines.mean_texture, baselines.mean_displacement, confident,
                                   surface, vs_bake))
    return out


def bake_ceiling(per_frame: list[dict], sums: dict[str, R2Sums]) -> dict:
    """The ceiling of the pose-dependent R² (:mod:`uvatar.avh.own_bake`): the frames scored, the own
    bakes' ``texture_r2`` / ``displacement_r2`` against gt, and every method's on the same frames."""
    frames = [e["frame"] for e in per_frame if e.get("own_bake_displacement_r2") is not None]
    out = {"frames": frames, "texture_r2": None, "displacement_r2": None, "methods_same_frames": {}}
    for kind, s in sums.items():
        for m, value in s.r2().items():
            if m == "own_bake":
                out[f"{kind}_r2"] = value
            else:
                out["methods_same_frames"].setdefault(m, {})[f"{kind}_r2"] = value
    return out


def crop_to_masks(images: list[np.ndarray], masks: list[np.ndarray], height: int = 320, margin: int = 4):
    """Crop (H, W, 3) images to the union bounding box of ``masks`` (+ margin) and scale to ``height`` px."""
    import cv2

    union = np.logical_or.reduce(masks)
    if not union.any():
        return images
    rows, cols = np.flatnonzero(union.any(1)), np.flatnonzero(union.any(0))
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, union.shape[0])
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, union.shape[1])
    s = height / (r1 - r0)
    size = (max(int(round((c1 - c0) * s)), 1), height)
    interp = cv2.INTER_NEAREST if s > 1 else cv2.INTER_AREA
    return [cv2.resize(np.ascontiguousarray(im[r0:r1, c0:c1]), size, interpolation=interp) for im in images]


def write_comparison_images(image_dir: str | Path, sheets) -> list[str]:
    """One PNG per sheet (``<name>.png``): ground truth | AVH | mean texture | nearest pose (PSNR in
    labels), and below each method its error heat map (silhouette IoU in labels).

    sheets: (name, images, labels, columns) tuples."""
    from uvatar.io_utils import write_image
    from uvatar.render import contact_sheet

    paths = []
    for frame, row, labels, cols in sheets:
        sheet = contact_sheet(row, cols=cols, labels=labels)
        path = Path(image_dir) / f"{frame}.png"
        write_image(path, sheet)
        paths.append(str(path))
    return paths
