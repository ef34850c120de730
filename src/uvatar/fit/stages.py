"""The configs of ``uvatar fit``'s stages, passed together (:class:`FitStages`)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["FitStages"]


@dataclass
class FitStages:
    """Configs of the stages (each with its own defaults)."""

    views: object = None        # uvatar.fit.views.ScanViewsConfig
    detector: object = None     # uvatar.fit.keypoints.DetectorConfig
    triangulate: object = None  # uvatar.fit.triangulate.TriangulateConfig
    body: object = None         # uvatar.fit.body_fit.BodyFitConfig
    timings: dict = field(default_factory=dict)
