"""Volograms takes for ``uvatar capture import``: finding one and listing its frames.

What Volograms delivers (and its players, Volograms/vol_libs and the Unity plugin, read):

- **header + sequence** (every version): ``header.vols`` and ``sequence_0.vols`` in one folder, the
  textures a video beside them (``texture_1024_h264.mp4``, ``texture_2048_h264.mp4``: the largest is
  taken); older takes name them ``*_hdr.vol`` / ``*_seq.vol``.
- **one file** (1.3): ``NAME.vols`` holding the header, the audio and the frames, each frame with its own
  ``.basis`` (or KTX2) texture, or with ``mp4`` compression a video beside it.

The format is :mod:`uvatar.capture.vols_format`'s; frames are decoded by :mod:`uvatar.capture.mesh_vols`.
Mesh frame ``i`` wears video frame ``i`` (the players decode the video alongside at the take's rate;
where the video runs at another rate, the frame shown at the mesh frame's time).
"""

from __future__ import annotations

import re
from pathlib import Path

from uvatar.capture.importers.sequence import FrameSource, MeshSequence
from uvatar.capture.importers.uvol1 import VIDEO_SUFFIXES, video_frame
from uvatar.capture.mesh_vols import VolsTake, open_vols
from uvatar.capture.texture_video import open_video
from uvatar.capture.vols_format import IFF_TAG, UNITY_TAG
from uvatar.errors import InputError

__all__ = ["VOLS_SUFFIXES", "find_vols_take", "vols_sequence", "vols_take", "close_vols", "is_vols_file"]

VOLS_SUFFIXES = (".vols", ".vol")
DEFAULT_FPS = 30.0                      # the players' rate for takes whose header states none (before 1.3)

_open: dict[Path, VolsTake] = {}        # the takes listed by this import, by sequence file


def is_vols_file(path: Path) -> bool:
    """A file that starts with a Volograms header."""
    try:
        with Path(path).open("rb") as f:
            head = f.read(5)
    except OSError:
        return False
    return head[:4] == IFF_TAG or head == UNITY_TAG


def _header_only(path: Path) -> bool:
    from uvatar.capture.mesh_vols import read_vols_header

    header = read_vols_header(path)
    return path.stat().st_size <= (header.frame_body_start or header.size)


def find_vols_take(src: Path) -> tuple[Path, Path | None] | None:
    """(header, sequence or None for a one-file take) of the Volograms take at ``src`` (a folder, a header,
    a sequence or a one-file ``.vols``); None when ``src`` is no Volograms take; InputError when a folder
    holds several or a header's sequence is missing."""
    src = Path(src)
    if src.is_file():
        if src.suffix.lower() not in VOLS_SUFFIXES:
            return None
        folder = src.parent
        if is_vols_file(src) and not _header_only(src):
            return src, None
    elif src.is_dir():
        folder = src
    else:
        return None
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VOLS_SUFFIXES
                   and not p.name.startswith("."))
    if not files:
        return None
    headers = [p for p in files if is_vols_file(p)]
    singles = [p for p in headers if not _header_only(p)]
    headers = [p for p in headers if p not in singles]
    sequences = [p for p in files if p not in headers and p not in singles]
    if src.is_file():
        if src in headers:
            sequence = _pair(src, sequences)
            if sequence is None:
                raise InputError(src, "Volograms header without its sequence file (sequence_0.vols beside it)")
            return src, sequence
        header = next((h for h in headers if _pair(h, [src]) == src), None)
        if header is None:
            raise InputError(src, "Volograms sequence without its header (header.vols beside it)")
        return header, src
    takes = [(h, _pair(h, sequences)) for h in headers] + [(s, None) for s in singles]
    takes = [(h, s) for h, s in takes if s is not None or h in singles]
    if len(takes) > 1:
        raise InputError(src, f"holds {len(takes)} Volograms takes ({', '.join(h.name for h, _ in takes[:4])}); give "
                              "one's .vols file")
    if not takes:
        if headers:
            raise InputError(headers[0], "Volograms header without its sequence file (sequence_0.vols beside it)")
        return None
    return takes[0]


