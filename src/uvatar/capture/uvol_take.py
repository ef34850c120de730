"""Writing a UVOL 2 take, the format the Universal Volumetric player streams (and ``uvatar capture
import`` reads back): ``geometry_draco/NNNNN.drc`` (one Draco mesh a frame, UVs as glTF's, v from the
top; 14-bit positions, edgebreaker-coded), ``texture_ktx2/NNNNN.ktx2`` (one Basis ETC1S texture a frame) and ``NAME.uvol.json`` (the player's
manifest, written last: a take without it is unfinished). Needs the ``volumetric`` extra.

    with UvolTakeWriter(folder, fps=30) as take:
        for mesh in meshes:          # TexturedMesh in metres, +Y up, texture float [0, 1] or uint8
            take.add(mesh)
"""

from __future__ import annotations

from pathlib import Path

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["UvolTakeWriter", "POSITION_BITS"]

#: Draco's quantization of a streamed frame: 14 bits over a person's ~1.8 m, a step of ~0.1 mm (the
#: studio takes the player ships use 11-14); Draco's edgebreaker at level 7 reorders the faces
POSITION_BITS = 14


class UvolTakeWriter:
    """Frames in, a UVOL 2 take out (see the module doc). Frame numbers count from 0 in the order added;
    every texture must have the first one's size (the manifest has one resolution)."""

    def __init__(self, folder: str | Path, fps: float, name: str = "avatar"):
        if not fps or fps <= 0:
            raise InputError(folder, f"a UVOL take needs a frame rate > 0, not {fps}")
        self.folder, self.fps, self.name = Path(folder), float(fps), name
        self.count, self.size = 0, None
        (self.folder / "geometry_draco").mkdir(parents=True, exist_ok=True)
        (self.folder / "texture_ktx2").mkdir(parents=True, exist_ok=True)
        # a take rewritten in place is unfinished until its new manifest lands: the old one goes first
        (self.folder / f"{self.name}.uvol.json").unlink(missing_ok=True)

    def add(self, mesh: TexturedMesh) -> None:
        """Write the next frame's Draco mesh and KTX2 texture."""
        from uvatar.capture.mesh_draco import write_drc
        from uvatar.capture.take_frames import frame_texture
        from uvatar.capture.texture_ktx2 import write_ktx2

        texture, self.size = frame_texture(mesh, self.folder, self.count, self.size, "UVOL")
        write_drc(self.folder / "geometry_draco" / f"{self.count:05d}.drc", mesh, quantization_bits=POSITION_BITS,
                  compression_level=7, preserve_order=False)
        write_ktx2(self.folder / "texture_ktx2" / f"{self.count:05d}.ktx2", texture)
        self.count += 1

    def close(self) -> Path | None:
        """Write the manifest (nothing when no frame was added); returns its path. Frames beyond this
        take's count, left by a longer take written to the same folder before, are deleted first."""
        from uvatar.capture.importers.uvol_manifest import write_manifest

        if not self.count:
            return None
        for folder, suffix in (("geometry_draco", ".drc"), ("texture_ktx2", ".ktx2")):
            for path in (self.folder / folder).glob(f"*{suffix}"):
                if path.stem.isdigit() and len(path.stem) == 5 and int(path.stem) >= self.count:
                    path.unlink()
        path = self.folder / f"{self.name}.uvol.json"
        write_manifest(path, self.count, self.fps, self.size)
        return path

    def __enter__(self) -> UvolTakeWriter:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
