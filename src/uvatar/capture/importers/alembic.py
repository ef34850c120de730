"""Alembic takes for ``uvatar capture import``: one ``.abc`` mesh cache and its textures beside it.

Studios export a volumetric take as an Alembic cache of its meshes (tracked: one topology; untracked:
each frame its own) with the textures as files of their own, since Alembic stores none: per-frame images,
a texture video or one image, found beside the file as
:func:`~uvatar.capture.importers.beside_textures.attach_beside_textures` finds them (frame numbers: the
samples' times x the frame rate).

A folder of numbered one-sample files (``take_0001.abc``, ...) is a mesh folder like one of OBJs: each
file a frame, its image of the same name beside it or in ``textures/``.

The mesh is :mod:`uvatar.capture.mesh_abc`'s; the archive has no units (Maya writes centimetres,
Houdini metres): they come from ``--units`` or the person's height, as for any mesh folder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.importers.beside_textures import attach_beside_textures
from uvatar.capture.importers.sequence import FrameSource, MeshSequence, frame_number
from uvatar.capture.mesh_abc import AlembicTake
from uvatar.errors import InputError

__all__ = ["ABC_SUFFIXES", "find_alembic", "alembic_sequence", "alembic_mesh", "close_alembic"]

ABC_SUFFIXES = (".abc",)
DEFAULT_FPS = 30.0      # where neither the sampling nor the archive says

_open: dict[Path, tuple[AlembicTake, dict[int, int]]] = {}   # listed takes: (take, sample of each frame number)
_opened_here: dict[Path, AlembicTake] = {}                   # takes a worker process opened to read samples


def find_alembic(src: Path) -> Path | None:
    """The ``.abc`` take of ``src`` (the file itself or the only one in a folder); None when there is
    none, or when the folder's several are per-frame files (``take_0001.abc``, ...: a mesh folder's
    frames); InputError when a folder holds several that are not."""
    src = Path(src)
    if src.is_file():
        return src if src.suffix.lower() in ABC_SUFFIXES else None
    if not src.is_dir():
        return None
    files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix.lower() in ABC_SUFFIXES
                   and not p.name.startswith("."))
    if len(files) > 1:
        numbers = [frame_number(p) for p in files]
        if None not in numbers and len(set(numbers)) == len(files):
            return None
        raise InputError(src, f"holds {len(files)} Alembic files ({', '.join(p.name for p in files[:4])}); give "
                              "one's .abc file")
    return files[0] if files else None


def alembic_mesh(path: Path, frame: int, sample: int | None = None):
    """Frame ``frame`` of the listed take ``path`` (or, in a worker process that did not list it, its
    sample ``sample``), or the one sample of a per-frame file (the archive's units and axes, no texture)."""
    listed = _open.get(Path(path))
    if listed is not None:
        take, sample_of = listed
        return take.mesh(sample_of[frame])
    if sample is not None:                        # a worker: the take opened once in this process
        if Path(path) not in _opened_here:
            _opened_here[Path(path)] = AlembicTake(path)
        return _opened_here[Path(path)].mesh(sample)
    take = AlembicTake(path)                      # one frame of a folder of per-frame files
    try:
        if take.count != 1:
            raise InputError(path, f"holds {take.count} samples, beside other numbered .abc files: a folder of "
                                   "per-frame Alembic files needs one sample a file")
        return take.mesh(0)
    finally:
        take.close()


def close_alembic() -> None:
    """Close the takes listed by this import."""
    for take in [t for t, _ in _open.values()] + list(_opened_here.values()):
        take.close()
    _open.clear()
    _opened_here.clear()


def _frame_numbers(take: AlembicTake, fps: float, seq: MeshSequence) -> list[int]:
    """Each sample's frame number: its time x ``fps`` where that names every sample once, else its index."""
    times = np.array([take.time(i) for i in range(take.count)])
    numbers = np.rint(times * fps).astype(np.int64)
    if len(set(numbers.tolist())) == take.count and (numbers >= 0).all():
        return numbers.tolist()
    seq.notes.append(f"{take.path}: sample times do not fall on distinct frames at {fps:g} fps (subframes or "
                     "negative times): frames are numbered by sample, from 0")
    return list(range(take.count))


def alembic_sequence(path: Path, fps: float = 0.0) -> MeshSequence:
    """An Alembic take's frames and where each one's texture comes from; ``fps`` numbers the frames of a
    take whose sampling states no rate (acyclic times)."""
    path = Path(path)
    take = AlembicTake(path)
    fps = take.fps() or fps
    seq = MeshSequence({}, "alembic", fps=fps, manifest=path)
    seq.notes.append(f"{path}: {take.describe()}")
    seq.note_meshes(path, [p.name for p in take.parts], take.left_out)
    if take.uv_param is None:
        take.close()
        raise InputError(path, f"mesh {take.mesh_object.full_name} has no UVs (no uv parameter): its textures "
                               "cannot be mapped")
    if not fps:
        fps = DEFAULT_FPS
        seq.notes.append(f"{path}: no frame rate in the archive (acyclic times): frames numbered at "
                         f"{DEFAULT_FPS:g} fps (the import's fps option sets another)")
    numbers = _frame_numbers(take, fps, seq)
    _open[path] = (take, {n: i for i, n in enumerate(numbers)})
    seq.frames = {n: FrameSource(n, path, sample=i) for i, n in enumerate(numbers)}
    attach_beside_textures(seq, path, numbers, fps)
    return seq
