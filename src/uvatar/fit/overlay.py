"""Pictures of a body fit a person can check at a glance.

For a few frames spread over the capture, each view shows the image (the capture's photo, or the
scan rendered from the virtual camera), the fitted body laid over it in translucent blue, and the
detected keypoints (green: used by the triangulation, red: rejected as outliers or unseen).
Written to ``fitting/overlays/<frame>_<view>.jpg`` and ``fitting/contact_sheet.png``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import Camera
from uvatar.io_utils import write_image

__all__ = ["overlay_view", "write_overlays"]

BODY_COLOR = (0.25, 0.5, 1.0)


def overlay_view(image: np.ndarray, camera: Camera, body_vertices: np.ndarray, faces: np.ndarray,
                 xy: np.ndarray, conf: np.ndarray, used: np.ndarray | None, width: int,
                 min_conf: float = 0.3, alpha: float = 0.45) -> np.ndarray:
    """One overlay image (h, width, 3) float32: ``image`` (H, W, 3) of ``camera``, the body mesh
    (V, 3) world metres with ``faces``, keypoints ``xy`` (K, 2) pixels with ``conf`` (K,)."""
    import cv2

    from uvatar.render.mesh_renderer import render_mesh

    small = camera.scaled_to_width(width)
    img = cv2.resize(np.asarray(image, np.float32), (small.width, small.height), interpolation=cv2.INTER_AREA)
    body = render_mesh(body_vertices, faces, small, shading=True, background=0.0,
                       vertex_colors=np.broadcast_to(np.asarray(BODY_COLOR, np.float32), body_vertices.shape))
    a = alpha * body.mask[..., None]
    out = img * (1 - a) + body.rgb * a
    s = small.width / camera.width
    canvas = np.ascontiguousarray((np.clip(out, 0, 1) * 255).astype(np.uint8))
    radius = max(2, width // 128)
    for k in np.flatnonzero(conf >= min_conf):
        ok = used is None or bool(used[k])
        color = (40, 220, 40) if ok else (230, 40, 40)
        center = tuple(int(round(v)) for v in (xy[k] + 0.5) * s - 0.5)
        cv2.circle(canvas, center, radius, color, -1, lineType=cv2.LINE_AA)
    return canvas.astype(np.float32) / 255.0


def _views_for_overlay(capture, frame: str, obs, source: str, width: int):
    """Images of the frame's views (scans are rendered again at the overlay size)."""
    if source == "images":
        return [capture.load_image(cam.name, frame) for cam in obs.cameras]
    from uvatar.fit.views import render_scan_views

    mesh = capture.load_scan(frame)
    smalls = [cam.scaled_to_width(width) for cam in obs.cameras]
    return render_scan_views(mesh, smalls)


def write_overlays(capture, frames: list[str], observations: dict, posed, body, source: str, stages,
                   config) -> Path:
    """Overlays of ``config.overlay_frames`` frames spread over the capture and their contact sheet;
    returns the contact sheet's path."""
    from uvatar.render.contact import contact_sheet

    out_dir = capture.fitting_dir / "overlays"
    picks = [f for f in frames if f in observations]
    if not picks:
        return out_dir
    idx = np.unique(np.linspace(0, len(picks) - 1, min(config.overlay_frames, len(picks))).round().astype(int))
    faces = body.template.faces
    vertices = posed.vertices.detach().cpu().numpy()
    sheet_images, labels = [], []
    for i in idx:
        frame = picks[i]
        t = frames.index(frame)
        obs = observations[frame]
        images = _views_for_overlay(capture, frame, obs, source, config.overlay_width)
        used = np.isfinite(obs.reprojection_px)
        for c, cam in enumerate(obs.cameras):
            if images[c].shape[1] != cam.width:  # already rendered at the overlay size
                view = overlay_view(images[c], cam.scaled_to_width(images[c].shape[1]), vertices[t], faces,
                                    (obs.xy[c] + 0.5) * images[c].shape[1] / cam.width - 0.5, obs.conf[c],
                                    used[c], config.overlay_width, stages.triangulate.min_conf)
            else:
                view = overlay_view(images[c], cam, vertices[t], faces, obs.xy[c], obs.conf[c], used[c],
                                    config.overlay_width, stages.triangulate.min_conf)
            write_image(out_dir / f"{frame}_{cam.name}.jpg", view)
            sheet_images.append(view)
            labels.append(f"{frame} {cam.name}")
    cols = len(observations[picks[idx[0]]].cameras)
    path = capture.fitting_dir / "contact_sheet.png"
    write_image(path, contact_sheet(sheet_images, cols=min(cols, 8), labels=labels))
    return path
