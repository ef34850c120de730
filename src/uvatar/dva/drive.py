"""Drive a trained DVA avatar: a pose sequence plus 2-3 driving views (images + cameras) -> any camera.

For every frame the driving views are unwrapped into UV (visible texels only) and averaged, the model
decodes the primitives for the target camera (view features depend on it) and the image is ray
marched and composited over ``background``.
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.dva.dataset import body_inputs
from uvatar.dva.features import average_views, unwrap_views
from uvatar.dva.model import pixel_rays


@torch.no_grad()
def render_camera(model, posed_vertices, joint_rotvecs, image_texture, camera, background=(0.0, 0.0, 0.0),
                  residual=None):
    """One frame, one camera. posed_vertices (V,3), joint_rotvecs (J,3), image_texture (4,R,R) torch;
    residual: the frame's :class:`~uvatar.dva.residual.FrameResidual` fitted to its driving views, or None.

    Returns rgb (H, W, 3) float32 numpy composited over ``background``, alpha (H, W)."""
    dev = posed_vertices.device
    center = torch.as_tensor(camera.center, dtype=torch.float32, device=dev)[None]
    out = model(posed_vertices[None], joint_rotvecs[None], image_texture[None].to(dev), center)
    if residual is not None:
        out = residual(out)
    H, W = camera.height, camera.width
    yy, xx = np.mgrid[:H, :W]
    pix = np.stack([xx.ravel(), yy.ravel()], 1)
    o, d = pixel_rays(camera, pix, dev)
    bg = torch.as_tensor(np.asarray(background, np.float32), device=dev)
    rgb, alpha = model.render_rays(out, 0, o, d, bg, camera=camera, pixels=pix)
    return rgb.reshape(H, W, 3).clamp(0, 1).cpu().numpy(), alpha.reshape(H, W).cpu().numpy()


def driving_texture(model, posed_vertices: np.ndarray, cameras, images, masks=None) -> torch.Tensor:
    """(4, R, R) texel-aligned image input from driving views (lists of Camera / (H,W,3) / (H,W))."""
    tex, vis = unwrap_views(model.image_raster, model.template, posed_vertices, cameras, images, masks)
    return average_views(torch.as_tensor(tex)[None], torch.as_tensor(vis)[None])[0]


def drive_sequence(model, body, source, frames, driving_cameras, target_camera, background=(0, 0, 0),
                   progress=True, refine_pose: int = 0, refine_residual: int = 0, frame=None):
    """Render ``target_camera`` (one Camera, or a list with one per frame) for each frame of ``source``
    (fits + driving images). Returns a list of (H, W, 3) float32 images; frames whose data cannot be
    read are skipped with a warning. ``refine_pose`` > 0: each frame's fit is first refined against its
    driving views for that many steps (:mod:`uvatar.dva.refine`, as ``uvatar eval dva`` does);
    ``refine_residual`` > 0: then a residual of its decoded primitives is fitted to them
    (:mod:`uvatar.dva.residual`). ``frame``: a :class:`~uvatar.dva.frame.FrameConfig` renders through the
    fast path (:class:`~uvatar.dva.frame.FrameRenderer`: bf16 / fp16 decoders, compiled) where no
    residual is fitted; None: the fp32 reference (:func:`render_camera`)."""
    import logging

    from tqdm import tqdm

    from uvatar.errors import InputError

    log = logging.getLogger(__name__)
    out = []
    cams = [source.cameras[c] for c in driving_cameras]
    frames = list(frames)
    renderer = None
    if frame is not None:
        from uvatar.dva.frame import FrameRenderer

        renderer = FrameRenderer(model, frame)
    targets = target_camera if isinstance(target_camera, list | tuple) else [target_camera] * len(frames)
    for frame, target in tqdm(list(zip(frames, targets, strict=False)), desc="render dva", disable=not progress, unit="frame"):
        try:
            fit = source.fit(frame)
            rot, verts = body_inputs(body, [fit])
            imgs = [source.image(c, frame) for c in driving_cameras]
            masks = [source.mask(c, frame) for c in driving_cameras]
        except InputError as exc:
            log.warning("skipping frame %s: %s", frame, exc)
            continue
        tex = driving_texture(model, verts[0].numpy(), cams, imgs, masks)
        rot, verts = rot[0], verts[0]
        views = _driving_views(imgs, masks) if (refine_pose > 0 or refine_residual > 0) else None
        if refine_pose > 0:
            rot, verts = _refined(model, body, fit, tex, cams, views, refine_pose)
        residual = None
        if refine_residual > 0:
            from uvatar.dva.residual import ResidualConfig, fit_residual

            residual, _ = fit_residual(model, verts, rot, tex, cams, *views, ResidualConfig(iters=refine_residual))
        if renderer is not None and residual is None:
            rgb = renderer.render(verts, rot, tex, target, background)[0].cpu().numpy()
        else:
            rgb, _ = render_camera(model, verts, rot, tex, target, background, residual)
        out.append(rgb)
    return out


def _driving_views(images, masks):
    """(photos (H, W, 3) uint8, masks (H, W) bool, background colours (3,)) of the driving views from
    float images in [0, 1] and masks, as the refinements take them."""
    from uvatar.dva.dataset import estimate_background
    from uvatar.render.video import to_uint8

    inside = [np.asarray(m) > 0.5 for m in masks]
    backs = [estimate_background(np.asarray(i, np.float32), m) for i, m in zip(images, inside, strict=True)]
    return [to_uint8(i) for i in images], inside, backs


def _refined(model, body, fit, tex, cams, views, iters: int):
    """(joint rotvecs (J, 3), vertices (V, 3)) of ``fit`` refined against the driving views
    (:func:`_driving_views`) for ``iters`` steps."""
    from uvatar.dva.dataset import fit_params
    from uvatar.dva.refine import RefineConfig, refine_frame

    rot, verts, _ = refine_frame(model, body, fit_params(body, [fit]), tex, cams, *views, RefineConfig(iters=iters))
    return rot, verts
