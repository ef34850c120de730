"""``uvatar capture import`` of a volumetric video: a sequence of textured meshes, one per frame.

Two layouts are read (:func:`find_mesh_sequence`):

- **UVOL 2** (the Universal Volumetric player's output): ``geometry_<target>/NNNNN.drc`` (Draco, one
  mesh per frame) and ``texture_<target>/NNNNN.ktx2`` (KTX2 array textures, ``n`` frames per file:
  frame ``i`` is file ``i // n``, layer ``i % n``) or per-frame ``.png``/``.jpg``; a manifest
  (``*.uvol.json``, ``*.manifest``, ``manifest.json``) when there is one gives the frame rate, the
  frame count, the frames per KTX2 file and the path templates; without one, the folders are found
  by name and ``n`` is the layer count of the first KTX2 file.
- **Plain folders** of per-frame ``.obj``/``.ply``/``.glb``/``.drc`` (frame number = the last run of
  digits in the file name) with their own textures (OBJ's .mtl, PLY's ``TextureFile`` comment, GLB's
  embedded image) or an image of the same stem beside them or in ``textures/``.

Every frame becomes ``OUT/scans/<frame>.ply`` + ``<frame>.png`` (texture at its own resolution) in
uvatar's world (metres, +Y up); frame names keep the take's numbering (frame 17 → ``000017``).
Units and up axis: what the file says (glTF/GLB: metres, +Y up), else ``--units``/``--up``, else
detected: the units that make the first frame's height a person's (0.5-2.5 m), +Y up unless the
mesh is tallest along another axis (then the import asks for ``--up``). A KTX2 *animation*'s P-frames
are decoded after the frames before them in their file (:mod:`uvatar.capture.texture_ktx2`), so every
frame has its own texture in its own UV atlas. A frame whose mesh or texture is broken is reported in
one line naming its file and skipped; the others are imported.
Resumable: frames already written are kept (all writes are atomic; ``capture.json`` comes last).
"""

from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.importers.calibration import UNIT_SCALE, up_rotation
from uvatar.capture.layout import frame_name
from uvatar.capture.meshio import IMAGE_SUFFIXES, MESH_FORMATS, read_mesh
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, one_line

log = logging.getLogger(__name__)

MANIFEST_PATTERNS = ("*.uvol.json", "*.manifest", "manifest.json", "*.uvol")
PERSON_HEIGHT_M = (0.5, 2.5)  # a frame's extent along up, in metres, that the unit detection accepts
UVOL_DEFAULT_FPS = 30.0       # the UVOL encoder's default frame rate, used when nothing says otherwise
KTX2_ANIMATION_TEXTURES = "p-frames-decoded"  # how this version gives an animation's frames their textures
OLDER_KTX2_TEXTURES = ("imported by an older uvatar, which gave a KTX2 animation's P-frames their I-frame's "
                       "texture; this one decodes them")


@dataclass
class FrameSource:
    """Where one frame's mesh and texture come from: ``texture`` is an image path, a ``(ktx2 path,
    layer)`` pair, None (the mesh's own texture) or () (none: the frame cannot be imported)."""

    index: int
    mesh: Path
    texture: Path | tuple[Path, int] | None = None


@dataclass
class MeshSequence:
    """A found mesh sequence: frames by take index, the layout's name, the frame rate when known,
    the units / up axis the files declare ("" when they say nothing) and problems found while
    listing (one line each: counts that disagree, frames without texture)."""

    frames: dict[int, FrameSource]
    layout: str
    fps: float = 0.0
    units: str = ""
    up: str = ""
    manifest: Path | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def is_mesh_sequence(src: str | Path) -> bool:
    """True if ``src`` looks like a mesh sequence (UVOL 2 folders, a manifest, or per-frame meshes)."""
    src = Path(src)
    if not src.is_dir():
        return False
    if _uvol_folders(src)[0] or _find_manifest(src):
        return True
    return any(p.suffix.lower() in MESH_FORMATS or p.suffix.lower() == ".drc" for p in src.iterdir() if p.is_file())


def _frame_number(path: Path) -> int | None:
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def _find_manifest(src: Path) -> Path | None:
    for pattern in MANIFEST_PATTERNS:
        found = sorted(p for p in src.glob(pattern) if p.is_file())
        if found:
            return found[0]
    return None


