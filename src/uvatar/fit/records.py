"""What ``uvatar fit``'s stage records keep (:mod:`uvatar.stage_record`), and the ``--person`` check
against the capture that runs before any work.

``fitting/stage.json``: the fit's settings (``uvatar fit``'s flags, the stages' configs) and the files
its keypoints come from; ``fitting/keypoints/stage.json``: what the keypoints depend on (the detector,
the triangulation, the version of the rules that reject views and hold frames (``VIEW_RULES``: keypoints
saved under older rules are detected again), with images the person followed, with scans the virtual
views). A changed ``--person`` makes the keypoints from images stale (the person is tracked in them),
never those from scans. ``fitting/keypoints/identity.json``: the subject tracker's statuses, which a
resumed run keeps (:func:`read_identity_record`).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from uvatar import stage_record
from uvatar.capture.layout import Capture
from uvatar.errors import InputError
from uvatar.io_utils import read_json, write_json

if TYPE_CHECKING:  # annotations only
    from uvatar.fit.stages import FitStages

__all__ = ["check_person_choice", "fit_inputs", "fit_record_config", "keypoint_record_config", "VIEW_RULES",
           "read_identity_record", "write_identity_record"]

VIEW_RULES = 3   # the version of the rules that reject views and hold frames, whose results the keypoints keep


# FitConfig fields that do not change the fits: where the fit runs, replacing, and the contact sheet
_FIT_VOLATILE = ("force", "device", "overlay_frames", "overlay_width")


def fit_record_config(config, stages: FitStages, source: str) -> dict:
    """The settings a fit's stage record keeps (``config``: the fit's ``FitConfig``): ``uvatar fit``'s flags (``source`` resolved from
    ``auto``; ``count``: the scan views of ``--views``) and the stages' configs."""
    return stage_record.config_values(
        config, drop=_FIT_VOLATILE, source=source, count=stages.views.count if source == "scans" else None,
        stages={name: asdict(getattr(stages, name)) for name in ("detector", "triangulate", "body")})


def fit_inputs(capture: Capture, source: str) -> dict:
    """The files a fit reads its keypoints from: the capture's images, or its scans."""
    return stage_record.file_identities(capture.root / "images" if source == "images" else capture.scans_dir)


def keypoint_record_config(capture: Capture, config, stages: FitStages, source: str, detector) -> dict:
    """The settings that the keypoints of ``fitting/keypoints`` depend on: the detector and the
    triangulation, with images the person followed (``--person``) and their cut distance, with scans
    the virtual views (the person does not change what a scan's views show)."""
    settings = {"source": source, "detector": config.detector, "detector_version": str(detector.version),
                "view_rules": VIEW_RULES,
                "stages": {"detector": asdict(stages.detector), "triangulate": asdict(stages.triangulate)}}
    if source == "images":
        settings.update(person=config.person, cut_distance=config.cut_distance, person_id=capture.person)
    else:
        settings.update(count=stages.views.count, views=asdict(stages.views))
    return stage_record.config_values(**settings)


IDENTITY_JSON = "identity.json"   # fitting/keypoints/identity.json: the tracker's statuses so far (a resume keeps them)


def read_identity_record(keypoints_dir: str | Path) -> dict:
    """{"statuses": {frame: "lost" | "ambiguous" | "crowded" | "reassociated"}, "other_people_seen": n} of
    the run that left ``keypoints_dir`` (its keypoints kept: the same settings); empty where there is none.
    A resumed run holds the frames held before and reports the statuses of the frames it reads back
    instead of tracking them: the tracker's knowledge of the other people is not saved, and a frame held
    beside someone must not be fitted because a resumed tracker has not seen them yet."""
    path = Path(keypoints_dir) / IDENTITY_JSON
    if not path.is_file():
        return {"statuses": {}, "other_people_seen": 0}
    record = read_json(path)
    return {"statuses": dict(record.get("statuses") or {}), "other_people_seen": int(record.get("other_people_seen") or 0)}


def write_identity_record(keypoints_dir: str | Path, statuses: dict, other_people_seen: int) -> None:
    """Write the tracker's statuses so far (:func:`read_identity_record`), atomically."""
    write_json(Path(keypoints_dir) / IDENTITY_JSON, {"statuses": dict(sorted(statuses.items())),
                                                     "other_people_seen": int(other_people_seen)})


def check_person_choice(capture: Capture, frames: list[str], choice, spec: str, source: str) -> None:
    """Before any work, check ``--person`` against the capture: not empty; a rule that picks among the
    people of the images needs the images; a box or point names a camera of the capture, one of the
    frames being fitted (listed when not), and lies inside that camera's image."""
    if not str(spec).strip():
        raise InputError("person", "is empty: give most-views, largest, centre, nearest-to:X,Y,Z, "
                                   "box:CAM:FRAME:X0,Y0,X1,Y1, point:CAM:FRAME:X,Y, all, or a person id")
    if source != "images" and (choice.several or choice.rule != "most-views"):
        raise InputError(capture.root, f"person={spec.strip()!r} picks among the people in the capture's images: it "
                                   f"needs source='images' (this run: source={source!r})")
    if choice.rule not in ("box", "point"):
        return
    cameras = capture.cameras()
    if choice.camera not in cameras:
        raise InputError("person", f"{spec!r}: the capture has no camera {choice.camera!r} (it has "
                                   f"{', '.join(sorted(cameras))})")
    if choice.frame not in frames:
        shown = ", ".join(frames[:3]) + (f", ..., {frames[-1]}" if len(frames) > 3 else "")
        raise InputError("person", f"{spec!r}: no frame {choice.frame!r} among the {len(frames)} frames being "
                                   f"fitted ({shown})")
    cam = cameras[choice.camera]
    if cam.width and cam.height:
        x0, y0, x1, y1 = choice.box
        if x1 < 0 or y1 < 0 or x0 >= cam.width or y0 >= cam.height or (
                choice.rule == "point" and not (0 <= x0 < cam.width and 0 <= y0 < cam.height)):
            raise InputError("person", f"{spec!r}: lies outside camera {choice.camera}'s {cam.width}x{cam.height} "
                                       "image (pixels: x right, y down from the top-left corner)")
