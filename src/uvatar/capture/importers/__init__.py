"""Import real recordings (per-camera videos or image folders + a calibration) as capture folders.

``calibration``: EasyMocap yml, Qualisys .qca, Pose2Sim / OpenCV-style TOML and JSON readers and
the world-up / unit change; ``sources``: lazy per-camera frame decoding; ``pipeline``: the import.
"""

from uvatar.capture.importers.calibration import Calibration, read_calibration, to_uvatar_world
from uvatar.capture.importers.pipeline import ImportConfig, import_capture

__all__ = ["Calibration", "ImportConfig", "import_capture", "read_calibration", "to_uvatar_world"]
