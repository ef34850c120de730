"""UVOL 1 takes: the one reader of the Universal Volumetric player's first format (its ``V1`` player and
the encoder in ``deprecated/encoder`` of EtherealEngine/Universal-Volumetric).

A take is three files of one name: ``NAME.drcs`` (every frame's Corto mesh, end to end; ``NAME.uvol``
for the player's Unity version),
``NAME.manifest`` (JSON, the player's ``V1Schema``: ``frameRate``, ``maxVertices``, ``maxTriangles`` and
``frameData``, one entry a frame with ``frameNumber``, ``keyframeNumber``, ``startBytePosition``,
``meshLength``, ``vertices``, ``faces`` and ``type``) and ``NAME.mp4`` (the textures, one video frame a
mesh frame). The player shows, beside the video frame at media time t, mesh frame
``round(t * frameRate)``: so mesh frame ``i`` wears the video frame shown at ``i / frameRate``
(:func:`video_frame`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from uvatar.capture.importers.sequence import FrameSource, MeshSequence
from uvatar.capture.texture_video import COUNTER_COLUMNS, COUNTER_ROWS, open_video
from uvatar.errors import InputError

__all__ = ["V1Frame", "V1Take", "find_v1_manifest", "read_v1_manifest", "video_frame", "uvol1_sequence"]

VIDEO_SUFFIXES = (".mp4", ".webm", ".mov", ".mkv")
MESH_FILE_SUFFIXES = (".drcs", ".uvol")       # the web player's and the Unity player's names for the meshes


@dataclass
class V1Frame:
    """One manifest entry: the frame's number and its Corto bytes in the ``.drcs``."""

    number: int
    start: int
    length: int


@dataclass
class V1Take:
    """A UVOL 1 take: its manifest, ``.drcs``, texture video (None when missing), frame rate (0 when
    the manifest gives none) and frames; ``problems``: one line each for entries that cannot be read."""

    manifest: Path
    drcs: Path
    video: Path | None
    fps: float
    frames: list[V1Frame]
    problems: list[str] = field(default_factory=list)


def _is_v1(path: Path) -> bool:
    """A ``.manifest`` of UVOL 1 (its ``frameData``), not another format's file of that suffix."""
    try:
        with path.open("rb") as f:
            return b'"frameData"' in f.read(1 << 20)
    except OSError:
        return False


def find_v1_manifest(src: Path) -> Path | None:
    """The UVOL 1 manifest of ``src``: the file itself (a ``.manifest``, or a ``.drcs``/``.uvol`` beside its
    manifest), or the one ``*.manifest`` with ``frameData`` in the folder; InputError when a folder holds
    several takes (give one's manifest)."""
    src = Path(src)
    if src.is_file():
        manifest = src.with_suffix(".manifest") if src.suffix.lower() in MESH_FILE_SUFFIXES else src
        if src.suffix.lower() in (".manifest",) + MESH_FILE_SUFFIXES:
            if not manifest.is_file():
                raise InputError(src, f"UVOL 1 mesh file without its manifest ({manifest.name})")
            return manifest
        return None
    if not src.is_dir():
        return None
    found = sorted(p for p in src.glob("*.manifest") if p.is_file() and _is_v1(p))
    if len(found) > 1:
        raise InputError(src, f"holds {len(found)} UVOL 1 takes ({', '.join(p.name for p in found[:4])}); give one's "
                              ".manifest")
    return found[0] if found else None


def _int(entry: dict, key: str) -> int | None:
    value = entry.get(key)
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) and value >= 0 \
        and float(value).is_integer() else None


def _rate(value) -> float:
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            return 0.0
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    return float(value) if ok else 0.0


