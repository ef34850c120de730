"""The Volograms ``.vols`` format (versions 1.0-1.3): the one owner of its bytes, read and written.

Written from Volograms' own reader, ``vol_geom`` of Volograms/vol_libs (MIT), which the web, Unity and
native players share. A take is either two files, a **header** (``header.vols``) and a **sequence**
(``sequence_0.vols``, the frames end to end), or, from 1.3, one file holding both (and the audio).

- The header: the format tag (Unity's length-prefixed string ``\\x04VOLS`` before 1.3, the 4 bytes
  ``VOLS`` after), the version (10-13), a compression code, before 1.3 three strings (mesh name,
  material, shader) and a topology code, the frame count; from 1.1 whether frames carry normals and a
  texture, the texture's size and (before 1.3) a Unity texture format; 1.2 adds a translation,
  rotation and scale that no player applies; 1.3 drops the strings and the transform and adds the
  texture's compression (mp4, ETC1S, UASTC) and container (raw, ``.basis``, KTX2), the frame rate, the
  audio's place and where the frames begin.
- A frame: its number, the byte size of its mesh data, its kind (0 a tracked frame, 1 a keyframe, 2 from
  1.2 the last tracked frame, for backward play), then sections of a 4-byte byte count and the bytes:
  positions (float32 x 3), normals (float32 x 3; 1.1 on, when the header says so), on keyframes (and
  kind-2 frames) the triangle indices (uint16: the players draw them as such) and the UVs (float32 x
  2, one per vertex, v up), and from 1.1 on a textured take the frame's texture (1.3: a ``.basis`` or KTX2
  file). A repeat of the mesh data size closes the frame. Tracked frames keep their keyframe's
  triangles and UVs and move only the vertices. Before 1.2 the mesh data size leaves out the section
  counts, which the reader adds back exactly as ``vol_geom`` does.

Coordinates are kept as stored: Volograms' web player draws the positions as a right-handed frame, +Y
up, the person facing +Z, and maps image row 0 at v = 1 (uvatar's conventions); no unit is stated.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

__all__ = ["VolsError", "VolsHeader", "VolsFrameEntry", "VolsFrame", "parse_header", "frame_entry",
           "parse_frame", "header_bytes", "frame_bytes", "TEXTURE_COMPRESSIONS", "TEXTURE_CONTAINERS",
           "VERSIONS", "UINT16_VERTICES"]

VERSIONS = (10, 11, 12, 13)
TEXTURE_COMPRESSIONS = ("mp4", "ETC1S", "UASTC")     # 1.3's texture_compression codes 0, 1, 2
TEXTURE_CONTAINERS = ("raw", "basis", "KTX2")        # 1.3's texture_container_format codes 0, 1, 2
UNITY_TAG = b"\x04VOLS"                              # the format tag before 1.3: a length-prefixed string
IFF_TAG = b"VOLS"
FRAME_HEADER_BYTES = 9                               # frame number, mesh data size, kind
V13_HEADER_BYTES = 44
UINT16_VERTICES = 65536       # indices are uint16 (the players draw them so); a bigger frame needs uint32
KEYFRAME, LAST_TRACKED = 1, 2


class VolsError(ValueError):
    """The bytes are not a readable ``.vols`` header or frame (the message says where and why)."""


@dataclass
class VolsHeader:
    """A ``.vols`` header; ``size``: its length in bytes; ``frame_body_start``: where a one-file take's
    frames begin (1.3; 0 = right after the header). Texture fields: 1.1 on; fps, audio and the texture
    codes: 1.3 (``fps`` 0 before)."""

    version: int
    frame_count: int
    compression: int = 0
    mesh_name: str = ""
    material: str = ""
    shader: str = ""
    topology: int = 0
    normals: bool = False
    textured: bool = False
    texture_compression: int = 0
    texture_container: int = 0
    texture_width: int = 0
    texture_height: int = 0
    texture_format: int = 0
    fps: float = 0.0
    audio: int = 0
    audio_start: int = 0
    frame_body_start: int = 0
    translation: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (1.0, 0.0, 0.0, 0.0)        # w, x, y, z
    scale: float = 1.0
    size: int = 0
    unity_tag: bool = True                        # the length-prefixed tag (every version before 1.3)

    def has_topology(self, kind: int) -> bool:
        """Whether a frame of this kind carries triangles and UVs (``vol_geom``'s rule)."""
        return kind == KEYFRAME or (self.version >= 12 and kind == LAST_TRACKED)

    @property
    def has_normals(self) -> bool:
        return self.version >= 11 and self.normals

    @property
    def has_textures(self) -> bool:
        """Whether each frame carries its own texture (else the texture is a video beside the take)."""
        return self.version >= 11 and self.textured


def _string(data: bytes, offset: int, what: str) -> tuple[str, int]:
    if offset >= len(data):
        raise VolsError(f"the header ends before its {what}")
    n = data[offset]
    if n > 127:
        raise VolsError(f"the header's {what} is {n} bytes long (at most 127)")
    if offset + n >= len(data):
        raise VolsError(f"the header ends inside its {what}")
    return data[offset + 1:offset + 1 + n].decode("utf-8", "replace"), offset + 1 + n


def parse_header(data: bytes) -> VolsHeader:
    """A ``.vols`` header from the first bytes of a file (a whole header file, or a one-file take's start)."""
    if data[:4] == IFF_TAG:
        offset, unity = 4, False
    elif data[:5] == UNITY_TAG:
        offset, unity = 5, True
    else:
        raise VolsError("not a Volograms file (it does not start with the VOLS tag)")
    if offset + 19 >= len(data):
        raise VolsError(f"the header is cut short ({len(data)} bytes)")
    version, compression = struct.unpack_from("<2I", data, offset)
    offset += 8
    if version not in VERSIONS:
        raise VolsError(f"version {version} (uvatar reads {VERSIONS[0]}-{VERSIONS[-1]}, i.e. 1.0-1.3)")
    h = VolsHeader(version, 0, compression=compression, unity_tag=unity)
    if version < 13:
        h.mesh_name, offset = _string(data, offset, "mesh name")
        h.material, offset = _string(data, offset, "material name")
        h.shader, offset = _string(data, offset, "shader name")
        if offset + 8 > len(data):
            raise VolsError("the header ends before its frame count")
        h.topology, = struct.unpack_from("<I", data, offset)
        offset += 4
    if offset + 4 > len(data):
        raise VolsError("the header ends before its frame count")
    h.frame_count, = struct.unpack_from("<I", data, offset)
    offset += 4
    if version >= 11:
        if offset + 8 > len(data):
            raise VolsError("the header ends inside its texture fields")
        h.normals, h.textured = bool(data[offset]), bool(data[offset + 1])
        offset += 2
        if version >= 13:
            if offset + 24 > len(data):
                raise VolsError("the header ends inside its 1.3 fields")
            h.texture_compression, h.texture_container = data[offset], data[offset + 1]
            (h.texture_width, h.texture_height, h.fps, h.audio, h.audio_start,
             h.frame_body_start) = struct.unpack_from("<2If3I", data, offset + 2)
            offset += 26
            if offset != V13_HEADER_BYTES:
                raise VolsError(f"a 1.3 header of {offset} bytes (1.3 headers are {V13_HEADER_BYTES})")
        else:
            h.texture_width, h.texture_height, h.texture_format = struct.unpack_from("<3H", data, offset)
            offset += 6
            if version >= 12:
                if offset + 32 > len(data):
                    raise VolsError("the header ends inside its transform")
                values = struct.unpack_from("<8f", data, offset)
                h.translation, h.rotation, h.scale = values[:3], values[3:7], values[7]
                offset += 32
    h.size = offset
    return h


def header_bytes(h: VolsHeader) -> bytes:
    """The bytes of a header (the inverse of :func:`parse_header`; 1.3 takes the IFF tag, older ones Unity's)."""
    out = bytearray(IFF_TAG if h.version >= 13 else UNITY_TAG)
    out += struct.pack("<2I", h.version, h.compression)
    if h.version < 13:
        for text in (h.mesh_name, h.material, h.shader):
            raw = text.encode("utf-8")[:127]
            out += bytes([len(raw)]) + raw
        out += struct.pack("<I", h.topology)
    out += struct.pack("<I", h.frame_count)
    if h.version >= 11:
        out += bytes([int(h.normals), int(h.textured)])
        if h.version >= 13:
            out += bytes([h.texture_compression, h.texture_container])
            out += struct.pack("<2If3I", h.texture_width, h.texture_height, h.fps, h.audio, h.audio_start,
                               h.frame_body_start)
        else:
            out += struct.pack("<3H", h.texture_width, h.texture_height, h.texture_format)
            if h.version >= 12:
                out += struct.pack("<8f", *h.translation, *h.rotation, h.scale)
    return bytes(out)


def _size_correction(h: VolsHeader, kind: int) -> int:
    """What ``vol_geom`` adds to a frame's stated mesh data size to reach its bytes: before 1.2 the size
    leaves out section counts (8 bytes on a keyframe; in 1.1 4 more, and 4 more again when textured)."""
    if h.version >= 12:
        return 0
    return (8 if kind == KEYFRAME else 0) + ((4 + (4 if h.textured else 0)) if h.version == 11 else 0)


@dataclass
class VolsFrameEntry:
    """Where one frame lies: its number and kind, the file offset of its frame header, and its mesh data
    (``payload_offset``, ``payload_size``: the sections with their counts); ``keyframe``: the number of
    the keyframe whose triangles and UVs it wears."""

    number: int
    kind: int
    offset: int
    payload_offset: int
    payload_size: int
    keyframe: int

    @property
    def end(self) -> int:
        """The offset just past the frame (its closing size included)."""
        return self.payload_offset + self.payload_size + 4


def frame_entry(h: VolsHeader, head: bytes, offset: int, index: int, file_size: int,
                previous: VolsFrameEntry | None) -> VolsFrameEntry:
    """The directory entry of frame ``index`` from its 9 header bytes ``head`` found at ``offset`` of a
    ``file_size``-byte sequence (``vol_geom``'s checks: the number must be ``index``, the frame must fit)."""
    if len(head) < FRAME_HEADER_BYTES or offset + 16 > file_size:   # vol_geom wants its 16-byte struct to fit
        raise VolsError(f"frame {index}: the file ends before its frame header (byte {offset})")
    number, size = struct.unpack_from("<2I", head, 0)
    kind = head[8]
    if number != index:
        raise VolsError(f"frame {index}: its header at byte {offset} says frame {number}")
    payload = size + _size_correction(h, kind)
    if size > file_size or offset + size > file_size or offset + FRAME_HEADER_BYTES + payload + 4 > file_size:
        raise VolsError(f"frame {index}: its {payload} bytes of mesh data at byte {offset} run past the file's "
                        f"end ({file_size} bytes)")
    if kind in (KEYFRAME, LAST_TRACKED):
        keyframe = number
    elif previous is not None:
        keyframe = previous.keyframe
    else:
        raise VolsError("frame 0 is a tracked frame: no keyframe before it gives its triangles")
    return VolsFrameEntry(number, kind, offset, offset + FRAME_HEADER_BYTES, payload, keyframe)


@dataclass
class VolsFrame:
    """One frame's arrays as stored: ``positions`` float32 (N, 3); ``normals`` float32 (N, 3) or None;
    on frames that carry topology ``indices`` int64 (F, 3) and ``uvs`` float32 (N, 2) (else None: the
    keyframe's); ``texture``: the frame's texture file bytes or None."""

    positions: np.ndarray
    normals: np.ndarray | None = None
    indices: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texture: bytes | None = None
    sizes: dict = field(default_factory=dict)     # each section's byte count, as stored


def _section(payload: bytes, offset: int, name: str, number: int) -> tuple[bytes, int]:
    if offset + 4 > len(payload):
        raise VolsError(f"frame {number}: its mesh data ends before the {name}")
    n, = struct.unpack_from("<I", payload, offset)
    if offset + 4 + n > len(payload):
        raise VolsError(f"frame {number}: its {name} ({n} bytes) run past its mesh data ({len(payload)} bytes)")
    return payload[offset + 4:offset + 4 + n], offset + 4 + n


def parse_frame(h: VolsHeader, entry: VolsFrameEntry, payload: bytes) -> VolsFrame:
    """A frame's sections from its mesh data bytes, checked for shape (the indices stay unchecked
    against the vertex count until the keyframe's are known: see :func:`topology`)."""
    number = entry.number
    raw, offset = _section(payload, 0, "positions", number)
    if len(raw) % 12:
        raise VolsError(f"frame {number}: {len(raw)} bytes of positions, not a multiple of 12 (float32 x 3)")
    frame = VolsFrame(np.frombuffer(raw, "<f4").reshape(-1, 3).astype(np.float32))
    frame.sizes["positions"] = len(raw)
    if h.has_normals:
        raw, offset = _section(payload, offset, "normals", number)
        frame.sizes["normals"] = len(raw)
        if len(raw) == 12 * len(frame.positions):
            frame.normals = np.frombuffer(raw, "<f4").reshape(-1, 3).astype(np.float32)
        elif raw:
            raise VolsError(f"frame {number}: {len(raw) // 12} normals for {len(frame.positions)} vertices")
    if h.has_topology(entry.kind):
        raw_indices, offset = _section(payload, offset, "triangle indices", number)
        raw_uvs, offset = _section(payload, offset, "UVs", number)
        frame.sizes["indices"], frame.sizes["uvs"] = len(raw_indices), len(raw_uvs)
        wide = len(frame.positions) > UINT16_VERTICES
        width = 4 if wide else 2
        if len(raw_indices) % (3 * width):
            raise VolsError(f"frame {number}: {len(raw_indices)} bytes of triangle indices, not whole "
                            f"triangles of uint{8 * width}")
        frame.indices = np.frombuffer(raw_indices, "<u4" if wide else "<u2").reshape(-1, 3).astype(np.int64)
        if len(raw_uvs) != 8 * len(frame.positions):
            raise VolsError(f"frame {number}: {len(raw_uvs) // 8} UVs for {len(frame.positions)} vertices")
        frame.uvs = np.frombuffer(raw_uvs, "<f4").reshape(-1, 2).astype(np.float32)
    if h.has_textures:
        raw, offset = _section(payload, offset, "texture", number)
        frame.sizes["texture"] = len(raw)
        frame.texture = bytes(raw) if raw else None
    return frame


def frame_bytes(h: VolsHeader, number: int, kind: int, positions: np.ndarray, normals: np.ndarray | None = None,
                indices: np.ndarray | None = None, uvs: np.ndarray | None = None, texture: bytes | None = None) -> bytes:
    """One frame's bytes (header, sections, closing size) as :func:`frame_entry`/:func:`parse_frame` read
    them; ``indices`` (F, 3) and ``uvs`` (N, 2) on frames that carry topology."""
    sections = [np.ascontiguousarray(positions, "<f4").tobytes()]
    if h.has_normals:
        sections.append(b"" if normals is None else np.ascontiguousarray(normals, "<f4").tobytes())
    if h.has_topology(kind):
        if indices is None or uvs is None:
            raise VolsError(f"frame {number} is a keyframe: it needs its triangles and UVs")
        dtype = "<u4" if len(positions) > UINT16_VERTICES else "<u2"
        sections.append(np.ascontiguousarray(indices, dtype).tobytes())
        sections.append(np.ascontiguousarray(uvs, "<f4").tobytes())
    if h.has_textures:
        sections.append(texture or b"")
    body = b"".join(struct.pack("<I", len(s)) + s for s in sections)
    size = len(body) - _size_correction(h, kind)
    return struct.pack("<2IB", number, size, kind) + body + struct.pack("<I", size)
