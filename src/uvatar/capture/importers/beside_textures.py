"""Textures stored beside a mesh file that holds none (an Alembic cache, a USD take without a material):
what a take's frames wear, found in the file's folder, its ``textures/`` (or ``texture*/``, or
``<name>/``) sub-folder, in this order:

1. **per-frame images** (``body_000017.png``: the last run of digits is the frame) whose numbers are the
   take's frame numbers, or those numbers shifted by one offset (images from 0 for a take from frame 1),
   or as many images as frames (then in order; said so);
2. **a texture video** (``*.mp4``, ``.mov``, ...; ``texture*`` first): the k-th frame wears the video frame
   shown at its time;
3. **one image**: every frame wears it (a tracked take with one atlas).
"""

from __future__ import annotations

from pathlib import Path

from uvatar.capture.importers.sequence import MeshSequence, files_by_frame
from uvatar.capture.importers.uvol1 import VIDEO_SUFFIXES, video_frame
from uvatar.capture.meshio import IMAGE_SUFFIXES
from uvatar.capture.texture_video import open_video

__all__ = ["attach_beside_textures"]


def _texture_folders(folder: Path, stem: str) -> list[Path]:
    subs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    named = [p for p in subs if p.name.lower() in ("textures", "texture", stem.lower())]
    return [folder] + named + [p for p in subs if p.name.lower().startswith("tex") and p not in named]


def _match_images(images: dict[int, Path], numbers: list[int]) -> tuple[dict[int, Path], str] | None:
    """Each frame number's image: by number, by one shift, or in order where the counts are equal."""
    if not images:
        return None
    if all(n in images for n in numbers):
        return {n: images[n] for n in numbers}, ""
    shift = min(images) - min(numbers)
    if all(n + shift in images for n in numbers):
        return {n: images[n + shift] for n in numbers}, f"images numbered from {min(images)} for frames from " \
                                                          f"{min(numbers)}: frame n wears image n{shift:+d}"
    if len(images) == len(numbers):
        return dict(zip(numbers, (images[k] for k in sorted(images)), strict=True)), \
            "image numbers are not the frames': the images in order, one a sample"
    return None


def attach_beside_textures(seq: MeshSequence, path: Path, numbers: list[int], fps: float) -> None:
    """Give each frame its texture (see the module doc); frames without one are problems."""
    folders = _texture_folders(path.parent, path.stem)
    best: tuple[int, Path, dict[int, Path]] | None = None
    for folder in folders:
        images = files_by_frame(folder, IMAGE_SUFFIXES)
        match = _match_images(images, numbers)
        if match is not None:
            textures, how = match
            for n in numbers:
                seq.frames[n].texture = textures[n]
            seq.notes.append(f"{folder}: per-frame texture images" + (f" ({how})" if how else ""))
            return
        covered = sum(n in images for n in numbers)
        if covered and (best is None or covered > best[0]):
            best = (covered, folder, images)
    videos = [p for folder in folders for p in sorted(folder.iterdir())
              if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES]
    videos.sort(key=lambda p: not p.stem.lower().startswith("tex"))
    if videos:
        video = open_video(videos[0])
        for k, n in enumerate(numbers):
            f = video_frame(k, fps, video.fps)
            seq.frames[n].texture = (videos[0], f) if f < video.count else ()
            if f >= video.count:
                seq.problems.append(f"{videos[0]}: no video frame for frame {n} ({video.count} frames)")
        seq.notes.append(f"{videos[0]}: the texture video, a frame per sample")
        return
    singles = [p for folder in folders for p in sorted(folder.iterdir())
               if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    if len(singles) == 1:
        for n in numbers:
            seq.frames[n].texture = singles[0]
        seq.notes.append(f"{singles[0]}: the only texture image: every frame wears it")
        return
    if best is not None:
        covered, folder, images = best
        for n in numbers:
            seq.frames[n].texture = images.get(n, ())
            if n not in images:
                seq.problems.append(f"{folder}: no image for frame {n}: it has no texture")
        return
    for n in numbers:
        seq.frames[n].texture = ()
    seq.problems.append(f"{path}: no texture beside it (per-frame images, a texture video or one image, in its folder "
                        "or textures/): no frame can be imported")
