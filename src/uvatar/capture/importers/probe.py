"""``uvatar capture probe SRC``: what ``uvatar capture import`` would make of a volumetric video, without
importing it: the layout found, the frames kept, the frame rate, where the textures come from, the units
and up axis (stated by the files, given, or detected on the first frame that reads, as the import decides
them), the first frame's size, and every problem and note the listing found. Decodes one frame (more
only while frames fail to read)."""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import numpy as np

from uvatar.capture.importers.frame_reader import point_cloud_config, read_frame
from uvatar.capture.importers.mesh_sequence import (
    UVOL_DEFAULT_FPS,
    close_sources,
    find_mesh_sequence,
    wanted_frames,
)
from uvatar.capture.importers.sequence import FrameSource
from uvatar.capture.importers.source_world import world_from_source
from uvatar.errors import InputError

__all__ = ["probe_mesh_sequence", "texture_kind"]

MAX_TRIES = 8   # frames decoded while looking for one that reads


def texture_kind(source: FrameSource) -> str:
    """Where a frame's texture comes from, in words."""
    texture = source.texture
    if texture is None:
        return "the mesh file's own"
    if texture == ():
        return "none"
    if isinstance(texture, tuple):
        suffix = texture[0].suffix.lower()
        return {".ktx2": "KTX2 layers", ".ktx": "KTX 1 layers", ".etc2": "ETC2 files"}.get(suffix, "video frames")
    return "image files"


def probe_mesh_sequence(src: str | Path, cfg=None) -> dict:
    """The summary described in the module doc; InputError when no frame is listed or none of the first
    frames reads (naming the first failure)."""
    from uvatar.capture.importers.pipeline import ImportConfig

    cfg = cfg or ImportConfig()
    src = Path(src)
    t0 = time.perf_counter()
    try:
        seq = find_mesh_sequence(src, cfg.fps or 0.0)
        wanted, problems = wanted_frames(seq, src, cfg)
        first, failures = None, []
        for i in wanted[:MAX_TRIES]:
            try:
                first = (i, read_frame(seq.frames[i], seq.texture_size, seq.notes, point_cloud_config(cfg),
                                       bool(cfg.units or seq.units)))
                break
            except InputError as exc:
                failures.append(str(exc))
        if first is None:
            raise InputError(src, f"none of the first {len(failures)} frames reads (first: {failures[0]})")
        i, mesh = first
        S, units, up, notes = world_from_source(mesh, seq.frames[i].mesh, cfg.units or seq.units, cfg.up or seq.up)
        world = mesh.vertices @ S[:3, :3].T.astype(np.float32) + S[:3, 3].astype(np.float32)
        fps = cfg.fps or seq.fps
        return {
            "source": str(src), "layout": seq.layout, "manifest": str(seq.manifest) if seq.manifest else None,
            "frames": len(wanted), "frames_listed": len(seq.frames), "first_frame": wanted[0], "last_frame": wanted[-1],
            "fps": fps or UVOL_DEFAULT_FPS, "fps_stated": bool(fps),
            "units": units, "up": up, "units_stated": bool(cfg.units or seq.units), "up_stated": bool(cfg.up or seq.up),
            "textures": dict(Counter(texture_kind(seq.frames[k]) for k in wanted)),
            "sample_frame": {"frame": i, "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
                             "texture": [int(mesh.texture.shape[1]), int(mesh.texture.shape[0])],
                             "height_m": round(float(np.ptp(world[:, 1])), 3)},
            "frames_failing_first": failures, "problems": problems, "notes": list(seq.notes) + notes,
            "seconds": round(time.perf_counter() - t0, 2)}
    finally:
        close_sources()
