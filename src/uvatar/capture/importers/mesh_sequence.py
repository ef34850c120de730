"""``uvatar capture import`` of a volumetric video: a sequence of textured meshes, one per frame.

Seven layouts are read (:func:`find_mesh_sequence`):

- **UVOL 1** (the player's first format, :mod:`~uvatar.capture.importers.uvol1`): ``NAME.manifest``,
  ``NAME.drcs`` (Corto meshes end to end, :mod:`uvatar.capture.mesh_corto`) and ``NAME.mp4`` (the
  textures as a video, :mod:`uvatar.capture.texture_video`; each mesh wears the video frame the player
  shows with it, and where the video carries UVOL 1's frame counter, the frame whose counter is its own).

- **Volograms** (:mod:`~uvatar.capture.importers.vologram`, versions 1.0-1.3): ``header.vols`` +
  ``sequence_0.vols`` with a texture video beside them, or one 1.3 ``NAME.vols`` whose frames embed
  ``.basis``/KTX2 textures; tracked frames wear their keyframe's triangles and UVs.

- **Alembic** (:mod:`~uvatar.capture.importers.alembic`): one ``.abc`` mesh cache (Ogawa; PolyMesh or SubD,
  tracked or each frame its own topology) with per-frame images, a texture video or one image beside it.

- **FBX** (:mod:`~uvatar.capture.importers.fbx`): one ``.fbx`` scene holding a mesh a frame, each shown at its
  frame by its visibility keys, or a tracked mesh moved by blend shapes or a point cache (``.pc2``, Maya
  ``.xml`` + ``.mc``); each wearing its own material's
  image (or the textures beside the file).

- **USD** (:mod:`~uvatar.capture.importers.usd`): one ``.usd``/``.usda``/``.usdc``/``.usdz`` stage whose mesh
  moves, each frame wearing its material's texture (or the textures beside it).

- **UVOL 2** (the Universal Volumetric player's format): ``geometry_<target>/NNNNN.drc`` (Draco, one
  mesh per frame) and ``texture_<target>/NNNNN.ktx2`` (KTX2 array textures, ``n`` frames per file:
  texture frame ``t`` is file ``t // n``, layer ``t % n``; ETC1S, UASTC or plain texels: 8-bit RGB(A),
  ETC2, ASTC), ``NNNNN.ktx`` (KTX 1, e.g. the ``astc/ktx`` target), ``NNNNN.etc2`` (headerless RGB_ETC2
  blocks, one image per file, its size the manifest's ``resolution``) or per-frame ``.png``/``.jpg``. A manifest
  (:mod:`~uvatar.capture.importers.uvol_manifest`: the player's ``*.uvol.json`` or its encoder's
  ``uvol.json``, whose folders are ``DRC/`` and ``KTX2/``) gives the frame rates, the frame count, the
  frames per file, the path templates and the texture target; where the textures run at another
  rate than the geometry, each mesh takes the texture frame the player shows with it. Without one,
  the folders are found by name and ``n`` is the layer count of the first KTX2 file.
- **Plain folders** of per-frame ``.obj``/``.ply``/``.glb``/``.gltf``/``.fbx``/``.drc``/``.crt``/``.abc``
  (frame number = the last run of digits in the file name) with their own textures (OBJ's .mtl, PLY's ``TextureFile`` comment, GLB's
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

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.importers.alembic import (
    ABC_SUFFIXES,
    alembic_sequence,
    close_alembic,
    find_alembic,
)
from uvatar.capture.importers.fbx import close_fbx, fbx_sequence, find_fbx_take
from uvatar.capture.importers.frame_reader import (
    layered_format,
    point_cloud_config,
    read_frame,
)
from uvatar.capture.importers.sequence import FrameSource, MeshSequence, files_by_frame
from uvatar.capture.importers.source_world import world_from_source
from uvatar.capture.importers.usd import USD_SUFFIXES, close_usd, find_usd, usd_sequence
from uvatar.capture.importers.uvol1 import (
    MESH_FILE_SUFFIXES,
    find_v1_manifest,
    read_v1_manifest,
    uvol1_sequence,
)
from uvatar.capture.importers.uvol_manifest import (
    TEXTURE_SUFFIX,
    UvolManifest,
    find_manifest,
    read_manifest,
    template_folder,
    texture_frame,
)
from uvatar.capture.importers.vologram import (
    VOLS_SUFFIXES,
    close_vols,
    find_vols_take,
    vols_sequence,
)
from uvatar.capture.layout import frame_name
from uvatar.capture.meshio import IMAGE_SUFFIXES, MESH_FORMATS
from uvatar.capture.texture_video import close_videos
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".drc", ".glb", ".obj", ".ply")   # a UVOL geometry folder's, in order of preference
TEXTURELESS_MESHES = (".drc", ".crt", ".abc")       # mesh files that never carry a texture image (Draco, Corto, Alembic)
#: a texture folder's files, in order of preference where no manifest names the format (KTX 2 and 1 say
#: their size; a headerless .etc2 file needs the manifest's resolution unless it is square)
TEXTURE_SUFFIXES = (".ktx2",) + IMAGE_SUFFIXES + (".ktx", ".etc2")
LAYERED_SUFFIXES = (".ktx2", ".ktx", ".etc2")   # files of one image or an array of frames


UVOL_DEFAULT_FPS = 30.0       # the UVOL encoder's default frame rate, used when nothing says otherwise
KTX2_ANIMATION_TEXTURES = "p-frames-decoded"  # how this version gives an animation's frames their textures
OLDER_KTX2_TEXTURES = ("imported by an older uvatar, which gave a KTX2 animation's P-frames their I-frame's "
                       "texture; this one decodes them")


def is_mesh_sequence(src: str | Path) -> bool:
    """True if ``src`` looks like a mesh sequence (UVOL 2 folders, a manifest, or per-frame meshes)."""
    src = Path(src)
    if src.is_file():            # a take file, or one frame's mesh (told to give its folder)
        return src.suffix.lower() in ((".manifest",) + MESH_FILE_SUFFIXES + VOLS_SUFFIXES + ABC_SUFFIXES + USD_SUFFIXES
                                      + tuple(MESH_FORMATS) + TEXTURELESS_MESHES)
    if not src.is_dir():
        return False
    if _uvol_folders(src)[0] or find_manifest(src):
        return True
    return any(p.suffix.lower() in MESH_FORMATS or p.suffix.lower() in TEXTURELESS_MESHES + VOLS_SUFFIXES + ABC_SUFFIXES
               + USD_SUFFIXES
               for p in src.iterdir() if p.is_file())


def _uvol_folders(src: Path) -> tuple[list[Path], list[Path]]:
    geometry = sorted(p for p in src.glob("geometry_*") if p.is_dir())
    texture = sorted(p for p in src.glob("texture_*") if p.is_dir())
    return geometry, texture


def _pick(folders: list[Path], suffixes: tuple[str, ...]) -> Path | None:
    """The first folder holding files of the preferred suffix order (e.g. Draco before GLB)."""
    for suffix in suffixes:
        for folder in folders:
            if any(folder.glob(f"*{suffix}")):
                return folder
    return None


def find_mesh_sequence(src: str | Path, fps: float = 0.0) -> MeshSequence:
    """List a mesh sequence's frames (nothing decoded but KTX2 headers); InputError when none. ``fps``:
    the rate the user gave, for a take whose files state none (an acyclic Alembic's frame numbers)."""
    src = Path(src)
    v1 = find_v1_manifest(src)
    if v1 is not None:
        return uvol1_sequence(read_v1_manifest(v1))
    vols = find_vols_take(src)
    if vols is not None:
        return vols_sequence(*vols)
    abc = find_alembic(src)
    if abc is not None:
        return alembic_sequence(abc, fps)
    usd = find_usd(src)
    if usd is not None:
        return usd_sequence(usd, fps)
    fbx = find_fbx_take(src, fps)
    if fbx is not None:
        return fbx_sequence(fbx)
    if src.is_file():
        raise InputError(src, "is one file, not a take: give the folder of its per-frame meshes, or a take "
                              "file (.abc, .fbx, .usd/.usda/.usdc/.usdz, .vols, a UVOL .manifest)")
    if not src.is_dir():
        raise InputError(src, "volumetric video folder does not exist")
    manifest_path = find_manifest(src)
    manifest = read_manifest(manifest_path) if manifest_path else UvolManifest(src)
    geometry_dirs, texture_dirs = _uvol_folders(src)
    if not geometry_dirs and not manifest.geometry_path:
        return _plain_folder(src)
    geometry = template_folder(src, manifest.geometry_path, manifest.geometry_target, "geometry") \
        or _pick(geometry_dirs, MESH_SUFFIXES)
    if geometry is None:
        raise InputError(src, "no geometry_*/ folder with .drc/.glb/.obj/.ply frames")
    meshes = files_by_frame(geometry, MESH_SUFFIXES)
    if not meshes:
        raise InputError(geometry, "holds no mesh frames (NNNNN.drc)")
    suffixes = ((TEXTURE_SUFFIX[manifest.texture_format],) if manifest.texture_format in TEXTURE_SUFFIX
                else TEXTURE_SUFFIXES)
    texture = template_folder(src, manifest.texture_path, manifest.texture_target, "texture") \
        or _pick(texture_dirs, suffixes) or _pick(texture_dirs, TEXTURE_SUFFIXES)   # the named target's, else any
    suffixes = suffixes + tuple(s for s in TEXTURE_SUFFIXES if s not in suffixes)
    seq = MeshSequence({i: FrameSource(i, p) for i, p in meshes.items()}, "uvol2", fps=manifest.fps or 0.0,
                       manifest=manifest_path)
    if manifest.skipped_targets:
        seq.notes.append(f"{manifest_path}: texture target{'s' if len(manifest.skipped_targets) > 1 else ''} "
                         f"{', '.join(manifest.skipped_targets)} not read"
                         + (f" (the {manifest.texture_target} target is)" if manifest.texture_target else ""))
    suffix = next((s for s in suffixes if any(texture.glob(f"*{s}"))), None) if texture else None
    if suffix is None:
        _refuse_unreadable_textures(texture_dirs + ([texture] if texture else []), meshes, manifest)
    if texture is None:
        seq.problems.append(f"{src}: no texture_*/ folder: frames take their meshes' own textures")
    else:
        if suffix in LAYERED_SUFFIXES:
            _layered_textures(seq, texture, geometry, suffix, manifest)
        else:
            images = files_by_frame(texture, IMAGE_SUFFIXES)
            for i, source in seq.frames.items():
                source.texture = images.get(i, ())
                if not source.texture:
                    seq.problems.append(f"{texture}: no image for frame {i} ({meshes[i].name})")
            if len(images) != len(seq.frames):
                seq.problems.append(f"{texture}: {len(images)} images for {len(seq.frames)} meshes in {geometry}: "
                                    "the counts disagree")
    count = manifest.frame_count
    if count is not None and count != len(seq.frames):
        seq.problems.append(f"{manifest_path}: says {count} frames, {geometry} holds {len(seq.frames)}: the counts "
                            "disagree")
    if all(p.suffix.lower() in (".glb", ".gltf") for p in meshes.values()):  # glTF says: metres, +Y up
        seq.units, seq.up = "m", "+y"
    return seq


def _refuse_unreadable_textures(folders: list[Path], meshes: dict[int, Path], manifest: UvolManifest) -> None:
    """Draco meshes (no texture of their own) whose take holds only textures uvatar cannot decode: one
    line saying what to give instead."""
    if not all(p.suffix.lower() == ".drc" for p in meshes.values()):
        return
    if manifest.skipped_targets and not manifest.texture_target:
        raise InputError(manifest.path, f"lists only texture targets uvatar does not decode "
                                        f"({', '.join(manifest.skipped_targets)}); give the take with its ktx2 or "
                                        "etc2 target, or per-frame images")
    video = _pick(folders, (".mp4",))
    if video is not None:
        raise InputError(video, "holds a texture video (.mp4), which uvatar does not decode; give the take with its "
                                "ktx2 or etc2 target, or per-frame images")


def _layered_textures(seq: MeshSequence, texture: Path, geometry: Path, suffix: str, manifest: UvolManifest) -> None:
    """Give each frame its texture file and layer: texture frame ``t`` (the player's, at the geometry's
    and texture's frame rates) is file ``t // n``, layer ``t % n`` of a KTX 2 (or KTX 1) array; an
    ``.etc2`` file is one image for its ``n`` texture frames."""
    from uvatar.capture.texture_etc import etc2_image_size

    files = files_by_frame(texture, (suffix,))
    kind, info_of, _ = layered_format(suffix)
    first = files[min(files)]
    layers: dict[Path, int] = {}
    if info_of is not None:
        info = info_of(first)
        per_file = manifest.frames_per_file or info["layers"]
        if info["animation"] and per_file > 1:
            seq.notes.append(f"{texture}: KTX2 animations (KTXanimData): each file's {per_file - 1} P-frames decoded "
                             "after its I-frame")
    else:
        per_file = manifest.frames_per_file or 1
        seq.texture_size, note = etc2_image_size(first, manifest.texture_resolution)
        if note:
            seq.notes.append(note)
    rates = (manifest.geometry_fps, manifest.texture_fps)
    if manifest.geometry_fps and manifest.texture_fps and texture_frame(1000, *rates) != 1000:
        seq.notes.append(f"{manifest.path}: textures at {manifest.texture_fps:g} fps for geometry at "
                         f"{manifest.geometry_fps:g} fps: each mesh takes the texture frame the player shows with it")
    for i, source in seq.frames.items():
        t = texture_frame(i, *rates)
        path = files.get(t // per_file)
        if path is None:
            seq.problems.append(f"{texture / f'{t // per_file:05d}{suffix}'}: missing: frame {i} "
                                + (f"(texture frame {t}) " if t != i else "") + "has no texture")
            source.texture = ()
            continue
        if info_of is None:                    # one image a file
            source.texture = (path, 0)
            continue
        if path not in layers:
            try:
                layers[path] = info_of(path)["layers"]
            except InputError as exc:
                layers[path] = 0
                seq.problems.append(str(exc))
        if t % per_file >= layers[path]:
            if layers[path]:
                seq.problems.append(f"{path}: has {layers[path]} layers, fewer than the {per_file} frames per file: "
                                    f"frame {i} (layer {t % per_file}) has no texture")
            source.texture = ()
            continue
        source.texture = (path, t % per_file)
    needed = {texture_frame(i, *rates) for i in seq.frames}   # the texture frames the meshes show
    covered = max(files) * per_file + per_file
    if covered < max(needed) + 1 or len(files) * per_file < len(needed) - per_file + 1:
        seq.problems.append(f"{texture}: {len(files)} {kind} files x {per_file} frames for {len(seq.frames)} meshes "
                            f"in {geometry}: the counts disagree")
    elif max(files) * per_file > max(needed):
        seq.problems.append(f"{texture}: textures for frames past the last mesh ({max(seq.frames)}): the counts "
                            "disagree; those textures are not used")


def _plain_folder(src: Path) -> MeshSequence:
    suffixes = tuple(MESH_FORMATS) + TEXTURELESS_MESHES
    meshes = files_by_frame(src, suffixes)
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
            if image is not None and path.suffix.lower() in TEXTURELESS_MESHES + (".ply",):
                texture = image
                break
        if path.suffix.lower() == ".abc" and texture is None:    # Draco and Corto files may hold colours
            problems.append(f"{path}: an Alembic mesh without an image of the same name: frame {i} has no texture")
            texture = ()
        frames[i] = FrameSource(i, path, texture)
    glb = all(p.suffix.lower() in (".glb", ".gltf") for p in meshes.values())     # glTF says: metres, +Y up
    seq = MeshSequence(frames, "mesh folder", units="m" if glb else "", up="+y" if glb else "", problems=problems)
    if all(p.suffix.lower() == ".fbx" for p in meshes.values()):     # FBX's GlobalSettings say: read in metres, +Y up
        from uvatar.capture.mesh_fbx import FbxScene

        first = meshes[min(meshes)]
        seq.units, seq.up = "m", "+y"
        seq.notes.append(f"{first}: {FbxScene(first).describe_settings()}")
    return seq


def import_mesh_sequence(src: str | Path, out: str | Path, cfg=None, progress: bool = True) -> dict:
    """Import the volumetric video ``src`` into the capture ``out`` (see the module doc); returns the
    summary. ``cfg``: :class:`uvatar.capture.importers.ImportConfig` (start, end, stride, up, units,
    fps, body_model; its image options do not apply: textures are kept as decoded, in PNG)."""
    from uvatar.capture.importers.pipeline import ImportConfig

    cfg = cfg or ImportConfig()
    src, out = Path(src), Path(out)
    t0 = time.perf_counter()
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    try:
        return _import_sequence(src, out, cfg, progress, t0)
    finally:
        close_sources()


def close_sources() -> None:
    """Close what listing and reading a sequence opened (texture videos, Volograms, Alembic, USD takes)."""
    close_videos()
    close_vols()
    close_alembic()
    close_fbx()
    close_usd()


def wanted_frames(seq: MeshSequence, src: Path, cfg) -> tuple[list[int], list[str]]:
    """The frames of ``seq`` that ``cfg``'s start, end and stride keep, and the listing's problems that
    concern them; InputError when none is kept."""
    if not seq.frames:
        raise InputError(src, "no frame listed: " + "; ".join(seq.problems[:2]))
    end = cfg.end or max(seq.frames) + 1
    wanted = [i for i in sorted(seq.frames) if cfg.start <= i < end and (i - cfg.start) % cfg.stride == 0]
    if not wanted:
        raise InputError(src, f"no frame in [{cfg.start}, {end}) with stride {cfg.stride} (the take has frames "
                              f"{min(seq.frames)}..{max(seq.frames)})")
    problems = [p for p in seq.problems if not any(f"frame {i} " in p for i in set(seq.frames) - set(wanted))]
    return wanted, problems


@dataclass(frozen=True)
class FrameTasks:
    """What every frame's task needs (sent once to each worker process): the take's frames, a headerless
    texture's size, the point-cloud options, whether the units were stated, the (4, 4) world-from-source
    similarity and the scans folder."""

    frames: dict[int, FrameSource]
    texture_size: tuple[int, int] | None
    point_cloud: object
    units_stated: bool
    world_from_source: np.ndarray
    scans: Path


def _is_written(target: Path) -> bool:
    return target.is_file() and target.with_suffix(".png").is_file()


def _write_in_world(target: Path, mesh: TexturedMesh, S: np.ndarray) -> None:
    from uvatar.capture.meshio import write_mesh

    mesh.vertices = mesh.vertices @ S[:3, :3].T.astype(np.float32) + S[:3, 3].astype(np.float32)
    write_mesh(target, mesh)


def _import_frame(shared: FrameTasks, i: int) -> tuple[list[str], str]:
    """Frame ``i`` read, taken to uvatar's world and written (atomically): (the notes it gave, "") or
    ([], its one-line problem)."""
    notes: list[str] = []
    try:
        mesh = read_frame(shared.frames[i], shared.texture_size, notes, shared.point_cloud, shared.units_stated)
    except InputError as exc:
        return [], str(exc)
    _write_in_world(shared.scans / f"{frame_name(i)}.ply", mesh, shared.world_from_source)
    return notes, ""


def _one_thread() -> None:
    from uvatar.threads import limit_process_to_one_thread

    limit_process_to_one_thread()


def _import_sequence(src: Path, out: Path, cfg, progress: bool, t0: float) -> dict:
    from uvatar.capture.layout import write_capture_info
    from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks

    seq = find_mesh_sequence(src, cfg.fps or 0.0)
    wanted, problems = wanted_frames(seq, src, cfg)
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
    imported, skipped, written, first_error = [], [], 0, ""

    def failed(i: int, message: str) -> None:
        nonlocal first_error
        skipped.append(i)
        first_error = first_error or message
        problems.append(message)
        log.warning("%s", message)

    units_stated = bool(cfg.units or seq.units)   # then the voxel grid's hint has nothing to add
    # the first frame that reads decides the units and up axis (read even when written before: a resume)
    rest = list(wanted)
    while rest and S is None:
        i = rest.pop(0)
        target = scans / f"{frame_name(i)}.ply"
        try:
            mesh = read_frame(seq.frames[i], seq.texture_size, notes, point_cloud_config(cfg), units_stated)
        except InputError as exc:
            failed(i, str(exc))
            continue
        S, units, up, axis_notes = world_from_source(mesh, seq.frames[i].mesh, cfg.units or seq.units,
                                                     cfg.up or seq.up)
        notes += axis_notes
        # what the scans on disk are made with (recorded once the first frame reads, before any write):
        # a resume with other units / up / source is refused; the frame range may grow
        stage_record.begin(scans, "capture import", {"source": str(src.resolve()), "units": cfg.units,
                                                     "up": cfg.up, "ktx2_animation_textures": KTX2_ANIMATION_TEXTURES},
                           total=len(wanted), redo_hint="another output folder starts over",
                           made_by={"ktx2_animation_textures": OLDER_KTX2_TEXTURES})
        if not _is_written(target):
            _write_in_world(target, mesh, S)
            written += 1
            stage_record.mark_progress(scans, 1)
        imported.append(i)
    written_before = {i for i in rest if _is_written(scans / f"{frame_name(i)}.ply")}
    imported += sorted(written_before)
    todo = [i for i in rest if i not in written_before]
    shared = FrameTasks(seq.frames, seq.texture_size, point_cloud_config(cfg), units_stated, S, scans)
    for i, result in run_tasks(_import_frame, todo, shared, ExecutorConfig(workers=cfg.workers),
                               desc="import", progress=progress, initializer=_one_thread):
        if isinstance(result, TaskFailure):     # the worker process died (memory, a crash): that frame only
            failed(i, f"{seq.frames[i].mesh}: {result.reason}")
            continue
        frame_notes, error = result
        if error:
            failed(i, error)
            continue
        notes += [n for n in frame_notes if n not in notes]
        imported.append(i)
        written += 1
        stage_record.mark_progress(scans, len(imported))  # what a refusal of the half-made import counts
    imported.sort()
    if not imported:
        raise InputError(src, f"no frame could be imported ({len(skipped)} broken; first: {first_error})")
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
