"""One-file FBX takes for ``uvatar capture import``: a mesh a frame shown by its visibility, or a tracked
mesh moved by blend shapes or a point cache (:mod:`uvatar.capture.fbx_take`), each frame wearing its meshes' own images; a take whose meshes wear
none wears the textures beside the file (:mod:`~uvatar.capture.importers.beside_textures`). FBX's
GlobalSettings give the axes and units (read in metres, +Y up) and the frame rate.

A folder of per-frame ``.fbx`` files is a mesh folder (each file a frame), as before; a folder holding
one ``.fbx`` is that file's take when it is one.
"""

from __future__ import annotations

from pathlib import Path

from uvatar.capture.fbx_take import FbxTake
from uvatar.capture.importers.beside_textures import attach_beside_textures
from uvatar.capture.importers.sequence import FrameSource, MeshSequence
from uvatar.errors import InputError

__all__ = ["FBX_SUFFIXES", "find_fbx_take", "fbx_sequence", "fbx_take_mesh", "close_fbx"]

FBX_SUFFIXES = (".fbx",)

_open: dict[Path, FbxTake] = {}     # listed takes


def find_fbx_take(src: Path, fps: float = 0.0) -> FbxTake | None:
    """The take of ``src``: an ``.fbx`` file (InputError where it is one frame's mesh), or a folder's only
    ``.fbx`` file where it is a take (None otherwise: a folder of per-frame files, or of one frame)."""
    src = Path(src)
    if src.is_file():
        return FbxTake(src, fps) if src.suffix.lower() in FBX_SUFFIXES else None
    if not src.is_dir():
        return None
    files = [p for p in src.iterdir() if p.is_file() and p.suffix.lower() in FBX_SUFFIXES and not p.name.startswith(".")]
    if len(files) != 1:
        return None
    try:
        return FbxTake(files[0], fps)
    except InputError:                       # one frame's mesh (or unreadable): the folder's one frame, as before
        return None


def fbx_take_mesh(path: Path, frame: int, ktime: int | None = None):
    """Frame ``frame`` of the listed take ``path`` (or, in a worker process that did not list it, the take
    at ``ktime``, opened once in this process): metres, +Y up, its meshes' images."""
    take = _open.get(Path(path))
    if take is None:
        if ktime is None:
            raise InputError(path, "FBX take not listed before its frames were read")
        _open[Path(path)] = take = FbxTake(path)      # its frame numbers may differ here (the rate): times do not
    return take.mesh(frame) if ktime is None else take.mesh_at(ktime)


def close_fbx() -> None:
    _open.clear()


def fbx_sequence(take: FbxTake) -> MeshSequence:
    """A listed FBX take's frames and where each one's texture comes from."""
    numbers = sorted(take.frames)
    seq = MeshSequence({n: FrameSource(n, take.path, sample=take.time_of[n]) for n in numbers}, "fbx take", fps=take.fps if take.fps_stated
                       else 0.0, units="m", up="+y", manifest=take.path)
    seq.notes.append(f"{take.path}: {take.describe()}")
    seq.notes += take.notes
    _open[take.path] = take
    if not take.has_textures():
        attach_beside_textures(seq, take.path, numbers, take.fps)
    return seq
