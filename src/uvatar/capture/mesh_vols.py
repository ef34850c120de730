"""Volograms takes read as textured meshes: a header and a sequence file (or one 1.3 file) → frames.

The bytes are :mod:`uvatar.capture.vols_format`'s. :func:`open_vols` lists a take's frames the way
``vol_geom`` does (a frame header each, seeking past the mesh data); :meth:`VolsTake.mesh` decodes one
frame: its positions, the triangles and UVs of its keyframe, welded by position like every per-vertex-UV
format (:func:`uvatar.capture.mesh_glb.weld_by_position`), and its own texture where the take embeds one
(1.3: a ``.basis`` file, :mod:`uvatar.capture.texture_basis`, or a KTX2 file). Takes whose textures are a
video beside them (every take before 1.3, and 1.3 takes with ``mp4`` compression) leave the texture to
the importer. A broken frame raises InputError naming the file and the frame; the others still read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.mesh_glb import weld_by_position
from uvatar.capture.types import TexturedMesh
from uvatar.capture.vols_format import (
    FRAME_HEADER_BYTES,
    TEXTURE_COMPRESSIONS,
    TEXTURE_CONTAINERS,
    VolsError,
    VolsFrame,
    VolsFrameEntry,
    VolsHeader,
    frame_entry,
    parse_frame,
    parse_header,
)
from uvatar.errors import InputError

__all__ = ["VolsTake", "open_vols", "read_vols_header"]

HEADER_READ_BYTES = 512       # every header version fits (three 127-byte strings at most)


def read_vols_header(path: Path) -> VolsHeader:
    """The header of a ``.vols`` file (a header file or a one-file take); InputError naming it."""
    try:
        with Path(path).open("rb") as f:
            data = f.read(HEADER_READ_BYTES)
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    try:
        return parse_header(data)
    except VolsError as exc:
        raise InputError(path, f"Volograms header: {exc}") from None


@dataclass
class VolsTake:
    """A Volograms take: its header file, its sequence file (the same file for a one-file take, whose
    frames begin at ``start``), the header, the frames listed and problems met while listing (a frame
    that cannot be found ends the list, as in ``vol_geom``)."""

    header_path: Path
    sequence: Path
    header: VolsHeader
    start: int
    frames: list[VolsFrameEntry]
    problems: list[str] = field(default_factory=list)
    _topology: tuple[int, np.ndarray, np.ndarray] | None = None

    @property
    def one_file(self) -> bool:
        return self.header_path == self.sequence

    def texture_kind(self) -> str:
        """What a frame's texture is: "video" (beside the take), or the embedded file's container."""
        h = self.header
        if not h.has_textures:
            return "video"
        if h.version < 13:
            return "unity"            # 1.1/1.2 embedded textures: a Unity texture format (none seen in takes)
        return TEXTURE_CONTAINERS[h.texture_container] if h.texture_container < len(TEXTURE_CONTAINERS) else "?"

    def describe(self) -> str:
        h = self.header
        texture = ("a video beside it" if self.texture_kind() == "video" else
                   f"{TEXTURE_COMPRESSIONS[h.texture_compression] if h.texture_compression < 3 else '?'} in "
                   f"{self.texture_kind()} files, one a frame")
        return (f"Volograms {h.version // 10}.{h.version % 10} take, {'one file' if self.one_file else 'header + sequence'}"
                f", {h.frame_count} frames, textures: {texture}")

    def _payload(self, entry: VolsFrameEntry) -> bytes:
        with self.sequence.open("rb") as f:
            f.seek(entry.payload_offset)
            data = f.read(entry.payload_size)
        if len(data) < entry.payload_size:
            raise InputError(self.sequence, f"frame {entry.number} is cut short")
        return data

    def arrays(self, number: int) -> VolsFrame:
        """Frame ``number``'s sections as stored, its keyframe's triangles and UVs filled in."""
        entry = self._entry(number)
        try:
            frame = parse_frame(self.header, entry, self._payload(entry))
        except VolsError as exc:
            raise InputError(self.sequence, str(exc)) from None
        if frame.indices is None:
            key, indices, uvs = self._keyframe_topology(entry.keyframe)
            if len(uvs) != len(frame.positions):
                raise InputError(self.sequence, f"frame {number} has {len(frame.positions)} vertices, its keyframe "
                                                f"{key} {len(uvs)}: the tracked frame does not fit its keyframe")
            frame.indices, frame.uvs = indices, uvs
        else:
            self._topology = (number, frame.indices, frame.uvs)
        if len(frame.indices) and (frame.indices.max() >= len(frame.positions)):
            raise InputError(self.sequence, f"frame {number}: a triangle index {int(frame.indices.max())} past its "
                                            f"{len(frame.positions)} vertices")
        return frame

    def _entry(self, number: int) -> VolsFrameEntry:
        if not 0 <= number < len(self.frames):
            raise InputError(self.sequence, f"no frame {number} (the take lists {len(self.frames)})")
        return self.frames[number]

    def _keyframe_topology(self, key: int) -> tuple[int, np.ndarray, np.ndarray]:
        if self._topology is None or self._topology[0] != key:
            entry = self._entry(key)
            try:
                frame = parse_frame(self.header, entry, self._payload(entry))
            except VolsError as exc:
                raise InputError(self.sequence, f"keyframe {key}: {exc}") from None
            if frame.indices is None:
                raise InputError(self.sequence, f"keyframe {key} carries no triangles")
            self._topology = (key, frame.indices, frame.uvs)
        return self._topology

    def mesh(self, number: int) -> TexturedMesh:
        """Frame ``number`` as a TexturedMesh in the file's units and axes (welded; UVs v up), with its
        embedded texture decoded where the take has one (else no texture)."""
        frame = self.arrays(number)
        if not np.isfinite(frame.positions).all():
            raise InputError(self.sequence, f"frame {number} has non-finite vertices: corrupt")
        if len(frame.indices) == 0:
            raise InputError(self.sequence, f"frame {number} has no triangles")
        vertices, faces = weld_by_position(frame.positions, frame.indices)
        mesh = TexturedMesh(vertices, faces, frame.uvs, frame.indices, None)
        if self.header.has_textures:
            mesh.texture = self._texture(number, frame.texture)
        return mesh

    def _texture(self, number: int, data: bytes | None) -> np.ndarray:
        where = f"{self.sequence} (frame {number}'s texture)"
        if not data:
            raise InputError(self.sequence, f"frame {number} has no texture bytes")
        kind = self.texture_kind()
        if kind == "basis":
            from uvatar.capture.texture_basis import read_basis_bytes

            return read_basis_bytes(data, where)
        if kind == "KTX2":
            from uvatar.capture.texture_ktx2 import read_ktx2_bytes

            return read_ktx2_bytes(data, where)
        raise InputError(self.header_path, f"frame textures in a {kind} container are not read (uvatar reads .basis "
                                           "and KTX2 ones, and texture videos)")


def open_vols(header_path: Path, sequence: Path | None = None) -> VolsTake:
    """List a take's frames: ``header_path`` a one-file take (``sequence`` None) or a header whose frames
    are in ``sequence``. InputError when the header is unreadable or no frame can be found."""
    header_path = Path(header_path)
    header = read_vols_header(header_path)
    sequence = Path(sequence) if sequence is not None else header_path
    if sequence == header_path:
        start = header.frame_body_start or header.size
    else:
        start = 0
    if not sequence.is_file():
        raise InputError(sequence, "missing: the Volograms take's sequence file")
    size = sequence.stat().st_size
    take = VolsTake(header_path, sequence, header, start, [])
    previous = None
    with sequence.open("rb") as f:
        offset = start
        for index in range(header.frame_count):
            f.seek(offset)
            head = f.read(FRAME_HEADER_BYTES)
            try:
                entry = frame_entry(header, head, offset, index, size, previous)
            except VolsError as exc:
                take.problems.append(f"{sequence}: {exc}: frames {index}-{header.frame_count - 1} not found")
                break
            take.frames.append(entry)
            previous, offset = entry, entry.end
    if not take.frames:
        raise InputError(sequence, "no frame of the Volograms take can be found: " + "; ".join(take.problems)
                         if take.problems else "the Volograms header lists no frame")
    return take
