"""Body fits for captures that come without them (issue 13): 2D keypoints, virtual views of scans,
triangulation and person masks (this half), and the body optimiser (``body_fit``).

Heavy optional dependencies (mediapipe) are imported lazily by the detectors and segmenters; the
extra is ``uvatar[fit]``.
"""

from uvatar.fit.keypoints import (
    BLAZEPOSE_NAMES,
    DETECTORS,
    DetectorConfig,
    KeypointDetector,
    Keypoints2D,
    load_detector,
)
from uvatar.fit.projection import project_distorted, undistort_normalized
from uvatar.fit.segment import SEGMENTERS, PersonSegmenter, SegmenterConfig, load_segmenter, mask_iou
from uvatar.fit.triangulate import TriangulateConfig, Triangulation, triangulate
from uvatar.fit.views import ScanViewsConfig, render_scan_views, scan_cameras

__all__ = [
    "BLAZEPOSE_NAMES", "DetectorConfig", "KeypointDetector", "Keypoints2D", "DETECTORS",
    "load_detector", "project_distorted", "undistort_normalized",
    "TriangulateConfig", "Triangulation", "triangulate", "ScanViewsConfig", "render_scan_views",
    "scan_cameras", "PersonSegmenter", "SegmenterConfig", "load_segmenter", "mask_iou", "SEGMENTERS",
]