def _pair(header: Path, sequences: list[Path]) -> Path | None:
    """The sequence file of a header: ``sequence_0.vols`` for ``header.vols``, ``X_seq.vol`` for ``X_hdr.vol``,
    else the only sequence there is."""
    stem = header.stem.lower()
    names = {p.name.lower(): p for p in sequences}
    if stem == "header":
        for name in ("sequence_0" + header.suffix.lower(), "sequence_0.vols", "sequence.vols"):
            if name in names:
                return names[name]
    if stem.endswith("_hdr") or stem.endswith("hdr"):
        base = re.sub(r"_?hdr$", "", stem)
        for name, p in names.items():
            if re.fullmatch(re.escape(base) + r"_?seq(_0)?\.vols?", name):
                return p
    return sequences[0] if len(sequences) == 1 else None


def vols_take(sequence: Path) -> VolsTake:
    """The listed take whose sequence file is ``sequence`` (opened by :func:`vols_sequence`; in a worker
    process that did not list it, found from that file and opened once here)."""
    take = _open.get(Path(sequence))
    if take is None:
        found = find_vols_take(Path(sequence))
        if found is None:
            raise InputError(sequence, "Volograms take not listed before its frames were read")
        _open[Path(sequence)] = take = open_vols(*found)
    return take


def close_vols() -> None:
    """Forget the takes listed by this import."""
    _open.clear()


def _video(folder: Path) -> Path | None:
    """The take's texture video: the largest ``texture_<size>...`` one, else the only video in the folder."""
    videos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    named = [p for p in videos if p.stem.lower().startswith("texture")]

    def size(p: Path) -> int:
        digits = re.findall(r"\d+", p.stem)
        return int(digits[0]) if digits else 0

    if named:
        return max(named, key=lambda p: (size(p), p.suffix.lower() == ".mp4"))
    return videos[0] if len(videos) == 1 else None


def vols_sequence(header: Path, sequence: Path | None) -> MeshSequence:
    """A Volograms take's frames and where each one's texture comes from."""
    take = open_vols(header, sequence)
    _open[take.sequence] = take
    h = take.header
    seq = MeshSequence({}, "volograms", fps=h.fps if h.fps > 0 else 0.0, manifest=take.header_path,
                       problems=list(take.problems), up="+y")
    seq.notes.append(f"{take.header_path}: {take.describe()}")
    if h.version == 12 and (tuple(h.translation) != (0.0, 0.0, 0.0) or tuple(h.rotation) != (1.0, 0.0, 0.0, 0.0)
                            or h.scale != 1.0):
        seq.notes.append(f"{take.header_path}: the header's translation, rotation and scale are not applied (no "
                         "Volograms player applies them)")
    if h.audio:
        seq.notes.append(f"{take.header_path}: the take's audio is not imported")
    if len(take.frames) < h.frame_count:
        seq.problems.append(f"{take.sequence}: {len(take.frames)} of the header's {h.frame_count} frames found")
    if take.texture_kind() != "video":
        for entry in take.frames:
            seq.frames[entry.number] = FrameSource(entry.number, take.sequence)
        return seq
    video_path = _video(take.header_path.parent)
    if video_path is None:
        raise InputError(take.header_path, "Volograms take without its texture video (texture_1024_h264.mp4 "
                                           "beside it)")
    video = open_video(video_path)
    fps = seq.fps or DEFAULT_FPS
    if not seq.fps:
        seq.fps = fps
        seq.notes.append(f"{take.header_path}: no frame rate in a {h.version // 10}.{h.version % 10} header: "
                         f"{DEFAULT_FPS:g} fps, the Volograms players'")
    for entry in take.frames:
        k = video_frame(entry.number, fps, video.fps)
        if k >= video.count:
            seq.problems.append(f"{video_path}: no video frame for frame {entry.number} ({video.count} frames)")
        seq.frames[entry.number] = FrameSource(entry.number, take.sequence, () if k >= video.count else (video_path, k))
    if video.count != len(take.frames):
        seq.problems.append(f"{video_path}: {video.count} video frames for {len(take.frames)} meshes in "
                            f"{take.sequence}: the counts disagree")
    return seq
