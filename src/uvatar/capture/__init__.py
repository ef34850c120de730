"""The capture format: textured scans, EasyMocap fits and cameras, images and masks per camera.

See docs/ARCHITECTURE.md (contract ``capture``) and DESIGN.md (folder layout).
"""

from uvatar.capture.cameras import read_cameras, write_cameras
from uvatar.capture.fits import read_fit, read_fits, read_fits_dir, read_fits_npz, write_fit, write_fits_npz
from uvatar.capture.layout import Capture, frame_name, read_capture_info, write_capture_info
from uvatar.capture.meshio import (
                                 check_texture,
                                 load_texture,
                                 read_mesh,
                                 read_mesh_header,
                                 register_mesh_format,
                                 write_mesh,
)
from uvatar.capture.types import BodyFit, Camera, TexturedMesh
from uvatar.capture.validate import ValidateConfig, format_summary, validate_capture

__all__ = [
    "BodyFit", "Camera", "Capture", "TexturedMesh", "ValidateConfig", "check_texture", "format_summary", "frame_name",
    "load_texture", "read_cameras", "read_capture_info", "read_fit", "read_fits", "read_fits_dir",
    "read_fits_npz", "read_mesh", "read_mesh_header", "register_mesh_format", "validate_capture",
    "write_cameras", "write_capture_info", "write_fit", "write_fits_npz", "write_mesh",
]
