"""What an import of a mesh sequence lists before it decodes anything: each frame's sources
(:class:`FrameSource`) and the sequence found (:class:`MeshSequence`); made by
:mod:`~uvatar.capture.importers.mesh_sequence` and :mod:`~uvatar.capture.importers.uvol1`."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class FrameSource:
    """Where one frame's mesh and texture come from: ``texture`` is an image path, a ``(ktx2 path,
    layer)`` pair (or ``(etc2 path, 0)``, or ``(video path, video frame)``), None (the mesh's own
    texture) or () (none: the frame cannot be imported); ``mesh_bytes``: (start, length) of the frame in
    a file of many (a UVOL 1 ``.drcs``); ``sample``: the frame's place in a take file, for a worker
    process that did not list the take (an Alembic sample index, a USD frame index, an FBX take's time in
    KTime): it opens the file itself and reads that sample."""

    index: int
    mesh: Path
    texture: Path | tuple[Path, int] | None = None
    mesh_bytes: tuple[int, int] | None = None
    sample: int | None = None


@dataclass
class MeshSequence:
    """A found mesh sequence: frames by take index, the layout's name, the frame rate when known,
    the units / up axis the files declare ("" when they say nothing), problems found while listing
    (one line each: counts that disagree, frames without texture) and, for headerless ``.etc2``
    textures, their (width, height)."""

    frames: dict[int, FrameSource]
    layout: str
    fps: float = 0.0
    units: str = ""
    up: str = ""
    manifest: Path | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    texture_size: tuple[int, int] | None = None

    def note_meshes(self, path: Path, parts: list[str], left_out: dict[str, str]) -> None:
        """Note a take file's meshes: those joined into the take's one mesh, and each left out and why."""
        if len(parts) > 1:
            self.notes.append(f"{path}: {len(parts)} meshes joined into the take's one mesh each frame "
                              f"({', '.join(parts[:4])}{', ...' if len(parts) > 4 else ''})")
        for name, why in left_out.items():
            self.notes.append(f"{path}: mesh {name} left out: {why}")


def frame_number(path: Path) -> int | None:
    """A per-frame file's frame number: the last run of digits in its name (``scan_000017.obj`` → 17)."""
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def files_by_frame(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """The files of ``folder`` with one of ``suffixes`` by frame number (the first name wins a tie;
    hidden files skipped)."""
    files: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith("."):
            n = frame_number(p)
            if n is not None and n not in files:
                files[n] = p
    return files