def _uvol_folders(src: Path) -> tuple[list[Path], list[Path]]:
    geometry = sorted(p for p in src.glob("geometry_*") if p.is_dir())
    texture = sorted(p for p in src.glob("texture_*") if p.is_dir())
    return geometry, texture


def _read_manifest(path: Path) -> dict:
    """The fields uvatar uses from a UVOL manifest (v2 ``output`` targets and path templates, or the
    older flat ``geometry``/``texture`` blocks): fps, frame_count, frames_per_file, geometry/texture
    path templates and target names; missing fields are absent."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"UVOL manifest is not valid JSON ({one_line(exc)})") from None
    if not isinstance(data, dict):
        raise InputError(path, "UVOL manifest must be a JSON object")
    out: dict = {}
    blocks = data.get("output", data)
    geometry = blocks.get("geometry", {}) if isinstance(blocks, dict) else {}
    texture = blocks.get("texture", {}) if isinstance(blocks, dict) else {}
    if isinstance(texture, dict) and "baseColor" in texture and isinstance(texture["baseColor"], dict):
        texture = {**texture, **texture["baseColor"]}
    for block, key in ((geometry, "geometry"), (texture, "texture")):
        if not isinstance(block, dict):
            continue
        targets = block.get("targets", {})
        if isinstance(targets, dict) and targets:
            name, target = _readable_target(targets)
            out[f"{key}_target"] = name
            if isinstance(target, dict):
                block = {**block, **target}
        if isinstance(block.get("path"), str):
            out[f"{key}_path"] = block["path"]
        if key == "geometry" and isinstance(block.get("frameRate"), int | float) and block["frameRate"] > 0:
            out["fps"] = float(block["frameRate"])
        if key == "geometry" and isinstance(block.get("frameCount"), int):
            out["frame_count"] = int(block["frameCount"])
        if key == "texture" and isinstance(block.get("sequenceSize"), int) and block["sequenceSize"] > 0:
            out["frames_per_file"] = int(block["sequenceSize"])
        if key == "texture" and "fps" not in out and isinstance(block.get("frameRate"), int | float):
            out["texture_fps"] = float(block["frameRate"])
    return out


#: UVOL 2 texture formats uvatar cannot decode (the player's ``astc/ktx``: KTX 1 files of ASTC blocks)
UNREADABLE_TEXTURE_FORMATS = ("astc/ktx",)


def _readable_target(targets: dict) -> tuple[str, dict]:
    """The manifest's first target uvatar can read (UVOL 2 lists e.g. an ``astc/ktx`` texture target
    before its ``ktx2`` one); the first target when none says its format."""
    for name, target in targets.items():
        if not (isinstance(target, dict) and target.get("format") in UNREADABLE_TEXTURE_FORMATS):
            return name, target
    return next(iter(targets.items()))


def _template_folder(src: Path, template: str | None, target: str | None, kind: str) -> Path | None:
    """The folder of a manifest path template such as ``output/geometry_[target]/[index][ext]``."""
    if not template:
        return None
    folder = template.replace("[target]", target or "").replace("[type]", "baseColor").replace("[tag]", "default")
    folder = folder.rsplit("/", 1)[0]
    for base in (src, src.parent):
        for candidate in (base / folder, base / Path(folder).name):
            if candidate.is_dir():
                return candidate
    log.warning("%s folder %s named by the manifest is not there; looking by name", kind, folder)
    return None


def _pick(folders: list[Path], suffixes: tuple[str, ...]) -> Path | None:
    """The first folder holding files of the preferred suffix order (e.g. Draco before GLB)."""
    for suffix in suffixes:
        for folder in folders:
            if any(folder.glob(f"*{suffix}")):
                return folder
    return None


def _files_by_frame(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    files: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith("."):
            n = _frame_number(p)
            if n is not None and n not in files:
                files[n] = p
    return files


def find_mesh_sequence(src: str | Path) -> MeshSequence:
    """List a mesh sequence's frames (nothing decoded but KTX2 headers); InputError when none."""
    from uvatar.capture.texture_ktx2 import ktx2_info

    src = Path(src)
    if not src.is_dir():
        raise InputError(src, "volumetric video folder does not exist")
    manifest_path = _find_manifest(src)
    manifest = _read_manifest(manifest_path) if manifest_path else {}
    geometry_dirs, texture_dirs = _uvol_folders(src)
    if not geometry_dirs and not manifest.get("geometry_path"):
        return _plain_folder(src)
    geometry = _template_folder(src, manifest.get("geometry_path"), manifest.get("geometry_target"), "geometry") \
        or _pick(geometry_dirs, (".drc", ".glb", ".obj", ".ply"))
    if geometry is None:
        raise InputError(src, "no geometry_*/ folder with .drc/.glb/.obj/.ply frames")
    meshes = _files_by_frame(geometry, (".drc", ".glb", ".obj", ".ply"))
    if not meshes:
        raise InputError(geometry, "holds no mesh frames (NNNNN.drc)")
    texture = _template_folder(src, manifest.get("texture_path"), manifest.get("texture_target"), "texture") \
        or _pick(texture_dirs, (".ktx2",) + IMAGE_SUFFIXES)
    problems: list[str] = []
    notes: list[str] = []
    frames = {i: FrameSource(i, p) for i, p in meshes.items()}
    if _pick([texture] if texture else [], (".ktx2",) + IMAGE_SUFFIXES) is None:   # nothing readable
        astc = _pick(texture_dirs + ([texture] if texture else []), (".ktx",))
        if astc is not None and all(p.suffix.lower() == ".drc" for p in meshes.values()):
            raise InputError(astc, "holds KTX 1 textures (.ktx: UVOL 2's astc/ktx target, ASTC blocks), which uvatar "
                                   "does not decode; give the take with its ktx2 target (texture_ktx2/) or per-frame "
                                   "images")
    if texture is None:
        problems.append(f"{src}: no texture_*/ folder: frames take their meshes' own textures")
    else:
        ktx = _files_by_frame(texture, (".ktx2",))
        if ktx:
            first = ktx[min(ktx)]
            first_info = ktx2_info(first)
            per_file = manifest.get("frames_per_file") or first_info["layers"]
            if first_info["animation"] and per_file > 1:
                notes.append(f"{texture}: KTX2 animations (KTXanimData): each file's {per_file - 1} P-frames decoded "
                             "after its I-frame")
            layers: dict[Path, int] = {}
            for i, source in frames.items():
                path = ktx.get(i // per_file)
                if path is None:
                    problems.append(f"{texture / f'{i // per_file:05d}.ktx2'}: missing: frame {i} has no texture")
                    source.texture = ()
                    continue
                if path not in layers:
                    try:
                        layers[path] = ktx2_info(path)["layers"]
                    except InputError as exc:
                        layers[path] = 0
                        problems.append(str(exc))
                if i % per_file >= layers[path]:
                    if layers[path]:
                        problems.append(f"{path}: has {layers[path]} layers, fewer than the {per_file} frames per "
                                        f"file: frame {i} (layer {i % per_file}) has no texture")
                    source.texture = ()
                    continue
                source.texture = (path, i % per_file)
            covered = max(ktx) * per_file + per_file
            if covered < max(frames) + 1 or len(ktx) * per_file < len(frames) - per_file + 1:
                problems.append(f"{texture}: {len(ktx)} KTX2 files x {per_file} frames for {len(frames)} meshes in "
                                f"{geometry}: the counts disagree")
            elif max(ktx) * per_file > max(frames):
                problems.append(f"{texture}: textures for frames past the last mesh ({max(frames)}): the counts "
                                f"disagree; those textures are not used")
        else:
            images = _files_by_frame(texture, IMAGE_SUFFIXES)
            for i, source in frames.items():
                source.texture = images.get(i, ())
                if not source.texture:
                    problems.append(f"{texture}: no image for frame {i} ({meshes[i].name})")
            if len(images) != len(frames):
                problems.append(f"{texture}: {len(images)} images for {len(frames)} meshes in {geometry}: the counts "
                                f"disagree")
    count = manifest.get("frame_count")
    if count is not None and count != len(frames):
        problems.append(f"{manifest_path}: says {count} frames, {geometry} holds {len(frames)}: the counts disagree")
    fps = manifest.get("fps") or manifest.get("texture_fps") or 0.0
    glb = all(p.suffix.lower() == ".glb" for p in meshes.values())  # glTF says: metres, +Y up
    units, up = ("m", "+y") if glb else ("", "")
    return MeshSequence(frames, "uvol2", fps=fps, units=units, up=up, manifest=manifest_path, problems=problems,
                        notes=notes)


def _plain_folder(src: Path) -> MeshSequence:
    suffixes = tuple(MESH_FORMATS) + (".drc",)
    meshes = _files_by_frame(src, suffixes)
    if not meshes:
        raise InputError(src, "no volumetric video here: no geometry_*/ folder, no UVOL manifest and no per-frame "
                              f"meshes ({', '.join(suffixes)})")
    problems = []
    frames = {}
    for i, path in meshes.items():
        texture = None
        for folder in (src, src / "textures"):
            image = next((folder / f"{path.stem}{s}" for s in IMAGE_SUFFIXES if (folder / f"{path.stem}{s}").is_file()),
                         None)
            if image is not None and path.suffix.lower() in (".drc", ".ply"):
                texture = image
                break
        if path.suffix.lower() == ".drc" and texture is None:
            problems.append(f"{path}: a Draco mesh without an image of the same name: frame {i} has no texture")
            texture = ()
        frames[i] = FrameSource(i, path, texture)
    glb = all(p.suffix.lower() == ".glb" for p in meshes.values())
    return MeshSequence(frames, "mesh folder", units="m" if glb else "", up="+y" if glb else "", problems=problems)


def _read_mesh(path: Path) -> TexturedMesh:
    from uvatar.capture.mesh_draco import read_drc

    return read_drc(path) if path.suffix.lower() == ".drc" else read_mesh(path)


def _read_frame(source: FrameSource) -> TexturedMesh:
    """Decode a frame's mesh and texture (source units and axes); InputError naming the bad file."""
    from uvatar.capture.texture_ktx2 import read_ktx2_layer
    from uvatar.io_utils import read_image

    if source.texture == ():
        raise InputError(source.mesh, "frame has no texture")
    mesh = _read_mesh(source.mesh)
    if isinstance(source.texture, tuple):
        mesh.texture = read_ktx2_layer(*source.texture)
    elif source.texture is not None:
        mesh.texture = read_image(source.texture, "texture image")
    if mesh.texture is None:
        raise InputError(source.mesh, "mesh has no texture (no image beside it, none named by the file)")
    if not mesh.has_uvs:
        raise InputError(source.mesh, "mesh has no UVs: its texture cannot be mapped")
    return mesh


def detect_units(height: float, path: Path) -> str:
    """The units ("m", "cm", "mm") in which a standing person ``height`` source units tall measures
    PERSON_HEIGHT_M; InputError (asking for ``--units``) when none does."""
    for units, scale in UNIT_SCALE.items():
        if PERSON_HEIGHT_M[0] <= height * scale <= PERSON_HEIGHT_M[1]:
            return units
    raise InputError(path, f"the mesh is {height:g} units tall, which is no person's height in m, cm or mm; "
                           "give units")


def world_from_source(mesh: TexturedMesh, path: Path, units: str, up: str) -> tuple[np.ndarray, str, str, list[str]]:
    """The (4, 4) similarity taking the source's points to uvatar's world, and the units and up used.

    ``units``/``up`` "" = detect on this (first) frame: up defaults to +y, the convention of glTF,
    Draco and OBJ exporters; a mesh tallest along another axis asks for ``--up``.
    """
    notes = []
    extent = np.ptp(mesh.vertices, axis=0)
    if not up:
        up = "+y"
        tallest = "xyz"[int(np.argmax(extent))]
        if tallest != "y":
            raise InputError(path, f"the mesh is tallest along {tallest}, not y: give up (+{tallest}, or -{tallest} "
                                   f"if the head points to -{tallest})")
        notes.append("up axis not stated by the files: +y (the mesh is tallest along y)")
    axis = {"x": 0, "y": 1, "z": 2}[up[1]]
    if not units:
        units = detect_units(float(extent[axis]), path)
        notes.append(f"units not stated by the files: {units} (the first frame is {extent[axis]:.4g} {units} tall)")
    S = np.eye(4)
    S[:3, :3] = UNIT_SCALE[units] * up_rotation(up)
    return S, units, up, notes


def import_mesh_sequence(src: str | Path, out: str | Path, cfg=None, progress: bool = True) -> dict:
    """Import the volumetric video ``src`` into the capture ``out`` (see the module doc); returns the
    summary. ``cfg``: :class:`uvatar.capture.importers.ImportConfig` (start, end, stride, up, units,
    fps, body_model; its image options do not apply: textures are kept as decoded, in PNG)."""
    from tqdm import tqdm

    from uvatar.capture.importers.pipeline import ImportConfig
    from uvatar.capture.layout import write_capture_info
    from uvatar.capture.meshio import write_mesh

    cfg = cfg or ImportConfig()
    src, out = Path(src), Path(out)
    t0 = time.perf_counter()
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    seq = find_mesh_sequence(src)
    end = cfg.end or max(seq.frames) + 1
    wanted = [i for i in sorted(seq.frames) if cfg.start <= i < end and (i - cfg.start) % cfg.stride == 0]
    if not wanted:
        raise InputError(src, f"no frame in [{cfg.start}, {end}) with stride {cfg.stride} (the take has frames "
                              f"{min(seq.frames)}..{max(seq.frames)})")
    problems = [p for p in seq.problems if not any(f"frame {i} " in p for i in set(seq.frames) - set(wanted))]
    for line in problems:
        log.warning(line)
    scans = out / "scans"
    scans.mkdir(parents=True, exist_ok=True)
    from uvatar import stage_record
    for p in scans.glob(".*"):
        if p.is_file():
            p.unlink(missing_ok=True)
    S = units = up = None
    notes: list[str] = list(seq.notes)
    imported, skipped, written = [], [], 0
    bar = tqdm(wanted, desc="import", unit="frame", disable=not progress or None)
    for i in bar:
        target = scans / f"{frame_name(i)}.ply"
        done = target.is_file() and target.with_suffix(".png").is_file()
        if done and S is not None:
            imported.append(i)
            continue
        try:
            mesh = _read_frame(seq.frames[i])
        except InputError as exc:
            skipped.append(i)
            problems.append(str(exc))
            log.warning("%s", exc)
            continue
        if S is None:  # decided once, on the first frame that reads: not a per-frame problem
            S, units, up, axis_notes = world_from_source(mesh, seq.frames[i].mesh, cfg.units or seq.units,
                                                         cfg.up or seq.up)
            notes += axis_notes
            # what the scans on disk are made with (recorded once the first frame reads, before any write):
            # a resume with other units / up / source is refused; the frame range may grow
            stage_record.begin(scans, "capture import", {"source": str(src.resolve()), "units": cfg.units,
                                                         "up": cfg.up, "ktx2_animation_textures": KTX2_ANIMATION_TEXTURES},
                               total=len(wanted), redo_hint="another output folder starts over",
                               made_by={"ktx2_animation_textures": OLDER_KTX2_TEXTURES})
        if not done:
            mesh.vertices = mesh.vertices @ S[:3, :3].T.astype(np.float32) + S[:3, 3].astype(np.float32)
            write_mesh(target, mesh)
            written += 1
        imported.append(i)
        if not done:  # what a refusal of the half-made import counts ("3 of 12 frames")
            stage_record.mark_progress(scans, len(imported))
    bar.close()
    if not imported:
        raise InputError(src, f"no frame could be imported ({len(skipped)} broken; first: {problems[-1]})")
    fps = cfg.fps or seq.fps or UVOL_DEFAULT_FPS
    if not (cfg.fps or seq.fps):
        notes.append(f"frame rate not stated (no manifest, no --fps): {UVOL_DEFAULT_FPS:g} fps, the UVOL encoder's "
                     "default")
    provenance = {"tool": "uvatar capture import", "source": str(src.resolve()), "layout": seq.layout,
                  "manifest": str(seq.manifest) if seq.manifest else None, "source_units": units, "source_up": up,
                  "world_from_source": S.tolist(), "source_frames": [wanted[0], wanted[-1] + 1, cfg.stride],
                  "frames_skipped": [frame_name(i) for i in skipped], "problems": problems, "notes": notes,
                  "config": asdict(cfg)}
    write_capture_info(out, [frame_name(i) for i in imported], fps=fps, body_model=cfg.body_model,
                       provenance=provenance)
    stage_record.finish(scans, len(imported))
    return {"capture": str(out), "layout": seq.layout, "frames": len(imported), "skipped": len(skipped),
            "scans_written": written, "scans_kept": len(imported) - written, "fps": fps, "units": units, "up": up,
            "problems": problems, "notes": notes, "seconds": round(time.perf_counter() - t0, 1)}
