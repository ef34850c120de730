"""UVOL 2 manifests: the one reader of the Universal Volumetric player's manifest files.

Two writers make them, and both are read:

- **the player's schema** (``V2Schema`` of EtherealEngine/Universal-Volumetric's ``src/Interfaces.ts``):
  ``geometry`` and ``texture`` blocks, each with named ``targets`` (format, frame rate, frame count;
  a texture target also its ``resolution`` and ``sequenceSize``, the frames per KTX2 file) and one
  ``path`` template such as ``geometry_[target]/[######][ext]`` or
  ``texture_[target]_[type]_[tag]/[######][ext]``; older files wrap them in ``output`` and a texture's
  block in ``baseColor``;
- **its encoder** (``scripts/Encoder.py``, which writes ``uvol.json``): a flat ``geometry`` block (format,
  frameRate, frameCount, path) and ``texture.targets`` as a *list* whose targets carry their own paths
  (``KTX2/texture_[#######].ktx2``).

Geometry and texture may run at different frame rates; the player shows, at time t, geometry frame
``round(t * geometry fps)`` with texture frame ``round(t * texture fps)`` (:func:`texture_frame`).
Where several texture targets are listed, the one read is the player's choice among those uvatar
decodes (``etc2`` before ``ktx2``, as its ``TEXTURE_FORMAT_PRIORITY``; the KTX 1 targets ``astc/ktx``,
``astc.ktx`` after them); ``mp4`` (a texture video) is not decoded.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

from uvatar.errors import InputError, one_line

log = logging.getLogger(__name__)

MANIFEST_PATTERNS = ("*.uvol.json", "uvol.json", "*.manifest", "manifest.json", "*.uvol")
#: texture formats read, by the player's priority (``TEXTURE_FORMAT_PRIORITY``: higher first); the KTX 1
#: targets the player does not rank come after those it does, and a target without a format last
TEXTURE_FORMAT_PRIORITY = {"etc1.ktx": 2, "etc2": 1, "ktx2": 0, "astc/ktx": -1, "astc.ktx": -1}
#: texture formats a manifest may name that uvatar does not decode (a texture video)
UNREADABLE_TEXTURE_FORMATS = ("mp4",)
#: the file suffix of each texture format's files
TEXTURE_SUFFIX = {"ktx2": ".ktx2", "etc2": ".etc2", "astc/ktx": ".ktx", "astc.ktx": ".ktx", "etc1.ktx": ".ktx"}


@dataclass
class UvolManifest:
    """What uvatar takes from a UVOL manifest; fields the file does not give are None."""

    path: Path
    geometry_fps: float | None = None
    texture_fps: float | None = None
    frame_count: int | None = None
    frames_per_file: int | None = None
    geometry_path: str | None = None
    geometry_target: str | None = None
    texture_path: str | None = None
    texture_target: str | None = None
    texture_format: str | None = None
    texture_resolution: tuple[int, int] | None = None
    skipped_targets: tuple[str, ...] = ()

    @property
    def fps(self) -> float | None:
        """The take's frame rate: the geometry's (a capture frame is a mesh), else the texture's."""
        return self.geometry_fps or self.texture_fps


def find_manifest(src: Path) -> Path | None:
    for pattern in MANIFEST_PATTERNS:
        found = sorted(p for p in src.glob(pattern) if p.is_file())
        if found:
            return found[0]
    return None


def _positive(value) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) and value > 0 else None


def _targets(block: dict) -> list[tuple[str, dict]]:
    targets = block.get("targets")
    if isinstance(targets, dict):
        return [(str(k), v) for k, v in targets.items() if isinstance(v, dict)]
    if isinstance(targets, list):   # the encoder's: a list of targets with their own paths
        return [(str(v.get("format", i)), v) for i, v in enumerate(targets) if isinstance(v, dict)]
    return []


def _texture_choice(targets: list[tuple[str, dict]]) -> tuple[str, dict] | None:
    """The target the player would pick among those uvatar reads; None when all are unreadable."""
    readable = [(name, t) for name, t in targets if t.get("format") not in UNREADABLE_TEXTURE_FORMATS]
    if not readable:
        return None
    return max(readable, key=lambda nt: TEXTURE_FORMAT_PRIORITY.get(nt[1].get("format"), -2))


