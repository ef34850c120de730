"""Evaluate a DVA run on held-out cameras in held-out poses (``uvatar eval dva RUN CAP --json m.json``).

For each test frame x test camera of the source's protocol (see :mod:`uvatar.dva.data`), the avatar is
driven by ``driving_views`` training cameras (evenly spread over the run's training cameras) at that
frame, rendered in the held-out camera over that camera's background colour (median of the pixels
outside the mask) and compared with the photo: PSNR (dB) and SSIM from :mod:`uvatar.render.metrics`,
over the full image, or inside the projected body box for ZJU-MoCap (Neural Body). Side-by-side
comparison images (photo | render | 4x |error|) are written beside the JSON.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from uvatar.dva.dataset import FrameBank
from uvatar.dva.drive import render_camera
from uvatar.io_utils import write_image, write_json

log = logging.getLogger(__name__)


def spread(items, n):
    """n items evenly spread over the list (all of them when n >= len)."""
    items = list(items)
    if n >= len(items):
        return items
    return [items[(i * len(items)) // n] for i in range(n)]


def evaluate_dva(run_dir, source, json_path=None, driving_views: int = 3, max_frames: int | None = None,
                 max_cameras: int | None = None, device="cpu", images=True, progress=True) -> dict:
    """Render and score; returns the metrics dict (also written to ``json_path``)."""
    import torch

    from uvatar.dva.data import box_mask
    from uvatar.dva.train import load_run
    from uvatar.errors import InputError
    from uvatar.render.metrics import psnr, ssim

    model, body, meta, step = load_run(run_dir, device)
    frames = list(source.test_frames)[:max_frames] if max_frames else list(source.test_frames)
    test_cams = list(source.test_cameras)[:max_cameras] if max_cameras else list(source.test_cameras)
    train_cams = [c for c in meta["train_cameras"] if c in source.cameras and c not in test_cams]
    if not frames or not test_cams or not train_cams:
        raise InputError(getattr(source, "root", "source"), "no held-out frames/cameras or driving views to evaluate")
    driving = spread(train_cams, driving_views)
    cams = driving + test_cams
    bank = FrameBank(source, body, model.image_raster, model.template, frames, cams, progress)
    img_dir = Path(json_path).with_suffix("") if json_path else None
    per_image = []
    drive_idx = list(range(len(driving)))
    for fi, frame in enumerate(bank.frames):
        tex = bank.image_texture(fi, drive_idx).to(device)
        verts, rot = bank.vertices[fi].to(device), bank.rotvecs[fi].to(device)
        for ci, cam_name in enumerate(test_cams, start=len(driving)):
            cam = bank.cams[ci]
            gt = bank.images[fi][ci].astype(np.float32) / 255.0
            if (cam.height, cam.width) != gt.shape[:2]:
                cam.height, cam.width = gt.shape[:2]
            with torch.no_grad():
                pred, _ = render_camera(model, verts, rot, tex, cam, bank.backgrounds[ci])
            mask = box_mask(cam, verts.cpu().numpy(), *gt.shape[:2]) if source.eval_box_mask else None
            p, s = psnr(pred, gt, mask), ssim(pred, gt, mask)
            per_image.append({"frame": frame, "camera": cam_name, "psnr_db": p, "ssim": s})
            if images and img_dir is not None:
                err = np.clip(np.abs(pred - gt) * 4, 0, 1)
                write_image(img_dir / f"{frame}_{cam_name}.png", np.concatenate([gt, pred, err], 1))
    result = {
        "psnr_db": float(np.mean([r["psnr_db"] for r in per_image])),
        "ssim": float(np.mean([r["ssim"] for r in per_image])),
        "protocol": source.protocol.replace("{driving}", str(len(driving))) + f"; driving views {driving}",
        "frames": bank.frames, "cameras": test_cams, "driving_cameras": driving, "train_steps": step,
        "skipped_frames": bank.skipped, "per_image": per_image,
        "images": str(img_dir) if (images and img_dir is not None) else None,
    }
    if json_path:
        write_json(json_path, result)
    return result
