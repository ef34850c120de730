"""2D body keypoints: the detector interface and MediaPipe BlazePose (offline, weights in the wheel).

``load_detector("mediapipe", DetectorConfig(...))`` returns a :class:`KeypointDetector`; its ``detect``
takes an image (H, W, 3) float32 in [0, 1] and an optional region of interest and returns
:class:`Keypoints2D` in full-image OpenCV pixels (x right, y down, pixel centres at integers). A frame
without a person gives ``conf`` all 0, never an exception. More detectors register with
:data:`DETECTORS` (``DETECTORS.register(name, factory)``, factory ``config -> detector``).

BlazePose (legacy ``mediapipe.solutions.pose``, static-image mode): the mediapipe wheels 0.10.14 to
0.10.21 ship ``pose_detection.tflite`` and ``pose_landmark_full.tflite`` (model complexity 1) inside
the wheel; the lite/heavy models (complexity 0/2) are downloaded at run time and are refused here.
Small images are upsampled (bicubic) so the long side of the (cropped) image reaches
``upsample_to``: on the studio's 256^2 images BlazePose misses limbs otherwise. The confidence of a
landmark is its ``visibility`` (the legacy graph leaves ``presence`` at 0; where a model fills it, the
product of the two is used).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from uvatar.errors import UvatarError, check_values, require
from uvatar.fit._image import crop_to_image, prepare_image
from uvatar.fit._registry import GraphOwner, Registry

__all__ = [
    "BLAZEPOSE_NAMES", "Keypoints2D", "KeypointDetector", "DetectorConfig", "MediaPipePoseDetector",
    "load_detector", "DETECTORS", "import_mediapipe",
]

BLAZEPOSE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
    "left_foot_index", "right_foot_index",
)

@dataclass
class Keypoints2D:
    """xy (K, 2) float32 pixel coordinates (x right, y down; OpenCV: pixel centres at integers);
    conf (K,) float32 in [0, 1]; 0 = not detected (xy is then meaningless, set to 0)."""

    xy: np.ndarray
    conf: np.ndarray

    @classmethod
    def empty(cls, count: int) -> Keypoints2D:
        """``count`` undetected keypoints (conf 0)."""
        return cls(np.zeros((count, 2), np.float32), np.zeros(count, np.float32))

    @property
    def detected(self) -> bool:
        """True when at least one keypoint has a non-zero confidence."""
        return bool(np.any(self.conf > 0))


class KeypointDetector(Protocol):
    """A 2D keypoint detector: ``name``, ``version`` (for provenance), ``keypoint_names`` (K,)."""

    name: str
    version: str
    keypoint_names: tuple[str, ...]

    def detect(self, image: np.ndarray, roi=None) -> Keypoints2D:
        """image (H, W, 3) float32 in [0, 1]; roi optional (x0, y0, x1, y1) pixels (x1, y1 exclusive):
        detect only inside it; coordinates come back in the full image."""
        ...


@dataclass
class DetectorConfig:
    """model_complexity: BlazePose landmark model (1 = "full", the one the wheel ships; 0/2 download
    at run time and are refused); min_detection_confidence: person-detector threshold in [0, 1];
    upsample_to: upsample a crop whose long side is shorter than this many pixels (0 = never);
    min_visibility: landmark confidences below this are reported as 0 (not detected)."""

    model_complexity: int = 1
    min_detection_confidence: float = 0.5
    upsample_to: int = 512
    min_visibility: float = 0.0

    def __post_init__(self) -> None:
        check_values([
            (self.model_complexity in (0, 1, 2), f"model_complexity must be 0, 1 or 2, got {self.model_complexity}"),
            (0.0 <= self.min_detection_confidence <= 1.0,
             f"min_detection_confidence must be in [0, 1], got {self.min_detection_confidence}"),
            (0 <= self.upsample_to <= 8192, f"upsample_to must be in [0, 8192] pixels, got {self.upsample_to}"),
            (0.0 <= self.min_visibility <= 1.0, f"min_visibility must be in [0, 1], got {self.min_visibility}"),
        ])


def import_mediapipe():
    """The ``mediapipe`` module, or a one-line :class:`MissingDependencyError` naming ``uvatar[fit]``."""
    return require("mediapipe", "fit", "2D body keypoints and person masks")


_POSE_MODEL_FILES = {0: "pose_landmark_lite.tflite", 1: "pose_landmark_full.tflite",
                     2: "pose_landmark_heavy.tflite"}


def mediapipe_pose_model(mp, model_complexity: int) -> str:
    """Path of the BlazePose landmark model inside the installed wheel; raises a one-line
    :class:`UvatarError` when that wheel does not ship it (it would be downloaded at run time)."""
    path = os.path.join(os.path.dirname(mp.__file__), "modules", "pose_landmark",
                        _POSE_MODEL_FILES[model_complexity])
    if not os.path.isfile(path):
        raise UvatarError(
            f"{path}: not in the installed mediapipe {getattr(mp, '__version__', '?')} wheel "
            f"(model_complexity={model_complexity}); the mediapipe 0.10.14-0.10.21 wheels ship "
            "model_complexity=1 only: install 'uvatar[fit]' and use model_complexity=1")
    return path


class MediaPipePoseDetector(GraphOwner):
    """BlazePose (33 landmarks) through ``mediapipe.solutions.pose`` in static-image mode (one graph per
    detector, see :class:`GraphOwner`)."""

    name = "mediapipe-blazepose"
    keypoint_names = BLAZEPOSE_NAMES

    def __init__(self, config: DetectorConfig | None = None):
        self.config = config or DetectorConfig()
        mp = import_mediapipe()
        mediapipe_pose_model(mp, self.config.model_complexity)
        self.version = f"mediapipe {mp.__version__} pose_landmark complexity {self.config.model_complexity}"
        self._start(lambda: mp.solutions.pose.Pose(
            static_image_mode=True, model_complexity=self.config.model_complexity,
            enable_segmentation=False, min_detection_confidence=self.config.min_detection_confidence))

    def detect(self, image: np.ndarray, roi=None) -> Keypoints2D:
        """See :class:`KeypointDetector`; (K=33) keypoints in :data:`BLAZEPOSE_NAMES` order."""
        prep = prepare_image(image, roi, self.config.upsample_to)
        k = len(BLAZEPOSE_NAMES)
        if prep.rgb is None:
            return Keypoints2D.empty(k)
        result = self._process(prep.rgb)
        if result.pose_landmarks is None:
            return Keypoints2D.empty(k)
        lm = result.pose_landmarks.landmark
        raw = np.array([(p.x, p.y, p.visibility, p.presence) for p in lm], dtype=np.float64)  # 33 rows
        xy = crop_to_image(raw[:, :2], prep.box)
        conf = np.clip(raw[:, 2], 0.0, 1.0)
        if np.any(raw[:, 3] > 0):
            conf = conf * np.clip(raw[:, 3], 0.0, 1.0)
        conf = np.where(conf < self.config.min_visibility, 0.0, conf)
        xy = np.where(conf[:, None] > 0, xy, 0.0)
        return Keypoints2D(xy.astype(np.float32), conf.astype(np.float32))


DETECTORS = Registry("keypoint detector", {"mediapipe": MediaPipePoseDetector})
"""Known keypoint detectors: ``DETECTORS.register(name, factory)`` adds one (``factory(config: DetectorConfig) ->
KeypointDetector``), ``DETECTORS.names()`` lists them."""


def load_detector(name: str = "mediapipe", config: DetectorConfig | None = None) -> KeypointDetector:
    """A keypoint detector by name (see ``DETECTORS.names()``); unknown names raise ``ValueError``."""
    return DETECTORS.load(name, config or DetectorConfig())
