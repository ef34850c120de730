"""Rendering and reporting: cameras and rays, an Embree mesh renderer, image metrics, videos,
HTML reports and contact sheets. OpenCV cameras (``X_cam = R @ X_world + T``), images float32 HWC."""

from uvatar.render.cameras import camera_rays, look_at_camera, orbit_cameras, project_points, ring_cameras
from uvatar.render.contact import contact_sheet
from uvatar.render.mesh_renderer import RenderConfig, RenderResult, render_mesh, render_mesh_reference
from uvatar.render.metrics import mse, psnr, ssim, ssim_map
from uvatar.render.report import html_report
from uvatar.render.video import write_video

__all__ = [
    "look_at_camera", "orbit_cameras", "ring_cameras", "camera_rays", "project_points",
    "RenderConfig", "RenderResult", "render_mesh", "render_mesh_reference",
    "psnr", "ssim", "ssim_map", "mse", "write_video", "html_report", "contact_sheet",
]
