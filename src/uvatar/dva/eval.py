"""Evaluate a DVA run on held-out cameras in held-out poses (``uvatar eval dva RUN CAP --json m.json``).

For each test frame x test camera of the source's protocol (see :mod:`uvatar.dva.data`), the avatar is
driven by ``driving_views`` training cameras (evenly spread over the run's training cameras) at that
frame (each frame's fit first refined against those views, :mod:`uvatar.dva.refine`, unless
``refine_pose`` is 0, then a residual of its decoded primitives fitted to them, :mod:`uvatar.dva.residual`,
unless ``refine_residual`` is 0), rendered in the held-out camera over that camera's background colour (median of
the pixels outside the mask) and compared with the photo: PSNR (dB) and SSIM from :mod:`uvatar.render.metrics`.
``psnr_db`` / ``ssim`` keep the source's protocol: the full image, or inside the projected body box
for ZJU-MoCap (Neural Body). Two protocols shared with ``uvatar eval avh`` are always reported too:
``psnr_db_full`` / ``ssim_full`` over the full image, and ``psnr_db_union_mask`` / ``ssim_union_mask``
inside the union of the predicted mask (alpha > 0.5) and the photo's mask; and
``psnr_db_person_mask`` / ``ssim_person_mask`` inside the photo's person mask alone, that SSIM split at the
outline (``ssim_person_edge`` / ``ssim_person_interior``) with the render's mean opacity in each part
(``opacity_person_edge`` / ``opacity_person_interior``, :func:`edge_scores`). The same scores
for the two baselines of :mod:`uvatar.dva.baseline` (the fitted body in the driving views' mean person
colour; the fitted body textured with the driving views' pixels) are in ``baseline_mean_colour`` and
``baseline_projective_texture``. Side-by-side comparison images (photo | render | 4x |error| | mean
colour | projective texture) are written beside the JSON.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from uvatar.dva.baseline import mean_colour, mean_colour_render, projective_texture, textured_body_render
from uvatar.dva.dataset import FrameBank
from uvatar.dva.drive import render_camera
from uvatar.dva.losses import EMPTY_OPACITY
from uvatar.dva.refine import RefineConfig, frame_fit, refine_frame
from uvatar.dva.residual import ResidualConfig, fit_residual
from uvatar.io_utils import write_image, write_json

log = logging.getLogger(__name__)


def spread(items, n):
    """n items evenly spread over the list (all of them when n >= len)."""
    items = list(items)
    if n >= len(items):
        return items
    return [items[(i * len(items)) // n] for i in range(n)]


METRIC_KEYS = ("psnr_db", "ssim", "psnr_db_full", "ssim_full", "psnr_db_union_mask", "ssim_union_mask",
               "psnr_db_person_mask", "ssim_person_mask")
#: the person mask's scores split at its outline (:func:`edge_scores`)
EDGE_KEYS = ("ssim_person_edge", "ssim_person_interior", "opacity_person_edge", "opacity_person_interior")
SHARED_PROTOCOLS = ("also reported for comparison with uvatar eval avh: full-image PSNR/SSIM (psnr_db_full, "
                    "ssim_full) and PSNR/SSIM inside the union of the predicted mask (alpha > 0.5) and the "
                    "photo's mask (psnr_db_union_mask, ssim_union_mask)")


def image_scores(pred, gt, alpha, gt_mask, box=None) -> dict:
    """Scores of one render (H, W, 3) in [0, 1] against the photo: the source protocol (``box``: a
    (H, W) bool mask, or None for the full image), the full image, the union of alpha > 0.5 and
    ``gt_mask`` (NaN when that union is empty) and the photo's person mask ``gt_mask`` alone. One SSIM
    map serves every mask."""
    from uvatar.render.metrics import psnr, ssim_map, ssim_of_map

    smap = ssim_map(pred, gt)
    full_p, full_s = psnr(pred, gt), ssim_of_map(smap)
    union = (np.asarray(alpha) > 0.5) | np.asarray(gt_mask, bool)
    if union.any():
        union_p, union_s = psnr(pred, gt, union), ssim_of_map(smap, union)
    else:
        union_p = union_s = float("nan")
    person = np.asarray(gt_mask, bool)
    if person.any():
        person_p, person_s = psnr(pred, gt, person), ssim_of_map(smap, person)
    else:
        person_p = person_s = float("nan")
    main = (full_p, full_s) if box is None else (psnr(pred, gt, box), ssim_of_map(smap, box))
    return {"psnr_db": main[0], "ssim": main[1], "psnr_db_full": full_p, "ssim_full": full_s,
            "psnr_db_union_mask": union_p, "ssim_union_mask": union_s,
            "psnr_db_person_mask": person_p, "ssim_person_mask": person_s,
            **edge_scores(smap, alpha, person)}


def edge_scores(smap, alpha, gt_mask) -> dict:
    """Where the person-mask scores are lost: the mean of the render's SSIM map ``smap`` (H, W)
    (:func:`uvatar.render.metrics.ssim_map`) and its mean opacity ``alpha`` (H, W) in the mask's edge
    band (about the pixels whose SSIM window reaches past the photo's outline,
    :func:`uvatar.render.metrics.mask_edge_band`) and in the rest of the mask, its interior (NaN where a
    part is empty). Windows that leave the image do not count, as in :func:`~uvatar.render.metrics.ssim`.
    A volume that is half transparent along the outline blends the background into the person there
    (``docs/real.md``)."""
    from uvatar.render.metrics import mask_edge_band, ssim_windows_inside

    edge, interior = (part & ssim_windows_inside(np.shape(smap)) for part in mask_edge_band(gt_mask))
    alpha = np.asarray(alpha, np.float64)

    def mean(x, part):
        return float(x[part].mean()) if part.any() else float("nan")

    return {"ssim_person_edge": mean(smap, edge), "ssim_person_interior": mean(smap, interior),
            "opacity_person_edge": mean(alpha, edge), "opacity_person_interior": mean(alpha, interior)}


def _means(rows) -> dict:
    """The mean of each of :data:`METRIC_KEYS` and :data:`EDGE_KEYS` over images (NaNs left out)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a key NaN in every image stays NaN
        return {k: float(np.nanmean([r[k] for r in rows])) for k in METRIC_KEYS + EDGE_KEYS}