def read_v1_manifest(path: Path) -> V1Take:
    """Read a UVOL 1 manifest and find its ``.drcs`` and video; InputError naming the file when it is not
    JSON, has no ``frameData``, or its ``.drcs`` is missing. Entries past the ``.drcs``'s end or without
    their byte range are ``problems``, not errors."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"UVOL 1 manifest is not JSON ({type(exc).__name__})") from None
    entries = doc.get("frameData") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "UVOL 1 manifest has no frameData")
    drcs = next((path.with_suffix(s) for s in MESH_FILE_SUFFIXES if path.with_suffix(s).is_file()), None)
    if drcs is None:
        raise InputError(path.with_suffix(".drcs"), "missing (nor is there a .uvol): the UVOL 1 manifest's meshes")
    video = next((path.with_suffix(s) for s in VIDEO_SUFFIXES if path.with_suffix(s).is_file()), None)
    fps = _rate(doc.get("frameRate"))      # the encoder writes its command line's rate: "25", a string
    size = drcs.stat().st_size
    take = V1Take(path, drcs, video, fps, [])
    seen = set()
    for k, entry in enumerate(entries):
        entry = entry if isinstance(entry, dict) else {}
        number, start, length = _int(entry, "frameNumber"), _int(entry, "startBytePosition"), _int(entry, "meshLength")
        number = k if number is None else number
        if start is None or not length:
            take.problems.append(f"{path}: frameData[{k}] (frame {number}) has no byte range: frame {number} skipped")
        elif start + length > size:
            take.problems.append(f"{drcs}: frame {number} (bytes {start}-{start + length}) lies past the file's end "
                                 f"({size} bytes): frame {number} skipped")
        elif number in seen:
            take.problems.append(f"{path}: frame {number} listed twice: the first kept")
        else:
            seen.add(number)
            take.frames.append(V1Frame(number, start, length))
    return take


def video_frame(frame: int, mesh_fps: float, video_fps: float) -> int:
    """The video frame on screen while mesh frame ``frame`` shows (the player: mesh frame
    ``round(t * mesh_fps)`` at media time t): the last video frame that starts by ``(frame - 0.5) /
    mesh_fps``'s next frame time, i.e. the video frame at time ``frame / mesh_fps``."""
    if not mesh_fps or not video_fps or math.isclose(mesh_fps, video_fps, rel_tol=1e-4):
        return frame
    return int(math.floor(frame * video_fps / mesh_fps + 1e-6))


def uvol1_sequence(take: V1Take) -> MeshSequence:
    """A UVOL 1 take's frames: each mesh's bytes in the ``.drcs`` and the video frame it wears (the one
    the player shows with it; where the video carries UVOL 1's frame counter, the frame whose counter
    is the mesh's own, so a dropped or repeated video frame does not shift the textures after it)."""
    seq = MeshSequence({}, "uvol1", fps=take.fps, manifest=take.manifest, problems=list(take.problems))
    if take.video is None:
        raise InputError(take.manifest, "UVOL 1 take without its texture video (" + take.manifest.stem
                                        + ".mp4 beside it)")
    video = open_video(take.video)
    counters = video.counters()
    by_counter, offset = _counter_offset(counters)
    if not take.fps:
        seq.fps = video.fps
        seq.notes.append(f"{take.manifest}: no frameRate: the video's {video.fps:g} fps")
    if by_counter:
        video.has_counter = True
        seq.notes.append(f"{take.video}: carries UVOL 1's frame counter (mesh frame n in the video frame counting "
                         f"n{offset:+d}): each mesh wears the frame whose counter is its own, and the counter's "
                         f"corner of the texture (the bottom {COUNTER_ROWS} x {COUNTER_COLUMNS} texels) is filled "
                         "from the texels around it")
    for f in take.frames:
        k = by_counter.get(f.number + offset) if by_counter else video_frame(f.number, seq.fps, video.fps)
        if k is None or k >= video.count:
            seq.problems.append(f"{take.video}: no video frame for frame {f.number} ({video.count} frames"
                                + (", none counting " + str(f.number + offset) if by_counter else "") + ")")
            k = None
        seq.frames[f.number] = FrameSource(f.number, take.drcs, () if k is None else (take.video, k),
                                           mesh_bytes=(f.start, f.length))
    if by_counter:
        jumps = [k for k in range(1, len(counters)) if counters[k] is not None and counters[k - 1] is not None
                 and counters[k] != counters[k - 1] + 1]
        if jumps:
            seq.problems.append(f"{take.video}: its frame counter jumps at video frame{'s' if len(jumps) > 1 else ''} "
                                f"{', '.join(map(str, jumps[:5]))} (a video frame dropped or repeated): those meshes "
                                "wear the frame that counts their number")
    if len(take.frames) and video.count != len(take.frames) and not by_counter:
        seq.problems.append(f"{take.video}: {video.count} video frames for {len(take.frames)} meshes in "
                            f"{take.manifest}: the counts disagree")
    return seq


def _counter_offset(counters: list[int | None]) -> tuple[dict[int, int], int]:
    """({counter: video frame}, offset) when most frames carry a counter that steps by one with the
    video (offset: the counter of mesh frame 0's texture; the UVOL 1 encoder counts from 0 or 1); ({}, 0)
    when the video carries none."""
    known = [(k, c) for k, c in enumerate(counters) if c is not None]
    if len(known) < max(2, len(counters) // 2):
        return {}, 0
    steps = [c - k for k, c in known]
    offset = max(set(steps), key=steps.count)
    if steps.count(offset) < len(known) // 2 or len({c for _, c in known}) < 2:
        return {}, 0
    by_counter: dict[int, int] = {}
    for k, c in known:
        by_counter.setdefault(c, k)
    return by_counter, offset
