"""USD takes for ``uvatar capture import``: one ``.usd``/``.usda``/``.usdc``/``.usdz`` stage whose mesh
moves frame by frame (:mod:`uvatar.capture.mesh_usd`, the ``formats`` extra).

Each frame wears its material's texture (the ``UsdUVTexture`` file at its time); a stage without one
wears the textures beside it (:mod:`~uvatar.capture.importers.beside_textures`). Units and up come from
the stage's ``metersPerUnit`` and ``upAxis`` where it authors them; the frame rate from its
``timeCodesPerSecond``.
"""

from __future__ import annotations

from pathlib import Path

from uvatar.capture.importers.beside_textures import attach_beside_textures
from uvatar.capture.importers.sequence import FrameSource, MeshSequence
from uvatar.capture.mesh_usd import USD_SUFFIXES, UsdTake
from uvatar.errors import InputError

__all__ = ["USD_SUFFIXES", "find_usd", "usd_sequence", "usd_mesh", "close_usd"]

_open: dict[Path, tuple[UsdTake, dict[int, int]]] = {}   # listed takes: (take, frame index of each number)


def find_usd(src: Path) -> Path | None:
    """The USD stage of ``src`` (the file itself or the only one in a folder); None when there is none;
    InputError when a folder holds several."""
    src = Path(src)
    if src.is_file():
        return src if src.suffix.lower() in USD_SUFFIXES else None
    if not src.is_dir():
        return None
    files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix.lower() in USD_SUFFIXES
                   and not p.name.startswith("."))
    if len(files) > 1:
        raise InputError(src, f"holds {len(files)} USD files ({', '.join(p.name for p in files[:4])}); give one's "
                              "file")
    return files[0] if files else None


def usd_mesh(path: Path, frame: int, sample: int | None = None):
    """Frame ``frame`` of the listed take ``path`` (or, in a worker process that did not list it, its
    frame index ``sample``), wearing its material's texture where it has one."""
    listed = _open.get(Path(path))
    if listed is None:
        if sample is None:
            raise InputError(path, "USD take not listed before its frames were read")
        _open[Path(path)] = listed = (UsdTake(path), {})          # a worker: opened once in this process
        return listed[0].mesh(sample)
    take, index_of = listed
    return take.mesh(index_of[frame] if frame in index_of else sample)


def close_usd() -> None:
    for take, _ in _open.values():
        take.close()
    _open.clear()


def usd_sequence(path: Path, fps: float = 0.0) -> MeshSequence:
    """A USD take's frames and where each one's texture comes from."""
    path = Path(path)
    take = UsdTake(path)
    if take.uv_primvar is None:
        raise InputError(path, f"mesh {take.prim.GetPath()} has no UVs (no st primvar): its textures cannot be "
                               "mapped")
    numbers = take.frame_numbers()
    seq = MeshSequence({n: FrameSource(n, path, sample=i) for i, n in enumerate(numbers)}, "usd", fps=take.fps or fps, units=take.units,
                       up=take.up, manifest=path)
    seq.notes.append(f"{path}: {take.describe()}")
    if take.meters_per_unit and take.meters_per_unit != 1.0:
        seq.notes.append(f"{path}: metersPerUnit {take.meters_per_unit:g} applied")
    seq.note_meshes(path, [str(p.GetPath()) for p in take.parts], take.left_out)
    _open[path] = (take, {n: i for i, n in enumerate(numbers)})
    if take.texture_asset(0) is None:
        attach_beside_textures(seq, path, numbers, seq.fps or 30.0)
    return seq