def read_manifest(path: Path) -> UvolManifest:
    """Read a UVOL 2 manifest of either writer (see the module doc); InputError naming the file when it
    is not a JSON object."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"UVOL manifest is not valid JSON ({one_line(exc)})") from None
    if not isinstance(data, dict):
        raise InputError(path, "UVOL manifest must be a JSON object")
    blocks = data.get("output", data)
    blocks = blocks if isinstance(blocks, dict) else {}
    geometry = blocks.get("geometry") if isinstance(blocks.get("geometry"), dict) else {}
    texture = blocks.get("texture") if isinstance(blocks.get("texture"), dict) else {}
    if isinstance(texture.get("baseColor"), dict):
        texture = {**texture, **texture["baseColor"]}
    out = UvolManifest(path)
    targets = _targets(geometry)
    if targets:
        out.geometry_target, target = targets[0]
        geometry = {**geometry, **target}
    out.geometry_path = geometry.get("path") if isinstance(geometry.get("path"), str) else None
    out.geometry_fps = _positive(geometry.get("frameRate"))
    if isinstance(geometry.get("frameCount"), int) and not isinstance(geometry.get("frameCount"), bool):
        out.frame_count = int(geometry["frameCount"])
    targets = _targets(texture)
    choice = _texture_choice(targets)
    if targets and choice is None:
        out.skipped_targets = tuple(f"{name} ({t.get('format')})" for name, t in targets)
    elif choice is not None:
        out.texture_target, target = choice
        out.skipped_targets = tuple(f"{name} ({t.get('format')})" for name, t in targets if t is not target)
        texture = {**texture, **target}
        out.texture_format = target.get("format") if isinstance(target.get("format"), str) else None
    out.texture_path = texture.get("path") if isinstance(texture.get("path"), str) else None
    out.texture_fps = _positive(texture.get("frameRate"))
    size = texture.get("sequenceSize")
    if isinstance(size, int) and not isinstance(size, bool) and size > 0:
        out.frames_per_file = size
    resolution = texture.get("resolution")
    if isinstance(resolution, list) and len(resolution) == 2 and all(_positive(r) for r in resolution):
        out.texture_resolution = (int(resolution[0]), int(resolution[1]))
    return out


def template_folder(src: Path, template: str | None, target: str | None, kind: str) -> Path | None:
    """The folder of a manifest path template such as ``geometry_[target]/[######][ext]`` or
    ``KTX2/texture_[#######].ktx2``, looked for beside the manifest and one level up; None (with a
    warning) when it is not there."""
    if not template:
        return None
    folder = template.replace("[target]", target or "").replace("[type]", "baseColor").replace("[tag]", "default")
    folder = folder.rsplit("/", 1)[0] if "/" in folder else ""
    if not folder:
        return src
    for base in (src, src.parent):
        for candidate in (base / folder, base / Path(folder).name):
            if candidate.is_dir():
                return candidate
    log.warning("%s folder %s named by the manifest is not there; looking by name", kind, folder)
    return None


def texture_frame(frame: int, geometry_fps: float | None, texture_fps: float | None) -> int:
    """The texture frame the player shows with geometry frame ``frame``: ``round(texture fps * t)`` at
    ``t = frame / geometry fps`` (JavaScript's round: halves up); the same frame when either rate is
    unknown or both agree."""
    if not geometry_fps or not texture_fps or math.isclose(geometry_fps, texture_fps):
        return frame
    return math.floor(frame * texture_fps / geometry_fps + 0.5)


def write_manifest(path: Path, frame_count: int, fps: float, texture_size: tuple[int, int],
                   frames_per_file: int = 1) -> None:
    """Write a UVOL 2 manifest in the player's schema (``V2Schema``), atomically: one Draco geometry
    target (``geometry_draco/NNNNN.drc``) and one KTX2 texture target (``texture_ktx2/NNNNN.ktx2``,
    ``frames_per_file`` layers a file), both at ``fps``; ``texture_size``: (width, height)."""
    from uvatar.io_utils import atomic_path

    files = -(-frame_count // frames_per_file)
    doc = {"version": "v2",
           "geometry": {"targets": {"draco": {"format": "draco", "frameRate": fps, "frameCount": frame_count}},
                        "path": "geometry_[target]/[#####][ext]"},
           "texture": {"targets": {"ktx2": {"format": "ktx2", "type": "baseColor", "resolution": list(texture_size),
                                            "frameRate": fps, "sequenceSize": frames_per_file,
                                            "sequenceCount": files}},
                       "path": "texture_[target]/[#####][ext]"}}
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