def _names(wanted, available, source, what: str) -> list[str]:
    from uvatar.errors import InputError

    missing = [w for w in wanted if w not in available]
    if missing:
        raise InputError(getattr(source, "root", "source"), f"{what}(s) {', '.join(missing)} not found")
    return list(wanted)


def evaluate_dva(run_dir, source, json_path=None, driving_views: int = 3, max_frames: int | None = None,
                 max_cameras: int | None = None, device="cpu", images=True, progress=True,
                 frames=None, cameras=None, body_model=None, model_dir=None,
                 marcher: str | None = None, refine_pose: int = 40, refine_residual: int = 60) -> dict:
    """Render and score; returns the metrics dict (also written to ``json_path``): the means of
    :data:`METRIC_KEYS` over frames x cameras, ``protocol``, ``per_image`` and more. ``frames`` /
    ``cameras``: names replacing the source's test frames / cameras (cameras must not drive);
    ``marcher``: the ray marcher (``RaymarchConfig.marcher``; default: the run's); ``refine_pose``:
    steps of test-time pose refinement against the driving views (:mod:`uvatar.dva.refine`; 0: the
    fits as they are), as ``uvatar eval avh`` refines its held-out fits against their scans by
    default; the baselines are posed with the same refined fit. ``refine_residual``: steps of the
    test-time residual of the decoded primitives (colour in UV, each primitive's position and size)
    fitted to the driving views after the pose (:mod:`uvatar.dva.residual`; 0: none)."""
    import torch

    from uvatar.dva.data import box_mask
    from uvatar.dva.train import load_run
    from uvatar.errors import InputError

    model, body, meta, step = load_run(run_dir, device, body_model, model_dir, marcher)
    frames = _names(frames, source.frames, source, "frame") if frames else list(source.test_frames)
    test_cams = _names(cameras, source.cameras, source, "camera") if cameras else list(source.test_cameras)
    frames = frames[:max_frames] if max_frames else frames
    test_cams = test_cams[:max_cameras] if max_cameras else test_cams
    train_cams = [c for c in meta["train_cameras"] if c in source.cameras and c not in test_cams]
    if not frames or not test_cams or not train_cams:
        raise InputError(getattr(source, "root", "source"), "no held-out frames/cameras or driving views to evaluate")
    driving = spread(train_cams, driving_views)
    cams = driving + test_cams
    bank = FrameBank(source, body, model.image_raster, model.template, frames, cams, progress)
    img_dir = Path(json_path).with_suffix("") if json_path else None
    per_image, baseline, projective = [], [], []
    drive_idx = list(range(len(driving)))
    drive_cams = [bank.cams[d] for d in drive_idx]
    drive_backs = [bank.backgrounds[d] for d in drive_idx]
    refined, residuals = {}, {}
    for fi, frame in enumerate(bank.frames):
        tex = bank.image_texture(fi, drive_idx).to(device)
        verts, rot = bank.vertices[fi].to(device), bank.rotvecs[fi].to(device)
        photos, masks = [bank.images[fi][d] for d in drive_idx], [bank.masks[fi][d] for d in drive_idx]
        if refine_pose > 0:
            rot, verts, refined[frame] = refine_frame(
                model, body, frame_fit(bank.fits, fi), tex, drive_cams, photos, masks, drive_backs,
                RefineConfig(iters=refine_pose))
            rot, verts = rot.to(device), verts.to(device)
        residual, residuals[frame] = fit_residual(
            model, verts, rot, tex, drive_cams, photos, masks, drive_backs, ResidualConfig(iters=refine_residual))
        verts_np = verts.cpu().numpy()
        photo_tex = projective_texture(model.template, verts_np, drive_cams, photos, masks)
        colour = mean_colour(photos, masks)
        for ci, cam_name in enumerate(test_cams, start=len(driving)):
            if not bank.usable[fi, ci]:
                continue   # the subject's mask there is empty for want of it (masks/views.json): nothing to score
            cam = bank.cams[ci]
            gt = bank.images[fi][ci].astype(np.float32) / 255.0
            if (cam.height, cam.width) != gt.shape[:2]:
                cam.height, cam.width = gt.shape[:2]
            with torch.no_grad():
                pred, alpha = render_camera(model, verts, rot, tex, cam, bank.backgrounds[ci], residual)
            box = box_mask(cam, verts_np, *gt.shape[:2]) if source.eval_box_mask else None
            scores = image_scores(pred, gt, alpha, bank.masks[fi][ci], box)
            per_image.append({"frame": frame, "camera": cam_name, **scores})
            base, base_alpha = mean_colour_render(verts_np, model.template.faces, cam, colour, bank.backgrounds[ci])
            baseline.append(image_scores(base, gt, base_alpha, bank.masks[fi][ci], box))
            proj, proj_alpha = textured_body_render(verts_np, model.template, cam, photo_tex, bank.backgrounds[ci])
            projective.append(image_scores(proj, gt, proj_alpha, bank.masks[fi][ci], box))
            if images and img_dir is not None:
                err = np.clip(np.abs(pred - gt) * 4, 0, 1)
                write_image(img_dir / f"{frame}_{cam_name}.png", np.concatenate([gt, pred, err, base, proj], 1))
    result = {
        **_means(per_image),
        "baseline_mean_colour": _means(baseline),
        "baseline_projective_texture": _means(projective),
        "protocol": (source.protocol.replace("{driving}", str(len(driving))) + f"; driving views {driving}; "
                     + (f"each test frame's fit refined against its driving views ({refine_pose} steps); "
                        if refine_pose > 0 else "the fits as they are; ")
                     + (f"a residual of the decoded primitives fitted to the driving views ({refine_residual} "
                        "steps); " if refine_residual > 0 else "") + SHARED_PROTOCOLS),
        "frames": bank.frames, "cameras": test_cams, "driving_cameras": driving, "train_steps": step,
        "skipped_frames": bank.skipped, "per_image": per_image,
        "refine_pose": {"iters": int(refine_pose), "frames": refined} if refine_pose > 0 else None,
        "refine_residual": {"iters": int(refine_residual), "frames": residuals} if refine_residual > 0 else None,
        "images": str(img_dir) if (images and img_dir is not None) else None,
    }
    inside = result.get("opacity_person_interior", float("nan"))
    result["empty"] = bool(inside < EMPTY_OPACITY) if np.isfinite(inside) else None
    if result["empty"]:
        log.warning("the avatar renders no person on the test views: its opacity inside the person's mask "
                    "averages %.3f (a trained avatar: ~1); its run's summary says whether it was empty "
                    "when training ended (run.json: empty)", inside)
    if json_path:
        write_json(json_path, result)
    return result
