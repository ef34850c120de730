"""Where a take's points land in uvatar's world (metres, +Y up): the units and up axis its files state,
the flags give, or the first frame's height and extent say."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.importers.calibration import UNIT_SCALE, unit_scale, up_rotation
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

PERSON_HEIGHT_M = (0.5, 2.5)  # a frame's extent along up, in metres, that the unit detection accepts


def detect_units(height: float, path: Path) -> str:
    """The units ("m", "cm", "mm") in which a standing person ``height`` source units tall measures
    PERSON_HEIGHT_M; InputError (asking for ``--units``) when none does."""
    for units, scale in UNIT_SCALE.items():
        if PERSON_HEIGHT_M[0] <= height * scale <= PERSON_HEIGHT_M[1]:
            return units
    raise InputError(path, f"the mesh is {height:g} units tall, which is no person's height in m, cm or mm; "
                           "give units")


def world_from_source(mesh: TexturedMesh, path: Path, units: str, up: str) -> tuple[np.ndarray, str, str, list[str]]:
    """The (4, 4) similarity taking the source's points to uvatar's world, and the units and up used.

    ``units``/``up`` "" = detect on this (first) frame: up defaults to +y, the convention of glTF,
    Draco and OBJ exporters; a mesh tallest along another axis asks for ``--up``.
    """
    notes = []
    extent = np.ptp(mesh.vertices, axis=0)
    if not up:
        up = "+y"
        tallest = "xyz"[int(np.argmax(extent))]
        if tallest != "y":
            raise InputError(path, f"the mesh is tallest along {tallest}, not y: give up (+{tallest}, or -{tallest} "
                                   f"if the head points to -{tallest})")
        notes.append("up axis not stated by the files: +y (the mesh is tallest along y)")
    axis = {"x": 0, "y": 1, "z": 2}[up[1]]
    if not units:
        units = detect_units(float(extent[axis]), path)
        notes.append(f"units not stated by the files: {units} (the first frame is {extent[axis]:.4g} {units} tall)")
    S = np.eye(4)
    S[:3, :3] = unit_scale(units) * up_rotation(up)
    return S, units, up, notes
